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

import random
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import numpy.typing as npt

from fieldbus.core.dc.model import DcRegister, EscTiming, SyncActivation, wrap_signed
from fieldbus.core.ecat import DATAGRAM_HEADER_SIZE, LOCALLY_ADMINISTERED, datagram_offsets
from fieldbus.core.pdo.model import DriveMap
from sim_slaves.drive402 import Cia402Drive
from sim_slaves.drive_bank import DriveBank, runs, warm_up
from sim_slaves.drive_config import drive_params as map_drive_params
from sim_slaves.ethercat.al import AlState
from sim_slaves.ethercat.axes import MultiAxisDrive, device_od
from sim_slaves.ethercat.dc import DC_END, DC_FIRST, DC_MIN_SAMPLE_INTERVAL_NS, DcLine, EscDc
from sim_slaves.ethercat.diaghistory import record_fault
from sim_slaves.ethercat.esc import DEFAULT_DT_S, MEM_SIZE, App, Esc
from sim_slaves.ethercat.pdplan import CopyPlan, DriveLink, build_copy_plan, build_drive_link, pdo_offsets
from sim_slaves.ethercat.sii import SiiImage, build_sii
from sim_slaves.od import ObjectDictionary, is_cia402_drive

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
    # bit errors on the cable behind slave ``link_upstream`` (its port 1 -> the next slave's port 0):
    # each pass of a frame over it is corrupted with probability ``link_rate`` (seeded), for
    # ``link_frames`` more frames (-1: until cleared); directions "down", "up" or "both"
    link_upstream: int = -1
    link_rate: float = 0.0
    link_direction: str = "both"
    link_frames: int = -1
    link_rng: random.Random | None = None
    link_corrupted: int = 0  # passes corrupted so far


