"""A pysoem-shaped master on the in-process ESC chain: the EtherCAT backend's code without a network card.

:class:`InProcessMaster` and :class:`InProcessSlave` offer the part of
pysoem's ``Master`` / ``CdefSlave`` API that :mod:`fieldbus.backends.ethercat`
calls (``config_init``, ``config_map``, AL states, ``send_processdata`` /
``receive_processdata``, ``sdo_read`` / ``sdo_write``, ``_fprd`` / ``_fpwr``,
``output`` / ``input``), with SOEM's meaning, on
:class:`~fieldbus.wire.framemaster.FrameMaster`. Its frames go to the
emulated ESC chain, found through :mod:`fieldbus.emulators` (entry point
``ethercat_chain``; ``fieldbus`` never imports ``sim_slaves``). So
``open_network(path, backend="ethercat", transport="in-process")`` runs the
EtherCAT backend's bring-up, cycle, recovery and in-OP mailbox code against
real frames, working counters and AL states, in this process.

As SOEM: ``config_init`` resets the slaves, gives them station addresses
0x1001 + position, reads each one's SII and mailbox layout and requests
PRE-OP; ``config_map`` reads each slave's PDO assignment (0x1C12 / 0x1C13
and the mapped PDOs, by CoE; the SII's SyncManager lengths without a
mailbox), lays out one LRW image - all outputs from logical 0 in wire order,
then all inputs, split into frames on slave boundaries as SOEM segments it -
programs SyncManagers and FMMUs and requests SAFE-OP. The IO map is one
buffer (:attr:`InProcessMaster.iomap`) and each slave's ``output`` /
``input`` a part of it. Errors are pysoem's exception types, so the
backend's error mapping treats them as it treats SOEM's.

The cycle copies nothing it need not: the LRW frame is built once, in a
buffer of its own, and with one frame (up to 1486 bytes of process data) the
IO map *is* its LRW data, so the chain reads the outputs from and writes the
inputs into the IO map itself; per send only the working counters are
zeroed. ``send_processdata`` puts the frame on the "wire": the chain
processes it, at the send's time, when something next reaches the chain -
``receive_processdata``, another frame, or the next send - as a wire
delivers it while the master waits. A reply lost or held back past the
timeout is -1 as before; its inputs may then be in the IO map (SOEM would
not have copied them), so a caller takes inputs only after a working
counter in time, as the ethercat backend does.

Distributed clocks as SOEM sets them up (``config_dc``: delays and offsets
on a line, the first slave the reference; ``dc_sync``; the cycle's FRMW of
0x0910 gives ``dc_time``). Not (yet) offered: a redundant port, SOEM's own ``recover`` / ``reconfig`` (the backend uses its
own, :mod:`.ecat_raw`-free steps on ``_fprd`` / ``_fpwr`` here).
Time: the chain runs on ``clock`` (a :class:`~fieldbus.platform.clock.Clock`,
default the wall clock); a lost reply, or one held back longer than the
wait, counts as no frame (-1). On a virtual clock the master's waits pass
there (a lost frame costs its timeout, a state poll 1 ms, as in SOEM), so
runs are deterministic.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any

import numpy as np
import numpy.typing as npt
import pysoem

from fieldbus.core.al import AL_PREOP, AL_SAFEOP
from fieldbus.core.dc.master import line_propagation_delays, soem_offsets, sync0_start_time, sync1_period_ns
from fieldbus.core.dc.model import DcRegister, SyncActivation
from fieldbus.core.ecat import (
    DATAGRAM_HEADER_SIZE,
    ECAT_HEADER_SIZE,
    ETH_HEADER_SIZE,
    Command,
    Datagram,
    build_master_frame,
    decode_frame,
)
from fieldbus.core.pdo.model import DriveMap
from fieldbus.errors import BusTimeoutError, FieldbusError, SdoAbortError
from fieldbus.platform.clock import Clock, WallClock, is_virtual
from fieldbus.wire.framemaster import (
    SII_SM_INPUTS,
    SII_SM_OUTPUTS,
    FrameMaster,
    SlaveInfo,
    layout_image,
)

MAX_LRW_DATA = 1486  # datagram data per frame (SOEM's EC_MAXLRWDATA)
NO_FRAME = -1  # SOEM's EC_NOFRAME
RETURN_TIMEOUT_US = 2000  # SOEM's EC_TIMEOUTRET: a bring-up frame's wait
STATE_POLL_S = 0.001  # SOEM's statecheck polls every 1 ms
ASSIGN_RX, ASSIGN_TX = 0x1C12, 0x1C13  # PDO assignment objects (outputs, inputs)
_HEADER = ETH_HEADER_SIZE + ECAT_HEADER_SIZE + DATAGRAM_HEADER_SIZE  # where an LRW's data start
_WKC = 2  # bytes of a working counter
_FRMW_SIZE = DATAGRAM_HEADER_SIZE + 8 + _WKC  # the cycle's DC datagram (FRMW of 0x0910)
_ETH_MIN = 60  # a short frame is padded to the Ethernet minimum


class InProcessSlave:
    """One emulated slave as pysoem shows it (``Master.slaves[i]``); position 0-based."""

    def __init__(self, master: InProcessMaster, info: SlaveInfo) -> None:
        self._master = master
        self.info = info
        self.name, self.man, self.id, self.rev = info.name, info.vendor_id, info.product_id, info.revision
        self.state = 0  # AL state as last read (read_state / state_check) or set for write_state
        self.al_status = 0  # AL status code as last read
        self.is_lost = False
        self._out: npt.NDArray[np.uint8] = np.zeros(0, np.uint8)  # parts of the master's IO map
        self._in: npt.NDArray[np.uint8] = np.zeros(0, np.uint8)

    @property
    def output(self) -> bytes:
        return self._out.tobytes()

    @output.setter
    def output(self, value: bytes) -> None:
        if len(value) > self._out.size:
            raise ValueError(f"{len(value)} output bytes for a slave mapped with {self._out.size}")
        self._out[: len(value)] = np.frombuffer(value, np.uint8)

    @property
    def input(self) -> bytes:
        return self._in.tobytes()

    # -- registers: one frame each, no repeat (pysoem: WkcError unless exactly this slave answered) --
    def _fprd(self, address: int, size: int, timeout_us: int = 2000) -> bytes:
        d = self._master._once(
            Datagram.physical(Command.FPRD, self.info.station, address, bytes(size)), timeout_us
        )
        if d is None or d.wkc != 1:
            raise pysoem.WkcError()
        return bytes(d.data)

    def _fpwr(self, address: int, data: bytes, timeout_us: int = 2000) -> None:
        d = self._master._once(
            Datagram.physical(Command.FPWR, self.info.station, address, bytes(data)), timeout_us
        )
        if d is None or d.wkc != 1:
            raise pysoem.WkcError()

    # -- AL state ----------------------------------------------------------------------------------
    def write_state(self) -> int:
        return self._master.frames.fpwr(self.info.station, 0x0120, int(self.state).to_bytes(2, "little"))

    def state_check(self, expected_state: int, timeout: int = 2000) -> int:
        return self._master._state_check([self], expected_state, timeout)

    def recover(self, timeout: int = 500) -> int:
        """The slave at its position given its station address again (SOEM's ``recover``, simplified)."""
        try:
            if self._master.frames.al_status(self.info.station) is None:
                self._master.frames.assign_station(self.info.position)
        except FieldbusError:
            return 0
        self.is_lost = False
        return 1

    # -- CoE SDO (blocking, bring-up): pysoem's errors ---------------------------------------------
    def sdo_read(
        self, index: int, subindex: int, size: int = 0, ca: bool = False, *, release_gil: Any = None
    ) -> bytes:
        data = self._sdo(lambda: self._master.frames.sdo_upload(self.info, index, subindex), index, subindex)
        return bytes(data[:size]) if size else bytes(data)

    def sdo_write(
        self, index: int, subindex: int, data: bytes, ca: bool = False, *, release_gil: Any = None
    ) -> None:
        self._sdo(lambda: self._master.frames.sdo_download(self.info, index, subindex, data), index, subindex)

    def _sdo(self, call: Callable[[], Any], index: int, sub: int) -> Any:
        try:
            return call()
        except SdoAbortError as exc:
            raise pysoem.SdoError(self.info.position + 1, index, sub, exc.code, str(exc)) from None
        except BusTimeoutError:
            raise pysoem.WkcError() from None

    def dc_sync(
        self, act: bool, sync0_cycle_time: int, sync0_shift_time: int = 0, sync1_cycle_time: int | None = None
    ) -> None:
        """SYNC0 (and SYNC1) as SOEM's ``ecx_dcsync0`` / ``ecx_dcsync01``: off, start time, cycles, on."""
        self._fpwr(DcRegister.ACTIVATION, b"\x00")
        self._fpwr(DcRegister.CYCLIC_UNIT_CONTROL, b"\x00")
        now = int.from_bytes(self._fprd(DcRegister.SYSTEM_TIME, 8), "little")
        base = (
            sync0_cycle_time
            if sync1_cycle_time is None
            else sync1_period_ns(sync0_cycle_time, sync1_cycle_time)
        )
        start = sync0_start_time(now, base, sync0_shift_time)
        self._fpwr(DcRegister.START_TIME_CYCLIC, (start & (1 << 64) - 1).to_bytes(8, "little"))
        self._fpwr(DcRegister.SYNC0_CYCLE_TIME, sync0_cycle_time.to_bytes(4, "little"))
        bits = SyncActivation.CYCLIC_OPERATION | SyncActivation.SYNC0
        if sync1_cycle_time is not None:
            self._fpwr(DcRegister.SYNC1_CYCLE_TIME, sync1_cycle_time.to_bytes(4, "little"))
            bits |= SyncActivation.SYNC1
        self._fpwr(DcRegister.ACTIVATION, bytes([int(bits) if act else 0]))


class InProcessMaster:
    """pysoem's ``Master`` on the in-process ESC chain (see the module). Not thread-safe, as pysoem."""

    def __init__(
        self,
        maps: Sequence[DriveMap],
        *,
        drive_params: Sequence[Any] | None = None,
        clock: Clock | None = None,
    ) -> None:
        from fieldbus.emulators import emulator_part

        chain_cls = emulator_part("ethercat_chain")
        self.chain = chain_cls.from_maps(list(maps), drive_params=drive_params)
        # a virtual clock: the master's waits (a lost or held-back reply, state polls) pass on it
        self._waits: Clock = clock if clock is not None else WallClock()
        self._virtual = is_virtual(self._waits)
        self.clock: Callable[[], int] = self._waits.now_ns
        self._held_s = 0.0  # how long the last process-data reply was held back (chain fault: delay)
        self._hold_s, self._hold_cycles = 0.0, 0  # process-data replies still to hold back (hold_processdata)
        self.frames = FrameMaster(self._transport)
        self.slaves: list[InProcessSlave] = []
        self.iomap: npt.NDArray[np.uint8] | None = None  # the IO map: outputs, then inputs
        self.state = 0
        self.dc_time = 0
        self._expected_wkc = 0
        self._out_bytes = 0
        self._dc_reference: int | None = None  # station of the reference clock once config_dc ran
        # the cycle's LRW frames: preallocated, built at config_map / config_dc, sent in place
        self._frames: list[_LrwFrame] = []
        self._in_flight_ns: int | None = None  # a process-data send the chain has not processed yet: when
        self._wkc = NO_FRAME
        self._idx = 0

    # -- frames -------------------------------------------------------------------------------------
    def _transport(self, frame: bytes, timeout_us: int = RETURN_TIMEOUT_US) -> bytes | None:
        """One frame through the chain; a reply lost or held back longer than ``timeout_us`` is None.
        On a virtual clock the wait passes there (on the wall clock the reply is there at once)."""
        self._deliver()  # a process-data frame still on its way is processed first (wire order)
        reply: bytes | None = self.chain.process(frame, self.clock())
        held = self.chain.take_delay()
        late = reply is None or held > timeout_us / 1e6
        if self._virtual:
            self._waits.sleep(timeout_us / 1e6 if late else held)
        return None if late else reply

    def _once(self, datagram: Datagram, timeout_us: int = RETURN_TIMEOUT_US) -> Datagram | None:
        """One frame of one datagram, not repeated; the datagram as it came back, None when lost."""
        self._idx = (self._idx + 1) & 0xFF
        frame = build_master_frame([Datagram(datagram.cmd, self._idx, datagram.address, datagram.data)])
        reply = self._transport(frame, timeout_us)
        return None if reply is None else decode_frame(reply).datagrams[0]

    # -- bring-up -------------------------------------------------------------------------------------
    def open(self, ifname: str, ifname_red: str | None = None) -> None:
        if ifname_red:
            raise FieldbusError("the in-process transport has no redundant port")

    def close(self) -> None:
        self.iomap, self._frames, self._in_flight_ns = None, [], None

    def config_init(self, usetable: bool = False, *, release_gil: Any = None) -> int:
        """SOEM's ``config_init``: reset, station addresses, SII, mailbox SyncManagers, PRE-OP requested."""
        found = self.frames.scan()
        if found <= 0:
            self.slaves = []
            return found
        infos = self.frames.identify(found)
        self.slaves = [InProcessSlave(self, info) for info in infos]
        for info in infos:
            self.frames.setup_mailbox(info)
            self.frames.request_state(info.station, AL_PREOP)
        return found

    def config_map(self) -> None:
        """SOEM's ``config_map``: process data sizes from the slaves, SM2/SM3 and FMMUs, SAFE-OP requested."""
        sizes = [
            (
                self._pdo_bytes(s.info, ASSIGN_RX, SII_SM_OUTPUTS),
                self._pdo_bytes(s.info, ASSIGN_TX, SII_SM_INPUTS),
            )
            for s in self.slaves
        ]
        mappings, out_bytes, in_bytes = layout_image(sizes)
        self._out_bytes, self._in_flight_ns = out_bytes, None
        blocks = [(m.out_offset, m.out_size) for m in mappings if m.out_size]
        self._frames = _lrw_frames(
            blocks + [(m.in_offset, m.in_size) for m in mappings if m.in_size], out_bytes
        )
        # one frame: the IO map is its LRW data, in place (what the chain reads and writes); more: a map
        # of its own, each frame's part copied in before the send and its inputs out after the reply
        single = len(self._frames) == 1
        iomap = self._frames[0].data if single else np.zeros(out_bytes + in_bytes, np.uint8)
        for f in self._frames:
            f.iomap_part = None if single else iomap[f.lo : f.hi]
        for s, m in zip(self.slaves, mappings, strict=True):
            self.frames.map_process_data(s.info, m)
            s._out = iomap[m.out_offset : m.out_offset + m.out_size]
            s._in = iomap[m.in_offset : m.in_offset + m.in_size]
        self.iomap = iomap
        self._expected_wkc = 2 * sum(1 for o, _ in sizes if o) + sum(1 for _, i in sizes if i)
        self._build_frames()
        for s in self.slaves:
            self.frames.request_state(s.info.station, AL_SAFEOP)

    def _build_frames(self) -> None:
        """The cycle's LRW frame(s) written into their buffers; with DC, the first also carries SOEM's
        FRMW of the reference clock's system time (0x0910), read back as :attr:`dc_time`. The LRW
        data stay where they are (the IO map is a view of them)."""
        for k, f in enumerate(self._frames):
            frmw = k == 0 and self._dc_reference is not None
            f.write_headers(0x80 | k, self._dc_reference if frmw else None)

    def _pdo_bytes(self, info: SlaveInfo, assign: int, sm_type: int) -> int:
        """Process data bytes of one direction: the assigned PDOs' entries (CoE), else the SII SM length."""
        if not info.mbx_out[1]:
            sm = info.sm(sm_type)
            return sm.length if sm is not None else 0
        bits = 0
        for k in range(1, self.frames.sdo_upload(info, assign, 0)[0] + 1):
            pdo = int.from_bytes(self.frames.sdo_upload(info, assign, k)[:2], "little")
            for e in range(1, self.frames.sdo_upload(info, pdo, 0)[0] + 1):
                bits += self.frames.sdo_upload(info, pdo, e)[0]  # entry: index, sub-index, bit length
        return (bits + 7) // 8

    def config_dc(self) -> bool:
        """SOEM's ``ecx_configdc`` on a line: receive times latched, propagation delays (0x0928) and
        system time offsets (0x0920) written; the first slave is the reference clock. False: no DC."""
        if not self.slaves:
            return False
        if self._once(Datagram.physical(Command.BWR, 0, DcRegister.RECEIVE_TIME_PORT0, bytes(4))) is None:
            return False
        master_ns = self.clock()
        port0, port1, epu = [], [], []
        try:
            for k, s in enumerate(self.slaves):
                port0.append(int.from_bytes(s._fprd(DcRegister.RECEIVE_TIME_PORT0, 4), "little"))
                last = k == len(self.slaves) - 1  # its port 1 is closed (the end of the line)
                p1 = int.from_bytes(s._fprd(DcRegister.RECEIVE_TIME_PORT1, 4), "little")
                port1.append(None if last else p1)
                epu.append(int.from_bytes(s._fprd(DcRegister.RECEIVE_TIME_EPU, 8), "little"))
        except pysoem.WkcError:
            return False
        delays = line_propagation_delays(port0, port1)
        for s, offset, delay in zip(self.slaves, soem_offsets(master_ns, epu), delays, strict=True):
            s._fpwr(DcRegister.SYSTEM_TIME_OFFSET, (offset & (1 << 64) - 1).to_bytes(8, "little"))
            s._fpwr(DcRegister.SYSTEM_TIME_DELAY, (delay & (1 << 32) - 1).to_bytes(4, "little"))
        self._dc_reference = self.slaves[0].info.station
        if self.iomap is not None:
            self._build_frames()
        return True

    @property
    def expected_wkc(self) -> int:
        return self._expected_wkc

    # -- AL states --------------------------------------------------------------------------------------
    def write_state(self) -> int:
        """Every slave to :attr:`state` (one broadcast write); its working counter, -1 when lost."""
        d = self._once(Datagram.physical(Command.BWR, 0, 0x0120, int(self.state).to_bytes(2, "little")))
        return NO_FRAME if d is None else d.wkc

    def read_state(self) -> int:
        """Each slave's AL status and code read (``slave.state``, ``slave.al_status``); the lowest state."""
        lowest = 0xFF
        for s in self.slaves:
            got = self.frames.al_status(s.info.station) if not s.is_lost else None
            s.state, s.al_status = got if got is not None else (0, 0)
            lowest = min(lowest, s.state & 0x0F)
        return 0 if lowest == 0xFF else lowest

    def state_check(self, expected_state: int, timeout: int = 50000) -> int:
        return self._state_check(self.slaves, expected_state, timeout)

    def _state_check(self, slaves: Sequence[InProcessSlave], expected: int, timeout_us: int) -> int:
        """Poll the slaves' AL status until all show ``expected`` or ``timeout_us`` passed on the chain's
        clock (at least one poll); the state found (the lowest), as SOEM's ``statecheck``."""
        end = self.clock() + timeout_us * 1000
        while True:
            lowest, error = 0xFF, 0
            for s in slaves:
                got = self.frames.al_status(s.info.station)
                s.state, s.al_status = got if got is not None else (0, 0)
                lowest = min(lowest, s.state & 0x0F)
                error |= s.state & 0x10  # a slave that refused: its error indicator shows in the result
            found = 0 if lowest == 0xFF else lowest | error
            if found == expected or self.clock() >= end:
                return found
            self._waits.sleep(STATE_POLL_S)

    # -- cycle ----------------------------------------------------------------------------------------
    def send_processdata(self, *, release_gil: Any = None) -> int:
        """The LRW frame(s) of the IO map onto the wire: the chain processes them before anything else
        reaches it (:meth:`receive_processdata`, another frame or the next send), at this send's time."""
        if self.iomap is None:
            return 0
        if self._in_flight_ns is not None:
            self._deliver()  # the last cycle's frames if never received: processed, their reply dropped
        frames = self._frames
        for f in frames:
            if f.iomap_part is not None:
                np.copyto(f.data, f.iomap_part)
            buf, at = f.buf, f.wkc_at  # its working counters zeroed (LRW, and the FRMW's)
            buf[at] = buf[at + 1] = 0
            if f.frmw_at:
                buf[f.frmw_at + 8] = buf[f.frmw_at + 9] = 0
        self._held_s = 0.0
        if self._hold_cycles:
            self._hold_cycles -= 1
            self._held_s = self._hold_s
        self._in_flight_ns = self.clock()
        return len(frames)

    def _deliver(self) -> None:
        """The frames sent and not yet processed go through the chain now (as they would have on the wire
        meanwhile): their working counter and the DC time kept for :meth:`receive_processdata`."""
        now = self._in_flight_ns
        if now is None:
            return
        self._in_flight_ns = None
        wkc = 0
        chain = self.chain
        for f in self._frames:
            got = chain.process_into(f.buf, f.size, now)
            held = chain.take_delay()
            if held > self._held_s:
                self._held_s = held
            if got == 0:
                self._wkc = NO_FRAME
                return
            if f.frmw_at:
                self.dc_time = int.from_bytes(f.buf[f.frmw_at : f.frmw_at + 8], "little")
            if f.iomap_part is not None and f.in_lo < f.hi:  # its inputs into the IO map (outputs stay)
                np.copyto(f.iomap_part[f.in_lo - f.lo :], f.data[f.in_lo - f.lo :])
            buf, at = f.buf, f.wkc_at
            wkc += buf[at] | buf[at + 1] << 8
        self._wkc = wkc

    def hold_processdata(self, seconds: float, cycles: int) -> None:
        """The process-data replies of the next ``cycles`` sends come back ``seconds`` late (a fault hook:
        other frames are not held back, as the chain's ``delay_frames`` would hold them); 0 cycles: off."""
        self._hold_s, self._hold_cycles = seconds, cycles

    def receive_processdata(self, timeout: int = 2000, *, release_gil: Any = None) -> int:
        """The working counter of the last send, -1 (EC_NOFRAME) when its reply was lost or held back
        longer than ``timeout`` (µs); on a virtual clock the wait passes there."""
        if self._in_flight_ns is not None:
            self._deliver()
        wkc, self._wkc = self._wkc, NO_FRAME
        held, self._held_s = self._held_s, 0.0
        late = wkc == NO_FRAME or held > timeout / 1e6
        if self._virtual:
            self._waits.sleep(timeout / 1e6 if late else held)
        return NO_FRAME if late else wkc


class _LrwFrame:
    """One LRW frame of the cycle in a buffer of its own, allocated once: the LRW's data at a fixed place
    (:attr:`data`, a view), headers rewritten only at bring-up, the working counters zeroed per send."""

    def __init__(self, lo: int, hi: int, out_bytes: int) -> None:
        self.lo, self.hi = lo, hi  # the logical bytes it carries
        self.in_lo = min(max(lo, out_bytes), hi)  # where its inputs start (logical)
        n = hi - lo
        self.buf = bytearray(_HEADER + n + _WKC + _FRMW_SIZE + _ETH_MIN)
        self.data: npt.NDArray[np.uint8] = np.frombuffer(self.buf, np.uint8, n, _HEADER)
        self.iomap_part: npt.NDArray[np.uint8] | None = None  # the IO map's part when it is not ``data``
        self.wkc_at = _HEADER + n
        self.frmw_at = 0  # where the FRMW's data are (0: none)
        self.size = 0

    def write_headers(self, idx: int, dc_station: int | None) -> None:
        """Ethernet, EtherCAT and datagram headers (and the FRMW of 0x0910 at ``dc_station``) in place,
        around the LRW data as they are."""
        dgs = [Datagram(Command.LRW, idx, self.lo, bytes(self.data.size))]
        if dc_station is not None:
            dgs.append(Datagram.physical(Command.FRMW, dc_station, DcRegister.SYSTEM_TIME, bytes(8)))
        frame = build_master_frame(dgs)
        data = self.data.copy()
        self.buf[: len(frame)] = frame
        self.data[:] = data
        self.size = len(frame)
        self.frmw_at = self.wkc_at + _WKC + DATAGRAM_HEADER_SIZE if dc_station is not None else 0


def _lrw_frames(blocks: Sequence[tuple[int, int]], out_bytes: int) -> list[_LrwFrame]:
    """The IO map in LRW frames, split as SOEM's ``ecx_config_map`` segments it: on the slaves' FMMU
    blocks (``blocks``: logical offset and size, outputs then inputs), at most :data:`MAX_LRW_DATA`
    bytes a frame and the first one room left for the DC datagram; a block never spans two frames
    (its slave would answer in both: a working counter too high)."""
    frames: list[_LrwFrame] = []
    start = end = 0
    for off, size in blocks:
        room = MAX_LRW_DATA - (0 if frames else _FRMW_SIZE)
        if off + size - start > room and end > start:
            frames.append(_LrwFrame(start, end, out_bytes))
            start = off
        end = off + size
    if end > start:
        frames.append(_LrwFrame(start, end, out_bytes))
    return frames
