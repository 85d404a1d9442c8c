"""CANopen emergency (EMCY) error codes and their names (CiA 301 table 21, CiA 402 additions).

An EMCY frame (COB-ID 0x80 + node id) carries a 16-bit error code, the error
register (0x1001) and 5 bytes of manufacturer data. Codes are matched exactly
first, then by their class (the high byte, then the high nibble). The drive
codes (0x603F, EMCY) follow the error-code table of CiA 402-2 / IEC 61800-7-201
(annex "Error codes"); codes a manufacturer defines (0xFF00-0xFFFF, and those
the table leaves to the manufacturer) keep their number in the name.

The pre-defined error field 0x1003 (CiA 301 7.5.2.3): sub 0 the number of
errors recorded, subs 1..n the errors, newest first, each a UNSIGNED32 whose
low 16 bits are the error code and high 16 bits manufacturer-specific
additional information (:func:`decode_error_field`).
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
# CiA 402-2 / IEC 61800-7-201 drive error codes (those not above)
DRIVE_EXACT: dict[int, str] = {
    0x2110: "short circuit / earth leakage (input)",
    0x2120: "earth leakage (input)",
    0x2130: "short circuit (input)",
    0x2211: "internal current no. 1",
    0x2212: "internal current no. 2",
    0x2213: "over-current in ramp function",
    0x2214: "over-current in the sequence",
    0x2220: "continuous over-current (device internal)",
    0x2230: "short circuit / earth leakage (device internal)",
    0x2240: "earth leakage (device internal)",
    0x2250: "short circuit (device internal)",
    0x2311: "continuous over-current no. 1",
    0x2312: "continuous over-current no. 2",
    0x2330: "earth leakage (motor side)",
    0x2331: "earth leakage phase U",
    0x2332: "earth leakage phase V",
    0x2333: "earth leakage phase W",
    0x2340: "short circuit (motor side)",
    0x2341: "short circuit phases U-V",
    0x2342: "short circuit phases V-W",
    0x2343: "short circuit phases W-U",
    0x2350: "load level fault (I2t, thermal state)",
    0x2351: "load level warning (I2t, thermal state)",
    0x3110: "mains over-voltage",
    0x3120: "mains under-voltage",
    0x3130: "phase failure",
    0x3134: "phase sequence",
    0x3140: "mains frequency",
    0x3211: "DC link over-voltage no. 1",
    0x3212: "DC link over-voltage no. 2",
    0x3221: "DC link under-voltage no. 1",
    0x3222: "DC link under-voltage no. 2",
    0x3230: "load error",
    0x3310: "output over-voltage",
    0x3320: "armature circuit",
    0x3321: "armature circuit interrupted",
    0x3330: "field circuit",
    0x3331: "field circuit interrupted",
    0x4110: "excess ambient temperature",
    0x4120: "too low ambient temperature",
    0x4220: "too low temperature device",
    0x4320: "too low temperature drive",
    0x4410: "excess temperature supply",
    0x4420: "too low temperature supply",
    0x5110: "supply low voltage",
    0x5120: "supply intermediate circuit",
    0x5210: "measurement circuit",
    0x5220: "computing circuit",
    0x5410: "output stages",
    0x5420: "chopper",
    0x5430: "input stages",
    0x5440: "contacts",
    0x5450: "fuses",
    **{0x5440 + n: f"contact {n} (manufacturer specific)" for n in range(1, 6)},
    **{
        0x5450 + n: f"fuse S{n} (L{n})" if n < 4 else f"fuse S{n} (manufacturer specific)"
        for n in range(1, 5)
    },
    0x5510: "working memory",
    0x5520: "program memory",
    0x6100: "internal software",
    0x6200: "user software",
    0x6300: "data record",
    0x6310: "loss of parameters",
    0x6320: "parameter error",
    0x7110: "brake chopper",
    0x7111: "failure brake chopper",
    0x7112: "over-current brake chopper",
    0x7113: "protective circuit brake chopper",
    0x7120: "motor",
    0x7122: "motor error or commutation malfunction",
    0x7123: "motor tilted",
    0x7301: "tacho fault",
    0x7302: "tacho wrong polarity",
    0x7303: "resolver 1 fault",
    0x7304: "resolver 2 fault",
    0x7306: "incremental sensor 2 fault",
    0x7307: "incremental sensor 3 fault",
    0x7310: "speed",
    0x7320: "position",
    0x7510: "serial interface no. 1",
    0x7520: "serial interface no. 2",
    0x8311: "excess torque",
    0x8312: "difficult start up",
    0x8313: "standstill torque",
    0x8321: "insufficient torque",
    0x8331: "torque fault",
    0xF001: "deceleration",
    0xF002: "sub-synchronous run",
    0xF003: "stroke operation",
    0xF004: "control",
}
EXACT.update({k: v for k, v in DRIVE_EXACT.items() if k not in EXACT})
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
    0x43: "drive temperature",
    0x44: "supply temperature",
    0x50: "device hardware",
    0x51: "supply",
    0x52: "control",
    0x53: "operating unit",
    0x54: "power section",
    0x55: "data storage",
    0x60: "device software",
    0x61: "internal software",
    0x62: "user software",
    0x63: "data record",
    0x70: "additional modules",
    0x71: "power",
    0x72: "measurement circuit",
    0x73: "sensor",
    0x74: "computation circuit",
    0x75: "communication",
    0x76: "data storage",
    0x80: "monitoring",
    0x81: "communication",
    0x82: "protocol error",
    0x83: "torque control",
    0x84: "velocity / speed controller",
    0x85: "position controller",
    0x86: "positioning controller",
    0x87: "sync controller",
    0x88: "winding controller",
    0x89: "process data monitoring",
    0x8A: "control",
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


@dataclass(frozen=True)
class ErrorEntry:
    """One recorded error of a diagnosis history: its code, the name of the code, additional info."""

    code: int
    info: int = 0  # 0x1003: the high 16 bits, manufacturer specific

    @property
    def name(self) -> str:
        return emcy_name(self.code)

    def __str__(self) -> str:
        extra = f" (info 0x{self.info:04X})" if self.info else ""
        return f"0x{self.code:04X} {self.name}{extra}"


def decode_error_field(raw: bytes) -> ErrorEntry:
    """One 0x1003 sub-index (UNSIGNED32, little-endian): error code in the low 16 bits, info above."""
    value = int.from_bytes(bytes(raw[:4]).ljust(4, b"\0"), "little")
    return ErrorEntry(value & 0xFFFF, value >> 16)
