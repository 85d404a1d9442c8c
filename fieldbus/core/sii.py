"""The SII EEPROM image of an EtherCAT slave (ETG.1000.6 §5.4, ETG.2010): decode, checksum, alias, identity.

An image is the EEPROM's bytes in word order, little-endian (what SOEM's
``eepromtool`` and IgH's ``ethercat sii_read`` save). Word addresses
(16-bit words): 0x00-0x07 the ESC configuration area, which the ESC loads at
power-up (word 0 PDI control, 1 PDI configuration, 2 SYNC impulse length, 3
extended PDI configuration, 4 configured station alias -> register 0x0012, 7
low byte: CRC-8 of bytes 0-13); 0x08 vendor id, 0x0A product code, 0x0C
revision, 0x0E serial (u32 each); 0x14/0x16 bootstrap mailbox (offset, size:
receive, send); 0x18/0x1A standard mailbox; 0x1C mailbox protocols; 0x3E
EEPROM size (Kbit - 1); 0x3F SII version; from 0x40 categories: u16 type, u16
length in words, data; type 0xFFFF ends them.

The checksum: CRC-8, polynomial x^8 + x^2 + x + 1 (0x07), initial value 0xFF,
no reflection, over bytes 0-13 (words 0-6), stored in byte 14 (word 7 low
byte) - ETG.2010 (SII specification) and the Beckhoff ESC datasheet (section
II, "ESC configuration area"). An ESC that finds it wrong at power-up does not
load the area: 0x0502 bit 11 "checksum error" and bit 12 "EEPROM not loaded"
set, 0x0110 bit 0 "PDI operational" clear, the alias not taken over.
"""

from __future__ import annotations

import struct
from dataclasses import asdict, dataclass, field
from typing import Any

from fieldbus.errors import FieldbusError

WORD_ALIAS = 0x04
WORD_CHECKSUM = 0x07
WORD_VENDOR, WORD_PRODUCT, WORD_REVISION, WORD_SERIAL = 0x08, 0x0A, 0x0C, 0x0E
WORD_BOOT_MBX, WORD_STD_MBX, WORD_PROTOCOLS = 0x14, 0x18, 0x1C
WORD_SIZE, WORD_VERSION, WORD_CATEGORIES = 0x3E, 0x3F, 0x40
CONFIG_BYTES = 14  # bytes covered by the checksum
HEADER_BYTES = 2 * WORD_CATEGORIES
MAX_BYTES = 0x20000  # 1 Mbit: the largest EEPROM the address width allows here

CAT_STRINGS, CAT_DATATYPES, CAT_GENERAL, CAT_FMMU, CAT_SM = 10, 20, 30, 40, 41
CAT_FMMU_EX, CAT_SYNC_UNIT, CAT_TXPDO, CAT_RXPDO, CAT_DC, CAT_END = 42, 43, 50, 51, 60, 0xFFFF
CATEGORY_NAMES = {
    0: "nop",
    CAT_STRINGS: "strings",
    CAT_DATATYPES: "data types",
    CAT_GENERAL: "general",
    CAT_FMMU: "FMMU",
    CAT_SM: "SyncManager",
    CAT_FMMU_EX: "FMMU extended",
    CAT_SYNC_UNIT: "sync unit",
    CAT_TXPDO: "TxPDO",
    CAT_RXPDO: "RxPDO",
    CAT_DC: "distributed clock",
}
MAILBOX_PROTOCOLS = {0x01: "AoE", 0x02: "EoE", 0x04: "CoE", 0x08: "FoE", 0x10: "SoE", 0x20: "VoE"}
FMMU_USAGE = {0: "unused", 1: "outputs", 2: "inputs", 3: "mailbox state", 0xFF: "unused"}
SM_TYPES = {0: "unused", 1: "mailbox out", 2: "mailbox in", 3: "outputs", 4: "inputs"}


class SiiFormatError(FieldbusError, ValueError):
    """An SII image is malformed (where and why in the message)."""


class SiiIdentityError(FieldbusError):
    """An image's identity (vendor, product) is not the device's: writing it needs --force."""


