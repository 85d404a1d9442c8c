"""EtherCAT application layer (AL): states and status codes, for the masters and the emulator alike.

The master requests a state in AL control (register 0x0120: state in bits 0-3,
bit 4 acknowledges an error); the slave answers in AL status (0x0130: state in
bits 0-3, bit 4 = error indicator) and the AL status code (0x0134). States
and codes are ETG.1000.6 §6.4 and table 11.
"""

from __future__ import annotations

from enum import IntEnum


class AlState(IntEnum):
    """AL states as coded in AL control / AL status bits 0-3."""

    INIT = 0x1
    PRE_OP = 0x2
    BOOT = 0x3
    SAFE_OP = 0x4
    OP = 0x8


AL_INIT, AL_PREOP, AL_BOOT, AL_SAFEOP, AL_OP = (int(s) for s in AlState)
AL_ERROR = 0x10  # AL status bit 4: error indicator
AL_ACK = 0x10  # AL control bit 4: acknowledge the error indicator
STATE_NAMES: dict[int, str] = {
    AlState.INIT: "INIT",
    AlState.PRE_OP: "PRE-OP",
    AlState.BOOT: "BOOT",
    AlState.SAFE_OP: "SAFE-OP",
    AlState.OP: "OP",
}


def state_name(state: int) -> str:
    """AL status (state bits plus the error bit) as text, e.g. ``SAFE-OP+ERROR``; unknown: ``0x5``."""
    base = STATE_NAMES.get(state & 0x0F, f"0x{state & 0x0F:X}")
    return base + ("+ERROR" if state & AL_ERROR else "")


class AlStatusCode(IntEnum):
    """AL status codes (register 0x0134) the emulator reports."""

    NO_ERROR = 0x0000
    UNSPECIFIED = 0x0001
    INVALID_STATE_CHANGE = 0x0011
    UNKNOWN_STATE = 0x0012
    BOOTSTRAP_NOT_SUPPORTED = 0x0013
    NO_VALID_FIRMWARE = 0x0014
    INVALID_BOOT_MAILBOX_CONFIG = 0x0015
    INVALID_MAILBOX_CONFIG = 0x0016
    SYNC_MANAGER_WATCHDOG = 0x001B
    INVALID_OUTPUT_CONFIG = 0x001D
    INVALID_INPUT_CONFIG = 0x001E


AL_STATUS_CODES: dict[int, str] = {
    0x0000: "no error",
    0x0001: "unspecified error",
    0x0002: "no memory",
    0x0011: "invalid requested state change",
    0x0012: "unknown requested state",
    0x0013: "bootstrap not supported",
    0x0014: "no valid firmware",
    0x0015: "invalid mailbox configuration (BOOT)",
    0x0016: "invalid mailbox configuration (PRE-OP)",
    0x0017: "invalid sync manager configuration",
    0x0018: "no valid inputs available",
    0x0019: "no valid outputs",
    0x001A: "synchronization error",
    0x001B: "sync manager watchdog",
    0x001C: "invalid sync manager types",
    0x001D: "invalid output configuration",
    0x001E: "invalid input configuration",
    0x001F: "invalid watchdog configuration",
    0x0020: "slave needs cold start",
    0x0021: "slave needs INIT",
    0x0022: "slave needs PRE-OP",
    0x0023: "slave needs SAFE-OP",
    0x0024: "invalid input mapping",
    0x0025: "invalid output mapping",
    0x0026: "inconsistent settings",
    0x0027: "free run not supported",
    0x0028: "sync mode not supported",
    0x0029: "free run needs 3-buffer mode",
    0x002A: "background watchdog",
    0x002B: "no valid inputs and outputs",
    0x002C: "fatal sync error",
    0x002D: "no sync error",
    0x0030: "invalid DC SYNC configuration",
    0x0031: "invalid DC latch configuration",
    0x0032: "PLL error",
    0x0033: "DC sync IO error",
    0x0034: "DC sync timeout",
    0x0035: "DC invalid sync cycle time",
    0x0036: "DC invalid SYNC0 cycle time",
    0x0037: "DC invalid SYNC1 cycle time",
    0x0041: "mailbox AoE",
    0x0042: "mailbox EoE",
    0x0043: "mailbox CoE",
    0x0044: "mailbox FoE",
    0x0045: "mailbox SoE",
    0x004F: "mailbox VoE",
    0x0050: "EEPROM no access",
    0x0051: "EEPROM error",
    0x0060: "slave restarted locally",
    0x0061: "device identification value updated",
}


def al_status_name(code: int) -> str:
    """The name of an AL status code (``unknown AL status code`` when not in the table)."""
    return AL_STATUS_CODES.get(code, "unknown AL status code")
