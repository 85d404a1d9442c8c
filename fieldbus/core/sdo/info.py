"""CoE SDO Information service (ETG.1000.6 §5.6.3): message layout, requests and answers. Pure.

Every SDO Information message (CoE service 8) starts with a 6-byte header:
u16 CoE header, u8 opcode (bit 7: more fragments follow), u8 reserved, u16
fragments left. Then, per opcode:

- Get OD List (1 -> 2): u16 list type (0 counts, 1 all, 2 RxPDO-mappable,
  3 TxPDO-mappable, 4 backup, 5 settings); the answer repeats it and lists
  u16 indices (counts for type 0);
- Get Object Description (3 -> 4): u16 index; answer u16 index, u16 data
  type, u8 max sub-index, u8 object code, name;
- Get Entry Description (5 -> 6): u16 index, u8 sub-index, u8 value info;
  answer u16 index, u8 sub-index, u8 value info, u16 data type, u16 bit
  length, u16 object access, name;
- SDO Info Error (7): u32 abort code.

An answer longer than the slave's mailbox is cut into fragments, each with
the header; the data of all fragments joined is the answer.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass
from enum import IntEnum

from fieldbus.errors import SdoAbortError

COE_SERVICE_SDO_INFO = 8
HEADER = struct.Struct("<HBBH")  # CoE header, opcode, reserved, fragments left
MORE_FOLLOWS = 0x80


class InfoOpcode(IntEnum):
    OD_LIST_REQ = 1
    OD_LIST_RES = 2
    OD_REQ = 3
    OD_RES = 4
    OE_REQ = 5
    OE_RES = 6
    ERROR = 7


class ListType(IntEnum):
    COUNTS = 0
    ALL = 1
    RXPDO = 2
    TXPDO = 3
    BACKUP = 4
    SETTINGS = 5


# Object access bits of an entry description.
ACCESS_READ_PREOP, ACCESS_READ_SAFEOP, ACCESS_READ_OP = 0x01, 0x02, 0x04
ACCESS_WRITE_PREOP, ACCESS_WRITE_SAFEOP, ACCESS_WRITE_OP = 0x08, 0x10, 0x20
ACCESS_RXPDO, ACCESS_TXPDO = 0x40, 0x80
ACCESS_READ = ACCESS_READ_PREOP | ACCESS_READ_SAFEOP | ACCESS_READ_OP
ACCESS_WRITE = ACCESS_WRITE_PREOP | ACCESS_WRITE_SAFEOP | ACCESS_WRITE_OP

OBJECT_CODES = {7: "VAR", 8: "ARRAY", 9: "RECORD"}

# CoE data type codes -> this project's type names (strings and structures by their CiA 301 names).
TYPE_NAMES: dict[int, str] = {
    0x0001: "bool",
    0x0002: "int8",
    0x0003: "int16",
    0x0004: "int32",
    0x0005: "uint8",
    0x0006: "uint16",
    0x0007: "uint32",
    0x0008: "float",
    0x0009: "string",
    0x000A: "octets",
    0x000B: "unicode",
    0x000F: "domain",
    0x0011: "double",
    0x0015: "int64",
    0x001B: "uint64",
    0x0021: "PDO_MAPPING",
    0x0023: "IDENTITY",
    **{0x002F + n: f"bit{n}" for n in range(1, 9)},
}


def type_name(code: int) -> str:
    """The type name of CoE data type ``code`` (``0x....`` when not known)."""
    return TYPE_NAMES.get(code, f"0x{code:04X}")


def access_text(access: int) -> str:
    """``rw``, ``ro``, ``wo`` or per-state detail such as ``rw(pre-op)``, plus ``,rxpdo``/``,txpdo``."""
    r, w = access & ACCESS_READ, access & ACCESS_WRITE
    if w == ACCESS_WRITE and r:
        text = "rw"
    elif w == ACCESS_WRITE_PREOP and r:
        text = "rw(pre-op)"
    elif w and r:
        text = "rw(some states)"
    elif w:
        text = "wo"
    else:
        text = "ro"
    if access & ACCESS_RXPDO:
        text += ",rxpdo"
    if access & ACCESS_TXPDO:
        text += ",txpdo"
    return text


@dataclass(frozen=True)
class ObjectDescription:
    index: int
    data_type: int
    max_sub: int
    object_code: int
    name: str


@dataclass(frozen=True)
class EntryDescription:
    index: int
    sub_index: int
    value_info: int
    data_type: int
    bit_length: int
    access: int
    name: str


def header(opcode: int, fragments_left: int = 0) -> bytes:
    return HEADER.pack(COE_SERVICE_SDO_INFO << 12, opcode, 0, fragments_left)


def od_list_request(list_type: int = ListType.ALL) -> bytes:
    return header(InfoOpcode.OD_LIST_REQ) + struct.pack("<H", list_type)


def od_request(index: int) -> bytes:
    return header(InfoOpcode.OD_REQ) + struct.pack("<H", index)


def oe_request(index: int, sub: int, value_info: int = 0x07) -> bytes:
    return header(InfoOpcode.OE_REQ) + struct.pack("<HBB", index, sub, value_info)


def fragments(opcode: int, data: bytes, room: int) -> list[bytes]:
    """``data`` as answer payloads of at most ``room`` bytes each (header included)."""
    step = room - HEADER.size
    if step <= 0:
        raise ValueError(f"a {room}-byte mailbox holds no SDO Information data")
    chunks = [data[i : i + step] for i in range(0, len(data), step)] or [b""]
    n = len(chunks)
    return [header(opcode | (MORE_FOLLOWS if k < n - 1 else 0), n - 1 - k) + c for k, c in enumerate(chunks)]


def error_payload(code: int) -> bytes:
    return header(InfoOpcode.ERROR) + struct.pack("<I", code)


class Reassembly:
    """Collects the fragments of one answer: :meth:`add` each CoE payload until it returns the data."""

    def __init__(self, expect: int, index: int = 0, sub_index: int = 0) -> None:
        self.expect = expect
        self.index = index
        self.sub_index = sub_index
        self.data = bytearray()

    def add(self, coe: bytes) -> bytes | None:
        """The joined data once the last fragment is in, else None; aborts raise SdoAbortError."""
        if len(coe) < HEADER.size or coe[1] >> 4 != COE_SERVICE_SDO_INFO:
            raise SdoAbortError(
                0x05040001, index=self.index, sub_index=self.sub_index, detail="not an SDO Information answer"
            )
        _, opcode, _, left = HEADER.unpack_from(coe)
        if opcode & 0x7F == InfoOpcode.ERROR:
            (code,) = struct.unpack_from("<I", coe, HEADER.size)
            raise SdoAbortError(code, index=self.index, sub_index=self.sub_index, detail="SDO Information")
        if opcode & 0x7F != self.expect:
            raise SdoAbortError(
                0x05040001,
                index=self.index,
                sub_index=self.sub_index,
                detail=f"SDO Information opcode {opcode}",
            )
        self.data += coe[HEADER.size :]
        return bytes(self.data) if not opcode & MORE_FOLLOWS and left == 0 else None


def parse_od_list(data: bytes) -> tuple[int, list[int]]:
    """(list type, indices) of a joined Get OD List answer."""
    (list_type,) = struct.unpack_from("<H", data)
    n = (len(data) - 2) // 2
    return list_type, list(struct.unpack_from(f"<{n}H", data, 2))


def parse_od(data: bytes) -> ObjectDescription:
    index, dtype, max_sub, code = struct.unpack_from("<HHBB", data)
    return ObjectDescription(index, dtype, max_sub, code, _text(data[6:]))


def parse_oe(data: bytes) -> EntryDescription:
    index, sub, vinfo, dtype, bits, access = struct.unpack_from("<HBBHHH", data)
    return EntryDescription(index, sub, vinfo, dtype, bits, access, _text(data[10:]))


def _text(raw: bytes) -> str:
    return raw.split(b"\0", 1)[0].decode("latin-1")