def crc8(data: bytes) -> int:
    """CRC-8 of the ESC configuration area: polynomial 0x07, initial 0xFF, MSB first, no final XOR."""
    crc = 0xFF
    for b in data:
        crc ^= b
        for _ in range(8):
            crc = ((crc << 1) ^ 0x07) & 0xFF if crc & 0x80 else (crc << 1) & 0xFF
    return crc


def checksum_ok(image: bytes) -> bool:
    """True when word 7's low byte is the CRC-8 of bytes 0-13."""
    return len(image) >= 16 and image[14] == crc8(image[:CONFIG_BYTES])


def with_checksum(image: bytes | bytearray) -> bytes:
    """The image with word 7's low byte set to the CRC-8 of bytes 0-13 (high byte kept)."""
    _check_size(image, "image")
    out = bytearray(image)
    out[14] = crc8(bytes(out[:CONFIG_BYTES]))
    return bytes(out)


def with_alias(image: bytes | bytearray, alias: int) -> bytes:
    """The image with configured station alias ``alias`` (word 4, 0..65535) and the checksum recomputed."""
    if not 0 <= alias <= 0xFFFF:
        raise SiiFormatError(f"alias {alias} is outside 0..65535")
    out = bytearray(image)
    _check_size(out, "image")
    struct.pack_into("<H", out, 2 * WORD_ALIAS, alias)
    return with_checksum(out)


def word(image: bytes, addr: int) -> int:
    """Word ``addr`` of the image (0xFFFF past its end, as an erased EEPROM reads)."""
    b = 2 * addr
    return int.from_bytes(image[b : b + 2], "little") if b + 2 <= len(image) else 0xFFFF


def u32(image: bytes, addr: int) -> int:
    return word(image, addr) | word(image, addr + 1) << 16


def image_end(image: bytes) -> int:
    """Bytes up to and including the end marker of the categories (the image proper; the rest is erased)."""
    cats = _walk(image)
    end = cats[-1][3] if cats else HEADER_BYTES
    return min(len(image), end + 2)


def check_identity(image: bytes, vendor_id: int, product_code: int, *, force: bool = False) -> None:
    """Raise :class:`SiiIdentityError` when the image is for another device, unless ``force``."""
    iv, ip = u32(image, WORD_VENDOR), u32(image, WORD_PRODUCT)
    if force or (iv, ip) == (vendor_id, product_code):
        return
    raise SiiIdentityError(
        f"the image is for vendor 0x{iv:08X} product 0x{ip:08X}, the device is vendor 0x{vendor_id:08X} "
        f"product 0x{product_code:08X}: not written (--force writes it anyway)"
    )


def _check_size(image: bytes | bytearray, what: str) -> None:
    if len(image) < HEADER_BYTES or len(image) % 2 or len(image) > MAX_BYTES:
        raise SiiFormatError(
            f"{what}: {len(image)} bytes; an SII image is an even number of bytes, "
            f"{HEADER_BYTES}..{MAX_BYTES} (header through word 0x3F at least)"
        )


def _walk(image: bytes) -> list[tuple[int, int, int, int]]:
    """(type, data offset, data bytes, next offset) of each category; stops at the end marker or the end."""
    out = []
    off = HEADER_BYTES
    while off + 4 <= len(image):
        kind, words = struct.unpack_from("<HH", image, off)
        if kind == CAT_END:
            break
        data_end = off + 4 + 2 * words
        if data_end > len(image):
            raise SiiFormatError(
                f"category {CATEGORY_NAMES.get(kind, kind)} at word 0x{off // 2:04X} claims {words} words, "
                f"past the image's end (word 0x{len(image) // 2:04X})"
            )
        out.append((kind, off + 4, 2 * words, data_end))
        off = data_end
    return out


def strings(data: bytes) -> list[str]:
    """The strings of a STRINGS category (count, then length-prefixed latin-1 strings); stops where data ends."""
    out: list[str] = []
    if not data:
        return out
    pos = 1
    for _ in range(data[0]):
        if pos >= len(data):
            break
        n = data[pos]
        out.append(bytes(data[pos + 1 : pos + 1 + n]).decode("latin-1"))
        pos += 1 + n
    return out


