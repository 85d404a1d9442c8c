"""A minimal in-process master for an :class:`EscChain`: SOEM-like bring-up through frames.

For tests and benchmarks that need slaves in OP without a network: every
step is a real frame built with :mod:`fieldbus.core.ecat` and passed through
``chain.process``. Mapping as SOEM does it (LRW, legacy layout): all outputs
from logical address 0 in wire order, then all inputs. Station addresses
0x1001.. as SOEM assigns them.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass

from fieldbus.core.ecat import Command, Datagram, build_master_frame, decode_frame
from fieldbus.errors import FieldbusError
from sim_slaves.ethercat.al import AlState
from sim_slaves.ethercat.chain import EscChain
from sim_slaves.ethercat.sii import SM_TYPE_INPUTS, SM_TYPE_OUTPUTS

STATION_BASE = 0x1001


@dataclass(frozen=True)
class SlaveMapping:
    """Where one slave's data sit in the logical image (bytes)."""

    station: int
    out_offset: int
    out_size: int
    in_offset: int
    in_size: int


@dataclass(frozen=True)
class ProcessDataPlan:
    """The logical image: ``out_bytes`` from 0, then ``in_bytes``; the expected LRW WKC."""

    slaves: tuple[SlaveMapping, ...]
    out_bytes: int
    in_bytes: int
    expected_wkc: int

    @property
    def size(self) -> int:
        return self.out_bytes + self.in_bytes

    def lrw_frames(self, max_data: int = 1486) -> list[bytes]:
        """The cycle as SOEM sends a large image: one LRW frame per segment of at most ``max_data`` bytes.

        Segments end on slave boundaries (outputs of slaves in order, then inputs).
        """
        blocks = [(m.out_offset, m.out_size) for m in self.slaves if m.out_size]
        blocks += [(m.in_offset, m.in_size) for m in self.slaves if m.in_size]
        frames: list[bytes] = []
        start = 0
        end = 0
        for off, size in blocks:
            if off + size - start > max_data and end > start:
                frames.append(_lrw(start, end - start, len(frames)))
                start = off
            end = off + size
        if end > start:
            frames.append(_lrw(start, end - start, len(frames)))
        return frames

    def lrw(self, outputs: bytes | None = None, idx: int = 0) -> bytes:
        """The cycle frame: one LRW over the whole image (outputs, then zeros for the inputs)."""
        data = (outputs or bytes(self.out_bytes)).ljust(self.out_bytes, b"\0") + bytes(self.in_bytes)
        return build_master_frame([Datagram(Command.LRW, idx, 0, data)])


def _lrw(logical: int, size: int, idx: int) -> bytes:
    return build_master_frame([Datagram(Command.LRW, idx, logical, bytes(size))])


class BringupError(FieldbusError):
    """A slave did not take a bring-up step (wrong WKC or state)."""


def exchange(chain: EscChain, dgs: list[Datagram], now_ns: int) -> tuple[Datagram, ...]:
    """Send one frame of ``dgs`` and decode the answer."""
    reply = chain.process(build_master_frame(dgs), now_ns)
    if reply is None:
        raise BringupError("frame lost")
    return decode_frame(reply).datagrams


def _fp(cmd: Command, station: int, ado: int, data: bytes) -> Datagram:
    return Datagram.physical(cmd, station, ado, data)


def _request_state(chain: EscChain, state: AlState, now_ns: int) -> None:
    n = len(chain)
    for i in range(n):
        d = exchange(chain, [_fp(Command.FPWR, STATION_BASE + i, 0x0120, struct.pack("<H", state))], now_ns)
        if d[0].wkc != 1:
            raise BringupError(f"slave {i}: AL control write WKC {d[0].wkc}")
    for i in range(n):
        (st,) = exchange(chain, [_fp(Command.FPRD, STATION_BASE + i, 0x0130, bytes(6))], now_ns)
        status, _, code = struct.unpack("<HHH", st.data)
        if status != state:
            raise BringupError(f"slave {i}: AL status {status:#x}, code {code:#06x}, wanted {state:#x}")


def bring_up(chain: EscChain, now_ns: int = 0) -> ProcessDataPlan:
    """INIT -> PRE-OP -> SAFE-OP -> OP with SMs and FMMUs as SOEM programs them."""
    n = len(chain)
    exchange(chain, [Datagram.physical(Command.BWR, 0, 0x0120, bytes([0x11]))], now_ns)
    (d,) = exchange(chain, [Datagram.physical(Command.BRD, 0, 0x0000, bytes(2))], now_ns)
    if d.wkc != n:
        raise BringupError(f"BRD counted {d.wkc} slaves, chain has {n}")
    for i in range(n):
        exchange(
            chain,
            [Datagram.physical(Command.APWR, -i & 0xFFFF, 0x0010, struct.pack("<H", STATION_BASE + i))],
            now_ns,
        )
    for i, s in enumerate(chain.slaves):
        (o_start, o_len), (i_start, i_len) = s.sii.mailbox_out, s.sii.mailbox_in
        if o_len:
            sm01 = struct.pack("<HHI", o_start, o_len, 0x00010026) + struct.pack(
                "<HHI", i_start, i_len, 0x00010022
            )
            exchange(chain, [_fp(Command.FPWR, STATION_BASE + i, 0x0800, sm01)], now_ns)
    _request_state(chain, AlState.PRE_OP, now_ns)
    log = 0
    maps = []
    sizes = [(s.image.outputs.size, s.image.inputs.size) for s in chain.slaves]
    out_offsets = []
    for o, _ in sizes:
        out_offsets.append(log)
        log += o
    out_bytes = log
    in_offsets = []
    for _, i_size in sizes:
        in_offsets.append(log)
        log += i_size
    wkc = 0
    for i, s in enumerate(chain.slaves):
        o, inp = sizes[i]
        st = STATION_BASE + i
        sm2 = next(x for x in s.sii.sms if x.type == SM_TYPE_OUTPUTS)
        sm3 = next(x for x in s.sii.sms if x.type == SM_TYPE_INPUTS)
        dgs = []
        f = 0
        if o:
            dgs.append(
                _fp(Command.FPWR, st, 0x0810, struct.pack("<HHBBBB", sm2.start, o, sm2.control, 0, 1, 0))
            )
            fmmu = struct.pack("<IHBBHBBB", out_offsets[i], o, 0, 7, sm2.start, 0, 2, 1) + bytes(3)
            dgs.append(_fp(Command.FPWR, st, 0x0600 + 16 * f, fmmu))
            f += 1
            wkc += 2
        if inp:
            dgs.append(
                _fp(Command.FPWR, st, 0x0818, struct.pack("<HHBBBB", sm3.start, inp, sm3.control, 0, 1, 0))
            )
            fmmu = struct.pack("<IHBBHBBB", in_offsets[i], inp, 0, 7, sm3.start, 0, 1, 1) + bytes(3)
            dgs.append(_fp(Command.FPWR, st, 0x0600 + 16 * f, fmmu))
            wkc += 1
        if dgs:
            exchange(chain, dgs, now_ns)
        maps.append(SlaveMapping(st, out_offsets[i], o, in_offsets[i], inp))
    _request_state(chain, AlState.SAFE_OP, now_ns)
    _request_state(chain, AlState.OP, now_ns)
    return ProcessDataPlan(tuple(maps), out_bytes, log - out_bytes, wkc)
