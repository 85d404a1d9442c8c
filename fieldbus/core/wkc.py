"""Working-counter / timeout policy, shared by every backend (pure).

Every cycle a backend reports what came back (an EtherCAT working counter, or
for CAN the TPDOs received per node) and the policy answers: are the inputs
fresh, how many cycles in a row have missed, is it time for a safe stop?

The usual legged-robot policy (hardware tutorial §62.5): a short receive timeout (500 µs), reuse the
last good data on a miss, safe stop after 10 consecutive misses. Inputs that
are not fresh are *held* (the backend does not decode them) and flagged stale.

Expected WKC of an LRW (ETG.1000.4; SOEM ``expectedWKC``): every slave with
outputs adds 2 (write), every slave with inputs adds 1 (read).
"""

from __future__ import annotations

import enum
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from fieldbus.core.al import AL_ERROR, AL_OP, AL_SAFEOP
from fieldbus.core.pdo.layout import MapLayout


class Verdict(enum.IntEnum):
    """What a cycle's reply says about its inputs."""

    OK = 0  # reply complete: inputs fresh
    SHORT = 1  # reply came back but not every slave processed it (WKC too small or too big)
    TIMEOUT = 2  # no reply within the receive timeout


def expected_wkc(layouts: list[MapLayout], *, lrw: bool = True) -> int:
    """Expected working counter of one cycle's process-data datagram(s).

    With LRW a slave adds 2 if it has outputs and 1 if it has inputs. With
    LRD + LWR (a slave that forbids LRW) the two datagrams sum to the same
    figure when the WKCs are combined as SOEM does (outputs x2 + inputs).
    """
    del lrw  # same number either way, kept for readability at call sites
    total = 0
    for lay in layouts:
        total += 2 if lay.outputs.bits else 0
        total += 1 if lay.inputs.bits else 0
    return total


@dataclass(frozen=True)
class PolicyConfig:
    """``safe_stop_after``: consecutive misses that trigger the safe stop (seed: 10)."""

    safe_stop_after: int = 10

    def __post_init__(self) -> None:
        if self.safe_stop_after < 1:
            raise ValueError("safe_stop_after must be >= 1")


@dataclass
class PolicyStats:
    """Counters since start (or the last :meth:`WkcPolicy.reset_stats`)."""

    cycles: int = 0
    misses: int = 0
    timeouts: int = 0
    short: int = 0
    longest_streak: int = 0
    safe_stops: int = 0
    recoveries: int = 0  # streaks of misses that ended in a good cycle


class WkcPolicy:
    """Per-bus freshness policy. Call :meth:`judge` exactly once per cycle.

    ``fresh`` is one flag per slave (True: that slave's inputs were decoded this
    cycle). On EtherCAT one LRW carries every slave, so a short or missing
    reply makes every slave stale; on CAN a backend may pass per-node arrival.
    """

    def __init__(self, expected: int, n_slaves: int, config: PolicyConfig | None = None) -> None:
        self.expected = expected
        self.config = config or PolicyConfig()
        self.fresh: npt.NDArray[np.bool_] = np.zeros(n_slaves, dtype=bool)
        self.stale_cycles: npt.NDArray[np.int64] = np.zeros(n_slaves, dtype=np.int64)
        self.consecutive_misses = 0
        self.safe_stop = False  # latched until clear_safe_stop()
        self.last_verdict = Verdict.OK
        self.last_wkc = -1
        self.stats = PolicyStats()

    def judge(self, wkc: int | None, slave_ok: npt.NDArray[np.bool_] | None = None) -> Verdict:
        """Record one cycle: ``wkc`` received (None: timeout); optional per-slave arrival.

        Returns the verdict; afterwards ``fresh``, ``consecutive_misses`` and
        ``safe_stop`` describe this cycle. Allocates nothing.
        """
        st = self.stats
        st.cycles += 1
        if wkc is None or wkc < 0:
            verdict = Verdict.TIMEOUT
            self.last_wkc = -1
        else:
            self.last_wkc = wkc
            verdict = Verdict.OK if wkc == self.expected else Verdict.SHORT
        if slave_ok is not None:  # the bus can tell which slaves answered (CAN)
            np.copyto(self.fresh, slave_ok)
            if verdict is Verdict.OK and not slave_ok.all():
                verdict = Verdict.SHORT
        else:  # one datagram for all (EtherCAT): a miss makes every slave stale
            self.fresh.fill(verdict is Verdict.OK)
        self.stale_cycles += 1
        self.stale_cycles[self.fresh] = 0
        self.last_verdict = verdict
        if verdict is Verdict.OK:
            if self.consecutive_misses:
                st.recoveries += 1
            self.consecutive_misses = 0
            return verdict
        st.misses += 1
        if verdict is Verdict.TIMEOUT:
            st.timeouts += 1
        else:
            st.short += 1
        self.consecutive_misses += 1
        st.longest_streak = max(st.longest_streak, self.consecutive_misses)
        if self.consecutive_misses == self.config.safe_stop_after and not self.safe_stop:
            self.safe_stop = True
            st.safe_stops += 1
        return verdict

    def clear_safe_stop(self) -> None:
        """Release the latched safe stop (after the user or a recovery re-enabled drives)."""
        self.safe_stop = False

    def reset_stats(self) -> None:
        self.stats = PolicyStats()


class Recovery(enum.Enum):
    """What the recovery monitor should do for one slave (after SOEM's ecatcheck)."""

    NONE = "none"
    ACK_ERROR = "ack_error"  # SAFE-OP + error flag: write SAFE-OP + ACK (0x0014)
    REQUEST_OP = "request_op"  # in SAFE-OP without error: request OP
    RECONFIGURE = "reconfigure"  # fell back to INIT / PRE-OP (power cycle): reconfigure, SDO plan, OP
    RECOVER = "recover"  # no answer at its station address: re-address it (lost slave)


def recovery_action(al_state: int | None) -> Recovery:
    """Next recovery step for a slave whose AL status reads ``al_state`` (None: no answer)."""
    if al_state is None:
        return Recovery.RECOVER
    if al_state & AL_ERROR:
        return Recovery.ACK_ERROR
    state = al_state & 0x0F
    if state == AL_OP:
        return Recovery.NONE
    if state == AL_SAFEOP:
        return Recovery.REQUEST_OP
    return Recovery.RECONFIGURE
