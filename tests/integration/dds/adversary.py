"""An adversarial client of ``fieldbus serve`` written with cyclonedds only (no fieldbus import).

    python adversary.py MODE NAMESPACE GROUP DOMAIN

Every mode prints JSON lines; the last one is its result. Cycle numbers are
the served bus's (``AxisState.cycle``), so the test bounds them in cycles.

- ``forge``: participant A claims, enables and holds the joints where they are;
  participant B (another DDS participant: as another process is) sends commands
  under A's client_id with far higher sequence numbers and +0.06 rad. Result:
  positions before and after, A's last sequence and the one the bus applied,
  the refused count.
- ``nan``: claims, enables, sends one valid command, then only NaN. Result: the
  valid command's sequence and every (cycle, gate, command age, applied
  sequence, drive states) seen until 300 states after SAFE_STOP.
- ``commander``: claims, enables, holds the joints forever (to be killed);
  ``silent``: claims, enables and never sends a command, only a request every
  0.2 s (the owner's requests keep an IDLE group claimed; to be killed).
- ``claimer``: asks to claim until it may (each refusal and the cycle it came
  at). Result: the claim's cycle and the owner's last command cycle as the state
  showed it.
"""

import json
import math
import sys
import time
from dataclasses import dataclass, field

from cyclonedds.domain import DomainParticipant
from cyclonedds.idl import IdlStruct
from cyclonedds.idl import types as t
from cyclonedds.pub import DataWriter
from cyclonedds.sub import DataReader
from cyclonedds.topic import Topic
from ros2_peer import BEST_EFFORT, RELIABLE, Header_, JointCommand_, JointState_, Reply_, Request_


@dataclass
class AxisState_(IdlStruct, typename="fieldbus_msgs::msg::dds_::AxisState_"):
    """fieldbus_msgs/AxisState, field by field as docs/dds.md gives it."""

    header: Header_ = field(default_factory=Header_)
    cycle: t.uint64 = 0
    fresh: t.sequence[bool] = field(default_factory=list)
    drive_state: t.sequence[t.int8] = field(default_factory=list)
    inputs: t.sequence[t.float64] = field(default_factory=list)
    all_fresh: bool = False
    safe_stop: bool = False
    gate: t.uint8 = 0
    command_sequence: t.uint64 = 0
    command_age: t.uint32 = 0
    owner: str = ""
    dropped_sequences: t.uint32 = 0
    refused_commands: t.uint32 = 0


SAFE_STOP = 3


class Peer:
    """One DDS participant: requests, commands, joint states and axis states of one group."""

    def __init__(self, ns: str, group: str, domain: int, me: str) -> None:
        self.me, self.group, self.rid, self.seq = me, group, 0, 0
        dp = self.dp = DomainParticipant(domain)
        self.js = DataReader(dp, Topic(dp, f"rt/{ns}/{group}/joint_states", JointState_), qos=BEST_EFFORT)
        self.st = DataReader(dp, Topic(dp, f"rt/{ns}/{group}/axis_state", AxisState_), qos=BEST_EFFORT)
        self.cmd = DataWriter(dp, Topic(dp, f"rt/{ns}/{group}/command", JointCommand_), qos=BEST_EFFORT)
        self.req = DataWriter(dp, Topic(dp, f"rt/{ns}/request", Request_), qos=RELIABLE)
        self.rep = DataReader(dp, Topic(dp, f"rt/{ns}/reply", Reply_), qos=RELIABLE)
        self.last: AxisState_ | None = None

    def ask(self, verb: str, timeout_s: float = 20.0) -> Reply_:
        self.rid += 1
        end = time.monotonic() + timeout_s
        while time.monotonic() < end:  # resent until answered: discovery may still be under way
            self.req.write(Request_(client_id=self.me, request_id=self.rid, group=self.group, verb=verb))
            until = time.monotonic() + 0.5
            while time.monotonic() < until:
                for r in self.rep.take(N=16):
                    if isinstance(r, Reply_) and r.client_id == self.me and r.request_id == self.rid:
                        return r
                time.sleep(0.005)
        raise SystemExit(f"no reply to {verb}")

    def state(self, timeout_s: float = 10.0) -> AxisState_:
        """The next axis state."""
        end = time.monotonic() + timeout_s
        while time.monotonic() < end:
            got = [s for s in self.st.take(N=16) if isinstance(s, AxisState_)]
            if got:
                self.last = got[-1]
                return got[-1]
            time.sleep(0.001)
        raise SystemExit("no axis state")

    def positions(self) -> list[float]:
        end = time.monotonic() + 10.0
        while time.monotonic() < end:
            got = [s for s in self.js.take(N=16) if isinstance(s, JointState_)]
            if got:
                return list(got[-1].position)
            time.sleep(0.001)
        raise SystemExit("no joint states")

    def command(
        self, position: list[float], *, client_id: str | None = None, sequence: int | None = None
    ) -> None:
        self.seq += 1
        self.cmd.write(
            JointCommand_(client_id=client_id or self.me, sequence=sequence or self.seq, position=position)
        )

    def claim_and_enable(self) -> list[float]:
        for verb in ("claim", "enable"):
            r = self.ask(verb)
            if not r.ok:
                raise SystemExit(f"{verb} refused: {r.error}")
        return self.positions()


