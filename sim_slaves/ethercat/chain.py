"""A line of emulated ESCs, sans-IO: a master frame in, the returning frame out.

Each datagram passes every slave in wire order (processing datagram by
datagram is equivalent: a slave only changes its own memory). Working-counter
rules (ETG.1000.4): a read adds 1, a write 1; APRW/FPRW/BRW add 3 per slave
that reads and writes; LRW adds 1 per slave with a read FMMU hit and 2 per
slave with a write hit (3 for both); ARMW/FRMW add 1 per slave. Auto-increment
and broadcast commands increment ADP at every slave; a position command
addresses the slave where ADP arrives as 0. BRD ORs the slaves' data.
The reply has the request's length and the locally administered bit (0x02)
set in the first source-MAC byte. MAC addresses are not evaluated, and a
frame with an 802.1Q VLAN tag (ethertype 0x8100, TCI, then 0x88A4) is
processed like an untagged one, the tag returned unchanged (ESCs ignore the
tag's contents).

Distributed clocks: each slave's :class:`~sim_slaves.ethercat.dc.EscDc` sits
on the line as :func:`fieldbus.core.dc.master.line_timing` puts it (cable
``cable_m`` per hop, ESC delays ``dc_timing``), so a BWR to 0x0900 latches
per-port receive times consistent with the line. An ARMW/FRMW of 4 or 8 bytes
at 0x0910 is the system-time distribution: the addressed slave (the reference
clock) puts its system time into the datagram as the frame passes it, every
later slave gives that time to its time-control loop, every earlier one the
master's original data (as on the wire). The loop samples are queued with
their times and applied, in order, when the I/O layer is idle or before the
next access to a clock (:class:`~sim_slaves.ethercat.dc.DcLine`).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

from fieldbus.core.dc.model import DcRegister, EscTiming, SyncActivation, wrap_signed
from fieldbus.core.ecat import DATAGRAM_HEADER_SIZE, LOCALLY_ADMINISTERED, datagram_offsets
from fieldbus.core.pdo.model import DriveMap
from sim_slaves.ethercat.al import AlState
from sim_slaves.ethercat.dc import DC_END, DC_FIRST, DC_MIN_SAMPLE_INTERVAL_NS, DcLine, EscDc
from sim_slaves.ethercat.esc import App, Esc
from sim_slaves.ethercat.sii import SiiImage, build_sii
from sim_slaves.od import ObjectDictionary

ETHERTYPE_VLAN = 0x8100  # IEEE 802.1Q tag protocol identifier
VLAN_TAG_SIZE = 4  # TPID + TCI, between the source MAC and the EtherCAT ethertype [bytes]
WATCHDOG_CHECK_NS = 1_000_000  # process-data watchdogs are checked at most this often [ns]
#: ``from_maps``: slave i's local clock reads i x this at true time 0 (ESCs power up at different moments)
DC_POWER_UP_STAGGER_NS = 1_000_000
_SYSTEM_TIME = int(DcRegister.SYSTEM_TIME)
AppFactory = Callable[[DriveMap, ObjectDictionary], App | None]

_APRD, _APWR, _APRW = 1, 2, 3
_FPRD, _FPWR, _FPRW = 4, 5, 6
_BRD, _BWR, _BRW = 7, 8, 9
_LRD, _LWR, _LRW = 10, 11, 12
_ARMW, _FRMW = 13, 14
_ADDRESS_WRITERS = frozenset({_APWR, _APRW, _FPWR, _FPRW, _BWR, _BRW, _ARMW, _FRMW})


@dataclass
class Faults:
    """Pending fault injections of a chain (see :class:`EscChain` fault hooks)."""

    drop: int = 0
    drop_pd: int = 0  # process-data frames only (frames with a logical datagram)
    delay_frames: int = 0
    delay_s: float = 0.0
    corrupt_frames: int = 0
    corrupt_delta: int = -1
    corrupt_all: bool = False
    log: list[str] = field(default_factory=list)


class EscChain:
    """N slaves in a line. ``process(frame, now_ns)`` is the whole wire interface.

    ``dc_timing``: every ESC's processing/forwarding delay (default
    :class:`~fieldbus.core.dc.model.EscTiming`), ``cable_m``: metres of cable
    master -> slave 0 and between neighbours (5 ns/m);
    ``dc_min_sample_interval_ns``: see :class:`~sim_slaves.ethercat.dc.DcLine`
    (0: every ARMW/FRMW feeds the loops).
    """

    def __init__(
        self,
        slaves: Sequence[Esc],
        *,
        dc_timing: EscTiming | None = None,
        cable_m: float = 1.0,
        dc_min_sample_interval_ns: int = DC_MIN_SAMPLE_INTERVAL_NS,
    ) -> None:
        self.slaves = list(slaves)
        self.faults = Faults()
        self.frames = 0
        self.pending_delay = 0.0
        self._stations: dict[int, list[Esc]] | None = None
        self.drive_maps: list[DriveMap] | None = None  # set by from_maps: what a power cycle resets to
        self._watchdog_checked = -WATCHDOG_CHECK_NS
        self._wire_index = {id(s): i for i, s in enumerate(self.slaves)}
        self.dc_line = DcLine([s.dc for s in self.slaves], min_sample_interval_ns=dc_min_sample_interval_ns)
        self.dc_timing = dc_timing or EscTiming()
        self.cable_m = float(cable_m)
        self.dc_line.place(self.dc_timing, self.cable_m)

    @classmethod
    def from_maps(
        cls,
        maps: Sequence[DriveMap],
        *,
        app: str | AppFactory | None = "auto",
        sii: Sequence[SiiImage | None] | None = None,
        drift_ppm: Sequence[float] | None = None,
        dc_timing: EscTiming | None = None,
        cable_m: float = 1.0,
        dc_min_sample_interval_ns: int = DC_MIN_SAMPLE_INTERVAL_NS,
    ) -> EscChain:
        """One slave per map, in wire order. ``app``: "auto" (CiA 402 drive for 402 maps), None, or a factory.

        ``drift_ppm``: each slave's clock drift (default 0); slave i's local
        time starts at i x :data:`DC_POWER_UP_STAGGER_NS`.
        """
        n = len(maps)
        if drift_ppm is not None and len(drift_ppm) != n:
            raise ValueError(f"need {n} drifts (one per slave), got {len(drift_ppm)}")
        slaves = []
        for i, drive in enumerate(maps):
            od = ObjectDictionary.from_drive_map(drive)
            image = sii[i] if sii is not None and sii[i] is not None else build_sii(drive)
            assert image is not None
            factory = default_app if app == "auto" else app
            the_app = factory(drive, od) if callable(factory) else None
            dc = EscDc(
                drift_ppm=0.0 if drift_ppm is None else float(drift_ppm[i]),
                initial_local_ns=i * DC_POWER_UP_STAGGER_NS,
                timing=dc_timing,
            )
            slaves.append(Esc(image, od, position=i, chain_length=n, app=the_app, name=drive.name, dc=dc))
        chain = cls(
            slaves, dc_timing=dc_timing, cable_m=cable_m, dc_min_sample_interval_ns=dc_min_sample_interval_ns
        )
        chain.drive_maps = list(maps)
        return chain

    def __len__(self) -> int:
        return len(self.slaves)

    # -- wire --

    def process(self, frame: bytes | bytearray, now_ns: int) -> bytes | None:
        """The frame as it returns to the master, or None when it is lost (fault: drop)."""
        buf = bytearray(frame)
        n = self.process_into(buf, len(buf), now_ns)
        return bytes(buf[:n]) if n else None

    def process_into(self, buf: bytearray, n: int, now_ns: int, *, cycles: bool = True) -> int:
        """In place: process the first ``n`` bytes of ``buf``; returns the reply length (0: drop).

        ``cycles`` False leaves the slaves' application cycles (outputs -> OD,
        app step, OD -> inputs) to :meth:`run_cycles`, so an I/O layer can
        send the reply first: the inputs it computes travel in the next frame
        either way. A VLAN tag stays where it is. Raises
        :class:`~fieldbus.core.ecat.FrameError` for a malformed frame.
        """
        if n >= 18 and buf[12] == ETHERTYPE_VLAN >> 8 and buf[13] == ETHERTYPE_VLAN & 0xFF:
            # the codec reads the ethertype at byte 12: hand it the frame from 4 bytes on
            offsets = [off + VLAN_TAG_SIZE for off in datagram_offsets(memoryview(buf)[VLAN_TAG_SIZE:n])]
        else:
            offsets = datagram_offsets(memoryview(buf)[:n])
        self.frames += 1
        faults = self.faults
        slaves = self.slaves
        if now_ns - self._watchdog_checked >= WATCHDOG_CHECK_NS:
            self._watchdog_checked = now_ns
            for s in slaves:
                if s.state == AlState.OP:
                    s.check_watchdog(now_ns)
        if faults.drop:
            faults.drop -= 1
            return 0
        if faults.drop_pd and any(_LRD <= buf[off] <= _LRW for off in offsets):
            faults.drop_pd -= 1
            return 0
        count = len(slaves)
        logical = False
        for off in offsets:
            cmd = buf[off]
            adp = buf[off + 2] | buf[off + 3] << 8
            ado = buf[off + 4] | buf[off + 5] << 8
            length = (buf[off + 6] | buf[off + 7] << 8) & 0x7FF
            doff = off + DATAGRAM_HEADER_SIZE
            woff = doff + length
            wkc = buf[woff] | buf[woff + 1] << 8
            if _LRD <= cmd <= _LRW:
                logical = True
                laddr = adp | ado << 16
                for s in slaves:
                    if s.pd_active:
                        wkc += s.logical(cmd, laddr, buf, doff, length)
            elif cmd in (_FPRD, _FPWR, _FPRW, _FRMW):
                targets = self._by_station(adp)
                if cmd == _FRMW:
                    wkc += self._rmw(targets, buf, doff, length, ado, now_ns)
                else:
                    for s in targets:
                        wkc += _physical(s, cmd - 3, buf, doff, length, ado, now_ns)
            elif cmd in (_APRD, _APWR, _APRW):
                pos = (-adp) & 0xFFFF
                if pos < count:
                    wkc += _physical(slaves[pos], cmd, buf, doff, length, ado, now_ns)
                _put16(buf, off + 2, adp + count)
            elif cmd in (_BRD, _BWR, _BRW):
                wkc += self._broadcast(cmd, buf, doff, length, ado, now_ns)
                _put16(buf, off + 2, adp + count)
            elif cmd == _ARMW:
                pos = (-adp) & 0xFFFF
                targets = [slaves[pos]] if pos < count else []
                wkc += self._rmw(targets, buf, doff, length, ado, now_ns)
                _put16(buf, off + 2, adp + count)
            if cmd in _ADDRESS_WRITERS and ado <= 0x0103 and ado + length > 0x0010:
                self._stations = None  # station address / alias / DL control may have changed
            if faults.corrupt_frames and (logical or faults.corrupt_all):
                wkc += faults.corrupt_delta
            _put16(buf, woff, wkc)
        if faults.corrupt_frames and (logical or faults.corrupt_all):
            faults.corrupt_frames -= 1
        buf[6] |= LOCALLY_ADMINISTERED
        if cycles:
            if logical:
                self.run_cycles(now_ns)
            if self.dc_line.pending:
                self.dc_line.flush()
        if faults.delay_frames:
            faults.delay_frames -= 1
            self.pending_delay = faults.delay_s
        return n

    def run_cycles(self, now_ns: int) -> None:
        """Application cycle of every slave whose process data the last frame exchanged."""
        for s in self.slaves:
            if s.touched:
                s.cycle(now_ns)

    def tick(self, now_ns: int) -> None:
        """Time passes without frames (process-data watchdogs)."""
        for s in self.slaves:
            s.check_watchdog(now_ns)

    def take_delay(self) -> float:
        """Seconds the I/O layer should hold the last reply back (fault: delay), then 0."""
        d, self.pending_delay = self.pending_delay, 0.0
        return d

    # -- addressing helpers --

    def _by_station(self, adp: int) -> list[Esc]:
        st = self._stations
        if st is None:
            st = {}
            for s in self.slaves:
                st.setdefault(s.station_address, []).append(s)
                if s.alias_enabled and s.alias != s.station_address:
                    st.setdefault(s.alias, []).append(s)
            self._stations = st
        return st.get(adp, [])

    def _broadcast(self, cmd: int, buf: bytearray, doff: int, length: int, ado: int, now_ns: int) -> int:
        inc = 0
        data = bytes(buf[doff : doff + length])
        acc = int.from_bytes(data, "little")
        for s in self.slaves:
            if cmd != _BWR:
                got = s.read(ado, length, now_ns)
                if got is not None:
                    acc |= int.from_bytes(got, "little")
                    inc += 1
            if cmd != _BRD and s.write(ado, data, now_ns):
                inc += 1 if cmd == _BWR else 2
        if cmd != _BWR:
            buf[doff : doff + length] = acc.to_bytes(length, "little")
        return inc

    def _rmw(self, targets: list[Esc], buf: bytearray, doff: int, length: int, ado: int, now_ns: int) -> int:
        """ARMW/FRMW: the addressed slave reads into the datagram, every other slave writes it."""
        if ado == _SYSTEM_TIME and (length == 8 or length == 4) and len(targets) == 1:
            return self._distribute_system_time(targets[0], buf, doff, length, now_ns)
        inc = 0
        for s in self.slaves:
            if s in targets:
                got = s.read(ado, length, now_ns)
                if got is not None:
                    buf[doff : doff + length] = got
                    inc += 1
            elif s.write(ado, bytes(buf[doff : doff + length]), now_ns):
                inc += 1
        return inc

    def _distribute_system_time(self, ref: Esc, buf: bytearray, doff: int, length: int, now_ns: int) -> int:
        """ARMW/FRMW on 0x0910 (the cycle's DC datagram): the reference's time in, the others' loops fed.

        The loop samples are queued on :attr:`dc_line`: :meth:`process` applies
        them before it returns, an I/O layer that uses ``process_into(...,
        cycles=False)`` calls ``dc_line.flush()`` when idle; any other DC access
        applies them first anyway.
        """
        sent = buf[doff] | buf[doff + 1] << 8 | buf[doff + 2] << 16 | buf[doff + 3] << 24
        i_ref = self._wire_index[id(ref)]
        line = self.dc_line
        t = line.reference_time(i_ref, now_ns)
        buf[doff : doff + length] = t.to_bytes(8, "little")[:length]
        line.distribute(i_ref, sent, t & 0xFFFF_FFFF, now_ns)
        return len(self.slaves)

    # -- distributed clocks --

    def set_dc_line(self, timing: EscTiming | None = None, cable_m: float | None = None) -> None:
        """Put the slaves on a line: ESC delays ``timing``, ``cable_m`` metres per hop (None: keep)."""
        if timing is not None:
            self.dc_timing = timing
        if cable_m is not None:
            self.cable_m = float(cable_m)
        self.dc_line.place(self.dc_timing, self.cable_m)

    def set_dc_drift(self, drift_ppm: Sequence[float], now_ns: int) -> None:
        """Slave i's crystal runs ``drift_ppm[i]`` off from true time ``now_ns`` on."""
        if len(drift_ppm) != len(self.slaves):
            raise ValueError(f"need {len(self.slaves)} drifts (one per slave), got {len(drift_ppm)}")
        for s, d in zip(self.slaves, drift_ppm, strict=True):
            s.dc.set_drift(float(d), now_ns)

    def dc_status(self, now_ns: int) -> list[dict[str, Any]]:
        """Every slave's DC registers and clock at one true instant ``now_ns`` (JSON-friendly).

        ``system_time``/``local_time``: the clocks at ``now_ns`` itself (not
        shifted by the slave's place on the line), so their spread is how well
        the clocks agree. Register values as the master would read them;
        ``sync0_next_ns``: true time of the next SYNC0 pulse (None if off).
        """
        out: list[dict[str, Any]] = []
        for s in self.slaves:
            c = s.dc.clock
            mem = c.read_register(DC_FIRST, DC_END - DC_FIRST, now_ns)

            def u(reg: int, size: int, mem: bytes = mem) -> int:
                return int.from_bytes(mem[reg - DC_FIRST : reg - DC_FIRST + size], "little")

            diff = u(DcRegister.SYSTEM_TIME_DIFF, 4)
            out.append(
                {
                    "system_time": c.system_time(now_ns),
                    "local_time": c.local_time(now_ns),
                    "receive_time_ports": [u(DcRegister.RECEIVE_TIME_PORT0 + 4 * p, 4) for p in range(4)],
                    "receive_time_epu": u(DcRegister.RECEIVE_TIME_EPU, 8),
                    "offset": u(DcRegister.SYSTEM_TIME_OFFSET, 8),
                    "delay": u(DcRegister.SYSTEM_TIME_DELAY, 4),
                    "system_time_diff": -(diff & 0x7FFF_FFFF) if diff & 0x8000_0000 else diff,
                    "speed_counter_start": u(DcRegister.SPEED_COUNTER_START, 2),
                    "cyclic_unit_control": u(DcRegister.CYCLIC_UNIT_CONTROL, 1),
                    "activation": u(DcRegister.ACTIVATION, 1),
                    "start_time": u(DcRegister.START_TIME_CYCLIC, 8),
                    "sync0_cycle": u(DcRegister.SYNC0_CYCLE_TIME, 4),
                    "sync1_cycle": u(DcRegister.SYNC1_CYCLE_TIME, 4),
                    "sync0_next_ns": _next_sync0(s.dc, now_ns),
                    "drift_ppm": c.drift_ppm,
                    "rate_ppm": (c.rate - 1.0) * 1e6,
                    "port0_ns": s.dc.port0_ns,
                    "port1_ns": s.dc.port1_ns,
                }
            )
        return out

    # -- fault hooks --

    def drop_frames(self, count: int = 1, *, process_data: bool = False) -> None:
        """Lose the next ``count`` frames (no reply, nothing processed).

        ``process_data``: only frames carrying a logical datagram (the cycle's
        LRW) count, so a master's acyclic frames in between are not lost.
        """
        if process_data:
            self.faults.drop_pd += count
        else:
            self.faults.drop += count

    def delay_frames(self, seconds: float, count: int = 1) -> None:
        """Hold back the replies of the next ``count`` frames by ``seconds`` (the I/O layer sleeps)."""
        self.faults.delay_frames = count
        self.faults.delay_s = seconds

    def corrupt_wkc(self, delta: int = -1, count: int = 1, *, all_frames: bool = False) -> None:
        """Add ``delta`` to every datagram WKC of the next ``count`` process-data frames (or any frames)."""
        self.faults.corrupt_frames = count
        self.faults.corrupt_delta = delta
        self.faults.corrupt_all = all_frames

    def power_cycle(self, slave: int) -> None:
        """Slave ``slave`` (0-based) loses power and comes back: registers reset, state INIT.

        Its drive application restarts too (CiA 402: NOT READY TO SWITCH ON),
        and, for a chain built from drive maps, its object dictionary goes back
        to the map's defaults: PDO mapping and start-up values written by SDO are
        lost, as on a drive that did not store them, so the master must apply
        its SDO plan again (SOEM's reconfig hook, our recovery).
        """
        esc = self.slaves[slave]
        if self.drive_maps is not None:
            od = ObjectDictionary.from_drive_map(self.drive_maps[slave])
            esc.od = od
            esc.mailbox.sdo.od = od
        esc.power_on()
        reset = getattr(esc.app, "power_cycle", None)
        if callable(reset):
            reset()
        self._stations = None

    def refuse_state(self, slave: int, state: AlState, code: int) -> None:
        """Slave ``slave`` refuses to enter ``state`` with AL status code ``code`` (until cleared)."""
        self.slaves[slave].refuse[state] = code

    def abort_sdo(self, slave: int, index: int, sub: int | None, code: int) -> None:
        """SDO accesses to ``index:sub`` on slave ``slave`` abort with ``code`` (until cleared)."""
        self.slaves[slave].od.inject_abort(index, sub, code)

    def emergency(self, slave: int, error_code: int, error_register: int = 0) -> None:
        """Slave ``slave`` sends a CoE emergency message."""
        self.slaves[slave].send_emergency(error_code, error_register)

    def clear_faults(self) -> None:
        """Undo every pending or persistent fault injection."""
        self.faults = Faults()
        self.pending_delay = 0.0
        for s in self.slaves:
            s.refuse.clear()
            s.od.clear_aborts()


def _physical(s: Esc, cmd: int, buf: bytearray, doff: int, length: int, ado: int, now_ns: int) -> int:
    """APRD/APWR/APRW (FP* mapped onto them): one slave's read (+1), write (+1) or both (+3)."""
    if cmd == _APRD:
        got = s.read(ado, length, now_ns)
        if got is None:
            return 0
        buf[doff : doff + length] = got
        return 1
    data = bytes(buf[doff : doff + length])
    if cmd == _APWR:
        return 1 if s.write(ado, data, now_ns) else 0
    got = s.read(ado, length, now_ns)
    inc = 0
    if got is not None:
        inc += 1
    if s.write(ado, data, now_ns):
        inc += 2
    if got is not None:
        buf[doff : doff + length] = got
    return inc


def _next_sync0(dc: EscDc, now_ns: int) -> int | None:
    """True time of the first SYNC0 pulse at or after ``now_ns`` (None: SYNC0 off)."""
    c = dc.clock
    need = SyncActivation.CYCLIC_OPERATION | SyncActivation.SYNC0
    if c.activation & need != need:
        return None
    ahead = wrap_signed(c.system_time(now_ns) - c.start_time_ns, 64)  # > 0: past the start time
    cycle = c.sync0_cycle_ns
    k = 0 if ahead <= 0 or cycle <= 0 else -(-ahead // cycle)
    if ahead > 0 and cycle <= 0:
        return None  # the single pulse has gone
    return c.true_time_of_system(c.start_time_ns + k * cycle, now_ns)


def _put16(buf: bytearray, off: int, value: int) -> None:
    value &= 0xFFFF
    buf[off] = value & 0xFF
    buf[off + 1] = value >> 8


def default_app(drive: DriveMap, od: ObjectDictionary) -> App | None:
    """A CiA 402 drive (sim_slaves.drive402) for maps with a controlword, else None."""
    if not (od.has(0x6040) and od.has(0x6041)):
        return None
    try:
        from sim_slaves.drive402 import Cia402Drive
    except ImportError:
        return None
    return Cia402Drive()
