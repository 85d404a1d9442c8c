"""EtherCAT frame and datagram codec (ETG.1000.4), pure: bytes in, dataclasses out.

Wire layout (all fields little-endian)::

    Ethernet   dst(6) src(6) ethertype(2, big-endian 0x88A4)
    EtherCAT   u16: length (bits 0-10, bytes of datagrams) | reserved (bit 11) | type (bits 12-15, 1 = commands)
    Datagram   cmd(1) idx(1) address(4) u16: len (0-10) | R (11-13) | C circulating (14) | M more follows (15)
               irq(2) data(len) wkc(2)

``address`` is the 32-bit field as sent: for position (auto-increment) and
configured-address commands it is ``ADP | ADO << 16`` (``adp``/``ado``
properties), for logical commands the logical address.

Used by the emulated slaves (``sim_slaves.ethercat``) and by the in-process
sim backend to build master frames (:func:`build_master_frame`). The slave
side works in place on the frame buffer with :func:`datagram_offsets`.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass
from enum import IntEnum

from fieldbus.errors import FieldbusError

ETHERTYPE_ECAT = 0x88A4
ETH_HEADER_SIZE = 14
ECAT_HEADER_SIZE = 2
DATAGRAM_HEADER_SIZE = 10
WKC_SIZE = 2
ECAT_TYPE_COMMANDS = 1
MAX_DATAGRAM_DATA = 0x7FF  # 11-bit length field
MAX_ECAT_PAYLOAD = 1498  # largest datagram section in one untagged Ethernet frame (1500 - 2)
BROADCAST_MAC = b"\xff" * 6
SOEM_MASTER_MAC = b"\x01\x01\x01\x01\x01\x01"
LOCALLY_ADMINISTERED = 0x02  # bit a slave sets in the first source-MAC byte on the way back

_DG_HEADER = struct.Struct("<BBIHH")
_U16 = struct.Struct("<H")


class FrameError(FieldbusError, ValueError):
    """A frame or datagram is malformed (too short, wrong type, lengths that do not add up)."""


class Command(IntEnum):
    """EtherCAT datagram commands (ETG.1000.4 table 'command types')."""

    NOP = 0
    APRD = 1  # auto-increment physical read
    APWR = 2
    APRW = 3
    FPRD = 4  # configured address physical read
    FPWR = 5
    FPRW = 6
    BRD = 7  # broadcast read
    BWR = 8
    BRW = 9
    LRD = 10  # logical read
    LWR = 11
    LRW = 12
    ARMW = 13  # auto-increment physical read, multiple write
    FRMW = 14  # configured address physical read, multiple write

    @property
    def reads(self) -> bool:
        """The command returns slave data to the master."""
        return self in _READS

    @property
    def writes(self) -> bool:
        """The command carries master data into slaves."""
        return self in _WRITES


_READS = frozenset(
    {Command.APRD, Command.APRW, Command.FPRD, Command.FPRW, Command.BRD, Command.BRW}
    | {Command.LRD, Command.LRW, Command.ARMW, Command.FRMW}
)
_WRITES = frozenset(
    {Command.APWR, Command.APRW, Command.FPWR, Command.FPRW, Command.BWR, Command.BRW}
    | {Command.LWR, Command.LRW, Command.ARMW, Command.FRMW}
)


@dataclass(frozen=True)
class Datagram:
    """One EtherCAT datagram. ``more`` (more-follows bit) is set by the frame encoder."""

    cmd: Command
    idx: int
    address: int
    data: bytes
    wkc: int = 0
    irq: int = 0
    circulating: bool = False
    more: bool = False

    @property
    def adp(self) -> int:
        """Auto-increment position / configured station address (low 16 bits of ``address``)."""
        return self.address & 0xFFFF

    @property
    def ado(self) -> int:
        """Register offset in the slave (high 16 bits of ``address``)."""
        return self.address >> 16

    @property
    def size(self) -> int:
        """Bytes on the wire: header + data + WKC."""
        return DATAGRAM_HEADER_SIZE + len(self.data) + WKC_SIZE

    @staticmethod
    def physical(cmd: Command, adp: int, ado: int, data: bytes, idx: int = 0) -> Datagram:
        """A position/configured/broadcast datagram addressing register ``ado`` of ``adp``."""
        return Datagram(cmd, idx, (adp & 0xFFFF) | (ado & 0xFFFF) << 16, data)

    def encode(self, *, more: bool | None = None) -> bytes:
        """Wire bytes of this datagram (``more`` overrides the more-follows bit)."""
        _check_datagram(self)
        flags = len(self.data) | (0x4000 if self.circulating else 0)
        if self.more if more is None else more:
            flags |= 0x8000
        head = _DG_HEADER.pack(int(self.cmd), self.idx, self.address, flags, self.irq)
        return head + self.data + _U16.pack(self.wkc)


def _check_datagram(d: Datagram) -> None:
    if not 0 <= d.idx <= 0xFF:
        raise FrameError(f"datagram index {d.idx} out of 0..255")
    if not 0 <= d.address <= 0xFFFFFFFF:
        raise FrameError(f"datagram address {d.address:#x} out of 32 bits")
    if len(d.data) > MAX_DATAGRAM_DATA:
        raise FrameError(f"datagram data of {len(d.data)} bytes exceeds the 11-bit length field")
    if not 0 <= d.wkc <= 0xFFFF or not 0 <= d.irq <= 0xFFFF:
        raise FrameError("wkc and irq are 16-bit fields")


@dataclass(frozen=True)
class Frame:
    """An EtherCAT frame: Ethernet addresses and datagrams, in order."""

    dst: bytes
    src: bytes
    datagrams: tuple[Datagram, ...]

    def encode(self) -> bytes:
        """Wire bytes: Ethernet header, EtherCAT header, datagrams (more-follows set on all but the last).

        Not padded to the Ethernet minimum of 60 bytes (SOEM does not pad either).
        """
        if len(self.dst) != 6 or len(self.src) != 6:
            raise FrameError("MAC addresses are 6 bytes")
        if not self.datagrams:
            raise FrameError("a frame carries at least one datagram")
        last = len(self.datagrams) - 1
        body = b"".join(d.encode(more=i != last) for i, d in enumerate(self.datagrams))
        if len(body) > MAX_DATAGRAM_DATA:
            raise FrameError(f"datagrams of {len(body)} bytes exceed the 11-bit EtherCAT length field")
        ecat = _U16.pack(len(body) | ECAT_TYPE_COMMANDS << 12)
        return self.dst + self.src + ETHERTYPE_ECAT.to_bytes(2, "big") + ecat + body


def build_master_frame(
    datagrams: list[Datagram] | tuple[Datagram, ...],
    *,
    src: bytes = SOEM_MASTER_MAC,
    dst: bytes = BROADCAST_MAC,
) -> bytes:
    """Master -> slaves: the frame carrying ``datagrams`` (more-follows bits set by position)."""
    return Frame(dst, src, tuple(datagrams)).encode()


def decode_frame(frame: bytes | bytearray | memoryview) -> Frame:
    """Parse a whole frame; trailing Ethernet padding after the datagrams is ignored.

    Raises :class:`FrameError` for a wrong ethertype, a non-command EtherCAT
    type, or lengths that do not add up.
    """
    buf = bytes(frame)
    offsets = datagram_offsets(buf)
    dgs = []
    for off in offsets:
        cmd, idx, address, flags, irq = _DG_HEADER.unpack_from(buf, off)
        n = flags & 0x7FF
        data = buf[off + DATAGRAM_HEADER_SIZE : off + DATAGRAM_HEADER_SIZE + n]
        (wkc,) = _U16.unpack_from(buf, off + DATAGRAM_HEADER_SIZE + n)
        dgs.append(
            Datagram(Command(cmd), idx, address, data, wkc, irq, bool(flags & 0x4000), bool(flags & 0x8000))
        )
    return Frame(buf[0:6], buf[6:12], tuple(dgs))


def datagram_offsets(buf: bytes | bytearray | memoryview) -> list[int]:
    """Byte offsets of each datagram header in ``buf`` (a whole Ethernet frame), validated.

    The slave side uses this to process datagrams in place: data of the
    datagram at ``off`` is ``buf[off + 10 : off + 10 + length]``, its WKC follows.
    """
    size = len(buf)
    if size < ETH_HEADER_SIZE + ECAT_HEADER_SIZE:
        raise FrameError(f"frame of {size} bytes is shorter than the Ethernet + EtherCAT headers")
    ethertype = buf[12] << 8 | buf[13]
    if ethertype != ETHERTYPE_ECAT:
        raise FrameError(f"ethertype {ethertype:#06x} is not EtherCAT ({ETHERTYPE_ECAT:#06x})")
    head = buf[14] | buf[15] << 8
    length = head & 0x7FF
    kind = head >> 12
    if kind != ECAT_TYPE_COMMANDS:
        raise FrameError(f"EtherCAT type {kind} is not 1 (datagrams)")
    end = ETH_HEADER_SIZE + ECAT_HEADER_SIZE + length
    if end > size:
        raise FrameError(f"EtherCAT header announces {length} bytes, frame holds {size - 16}")
    offsets: list[int] = []
    off = ETH_HEADER_SIZE + ECAT_HEADER_SIZE
    while True:
        if off + DATAGRAM_HEADER_SIZE + WKC_SIZE > end:
            raise FrameError(f"datagram {len(offsets)} at byte {off} runs past the EtherCAT length")
        if buf[off] > Command.FRMW:
            raise FrameError(f"datagram {len(offsets)}: unknown command {buf[off]}")
        flags = buf[off + 6] | buf[off + 7] << 8
        n = flags & 0x7FF
        nxt = off + DATAGRAM_HEADER_SIZE + n + WKC_SIZE
        if nxt > end:
            raise FrameError(f"datagram {len(offsets)} of {n} data bytes runs past the EtherCAT length")
        offsets.append(off)
        off = nxt
        if not flags & 0x8000:
            break
    if off != end:
        raise FrameError(f"{end - off} bytes after the last datagram inside the EtherCAT length")
    return offsets