@dataclass
class SiiGeneral:
    """The GENERAL category: names (from the strings), mailbox details, flags, E-bus current [mA]."""

    group: str = ""
    image: str = ""
    order: str = ""
    name: str = ""
    coe_details: int = 0
    foe_details: int = 0
    eoe_details: int = 0
    flags: int = 0
    current_on_ebus_ma: int = 0
    physical_ports: str = ""


@dataclass
class SiiSyncManager:
    index: int
    start: int
    length: int
    control: int
    enable: int
    type: str


@dataclass
class SiiPdoEntry:
    index: int
    sub_index: int
    name: str
    data_type: int
    bits: int


@dataclass
class SiiPdo:
    index: int
    sync_manager: int
    name: str
    entries: list[SiiPdoEntry] = field(default_factory=list)


@dataclass
class SiiContents:
    """A decoded image (names resolved from its strings); :func:`decode` builds it."""

    size_bytes: int
    pdi_control: int
    pdi_config: int
    alias: int
    checksum: int
    checksum_expected: int
    vendor_id: int
    product_code: int
    revision: int
    serial: int
    bootstrap_mailbox: tuple[int, int, int, int]  # receive offset, size, send offset, size
    standard_mailbox: tuple[int, int, int, int]
    mailbox_protocols: list[str]
    eeprom_kbit: int
    version: int
    strings: list[str]
    general: SiiGeneral | None
    fmmus: list[str]
    sync_managers: list[SiiSyncManager]
    tx_pdos: list[SiiPdo]  # inputs (the slave transmits)
    rx_pdos: list[SiiPdo]  # outputs
    categories: list[tuple[str, int, int]]  # (name, word address, bytes)

    @property
    def checksum_ok(self) -> bool:
        return self.checksum == self.checksum_expected

    def as_dict(self) -> dict[str, Any]:
        d = asdict(self)
        d["checksum_ok"] = self.checksum_ok
        return d


