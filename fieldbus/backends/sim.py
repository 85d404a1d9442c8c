"""In-process sim backend: an EtherCAT bus whose slaves are the ``sim_slaves`` ESC chain.

Real EtherCAT without a network card, root or veth: bring-up and the cycle
are frames (built by :mod:`fieldbus.core.ecat`) passed to
:meth:`sim_slaves.ethercat.chain.EscChain.process_into`, so working counters,
AL states, the CoE mailbox and the SII are the emulator's, not shortcuts.
The bring-up is :class:`~fieldbus.wire.framemaster.FrameMaster`'s.

Options (``open_network(path, backend="sim", **options)``):

- ``chain_maps``: drive maps the emulated slaves are built from, in wire
  order (default: the network's maps) - a different list makes an identity
  mismatch;
- ``clock``: the emulator's time, a :class:`~fieldbus.runtime.clock.Clock`
  or a ``() -> ns`` function (default ``time.monotonic_ns``). On a virtual
  clock (:class:`~fieldbus.runtime.clock.VirtualClock`) runs are
  deterministic, and the master's waits pass on that clock: a lost frame
  costs the receive timeout, a delayed reply its delay.

Fault hooks: :attr:`SimBackend.chain` is the :class:`EscChain`
(``drop_frames``, ``delay_frames``, ``corrupt_wkc``, ``power_cycle``,
``refuse_state``, ``abort_sdo``, ``emergency``), and :meth:`SimBackend.corrupt_inputs`
here. A delayed reply longer than the receive timeout counts as lost, as it
would on the wire. The public face of these is :mod:`fieldbus.testing`.

Bus type ``ethercat`` run with ``backend="sim"``, or a bus of type ``sim``.

Recovery (after a miss) is a generator advanced by one frame exchange per
:meth:`recover_step` call, so the cycle never waits for a whole re-bring-up.
"""

from __future__ import annotations

import dataclasses
import itertools
import time
from collections.abc import Callable, Generator, Sequence
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from fieldbus.backends.base import Backend
from fieldbus.backends.sdo_exec import apply_plan
from fieldbus.core.al import AL_ACK, AL_INIT, AL_OP, AL_PREOP, AL_SAFEOP, al_status_name, state_name
from fieldbus.core.ecat import Command, Datagram, build_master_frame
from fieldbus.core.network import Bus
from fieldbus.core.pdo.model import DriveMap
from fieldbus.core.sdo import coe_plan
from fieldbus.core.wkc import Recovery, recovery_action
from fieldbus.errors import FieldbusError, StateTransitionError
from fieldbus.runtime.clock import Clock, is_virtual
from fieldbus.wire.framemaster import FrameMaster, Mapping, SlaveInfo, layout_image

MAX_FRAME_DATA = 1486  # datagram data per frame (SOEM's EC_MAXLRWDATA)
STATE_POLLS = 100


@dataclass
class _Segment:
    """One LRW frame of the cycle: a preallocated buffer, its pristine template and its WKC offset."""

    buf: bytearray
    template: npt.NDArray[np.uint8]
    view: npt.NDArray[np.uint8]
    size: int
    wkc_off: int
    data_off: int
    logical: int


