"""EtherCAT application-layer (AL) state machine as one table (ETG.1000.6 §6.4).

The master requests a state in AL control (0x0120: state bits 0-3, bit 4 =
error acknowledge); the slave answers in AL status (0x0130: state bits 0-3,
bit 4 = error indicator) and AL status code (0x0134).
"""

from __future__ import annotations

from enum import Enum

from fieldbus.core.al import AL_ERROR as AL_ERROR_INDICATOR  # AL status bit 4; in AL control: acknowledge
from fieldbus.core.al import AlState, AlStatusCode

__all__ = ["AL_ERROR_INDICATOR", "TRANSITIONS", "AlState", "AlStatusCode", "Check"]


class Check(Enum):
    """What the slave verifies before it takes a transition."""

    NONE = "none"
    MAILBOX = "mailbox"  # SM0/SM1 match the SII mailbox configuration (else 0x0016)
    BOOT_MAILBOX = "boot_mailbox"  # SM0/SM1 match the SII bootstrap mailbox (words 0x14-0x17; else 0x0016)
    PROCESS_DATA = "process_data"  # SM2/SM3 and FMMUs match the mapped PDOs (else 0x001D / 0x001E)


_I, _P, _B, _S, _O = AlState.INIT, AlState.PRE_OP, AlState.BOOT, AlState.SAFE_OP, AlState.OP

TRANSITIONS: dict[tuple[AlState, AlState], Check] = {
    (_I, _P): Check.MAILBOX,  # IP
    (_I, _B): Check.BOOT_MAILBOX,  # IB
    (_B, _I): Check.NONE,  # BI
    (_P, _S): Check.PROCESS_DATA,  # PS
    (_P, _I): Check.NONE,  # PI
    (_S, _O): Check.NONE,  # SO
    (_S, _P): Check.NONE,  # SP
    (_S, _I): Check.NONE,  # SI
    (_O, _S): Check.NONE,  # OS
    (_O, _P): Check.NONE,  # OP
    (_O, _I): Check.NONE,  # OI
}
"""Allowed transitions (from, to) and the check each needs. Any other change: 0x0011."""