class EscChain:
    """N slaves in a line. ``process(frame, now_ns)`` is the whole wire interface.

    ``dc_timing``: every ESC's processing/forwarding delay (default
    :class:`~fieldbus.core.dc.model.EscTiming`), ``cable_m``: metres of cable
    master -> slave 0 and between neighbours (5 ns/m);
    ``dc_min_sample_interval_ns``: see :class:`~sim_slaves.ethercat.dc.DcLine`
    (0: every ARMW/FRMW feeds the loops).

    ``lean`` (default): the per-frame work cached and said in fewer calls
    (datagram offsets per frame layout, byte compares for the flags that
    numpy reductions computed, slice copies, the drive link's gather and
    scatter in C where ``sim_slaves._pdlink`` is built, the drive bank's idle
    and CSP cycles one C call each, :attr:`DriveBank.lean`); False: the
    general path, the reference it must match bit for bit
    (tests/unit/test_chain_lean.py). Settable at any time (:attr:`lean`).
    """

    def __init__(
        self,
        slaves: Sequence[Esc],
        *,
        dc_timing: EscTiming | None = None,
        cable_m: float = 1.0,
        dc_min_sample_interval_ns: int = DC_MIN_SAMPLE_INTERVAL_NS,
        lean: bool = True,
    ) -> None:
        self._lean = lean
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
        self._adopt_memory_and_drives()
        self.power_losses: list[int] = []  # slaves whose power goes at the end of this frame (FoE cut)
        for i, s in enumerate(self.slaves):
            s.firmware.on_power_loss = lambda i=i: self.power_losses.append(i)

    # -- the fast process-data path --

    def _adopt_memory_and_drives(self) -> None:
        """Slave memory into one array; every plain :class:`Cia402Drive` app into one :class:`DriveBank`."""
        n = len(self.slaves)
        self.memory: npt.NDArray[np.uint8] = np.zeros(n * MEM_SIZE, dtype=np.uint8)
        warm_up()
        plain = [i for i, s in enumerate(self.slaves) if type(s.app) is Cia402Drive]
        self.bank = DriveBank([self.slaves[i].app.params for i in plain])  # type: ignore[union-attr]
        self.bank.lean = self._lean
        self._slots = [-1] * n
        for slot, i in enumerate(plain):
            old = self.slaves[i].app
            assert isinstance(old, Cia402Drive)
            drive = self.bank.drives[slot]
            drive.position_rad = drive._prev_target_rad = old.position_rad
            self.slaves[i].app = drive
            self._slots[i] = slot
        for i, s in enumerate(self.slaves):
            s.use_memory(self.memory[i * MEM_SIZE : (i + 1) * MEM_SIZE].data)
            s.on_change = self._invalidate
            s.sync_hook = self._sync_od
        self._plans: dict[tuple[int, int, int, int], CopyPlan] = {}
        self._valid = False
        self._link = DriveLink(self.bank)
        self._link_op: set[int] = set()  # bank slots whose inputs come from memory (ESC in OP)
        self._pending = np.zeros(self.bank.n, dtype=np.bool_)  # drives that exchanged data, not yet stepped
        self._last_step_ns = np.zeros(self.bank.n, dtype=np.int64)
        self._stepped = np.zeros(self.bank.n, dtype=np.bool_)
        self._last_out_ns = np.full(n, -1, dtype=np.int64)
        self._od_synced_ns = np.full(n, -1, dtype=np.int64)  # outputs up to this write are in the OD
        self._watchdog_ns: npt.NDArray[np.int64] | None = None  # per slave, from 0x0400/0x0420
        self._slow_touched: list[Esc] = []
        self._offset_cache: dict[int, tuple[Any, Any, Any]] = {}
        self._plan_sig: list[tuple[bool, tuple[tuple[int, int, int, bool], ...], int]] | None = None
        self._link_stale = False
        self._pending_ns = 0
        self._lockstep_ns: int | None = -1  # every drive of the link last stepped at this time (-1: none yet)
        self._link_mask = np.zeros(self.bank.n, dtype=np.bool_)
        self._link_runs: list[tuple[int, int]] = []
        # slaves exchanging process data with their outputs off (SAFE-OP): their writes do not count
        self._outputs_off = np.zeros(n, dtype=np.bool_)
        self._any_outputs_off = False
        # diagnosis history (0x10F3): each bank drive's error code as last seen, a fault is a change to non-0
        self._code_seen = self.bank.error_code.copy()
        self._code_changed = np.zeros(self.bank.n, dtype=np.bool_)
        self._slot_wire = {slot: i for i, slot in enumerate(self._slots) if slot >= 0}
        self._no_pending = bytes(self.bank.n)  # ``_pending`` with no drive pending, as bytes
        self._memory_bytes = self.memory.data  # (its bytes, for slice copies)
        # lean: frame layouts seen, (length, headers) -> (checked byte positions, their bytes, offsets)
        self._layouts: dict[tuple[int, bytes], tuple[tuple[int, ...], bytes, list[int]]] = {}
        self._watchdog_min_ns = 0  # the shortest process-data watchdog of the chain [ns]

    @property
    def lean(self) -> bool:
        """The lean per-frame path (True) or the general reference path (False); see the class."""
        return self._lean

    @lean.setter
    def lean(self, value: bool) -> None:
        self._lean = self.bank.lean = bool(value)

    def _invalidate(self) -> None:
        self._valid = False

    def _signature(self) -> list[tuple[bool, tuple[tuple[int, int, int, bool], ...], int]]:
        """What the copy plans depend on: each slave's process-data state, FMMU map and image."""
        return [(s.pd_active, s.lmap, id(s.image)) for s in self.slaves]

    def _revalidate(self) -> None:
        """After a change: copy plans again only if FMMUs, SMs or layouts moved; the drive link later."""
        off = self._outputs_off
        off[:] = [s.pd_active and not s.outputs_active for s in self.slaves]
        self._any_outputs_off = bool(off.any())
        if self._signature() == self._plan_sig:
            self._valid = True
            self._link_stale = True  # e.g. SAFE-OP -> OP: same copies, other drives take outputs
        else:
            self._rebuild()

    def _rebuild(self) -> None:
        """Copy plans and the drive link again (an FMMU, SM, AL state or layout changed)."""
        self._step_pending()
        keys = list(self._plans)
        self._plans.clear()
        self._rebuild_link()
        fast = [s.fast for s in self.slaves]
        for key in keys:  # the datagrams seen so far will come again: plan them now, off the reply path
            self._plans[key] = build_copy_plan(self.slaves, fast, self._slots, *key)
        self._plan_sig = self._signature()
        self._valid = True

    def _rebuild_link(self) -> None:
        """Which slaves are fast, and the gather/scatter plan of their drives."""
        self._link_stale = False
        bank = self.bank
        entries = []
        for i, s in enumerate(self.slaves):
            app = s.app
            slot = self._slots[i]
            if app is None:
                s.fast = True
            elif slot >= 0 and app is bank.drives[slot]:
                outs, ins = self._offsets(s)
                s.fast = outs is not None and ins is not None
                if s.fast and outs is not None and ins is not None and self._pd_ready(s):
                    entries.append((slot, i, s, outs, ins))
            else:
                s.fast = False
        for slot, _i, s, _o, _n in entries:
            if slot not in self._link_op:
                bank.load_inputs(slot, s.od)  # the OD holds what the drive last saw
        self._link = build_drive_link(bank, entries)
        self._link_op = self._link.op_slots()
        self._link_mask = np.zeros(bank.n, dtype=np.bool_)
        self._link_mask[self._link.slots] = True
        self._link_runs = runs(np.flatnonzero(self._link_mask))
        self._lockstep_ns = self._common_step_time()
        for s in self.slaves:
            if s.fast and self._pd_ready(s) and s.image.inputs.size:
                s.image.inputs.from_od(s.mem, s.sm[3][0])  # objects only SDO changes
        self._link.scatter(self.memory)

    def _common_step_time(self) -> int | None:
        """When every drive of the link last stepped, if at one time (-1: none stepped yet; None: mixed)."""
        slots = self._link.slots
        if not len(slots):
            return None
        stepped = self._stepped[slots]
        if not stepped.any():
            return -1
        times = self._last_step_ns[slots]
        return int(times[0]) if stepped.all() and (times == times[0]).all() else None

    def _offsets(self, s: Esc) -> tuple[dict[int, tuple[int, str]] | None, dict[int, tuple[int, str]] | None]:
        """CiA 402 objects in a slave's outputs and inputs (cached per process image)."""
        cached = self._offset_cache.get(id(s))
        if cached is None or cached[0] is not s.image:
            img = s.image
            cached = (img, pdo_offsets(img.outputs.layout), pdo_offsets(img.inputs.layout))
            self._offset_cache[id(s)] = cached
        return cached[1], cached[2]

    @staticmethod
    def _pd_ready(s: Esc) -> bool:
        """Process data active and laid out as the SyncManagers say."""
        img = s.image
        return (
            s.pd_active
            and s.sm[2][1] == img.outputs.size
            and s.sm[3][1] == img.inputs.size
            and (img.outputs.size > 0 or img.inputs.size > 0)
        )

    def _sync_od(self, esc: Esc, after: bool) -> None:
        """A fast slave's mailbox: the OD gets the process data before the SDO server runs, and back after.

        Outside SAFE-OP/OP (no process data) the drive only reports its state into the OD.
        """
        wire = self._wire_index[id(esc)]
        slot = self._slots[wire]
        drive = slot >= 0 and esc.app is self.bank.drives[slot]
        if not self._pd_ready(esc):
            if drive and not after and esc.app._od is esc.od:  # type: ignore[union-attr]
                self.bank.store_outputs(slot, esc.od)
            return
        if not self._valid:
            self._revalidate()
        if self._link_stale:
            self._rebuild_link()
        if not after:
            self._step_pending()
            written = int(self._last_out_ns[wire])
            if esc.state == AlState.OP and esc.image.outputs.size and written > self._od_synced_ns[wire]:
                # outputs the master wrote since the last request (as Esc.cycle would have put them)
                esc.image.outputs.to_od(esc.mem, esc.sm[2][0])
                self._od_synced_ns[wire] = written
            if drive:
                self.bank.store_outputs(slot, esc.od)
            return
        if drive:
            self.bank.load_inputs(slot, esc.od)
        if esc.image.inputs.size:
            esc.image.inputs.from_od(esc.mem, esc.sm[3][0])
        self._link.scatter(self.memory)

    def _step_pending(self) -> None:
        """Step the drives that exchanged data since their last step (together), outputs into memory."""
        pending = self._pending
        lean = self._lean
        if lean:
            pending_bytes = pending.tobytes()
            if pending_bytes == self._no_pending:
                return
        elif not pending.any():
            return
        if self._link_stale:
            self._rebuild_link()
        now = self._pending_ns
        link = self._link
        if lean:
            link.gather_lean(self.memory)
            usual = pending_bytes == self._link_mask.tobytes()
        else:
            link.gather(self.memory)
            usual = bool((pending == self._link_mask).all())
        lockstep = self._lockstep_ns
        if lockstep is not None and usual:  # the usual cycle: one dt for all
            dt_s = min(max((now - lockstep) * 1e-9, 1e-6), 0.1) if lockstep >= 0 else DEFAULT_DT_S
            for a, b in self._link_runs:
                self.bank.step(a, b, dt_s)
            self._lockstep_ns = now
            if lean:  # pending is the link's mask: its runs
                for a, b in self._link_runs:
                    self._last_step_ns[a:b] = now
                    self._stepped[a:b] = True
                pending.fill(False)
                link.scatter_lean(self.memory)
                if self.bank.error_code.tobytes() != self._code_seen.tobytes():
                    self._note_faults(now)
                return
            self._last_step_ns[pending] = now
            self._stepped[pending] = True
            pending[:] = False
            link.scatter(self.memory)
            self._note_faults(now)
            return
        idx = np.flatnonzero(pending)
        stepped = self._stepped[idx]
        dt_ns = now - self._last_step_ns[idx]
        dt = np.where(stepped, np.clip(dt_ns * 1e-9, 1e-6, 0.1), DEFAULT_DT_S)
        for a, b in runs(idx):
            lo = int(np.searchsorted(idx, a))
            d = dt[lo : lo + b - a]
            same = bool((d == d[0]).all())
            self.bank.step(a, b, float(d[0]) if same else d)
        self._last_step_ns[idx] = now
        self._stepped[idx] = True
        pending[:] = False
        self._lockstep_ns = self._common_step_time()
        (link.scatter_lean if lean else link.scatter)(self.memory)
        self._note_faults(now)

    def _note_faults(self, now_ns: int) -> None:
        """Bank drives whose error code changed to a fault: one diagnosis history message each (rare)."""
        codes = self.bank.error_code
        np.not_equal(codes, self._code_seen, out=self._code_changed)
        if not self._code_changed.any():
            return
        for slot in np.flatnonzero(self._code_changed):
            code = int(codes[slot])
            if code and slot in self._slot_wire:
                record_fault(self.slaves[self._slot_wire[int(slot)]].od, code, now_ns)
        np.copyto(self._code_seen, codes)

    def _logical(self, cmd: int, laddr: int, buf: bytearray, doff: int, length: int, now_ns: int) -> int:
        """LRD/LWR/LRW through the copy plan; returns the WKC increment."""
        if not self._valid:
            self._revalidate()
        key = (cmd, laddr, length, doff)
        plan = self._plans.get(key)
        if plan is None:
            plan = self._plans[key] = build_copy_plan(
                self.slaves, [s.fast for s in self.slaves], self._slots, cmd, laddr, length, doff
            )
        touched = plan.fast_touched
        if self._lean:
            pending = self._pending
            if plan.touched_runs and pending.tobytes() != self._no_pending and pending[touched].any():
                self._step_pending()  # new outputs for a drive that has not used its last ones
            with memoryview(buf) as frame:
                plan.apply_spans(frame, self._memory_bytes)
            last_out = self._last_out_ns
            for a, b in plan.written_runs:
                last_out[a:b] = now_ns
            if plan.touched_runs:
                for a, b in plan.touched_runs:
                    pending[a:b] = True
                self._pending_ns = now_ns
        else:
            if len(touched) and self._pending[touched].any():
                self._step_pending()  # new outputs for a drive that has not used its last ones: a new cycle
            plan.apply(np.frombuffer(buf, dtype=np.uint8), self.memory)
            if len(plan.fast_written):
                self._last_out_ns[plan.fast_written] = now_ns
            if len(touched):
                self._pending[touched] = True
                self._pending_ns = now_ns
        for s, written in plan.slow:
            s.touched = True
            if written:
                s.outputs_written = True
            self._slow_touched.append(s)
        if self._any_outputs_off and len(plan.writers):
            # SAFE-OP: the output SyncManager took no write (the bytes the plan copied are never used:
            # a drive takes targets in OP only); only its reads count
            return plan.wkc - plan.write_inc * int(np.count_nonzero(self._outputs_off[plan.writers]))
        return plan.wkc

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
        drive_params: Sequence[dict[str, Any] | None] | None = None,
    ) -> EscChain:
        """One slave per map, in wire order. ``app``: "auto" (CiA 402 drive for 402 maps), None, or a factory.

        ``drive_params``: per slave, options of its drive ("auto" only; None:
        none), e.g. a network file's ``emulator:`` options; a CiA 402 drive
        follows its map and these (:func:`sim_slaves.drive_config.drive_params`).

        ``drift_ppm``: each slave's clock drift (default 0); slave i's local
        time starts at i x :data:`DC_POWER_UP_STAGGER_NS`.
        """
        n = len(maps)
        if drift_ppm is not None and len(drift_ppm) != n:
            raise ValueError(f"need {n} drifts (one per slave), got {len(drift_ppm)}")
        slaves = []
        for i, drive in enumerate(maps):
            extra = drive_params[i] if drive_params is not None else None
            params = map_drive_params(drive, extra) if is_cia402_drive(drive) else None  # the map's drive
            od = device_od(drive, params)  # a multi-axis device: every axis's objects
            image = sii[i] if sii is not None and sii[i] is not None else build_sii(drive.bus_map)
            assert image is not None
            factory = default_app if app == "auto" else app
            the_app = factory(drive, od) if callable(factory) else None
            if params is not None and (extra or factory is default_app) and isinstance(the_app, Cia402Drive):
                the_app = Cia402Drive(params)
            if drive.axes > 1 and isinstance(the_app, Cia402Drive):  # one drive per axis, at +0x800 each
                the_app = MultiAxisDrive(
                    [the_app, *(Cia402Drive(the_app.params) for _ in range(drive.axes - 1))],
                    drive.object_offsets,
                )
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
        offsets = self._frame_offsets(buf, n) if self._lean else _datagram_offsets(buf, n)
        self.frames += 1
        faults = self.faults
        slaves = self.slaves
        if now_ns - self._watchdog_checked >= WATCHDOG_CHECK_NS:
            self._watchdog_checked = now_ns
            self._check_watchdogs(now_ns)
        if (faults.drop or faults.drop_pd or faults.link_rng is not None) and self._lost(
            faults, buf, offsets
        ):
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
                wkc += self._logical(cmd, adp | ado << 16, buf, doff, length, now_ns)
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
            if cmd in _ADDRESS_WRITERS and ado <= 0x0421 and ado + length > 0x0010:
                self._stations = None  # station address / alias / DL control may have changed
                self._watchdog_ns = None  # and the watchdog divider / time
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
        if self.power_losses:
            self._lose_power()
        return n

    def _frame_offsets(self, buf: bytearray, n: int) -> list[int]:
        """:func:`_datagram_offsets`, kept per frame layout: what it reads (the length, the ethertype and
        EtherCAT header, each datagram's command and length/flags bytes) the same, the same offsets."""
        vlan = n >= 18 and buf[12] == ETHERTYPE_VLAN >> 8 and buf[13] == ETHERTYPE_VLAN & 0xFF
        key = (n, bytes(buf[12 : 20 if vlan else 16]))
        seen = self._layouts.get(key)
        if seen is not None:
            at, was, offsets = seen
            if bytes(map(buf.__getitem__, at)) == was:
                return offsets
        offsets = _datagram_offsets(buf, n)
        at = tuple(i for off in offsets for i in (off, off + 6, off + 7))
        if len(self._layouts) >= 64:  # a master of many layouts: keep the cache bounded
            self._layouts.clear()
        self._layouts[key] = (at, bytes(map(buf.__getitem__, at)), offsets)
        return offsets

    def _lost(self, faults: Faults, buf: bytearray, offsets: list[int]) -> bool:
        """The frame is lost to an injected fault: dropped, dropped for carrying process data, or
        corrupted on a link (each counts its frames down)."""
        if faults.drop:
            faults.drop -= 1
            return True
        if faults.drop_pd and any(_LRD <= buf[off] <= _LRW for off in offsets):
            faults.drop_pd -= 1
            return True
        return bool(faults.link_rng is not None and faults.link_frames and self._corrupt_on_link(faults))

    def _lose_power(self) -> None:
        """The slaves whose power was cut (during a FoE transfer) restart, after the frame's reply."""
        for i in self.power_losses:
            self.power_cycle(i)
        self.power_losses.clear()

    def run_cycles(self, now_ns: int) -> None:
        """Application cycle of every slave whose process data the last frames exchanged.

        Drives of the bank step together once all of them have new outputs
        (a cycle of several frames), or when the master writes outputs again
        to one that has not used its last ones; a drive steps when the master
        wrote its outputs (a drive without outputs mapped: when its inputs
        were read). So every reply carries the inputs computed after the
        previous cycle, also for a slave whose data spans two frames.
        """
        touched = self._slow_touched
        if touched:
            for s in touched:
                if s.touched:
                    s.cycle(now_ns)
            touched.clear()
        pending = self._pending
        if self._lean:
            pending_bytes = pending.tobytes()
            if pending_bytes == self._no_pending:
                return
            if pending_bytes == self._link_mask.tobytes() and len(self._link.slots):
                self._step_pending()
                return
        if len(self._link.slots) and pending[self._link.slots].all():
            self._step_pending()

    def idle(self) -> bool:
        """Work left for a moment without frames (plans after an FMMU/SM/AL change); True if there was any.

        An I/O layer calls it when no frame waits, so the next process-data
        frame finds its copy plan built; otherwise that frame builds it.
        """
        if self._valid and not self._link_stale:
            return False
        if not self._valid:
            self._revalidate()
        if self._link_stale:
            self._rebuild_link()
        return True

    def _check_watchdogs(self, now_ns: int) -> None:
        """Process-data watchdogs; slaves whose outputs the copy plans wrote within their time are skipped."""
        time_ns = self._watchdog_ns
        if time_ns is None:
            rows = self.memory.reshape(len(self.slaves), MEM_SIZE)
            time_ns = (
                (rows[:, 0x0420] | rows[:, 0x0421].astype(np.int64) << 8)
                * ((rows[:, 0x0400] | rows[:, 0x0401].astype(np.int64) << 8) + 2)
                * 40
            )
            self._watchdog_ns = time_ns
            self._watchdog_min_ns = int(time_ns.min()) if len(time_ns) else 0
        last = self._last_out_ns
        if self._lean:  # every slave's outputs written within the shortest watchdog: nothing to check
            oldest = min(last.tolist(), default=0)
            if oldest >= 0 and now_ns - oldest <= self._watchdog_min_ns:
                return
        fine = (last >= 0) & (now_ns - last <= time_ns)
        if fine.all():
            return
        for i in np.flatnonzero(~fine).tolist():
            s = self.slaves[i]
            if s.state == AlState.OP:
                t = int(last[i])
                if s.fast and t >= 0 and (s.last_output_ns is None or t > s.last_output_ns):
                    s.last_output_ns = t
                s.check_watchdog(now_ns)

    def _sync_watchdogs(self) -> None:
        """Fast slaves' last output write (kept in an array by the copy plans) into the slaves."""
        for i, s in enumerate(self.slaves):
            t = int(self._last_out_ns[i])
            if s.fast and t >= 0 and (s.last_output_ns is None or t > s.last_output_ns):
                s.last_output_ns = t

    def tick(self, now_ns: int) -> None:
        """Time passes without frames (process-data watchdogs)."""
        self._sync_watchdogs()
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

    def bit_errors(
        self, upstream: int, rate: float, *, seed: int = 0, direction: str = "both", frames: int = -1
    ) -> None:
        """Bit errors on the cable between slave ``upstream``'s port 1 and slave ``upstream`` + 1's port 0.

        Each pass of a frame over that cable (``direction``: "down" away from
        the master, "up" back, or "both") is corrupted with probability
        ``rate`` (a seeded :class:`random.Random`), for the next ``frames``
        frames (-1: until cleared). A corrupted frame is lost to the master
        (its FCS is wrong) and not processed; the ESC that receives it there
        counts an invalid frame on that port, and every ESC after it on the
        frame's way back counts a forwarded error, as real ESCs do.
        """
        if not 0 <= upstream < len(self.slaves) - 1:
            raise ValueError(f"no cable behind slave {upstream} in a line of {len(self.slaves)}")
        if direction not in ("down", "up", "both") or not 0.0 <= rate <= 1.0:
            raise ValueError(f"direction {direction!r} / rate {rate}: 'down', 'up' or 'both', 0..1")
        f = self.faults
        f.link_upstream, f.link_rate, f.link_direction, f.link_frames = upstream, rate, direction, frames
        f.link_rng = random.Random(seed)
        f.link_corrupted = 0

    def flap_link(self, upstream: int) -> None:
        """The cable behind slave ``upstream`` loses its link for a moment: both ends count a lost link,
        the frame on the wire then is lost (the link is back for the next one)."""
        if not 0 <= upstream < len(self.slaves) - 1:
            raise ValueError(f"no cable behind slave {upstream} in a line of {len(self.slaves)}")
        for esc, port in ((self.slaves[upstream], 1), (self.slaves[upstream + 1], 0)):
            esc.set_link(port, False)
            esc.set_link(port, True)
        self.faults.drop += 1

    def _corrupt_on_link(self, f: Faults) -> bool:
        """One frame over the faulty cable: corrupted on the way down or back? Counts as the ESCs would."""
        assert f.link_rng is not None
        if f.link_frames > 0:
            f.link_frames -= 1
        k, slaves = f.link_upstream, self.slaves
        down = f.link_direction in ("down", "both") and f.link_rng.random() < f.link_rate
        up = not down and f.link_direction in ("up", "both") and f.link_rng.random() < f.link_rate
        if down:  # found bad at slave k+1's port 0; marked: forwarded on, and all the way back at port 1
            slaves[k + 1].count_error(0, "invalid")
            for s in slaves[k + 2 :]:
                s.count_error(0, "forwarded")
            for s in slaves[:-1]:
                s.count_error(1, "forwarded")
        elif up:  # fine on the way down, found bad at slave k's port 1 on the way back
            slaves[k].count_error(1, "invalid")
            for s in slaves[:k]:
                s.count_error(1, "forwarded")
        else:
            return False
        f.link_corrupted += 1
        return True

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
            od = device_od(self.drive_maps[slave], getattr(esc.app, "params", None))
            esc.od = od
            esc.mailbox.sdo.od = od
        self._step_pending()
        esc.power_on()
        reset = getattr(esc.app, "power_cycle", None)
        if callable(reset):
            reset()
        self._last_out_ns[slave] = -1
        self._stations = None
        self._watchdog_ns = None
        self._rebuild()

    def cut_power_during_foe(self, slave: int, after_bytes: int) -> None:
        """Slave ``slave`` loses power (and comes back, as :meth:`power_cycle`) once an FoE write has
        taken ``after_bytes`` more bytes: the frame that carried them is answered, the rest is lost."""
        self.slaves[slave].firmware.cut_after = after_bytes

    def foe_busy(self, slave: int, answers: int) -> None:
        """Slave ``slave`` answers its next ``answers`` FoE DATA packets with BUSY (erasing flash)."""
        self.slaves[slave].firmware.busy_answers = answers

    def refuse_state(self, slave: int, state: AlState, code: int) -> None:
        """Slave ``slave`` refuses to enter ``state`` with AL status code ``code`` (until cleared)."""
        self.slaves[slave].refuse[state] = code

    def abort_sdo(self, slave: int, index: int, sub: int | None, code: int) -> None:
        """SDO accesses to ``index:sub`` on slave ``slave`` abort with ``code`` (until cleared)."""
        self.slaves[slave].od.inject_abort(index, sub, code)

    def mute_mailbox(self, slave: int, *, stuck: bool = False) -> None:
        """Slave ``slave``'s mailbox never answers (until cleared): its application drops every request,
        or, ``stuck``, never takes one, so SM0 stays full and the master's later writes are refused."""
        self.slaves[slave].mailbox_fault = "stuck" if stuck else "silent"

    def stick_eeprom(self, slave: int) -> None:
        """Slave ``slave``'s EEPROM interface stays busy after the next command (until cleared)."""
        self.slaves[slave].eeprom_stuck = True

    def emergency(self, slave: int, error_code: int, error_register: int = 0) -> None:
        """Slave ``slave`` sends a CoE emergency message."""
        self.slaves[slave].send_emergency(error_code, error_register)

    def clear_faults(self) -> None:
        """Undo every pending or persistent fault injection."""
        self.faults = Faults()
        self.pending_delay = 0.0
        for s in self.slaves:
            s.clear_faults()
            s.od.clear_aborts()


def _datagram_offsets(buf: bytearray, n: int) -> list[int]:
    """Offsets of the datagram headers in the first ``n`` bytes of ``buf`` (an 802.1Q tag skipped)."""
    if n >= 18 and buf[12] == ETHERTYPE_VLAN >> 8 and buf[13] == ETHERTYPE_VLAN & 0xFF:
        # the codec reads the ethertype at byte 12: hand it the frame from 4 bytes on
        return [off + VLAN_TAG_SIZE for off in datagram_offsets(memoryview(buf)[VLAN_TAG_SIZE:n])]
    return datagram_offsets(memoryview(buf)[:n])


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
