"""Slaves of an :class:`EscChain` to OP in-process, for tests and benchmarks that need no network.

The bring-up is the product's own frame-level master
(:class:`fieldbus.wire.framemaster.FrameMaster`, the one the sim backend
uses) over ``chain.process``: station addresses 0x1001.., SII through the
EEPROM interface, mailbox SyncManagers, SM2/SM3 and FMMUs for an LRW image as
SOEM lays it out (all outputs from logical address 0 in wire order, then all
inputs). What this module adds is the cycle frame(s) for that image.
"""

from __future__ import annotations

from dataclasses import dataclass

from fieldbus.core.al import AL_OP, AL_PREOP, AL_SAFEOP, state_name
from fieldbus.core.ecat import Command, Datagram, build_master_frame, decode_frame
from fieldbus.errors import BusTimeoutError, StateTransitionError
from fieldbus.wire.framemaster import STATION_BASE, FrameMaster, Mapping, layout_image
from sim_slaves.ethercat.chain import EscChain

__all__ = ["STATION_BASE", "ProcessDataPlan", "bring_up", "exchange"]


@dataclass(frozen=True)
class ProcessDataPlan:
    """The logical image: ``out_bytes`` from 0, then ``in_bytes``; the expected LRW WKC."""

    slaves: tuple[Mapping, ...]
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


def exchange(chain: EscChain, dgs: list[Datagram], now_ns: int) -> tuple[Datagram, ...]:
    """Send one frame of ``dgs`` through ``chain`` and decode the answer (raw datagrams, for tests)."""
    reply = chain.process(build_master_frame(dgs), now_ns)
    if reply is None:
        raise BusTimeoutError("frame lost")
    return decode_frame(reply).datagrams


def bring_up(chain: EscChain, now_ns: int = 0) -> ProcessDataPlan:
    """INIT -> PRE-OP -> SAFE-OP -> OP through :class:`FrameMaster`; the image as SOEM maps it."""
    master = FrameMaster(lambda frame: chain.process(frame, now_ns))
    found = master.scan()
    if found != len(chain):
        raise StateTransitionError(f"BRD counted {found} slaves, the chain has {len(chain)}")
    infos = master.identify(found)
    for info in infos:
        master.setup_mailbox(info)
    stations = [info.station for info in infos]
    _go(master, stations, AL_PREOP)
    sizes = [(s.image.outputs.size, s.image.inputs.size) for s in chain.slaves]
    maps, out_bytes, in_bytes = layout_image(sizes)
    for info, m in zip(infos, maps, strict=True):
        master.map_process_data(info, m)
    _go(master, stations, AL_SAFEOP)
    _go(master, stations, AL_OP)
    wkc = sum((2 if m.out_size else 0) + (1 if m.in_size else 0) for m in maps)
    return ProcessDataPlan(tuple(maps), out_bytes, in_bytes, wkc)


def _go(master: FrameMaster, stations: list[int], state: int) -> None:
    for st in stations:
        master.request_state(st, state)
    missing = master.wait_state(stations, state)
    if missing:
        st, got = next(iter(missing.items()))
        have = "no answer" if got is None else f"{state_name(got[0])}, AL status code 0x{got[1]:04X}"
        raise StateTransitionError(f"station 0x{st:04X}: wanted {state_name(state)}, {have}")
