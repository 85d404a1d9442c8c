"""Bit-exact layout of a drive map's process data, per direction.

Offsets are in bits from the start of one slave's image in one direction.
On EtherCAT (CoE) the PDOs of a direction follow each other bit by bit
(``pdo_align=1``, as SOEM sums the entries' bit lengths); on CANopen each PDO
is its own frame and starts on a byte (``pdo_align=8``).

The scalar :func:`get_value` / :func:`set_value` are the reference codec for
one entry of one slave (used by emulators and as the oracle in tests); the
vectorised process image is in :mod:`fieldbus.core.pdo.image`.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass

from fieldbus.core.pdo.model import Channel, Direction, DriveMap
from fieldbus.errors import FieldbusError


@dataclass(frozen=True)
class EntryLayout:
    """Where one PDO entry sits: ``bit_offset`` from the start of the direction image."""

    channel: Channel
    pdo_index: int
    bit_offset: int

    @property
    def name(self) -> str:
        return self.channel.name

    @property
    def bits(self) -> int:
        return self.channel.bits

    @property
    def byte_offset(self) -> int:
        """First byte touched by this entry."""
        return self.bit_offset // 8

    @property
    def shift(self) -> int:
        """Bit position of the entry's least significant bit inside its first byte."""
        return self.bit_offset % 8

    @property
    def aligned(self) -> bool:
        """Starts on a byte and fills whole bytes with a numeric type (no bit handling)."""
        return self.shift == 0 and not self.channel.type.is_bits and self.bits % 8 == 0

    @property
    def span_bytes(self) -> int:
        """Number of bytes the entry touches."""
        return (self.shift + self.bits + 7) // 8


@dataclass(frozen=True)
class PdoPlacement:
    """Where one PDO sits in the direction image (bits)."""

    index: int
    bit_offset: int
    bits: int

    @property
    def byte_offset(self) -> int:
        return self.bit_offset // 8

    @property
    def size(self) -> int:
        return (self.bits + 7) // 8


@dataclass(frozen=True)
class DirectionLayout:
    """Layout of one direction (outputs = RxPDOs, inputs = TxPDOs) of one slave."""

    direction: Direction
    entries: tuple[EntryLayout, ...]  # wire order, gaps included
    pdos: tuple[PdoPlacement, ...]
    bits: int

    @property
    def size(self) -> int:
        """Bytes of one slave's image in this direction."""
        return (self.bits + 7) // 8

    @property
    def channels(self) -> tuple[EntryLayout, ...]:
        """Entries that carry data (gaps left out)."""
        return tuple(e for e in self.entries if not e.channel.is_gap)

    @property
    def names(self) -> tuple[str, ...]:
        return tuple(e.name for e in self.channels)

    def entry(self, name: str) -> EntryLayout:
        for e in self.entries:
            if not e.channel.is_gap and e.name == name:
                return e
        raise FieldbusError(
            f"no {self.direction.value} channel '{name}' (have: {', '.join(self.names) or 'none'})"
        )

    def find(self, index: int, sub_index: int = 0) -> EntryLayout | None:
        """The entry mapping object ``index:sub_index``, if any."""
        for e in self.channels:
            if e.channel.index == index and e.channel.sub_index == sub_index:
                return e
        return None

    def channel_for(self, index: int | None, name: str) -> str | None:
        """The channel mapping object ``index`` (CiA 402), else the channel called ``name``, else None."""
        if index is not None:
            e = self.find(index)
            if e is not None:
                return e.name
        return name if name in self.names else None


@dataclass(frozen=True)
class MapLayout:
    """Both directions of a drive map."""

    map: DriveMap
    outputs: DirectionLayout
    inputs: DirectionLayout
    pdo_align: int

    def direction(self, direction: Direction) -> DirectionLayout:
        return self.outputs if direction is Direction.OUTPUTS else self.inputs


def layout(drive: DriveMap, *, pdo_align: int = 1) -> MapLayout:
    """Lay out ``drive``; ``pdo_align`` 1 for EtherCAT, 8 for CANopen (PDO per frame)."""
    if pdo_align not in (1, 8):
        raise ValueError("pdo_align must be 1 (EtherCAT) or 8 (CANopen)")
    return MapLayout(
        map=drive,
        outputs=_direction(drive, Direction.OUTPUTS, pdo_align),
        inputs=_direction(drive, Direction.INPUTS, pdo_align),
        pdo_align=pdo_align,
    )


def _direction(drive: DriveMap, direction: Direction, pdo_align: int) -> DirectionLayout:
    entries: list[EntryLayout] = []
    pdos: list[PdoPlacement] = []
    cursor = 0
    for pdo in drive.pdos(direction):
        cursor = -(-cursor // pdo_align) * pdo_align
        start = cursor
        for ch in pdo.channels:
            entries.append(EntryLayout(ch, pdo.index, cursor))
            cursor += ch.bits
        pdos.append(PdoPlacement(pdo.index, start, cursor - start))
    return DirectionLayout(direction, tuple(entries), tuple(pdos), cursor)


_FLOAT_FMT = {32: "<f", 64: "<d"}


def get_value(buf: bytes | bytearray | memoryview, entry: EntryLayout, base: int = 0) -> int | float | bool:
    """Raw value of ``entry`` in ``buf`` (one slave's image starting at byte ``base``)."""
    dt = entry.channel.type
    start = base + entry.byte_offset
    chunk = bytes(buf[start : start + entry.span_bytes])
    if dt.is_float:
        return float(struct.unpack(_FLOAT_FMT[dt.bits], chunk[: dt.bits // 8])[0])
    raw = (int.from_bytes(chunk, "little") >> entry.shift) & ((1 << dt.bits) - 1)
    if dt.name == "bool":
        return bool(raw)
    if dt.signed and raw >> (dt.bits - 1):
        raw -= 1 << dt.bits
    return raw


def set_value(buf: bytearray | memoryview, entry: EntryLayout, value: float, base: int = 0) -> None:
    """Write raw ``value`` of ``entry`` into ``buf`` without touching other bits."""
    dt = entry.channel.type
    start = base + entry.byte_offset
    end = start + entry.span_bytes
    if dt.is_float:
        if entry.shift:
            raise FieldbusError(f"{entry.name}: a {dt.name} entry must start on a byte boundary")
        buf[start : start + dt.bits // 8] = struct.pack(_FLOAT_FMT[dt.bits], value)
        return
    mask = ((1 << dt.bits) - 1) << entry.shift
    word = int.from_bytes(bytes(buf[start:end]), "little")
    word = (word & ~mask) | ((int(value) << entry.shift) & mask)
    buf[start:end] = word.to_bytes(end - start, "little")
