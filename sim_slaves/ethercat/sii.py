"""SII EEPROM image (ETG.1000.6 §5.4, ETG.2010): built from a drive map, or loaded raw.

Word addresses (16-bit words):
0x00-0x07 ESC configuration area (word 7 low byte: CRC-8 of bytes 0-13),
0x08 vendor id, 0x0A product code, 0x0C revision, 0x0E serial (u32 each),
0x14-0x17 bootstrap mailbox, 0x18/0x19 standard receive mailbox (master ->
slave, SM0) offset/size, 0x1A/0x1B send mailbox (slave -> master, SM1),
0x1C mailbox protocols (0x0004 CoE), 0x3E EEPROM size (Kbit - 1), 0x3F version,
from 0x40 categories: u16 type, u16 length in words, data; 0xFFFF ends.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass

from fieldbus.core.pdo.layout import layout
from fieldbus.core.pdo.model import DriveMap, Pdo
from fieldbus.core.sii import crc8
from fieldbus.errors import FieldbusError
from fieldbus.wire.framemaster import sii_strings

CAT_STRINGS = 10
CAT_GENERAL = 30
CAT_FMMU = 40
CAT_SM = 41
CAT_TXPDO = 50  # inputs (drive transmits)
CAT_RXPDO = 51  # outputs (drive receives)
CAT_END = 0xFFFF

MBX_PROTO_COE = 0x0004
MBX_PROTO_FOE = 0x0008
BOOT_MBX_SIZE = 0x200  # bytes of each bootstrap mailbox (SM0 and SM1 in BOOTSTRAP), from MBX_OUT_START
COE_DETAILS = 0x01 | 0x02 | 0x04 | 0x08  # SDO, SDO info, PDO assign, PDO configuration (no complete access)

# SyncManager defaults: physical start, control byte (ESC register 0x0804+8n), SII type.
MBX_OUT_START = 0x1000  # SM0: master -> slave mailbox
PD_OUT_START = 0x1400  # SM2: outputs (RxPDO)
PD_IN_START = 0x1C00  # SM3: inputs (TxPDO)
SM_CTRL_MBX_OUT = 0x26  # mailbox, ECAT writes, PDI IRQ
SM_CTRL_MBX_IN = 0x22  # mailbox, ECAT reads, PDI IRQ
SM_CTRL_PD_OUT = 0x64  # buffered, ECAT writes, PDI IRQ, watchdog
SM_CTRL_PD_IN = 0x20  # buffered, ECAT reads, PDI IRQ
SM_TYPE_MBX_OUT, SM_TYPE_MBX_IN, SM_TYPE_OUTPUTS, SM_TYPE_INPUTS = 1, 2, 3, 4


class SiiError(FieldbusError, ValueError):
    """An SII image is malformed or cannot hold what it should."""


@dataclass(frozen=True)
class SiiSyncManager:
    """One SM as the SII SM category describes it (bytes, ESC register codes)."""

    start: int
    length: int
    control: int
    enable: int
    type: int


class SiiImage:
    """An SII EEPROM image with parsed identity, mailbox and SM information."""

    def __init__(self, data: bytes | bytearray) -> None:
        if len(data) < 0x82 or len(data) % 2:
            raise SiiError(f"SII image of {len(data)} bytes is too short or odd")
        self.data = bytearray(data)
        self.sms = self._parse_sms()

    def word(self, addr: int) -> int:
        """16-bit word at word address ``addr`` (0xFFFF past the end, like an erased EEPROM)."""
        b = addr * 2
        if b + 2 > len(self.data):
            return 0xFFFF
        return int(self.data[b] | self.data[b + 1] << 8)

    def read(self, addr: int, nbytes: int) -> bytes:
        """``nbytes`` from word address ``addr`` (erased 0xFF past the end)."""
        b = addr * 2
        chunk = bytes(self.data[b : b + nbytes])
        return chunk + b"\xff" * (nbytes - len(chunk))

    def write_word(self, addr: int, value: int) -> None:
        b = addr * 2
        if b + 2 <= len(self.data):
            self.data[b : b + 2] = (value & 0xFFFF).to_bytes(2, "little")

    def _u32(self, addr: int) -> int:
        return self.word(addr) | self.word(addr + 1) << 16

    @property
    def vendor_id(self) -> int:
        return self._u32(0x08)

    @property
    def product_code(self) -> int:
        return self._u32(0x0A)

    @property
    def revision(self) -> int:
        return self._u32(0x0C)

    @property
    def serial(self) -> int:
        return self._u32(0x0E)

    @property
    def mailbox_out(self) -> tuple[int, int]:
        """(offset, size) of the master -> slave mailbox (SM0)."""
        return self.word(0x18), self.word(0x19)

    @property
    def mailbox_in(self) -> tuple[int, int]:
        """(offset, size) of the slave -> master mailbox (SM1)."""
        return self.word(0x1A), self.word(0x1B)

    @property
    def boot_mailbox_out(self) -> tuple[int, int]:
        """(offset, size) of the bootstrap receive mailbox (master -> slave, SM0 in BOOTSTRAP; words 0x14/0x15)."""
        return self.word(0x14), self.word(0x15)

    @property
    def boot_mailbox_in(self) -> tuple[int, int]:
        """(offset, size) of the bootstrap send mailbox (slave -> master, SM1 in BOOTSTRAP; words 0x16/0x17)."""
        return self.word(0x16), self.word(0x17)

    @property
    def protocols(self) -> int:
        return self.word(0x1C)

    def categories(self) -> dict[int, bytes]:
        """Category type -> data bytes (first occurrence), walking from word 0x40."""
        out: dict[int, bytes] = {}
        addr = 0x40
        while addr * 2 + 4 <= len(self.data):
            kind = self.word(addr)
            if kind == CAT_END:
                break
            words = self.word(addr + 1)
            out.setdefault(kind, self.read(addr + 2, words * 2))
            addr += 2 + words
        return out

    def strings(self) -> list[str]:
        return sii_strings(self.categories().get(CAT_STRINGS, b""))

    @property
    def name(self) -> str:
        """String 1, which SOEM shows as the slave name."""
        s = self.strings()
        return s[0] if s else ""

    def _parse_sms(self) -> tuple[SiiSyncManager, ...]:
        data = self.categories().get(CAT_SM, b"")
        out = []
        for o in range(0, len(data) - 7, 8):
            start, length, control, _status, enable, kind = struct.unpack_from("<HHBBBB", data, o)
            out.append(SiiSyncManager(start, length, control, enable, kind))
        return tuple(out)


def build_sii(drive: DriveMap, *, alias: int = 0) -> SiiImage:
    """The SII image of an emulated slave for ``drive``: identity, mailbox, categories.

    Strings: 1 = ``drive.name`` (SOEM's slave name), 2 = the group "Drive".
    SM2 (outputs) and SM3 (inputs) carry the sizes of the map's RxPDOs and
    TxPDOs; the RxPDO / TxPDO categories list them (for masters without CoE).
    """
    lay = layout(drive)
    mbx = drive.ethercat.mailbox_size if drive.ethercat.coe else 0
    if mbx and MBX_OUT_START + 2 * mbx > PD_OUT_START:
        raise SiiError(f"mailbox of {mbx} bytes does not fit below 0x{PD_OUT_START:04X}")
    if lay.outputs.size > PD_IN_START - PD_OUT_START:
        raise SiiError(f"{lay.outputs.size} output bytes do not fit the emulated process RAM")
    mbx_out = MBX_OUT_START if mbx else 0
    mbx_in = MBX_OUT_START + mbx if mbx else 0
    head = bytearray(0x80)
    struct.pack_into("<HHHH", head, 0, 0x0005, 0x0000, 0x0000, 0x0000)  # PDI control (SPI), config
    struct.pack_into("<H", head, 8, alias)
    head[14] = crc8(bytes(head[:14]))
    revision = drive.revision or drive.ethercat.revision
    struct.pack_into("<IIII", head, 0x10, drive.vendor_id, drive.product_id, revision, drive.ethercat.serial)
    if mbx:  # bootstrap mailbox (FoE), in the same RAM as the standard one: never both in use
        struct.pack_into(
            "<HHHH", head, 0x28, MBX_OUT_START, BOOT_MBX_SIZE, MBX_OUT_START + BOOT_MBX_SIZE, BOOT_MBX_SIZE
        )
    struct.pack_into("<HHHH", head, 0x30, mbx_out, mbx, mbx_in, mbx)
    struct.pack_into("<H", head, 0x38, MBX_PROTO_COE | MBX_PROTO_FOE if mbx else 0)
    struct.pack_into("<HH", head, 0x7C, 0x000F, 0x0001)  # 16 Kbit, SII version 1

    strings = [drive.name[:255], "Drive"]
    cats = bytearray()
    cats += _category(CAT_STRINGS, bytes([len(strings)]) + b"".join(_pstr(s) for s in strings))
    general = bytearray(32)
    general[0] = 2  # group: string 2
    general[3] = 1  # name: string 1
    general[5] = COE_DETAILS if mbx else 0
    general[9] = 1 if drive.profile == "cia402" else 0  # DS402 channels
    general[11] = 0 if drive.ethercat.lrw else 0x02  # flags bit 1: LRW not supported
    cats += _category(CAT_GENERAL, bytes(general))
    cats += _category(CAT_FMMU, bytes([1, 2, 3, 0xFF]))  # outputs, inputs, mailbox state, unused
    sm = bytearray()
    if mbx:
        sm += struct.pack("<HHBBBB", mbx_out, mbx, SM_CTRL_MBX_OUT, 0, 1, SM_TYPE_MBX_OUT)
        sm += struct.pack("<HHBBBB", mbx_in, mbx, SM_CTRL_MBX_IN, 0, 1, SM_TYPE_MBX_IN)
    else:
        sm += struct.pack("<HHBBBB", 0, 0, 0, 0, 0, 0) * 2
    sm += struct.pack("<HHBBBB", PD_OUT_START, lay.outputs.size, SM_CTRL_PD_OUT, 0, 1, SM_TYPE_OUTPUTS)
    sm += struct.pack("<HHBBBB", PD_IN_START, lay.inputs.size, SM_CTRL_PD_IN, 0, 1, SM_TYPE_INPUTS)
    cats += _category(CAT_SM, bytes(sm))
    if drive.tpdo:  # SOEM reads at least one PDO from a present category: leave empty ones out
        cats += _category(CAT_TXPDO, _pdo_category(drive.tpdo, sm_index=3))
    if drive.rpdo:
        cats += _category(CAT_RXPDO, _pdo_category(drive.rpdo, sm_index=2))
    cats += struct.pack("<H", CAT_END)
    image = bytes(head) + bytes(cats)
    image += b"\xff" * (-len(image) % 8 + 8)
    return SiiImage(image)


def _pstr(s: str) -> bytes:
    raw = s.encode("latin-1", "replace")[:255]
    return bytes([len(raw)]) + raw


def _category(kind: int, data: bytes) -> bytes:
    if len(data) % 2:
        data += b"\x00"
    return struct.pack("<HH", kind, len(data) // 2) + data


def _pdo_category(pdos: tuple[Pdo, ...], *, sm_index: int) -> bytes:
    out = bytearray()
    for pdo in pdos:
        out += struct.pack("<HBBBBH", pdo.index, len(pdo.channels), sm_index, 0, 0, 0)
        for ch in pdo.channels:
            code = ch.type.coe_code
            out += struct.pack("<HBBBBH", ch.index, ch.sub_index, 0, code, ch.bits, 0)
    return bytes(out)
