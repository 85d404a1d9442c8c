"""Working-counter / timeout policy, shared by every backend (pure).

The expected working counter and the recovery decision. The per-cycle verdict
and the safe-stop latch are in :mod:`fieldbus.core.safety` (re-exported here).

Expected WKC of an LRW (ETG.1000.4; SOEM ``expectedWKC``): every slave with
outputs adds 2 (write), every slave with inputs adds 1 (read).
"""

from __future__ import annotations

import enum

from fieldbus.core.al import AL_ERROR, AL_OP, AL_SAFEOP
from fieldbus.core.pdo.layout import MapLayout
from fieldbus.core.safety import PolicyConfig, PolicyStats, SafetyPolicy, Verdict

WkcPolicy = SafetyPolicy  # the policy's earlier name; it lives in fieldbus.core.safety

__all__ = [
    "PolicyConfig",
    "PolicyStats",
    "Recovery",
    "SafetyPolicy",
    "Verdict",
    "WkcPolicy",
    "expected_wkc",
    "recovery_action",
]


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
