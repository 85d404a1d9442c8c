"""A ROS 2-style peer written with cyclonedds and the message definitions only: no fieldbus import.

    python ros2_peer.py NAMESPACE GROUP DOMAIN OFFSET_RAD

Reads ``sensor_msgs/JointState`` from ``rt/NAMESPACE/GROUP/joint_states``,
claims the group and enables it with fieldbus_msgs requests, then commands
every joint to its position + OFFSET_RAD with fieldbus_msgs/JointCommand.
Prints one JSON line: joint names, positions before and after, whether
anything of fieldbus was imported.
"""

import json
import sys
import time
from dataclasses import dataclass, field

from cyclonedds.core import Policy, Qos
from cyclonedds.domain import DomainParticipant
from cyclonedds.idl import IdlStruct
from cyclonedds.idl import types as t
from cyclonedds.idl.annotations import key
from cyclonedds.pub import DataWriter
from cyclonedds.sub import DataReader
from cyclonedds.topic import Topic
from cyclonedds.util import duration


# the ROS 2 definitions (builtin_interfaces/Time, std_msgs/Header, sensor_msgs/JointState) as rmw_cyclonedds names them
@dataclass
class Time_(IdlStruct, typename="builtin_interfaces::msg::dds_::Time_"):
    sec: t.int32 = 0
    nanosec: t.uint32 = 0


@dataclass
class Header_(IdlStruct, typename="std_msgs::msg::dds_::Header_"):
    stamp: Time_ = field(default_factory=Time_)
    frame_id: str = ""


@dataclass
class JointState_(IdlStruct, typename="sensor_msgs::msg::dds_::JointState_"):
    header: Header_ = field(default_factory=Header_)
    name: t.sequence[str] = field(default_factory=list)
    position: t.sequence[t.float64] = field(default_factory=list)
    velocity: t.sequence[t.float64] = field(default_factory=list)
    effort: t.sequence[t.float64] = field(default_factory=list)


# the fieldbus_msgs definitions, as docs/dds.md gives them
@dataclass
class JointCommand_(IdlStruct, typename="fieldbus_msgs::msg::dds_::JointCommand_"):
    header: Header_ = field(default_factory=Header_)
    client_id: str = ""
    key("client_id")
    sequence: t.uint64 = 0
    position: t.sequence[t.float64] = field(default_factory=list)
    velocity: t.sequence[t.float64] = field(default_factory=list)
    torque: t.sequence[t.float64] = field(default_factory=list)
    kp: t.sequence[t.float64] = field(default_factory=list)
    kd: t.sequence[t.float64] = field(default_factory=list)


@dataclass
class Request_(IdlStruct, typename="fieldbus_msgs::msg::dds_::Request_"):
    client_id: str = ""
    request_id: t.uint32 = 0
    group: str = ""
    verb: str = ""
    argument: str = ""


@dataclass
class Reply_(IdlStruct, typename="fieldbus_msgs::msg::dds_::Reply_"):
    client_id: str = ""
    request_id: t.uint32 = 0
    ok: bool = False
    error: str = ""
    detail: str = ""


BEST_EFFORT = Qos(Policy.Reliability.BestEffort, Policy.History.KeepLast(1), Policy.Durability.Volatile)
RELIABLE = Qos(Policy.Reliability.Reliable(duration(seconds=1)), Policy.History.KeepLast(32))
ME = "ros2-peer"


def main() -> int:
    ns, group, domain, offset = sys.argv[1], sys.argv[2], int(sys.argv[3]), float(sys.argv[4])
    dp = DomainParticipant(domain)
    states = DataReader(dp, Topic(dp, f"rt/{ns}/{group}/joint_states", JointState_), qos=BEST_EFFORT)
    commands = DataWriter(dp, Topic(dp, f"rt/{ns}/{group}/command", JointCommand_), qos=BEST_EFFORT)
    requests = DataWriter(dp, Topic(dp, f"rt/{ns}/request", Request_), qos=RELIABLE)
    replies = DataReader(dp, Topic(dp, f"rt/{ns}/reply", Reply_), qos=RELIABLE)

    def newest(timeout_s: float = 10.0) -> JointState_:
        end = time.monotonic() + timeout_s
        while time.monotonic() < end:
            got = [s for s in states.take(N=16) if isinstance(s, JointState_)]
            if got:
                return got[-1]
            time.sleep(0.002)
        raise SystemExit("no joint states")

    def ask(rid: int, verb: str) -> Reply_:
        end = time.monotonic() + 10.0
        while time.monotonic() < end:  # resent until answered: discovery may still be under way
            requests.write(Request_(client_id=ME, request_id=rid, group=group, verb=verb))
            until = time.monotonic() + 0.5
            while time.monotonic() < until:
                for r in replies.take(N=16):
                    if isinstance(r, Reply_) and r.client_id == ME and r.request_id == rid:
                        return r
                time.sleep(0.005)
        raise SystemExit(f"no reply to {verb}")

    first = newest()
    answers = {verb: ask(i + 1, verb) for i, verb in enumerate(("claim", "enable"))}
    time.sleep(0.5)  # the drives enable (a few cycles)
    before = newest().position
    goal = [p + offset for p in before]
    seq = 0
    end = time.monotonic() + 3.0
    while time.monotonic() < end:
        seq += 1
        commands.write(JointCommand_(client_id=ME, sequence=seq, position=goal))
        time.sleep(0.002)
    after = newest().position
    print(
        json.dumps(
            {
                "names": list(first.name),
                "answers": {v: [r.ok, r.error] for v, r in answers.items()},
                "before": list(before),
                "after": list(after),
                "goal": goal,
                "commands": seq,
                "fieldbus_imported": sorted(n for n in sys.modules if n.split(".")[0] == "fieldbus"),
            }
        ),
        flush=True,
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
