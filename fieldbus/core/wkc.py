"""Working-counter / timeout policy, shared by every backend (pure).

The expected working counter and the recovery decision. The per-cycle verdict
and the safe-stop latch are in :mod:`fieldbus.core.safety` (re-exported here).

Expected WKC of an LRW (ETG.1000.4; SOEM ``expectedWKC``): every slave with
outputs adds 2 (write), every slave with inputs adds 1 (read).
"""

from __future__ import annotations

import enum
from collections.abc import Sequence

from fieldbus.core.al import AL_BOOT, AL_ERROR, AL_INIT, AL_OP, AL_PREOP, AL_SAFEOP
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
    "answered_slaves",
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


AL_UNREAD = -1
"""A slave's AL status not read since the recovery began (see :func:`answered_slaves`)."""


def wkc_weights(layouts: list[MapLayout]) -> list[int]:
    """Per slave, what it adds to an LRW's working counter in OP: 2 with outputs, 1 with inputs."""
    return [(2 if lay.outputs.bits else 0) + (1 if lay.inputs.bits else 0) for lay in layouts]


def answered_slaves(
    wkc: int | None, weights: Sequence[int], al_status: Sequence[int | None]
) -> list[bool] | None:
    """Which slaves processed a short LRW, when the recovery's AL readings can tell; else None.

    ``al_status``: per slave, the AL status the recovery read last in its
    present run (None: no answer at its address; :data:`AL_UNREAD`: not read
    yet). The working counter alone names no slave; so the rule is: every
    slave was read, each is either in OP without the error flag (it processes
    the LRW and adds its weight) or in INIT, PRE-OP or BOOT or gone (its
    FMMUs are off: it adds nothing), and the counter is exactly the sum of
    the OP slaves' weights. Then those answered and the others did not. A
    slave in SAFE-OP (which may add its read but not its write), one in OP
    with an error, an unread one, or any other counter: None (cannot tell).
    """
    if wkc is None or wkc < 0 or len(weights) != len(al_status):
        return None
    in_op: list[bool] = []
    for st in al_status:
        if st is None:  # gone from its address (power-cycled): adds nothing
            in_op.append(False)
        elif st == AL_UNREAD:
            return None
        elif st & 0x0F == AL_OP and not st & AL_ERROR:
            in_op.append(True)
        elif st & 0x0F in (AL_INIT, AL_PREOP, AL_BOOT):
            in_op.append(False)
        else:  # SAFE-OP, or OP with an error: what it adds is not known
            return None
    if wkc != sum(w for w, ok in zip(weights, in_op, strict=True) if ok):
        return None
    return in_op


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