class SimBackend(Backend):
    """An EtherCAT bus emulated in-process (bus type ``ethercat`` run with ``backend="sim"``)."""

    kind = "sim"

    def __init__(self, bus: Bus, **options: object) -> None:
        if bus.type not in ("ethercat", "sim"):
            raise FieldbusError(
                f"bus '{bus.name}' is {bus.type}: the sim backend emulates EtherCAT segments "
                "(CAN buses run on python-can's virtual interface: fieldbus demo --backend canopen|rawcan)"
            )
        super().__init__(bus, **options)
        from fieldbus.emulators import emulator_part

        EscChain = emulator_part("ethercat_chain")

        maps = options.get("chain_maps")
        chain_maps: Sequence[DriveMap] = maps if isinstance(maps, Sequence) else [s.map for s in bus.slaves]
        # the emulator reads the network file's emulator: sections (opaque to fieldbus)
        emulator_options = emulator_part("emulator_options")
        emulated = [emulator_options(s.emulator) if s.emulator else None for s in bus.slaves]
        self.chain = EscChain.from_maps(
            list(chain_maps), drive_params=emulated if len(emulated) == len(chain_maps) else None
        )
        clock = options.get("clock")
        # a virtual clock: the master's waits (receive timeout, delayed replies) pass on it
        self._waits: Clock | None = clock if isinstance(clock, Clock) and is_virtual(clock) else None
        if isinstance(clock, Clock):
            self.clock: Callable[[], int] = clock.now_ns
        else:
            self.clock = clock if callable(clock) else time.monotonic_ns
        self._corrupt: dict[int, int] = {}  # slave -> cycles its inputs still arrive inverted
        self._delay_s, self._delay_cycles = 0.0, 0  # process-data replies held back (delay_cycles)
        self.master = FrameMaster(self._transport)
        self.infos: list[SlaveInfo] = []
        self.mappings: list[Mapping] = []
        self._timeout_s = bus.receive_timeout_us / 1e6
        self._segments: list[_Segment] = []
        self._out_copies: list[tuple[npt.NDArray[np.uint8], npt.NDArray[np.uint8]]] = []
        self._in_copies: list[tuple[npt.NDArray[np.uint8], npt.NDArray[np.uint8]]] = []
        self._wkc = 0
        self._lost = False
        self._open = False

    # -- transport ----------------------------------------------------------------------
    def _transport(self, frame: bytes) -> bytes | None:
        reply: bytes | None = self.chain.process(frame, self.clock())
        if not self._waited(reply is None, self.chain.take_delay()):
            return None
        return reply

    def _waited(self, lost: bool, delay_s: float) -> bool:
        """The master's wait for a reply (on a virtual clock it passes there); False: it counts as lost."""
        late = lost or delay_s > self._timeout_s
        if self._waits is not None:
            self._waits.sleep(self._timeout_s if late else delay_s)
        return not late

    def corrupt_inputs(self, slave: int, cycles: int = 1) -> None:
        """Slave ``slave``'s inputs (0-based on this bus) arrive with every bit inverted for ``cycles``
        process-data cycles, with a good working counter: fresh, wrong data."""
        self._corrupt[slave] = self._corrupt.get(slave, 0) + cycles

    def delay_cycles(self, seconds: float, cycles: int = 1) -> None:
        """The process-data replies of the next ``cycles`` cycles come back ``seconds`` late (recovery
        and SDO frames in between are not held back, as ``chain.delay_frames`` would hold them)."""
        self._delay_s, self._delay_cycles = seconds, cycles

    def clear_injections(self) -> None:
        """Undo :meth:`corrupt_inputs` and :meth:`delay_cycles` (the chain's own: ``chain.clear_faults()``)."""
        self._corrupt.clear()
        self._delay_s, self._delay_cycles = 0.0, 0

    # -- bring-up -------------------------------------------------------------------------
    def open(self) -> None:
        found = self.master.scan()
        self._open = True
        self.infos = self.master.identify(found)
        self.check_identities([(x.name, x.vendor_id, x.product_id) for x in self.infos], "(sim)")
        for info in self.infos:
            self.master.setup_mailbox(info)
        self._go(AL_PREOP, "PRE-OP")

    def _go(self, state: int, name: str, stations: list[int] | None = None) -> None:
        stations = stations if stations is not None else [m.station for m in self.infos]
        for st in stations:
            self.master.request_state(st, state)
        missing = self.master.wait_state(stations, state, STATE_POLLS)
        if missing:
            lines, first = [], None
            for st, got in missing.items():
                pos = next(i.position for i in self.infos if i.station == st)
                status, code = got if got is not None else (0, 0)
                first = code if first is None else first
                lines.append(
                    f"  position {pos} ({self.areas[pos].slave.name}): "
                    + (
                        f"{state_name(status)}, AL status code 0x{code:04X} {al_status_name(code)}"
                        if got
                        else "no answer"
                    )
                )
            raise StateTransitionError(
                f"bus '{self.bus.name}': not all slaves reached {name}:\n" + "\n".join(lines), al_status=first
            )

    def configure(self) -> None:
        for i, area in enumerate(self.areas):
            plan = coe_plan(area.slave.map)
            if plan.steps:
                apply_plan(plan, *self.plan_io(i), slave=area.slave.name)

    def safe_op(self) -> None:
        self.mappings, out_bytes, in_bytes = layout_image([(a.out_size, a.in_size) for a in self.areas])
        for info, m in zip(self.infos, self.mappings, strict=True):
            self.master.map_process_data(info, m)
        self._go(AL_SAFEOP, "SAFE-OP")
        self._build_cycle(out_bytes + in_bytes)

    def _build_cycle(self, size: int) -> None:
        """Preallocate the LRW frame(s) and the copy pairs between them and the process images."""
        cuts = [0]
        for m in self.mappings:  # cut at slave boundaries (outputs, then inputs)
            for off, n in ((m.out_offset, m.out_size), (m.in_offset, m.in_size)):
                if n and off + n - cuts[-1] > MAX_FRAME_DATA and off > cuts[-1]:
                    cuts.append(off)
        cuts.append(size)
        self._segments = []
        for k, (lo, hi) in enumerate(itertools.pairwise(cuts)):
            if hi <= lo:
                continue
            frame = build_master_frame([Datagram(Command.LRW, 0x80 | k, lo, bytes(hi - lo))])
            buf = bytearray(frame)
            view = np.frombuffer(buf, dtype=np.uint8)
            data_off = 14 + 2 + 10  # Ethernet, EtherCAT header, datagram header
            seg = _Segment(buf, view.copy(), view, len(buf), data_off + (hi - lo), data_off, lo)
            self._segments.append(seg)
        self._out_copies, self._in_copies = [], []
        for i, m in enumerate(self.mappings):
            for off, n, rows, dst in (
                (m.out_offset, m.out_size, self.out_row(i), self._out_copies),
                (m.in_offset, m.in_size, self.in_row(i), self._in_copies),
            ):
                if not n:
                    continue
                seg = next(s for s in self._segments if s.logical <= off < s.logical + s.wkc_off - s.data_off)
                start = seg.data_off + off - seg.logical
                # a multi-axis slave's rows are (axes, bytes): the frame's bytes as the same shape
                dst.append((seg.view[start : start + n].reshape(rows.shape), rows))

    def op(self) -> None:
        for _ in range(3):  # valid outputs before OP, so no watchdog trips on the way
            self.send()
            self.receive()
        stations = [m.station for m in self.infos]
        for st in stations:
            self.master.request_state(st, AL_OP)
        for _ in range(STATE_POLLS):
            self.send()
            self.receive()
            if not self.master.wait_state(stations, AL_OP, 1):
                break
        else:
            self._go(AL_OP, "OP")
        self._confirm_wkc()

    # -- cycle ----------------------------------------------------------------------------
    def send(self) -> None:
        for frame_np, row in self._out_copies:
            np.copyto(frame_np, row)
        now = self.clock()
        wkc, lost = 0, False
        held = 0.0
        if self._delay_cycles:
            self._delay_cycles -= 1
            held = self._delay_s
        for seg in self._segments:
            np.copyto(seg.view[: seg.data_off], seg.template[: seg.data_off])
            seg.buf[seg.wkc_off] = seg.buf[seg.wkc_off + 1] = 0
            n = self.chain.process_into(seg.buf, seg.size, now)
            if not self._waited(n == 0, max(held, self.chain.take_delay())):
                lost = True
            held = 0.0  # one wait per cycle
            wkc += seg.buf[seg.wkc_off] | seg.buf[seg.wkc_off + 1] << 8
        self._wkc, self._lost = wkc, lost

    def receive(self) -> int | None:
        if self._lost:
            return None
        for frame_np, row in self._in_copies:
            np.copyto(row, frame_np)
        if self._corrupt:
            for slave, left in list(self._corrupt.items()):
                row = self.in_row(slave)
                np.bitwise_xor(row, 0xFF, out=row)
                if left <= 1:
                    del self._corrupt[slave]
                else:
                    self._corrupt[slave] = left - 1
        return self._wkc

    def _recover(self) -> Generator[None, None, bool]:
        """ecatcheck-like: ack SAFE-OP+ERROR, request OP, re-bring-up slaves back in INIT or lost.

        Passes repeat (one frame per step) until a pass finds every slave in OP,
        like SOEM's ``docheckstate``: a slave may answer the LRW in SAFE-OP.
        """
        while True:
            all_ok = True
            for i, info in enumerate(self.infos):
                got = self.master.al_status(info.station)
                yield
                action = recovery_action(None if got is None else got[0])
                if action is Recovery.NONE:
                    continue
                all_ok = False
                if action is Recovery.ACK_ERROR:
                    self.master.request_state(info.station, AL_SAFEOP | AL_ACK)
                elif action is Recovery.REQUEST_OP:
                    self.master.request_state(info.station, AL_OP)
                else:  # RECONFIGURE / RECOVER: power-cycled (INIT, station address lost) or lost
                    yield from self._rebuild(i)
                yield
                back = self.master.al_status(info.station)
                if back is not None and back[0] & 0x1F == AL_OP:
                    self.recoveries += 1
            if all_ok:
                return True

    def _rebuild(self, i: int) -> Generator[None, None, None]:
        """Bring slave ``i`` from INIT (or a lost station address) back to OP, one step per yield."""
        info, m = self.infos[i], self.mappings[i]
        master = self.master
        try:
            if master.al_status(info.station) is None:
                master.assign_station(i)
                yield
            master.request_state(info.station, AL_INIT | AL_ACK)
            yield
            master.setup_mailbox(info)
            master.request_state(info.station, AL_PREOP)
            yield
            if master.wait_state([info.station], AL_PREOP, 1):
                return
            plan = coe_plan(self.areas[i].slave.map)
            write, read = self.plan_io(i)
            for step in plan.steps:  # one SDO per cycle
                one = dataclasses.replace(plan, steps=(step,))
                apply_plan(one, write, read, slave=self.areas[i].slave.name)
                yield
            master.map_process_data(info, m)
            master.request_state(info.station, AL_SAFEOP)
            yield
            master.request_state(info.station, AL_OP)
        except FieldbusError as exc:  # reported; the slave stays out of OP and is tried again
            self._recovery_failed(exc)

    # -- shut-down ------------------------------------------------------------------------
    def stop(self) -> None:
        if self._open:
            self.master.txrx([Datagram.physical(Command.BWR, 0, 0x0120, bytes([AL_INIT, 0]))])

    def close(self) -> None:
        self._open = False

    # -- acyclic ------------------------------------------------------------------------
    def sdo_read(self, slave: int, index: int, sub_index: int) -> bytes:
        return self.master.sdo_upload(self._info(slave), index, sub_index)

    def sdo_write(self, slave: int, index: int, sub_index: int, data: bytes) -> None:
        self.master.sdo_download(self._info(slave), index, sub_index, data)

    def _info(self, slave: int) -> SlaveInfo:
        if not self.infos:
            raise FieldbusError(f"bus '{self.bus.name}': not open")
        return self.infos[slave]

    @property
    def emergencies(self) -> list[tuple[int, int, int]]:
        """CoE emergencies seen in the mailbox: (station, error code, error register)."""
        return self.master.emergencies

    @property
    def emcy_count(self) -> int:  # type: ignore[override]
        """Emergencies seen in the mailbox since open."""
        return len(self.master.emergencies)
