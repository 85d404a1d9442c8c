"""CANopen emergency (EMCY) error codes and their names (CiA 301 table 21, CiA 402 additions).

An EMCY frame (COB-ID 0x80 + node id) carries a 16-bit error code, the error
register (0x1001) and 5 bytes of manufacturer data. Codes are matched exactly
first, then by their class (the high byte, then the high nibble).
"""

from __future__ import annotations

import struct
from dataclasses import dataclass

EXACT: dict[int, str] = {
    0x0000: "error reset or no error",
    0x1000: "generic error",
    0x2310: "continuous over-current",
    0x2320: "short circuit / earth leakage",
    0x3210: "DC link over-voltage",
    0x3220: "DC link under-voltage",
    0x4210: "excess temperature device",
    0x4310: "excess temperature drive",
    0x5530: "EEPROM / data storage error",
    0x6010: "software reset (watchdog)",
    0x7121: "motor blocked",
    0x7300: "sensor error",
    0x7305: "incremental sensor 1 fault",
    0x8110: "CAN overrun (objects lost)",
    0x8120: "CAN in error passive mode",
    0x8130: "life guard or heartbeat error",
    0x8140: "recovered from bus off",
    0x8141: "bus off",
    0x8150: "CAN-ID collision",
    0x8210: "PDO not processed due to length error",
    0x8220: "PDO length exceeded",
    0x8250: "RPDO timeout",
    0x8611: "following error",
    0x8612: "reference limit",
    0xFF00: "device specific",
}
CLASSES: dict[int, str] = {
    0x10: "generic error",
    0x20: "current",
    0x21: "current, device input side",
    0x22: "current inside the device",
    0x23: "current, device output side",
    0x30: "voltage",
    0x31: "mains voltage",
    0x32: "voltage inside the device",
    0x33: "output voltage",
    0x40: "temperature",
    0x41: "ambient temperature",
    0x42: "device temperature",
    0x50: "device hardware",
    0x60: "device software",
    0x70: "additional modules",
    0x80: "monitoring",
    0x81: "communication",
    0x82: "protocol error",
    0x84: "velocity / speed controller",
    0x86: "positioning controller",
    0x90: "external error",
    0xF0: "additional functions",
    0xFF: "device specific",
}


def emcy_name(code: int) -> str:
    """Name of EMCY error code ``code`` (exact, else its class, else 'unknown')."""
    if code in EXACT:
        return EXACT[code]
    for key in (code >> 8, (code >> 12) << 4):
        if key in CLASSES:
            return f"{CLASSES[key]} (0x{code:04X})"
    return f"unknown (0x{code:04X})"


@dataclass(frozen=True)
class Emergency:
    """One EMCY received: node, error code and its name, error register, manufacturer data, time (s)."""

    node_id: int
    code: int
    register: int
    data: bytes
    time_s: float

    @property
    def name(self) -> str:
        return emcy_name(self.code)

    @classmethod
    def decode(cls, node_id: int, payload: bytes, time_s: float) -> Emergency:
        code, register = struct.unpack_from("<HB", payload.ljust(3, b"\0"))
        return cls(node_id, code, register, bytes(payload[3:8]), time_s)

    def __str__(self) -> str:
        return f"node {self.node_id}: EMCY 0x{self.code:04X} {self.name} (register 0x{self.register:02X})"