def out(obj: object) -> None:
    print(json.dumps(obj), flush=True)


def main() -> int:
    mode, ns, group, domain = sys.argv[1], sys.argv[2], sys.argv[3], int(sys.argv[4])
    if mode == "forge":
        a, b = Peer(ns, group, domain, "owner"), Peer(ns, group, domain, "forger")
        hold = a.claim_and_enable()
        forged = [p + 0.06 for p in hold]
        end = time.monotonic() + 2.0
        while time.monotonic() < end:
            a.command(hold)
            b.command(forged, client_id="owner", sequence=1_000_000 + a.seq)
            time.sleep(0.002)
        a.command(hold)
        time.sleep(0.05)
        st = a.state()
        out(
            {
                "before": hold,
                "after": a.positions(),
                "owner_sequence": a.seq,
                "applied": st.command_sequence,
                "refused": st.refused_commands,
                "dropped": st.dropped_sequences,
                "owner": st.owner,
            }
        )
    elif mode == "nan":
        p = Peer(ns, group, domain, "nan")
        hold = p.claim_and_enable()
        p.command(hold)
        valid = p.seq
        seen: list[tuple[int, int, int, int, list[int]]] = []
        end = time.monotonic() + 60.0
        latched = 0
        while time.monotonic() < end and latched < 300:  # on past the latch: the drives leave OP ENABLED
            p.command([math.nan] * len(hold))
            st = p.state()
            seen.append((st.cycle, st.gate, st.command_age, st.command_sequence, list(st.drive_state)))
            latched += st.gate == SAFE_STOP
            time.sleep(0.001)
        out(
            {
                "valid_sequence": valid,
                "seen": seen,
                "refused": p.last.refused_commands if p.last else 0,
                "drive_state": list(p.last.drive_state) if p.last else [],
            }
        )
    elif mode in ("commander", "silent"):
        p = Peer(ns, group, domain, "commander")
        hold = p.claim_and_enable()
        out({"commanding": True})
        while True:
            if mode == "commander":
                p.command(hold)
                time.sleep(0.002)
            else:  # alive only by its requests (claiming again is a no-op for the owner)
                p.ask("claim")
                time.sleep(0.2)
    elif mode == "claimer":
        p = Peer(ns, group, domain, "claimer")
        refused = []
        end = time.monotonic() + 60.0
        while time.monotonic() < end:
            before = p.state().cycle  # the claim is asked after this cycle
            r = p.ask("claim")
            st = p.state()
            if r.ok:
                out(
                    {
                        "claimed_at": st.cycle,
                        "gate": st.gate,
                        "last_command_cycle": st.cycle - st.command_age,
                        "refused": refused,
                    }
                )
                return 0
            refused.append([before, r.error])
            out({"refused_after": before})
            time.sleep(0.01)
        raise SystemExit(f"never claimable: {refused[-3:]}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