def decode(image: bytes) -> SiiContents:
    """Decode an SII image (:class:`SiiFormatError` naming the word where it is malformed)."""
    _check_size(image, "image")
    cats = _walk(image)
    first: dict[int, bytes] = {}
    for kind, off, n, _ in cats:
        first.setdefault(kind, image[off : off + n])
    text = strings(first.get(CAT_STRINGS, b""))

    def s(i: int) -> str:
        return text[i - 1] if 0 < i <= len(text) else ""

    general = None
    g = first.get(CAT_GENERAL)
    if g is not None and len(g) >= 16:
        g = g.ljust(32, b"\x00")
        ports = g[16] | g[17] << 8
        general = SiiGeneral(
            group=s(g[0]),
            image=s(g[1]),
            order=s(g[2]),
            name=s(g[3]),
            coe_details=g[5],
            foe_details=g[6],
            eoe_details=g[7],
            flags=g[11],
            current_on_ebus_ma=struct.unpack_from("<h", g, 12)[0],
            physical_ports="".join(
                {0: "-", 1: "Y", 2: "H", 3: "K", 4: "E"}.get((ports >> (4 * k)) & 0x0F, "?") for k in range(4)
            ),
        )
    return SiiContents(
        size_bytes=len(image),
        pdi_control=word(image, 0),
        pdi_config=word(image, 1),
        alias=word(image, WORD_ALIAS),
        checksum=image[14],
        checksum_expected=crc8(image[:CONFIG_BYTES]),
        vendor_id=u32(image, WORD_VENDOR),
        product_code=u32(image, WORD_PRODUCT),
        revision=u32(image, WORD_REVISION),
        serial=u32(image, WORD_SERIAL),
        bootstrap_mailbox=tuple(word(image, WORD_BOOT_MBX + k) for k in range(4)),  # type: ignore[arg-type]
        standard_mailbox=tuple(word(image, WORD_STD_MBX + k) for k in range(4)),  # type: ignore[arg-type]
        mailbox_protocols=[n for bit, n in MAILBOX_PROTOCOLS.items() if word(image, WORD_PROTOCOLS) & bit],
        eeprom_kbit=word(image, WORD_SIZE) + 1,
        version=word(image, WORD_VERSION),
        strings=text,
        general=general,
        fmmus=[FMMU_USAGE.get(b, f"usage {b}") for b in first.get(CAT_FMMU, b"")],
        sync_managers=_sync_managers(first.get(CAT_SM, b"")),
        tx_pdos=[p for kind, off, n, _ in cats if kind == CAT_TXPDO for p in _pdos(image[off : off + n], s)],
        rx_pdos=[p for kind, off, n, _ in cats if kind == CAT_RXPDO for p in _pdos(image[off : off + n], s)],
        categories=[
            (CATEGORY_NAMES.get(kind, f"type {kind}"), (off - 4) // 2, n) for kind, off, n, _ in cats
        ],
    )


def _sync_managers(data: bytes) -> list[SiiSyncManager]:
    out = []
    for k in range(len(data) // 8):
        start, length, control, _status, enable, kind = struct.unpack_from("<HHBBBB", data, 8 * k)
        out.append(SiiSyncManager(k, start, length, control, enable, SM_TYPES.get(kind, f"type {kind}")))
    return out


def _pdos(data: bytes, s: Any) -> list[SiiPdo]:
    """A TxPDO/RxPDO category: 8-byte PDO header (index, entries, SM, DC, name, flags), 8-byte entries."""
    out: list[SiiPdo] = []
    pos = 0
    while pos + 8 <= len(data):
        index, n, sm, _dc, name, _flags = struct.unpack_from("<HBBBBH", data, pos)
        pos += 8
        pdo = SiiPdo(index, sm, s(name))
        for _ in range(n):
            if pos + 8 > len(data):
                break
            eidx, esub, ename, etype, ebits, _ef = struct.unpack_from("<HBBBBH", data, pos)
            pos += 8
            pdo.entries.append(SiiPdoEntry(eidx, esub, s(ename), etype, ebits))
        out.append(pdo)
    return out


def format_text(c: SiiContents) -> str:
    """A human-readable listing of a decoded image."""
    ok = "ok" if c.checksum_ok else f"WRONG (expected 0x{c.checksum_expected:02X})"
    lines = [
        f"identity    vendor 0x{c.vendor_id:08X} product 0x{c.product_code:08X} "
        f"revision 0x{c.revision:08X} serial {c.serial}",
        f"config      PDI control 0x{c.pdi_control:04X}, alias {c.alias}, checksum 0x{c.checksum:02X} {ok}",
        f"mailbox     receive 0x{c.standard_mailbox[0]:04X}+{c.standard_mailbox[1]}, send "
        f"0x{c.standard_mailbox[2]:04X}+{c.standard_mailbox[3]}, protocols "
        f"{', '.join(c.mailbox_protocols) or '-'}",
        f"eeprom      {c.eeprom_kbit} Kbit, SII version {c.version}, {c.size_bytes} bytes",
    ]
    if c.general is not None:
        g = c.general
        lines.append(
            f"general     name '{g.name}', group '{g.group}', order '{g.order}', CoE details 0x{g.coe_details:02X}"
        )
    lines.append(f"strings     {c.strings}")
    lines.append(f"FMMUs       {', '.join(c.fmmus) or '-'}")
    for sm in c.sync_managers:
        lines.append(
            f"SM{sm.index}         0x{sm.start:04X} {sm.length} bytes, control 0x{sm.control:02X}, {sm.type}"
        )
    for what, pdos in (("TxPDO", c.tx_pdos), ("RxPDO", c.rx_pdos)):
        for p in pdos:
            lines.append(f"{what}       0x{p.index:04X} '{p.name}' (SM{p.sync_manager})")
            for e in p.entries:
                lines.append(f"              0x{e.index:04X}:{e.sub_index:02X} {e.bits:2d} bit '{e.name}'")
    lines.append("categories  " + ", ".join(f"{n}@0x{w:04X}({b} B)" for n, w, b in c.categories))
    return "\n".join(lines)
