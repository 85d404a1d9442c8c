"""Emulated CANopen nodes behind ONE python-can bus instance, served by one thread.

python-can's ``virtual`` bus copies every frame to every other instance on the
channel, so all nodes share one instance here and frames are dispatched by
COB-ID: SYNC (0x080), RPDOs (a table from COB-ID to the nodes that consume it,
rebuilt after any NMT or SDO frame, the only ones that can change it), NMT
(0x000), SDO requests (0x600 + id). Heartbeats and event-timer TPDOs are
produced from the same thread (checked every millisecond at most).

``dt_s``: the time step of the drive models per SYNC (default: measured
between SYNCs, clamped to 0.1 ms..10 ms). ``clock``: the time the nodes read
(a :class:`~fieldbus.platform.clock.Clock`; default the machine's). Without a
thread (virtual time, :mod:`fieldbus.testing`): :meth:`boot` once, then
:meth:`deliver` each frame and :meth:`idle` as time passes.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import can
import numpy as np

from fieldbus.core.pdo.model import DriveMap
from fieldbus.platform.clock import Clock, monotonic_s
from fieldbus.wire.canlog import LoggedBus, open_log
from sim_slaves.busthread import BusThread
from sim_slaves.canopen.node import COB_NMT, COB_RSDO, COB_SYNC, App, CanopenNode, Frame, NmtState
from sim_slaves.drive402 import ObjectStore
from sim_slaves.drive_bank import DriveBank, runs
from sim_slaves.drive_config import drive_params
from sim_slaves.ethercat.axes import AxisObjects, MultiAxisDrive
from sim_slaves.od import is_cia402_drive

TIMER_TICK_S = 0.001  # heartbeats and event timers are checked this often at most
IDLE_WAIT_S = 0.005  # longest wait for a frame before the timers are looked at again


class CanopenSimulator(BusThread):
    """Nodes ``[(drive_map, node_id), ...]`` on ``bus``; a context manager (start/stop).

    Fault hooks (thread-safe): :meth:`drop_tpdos`, :meth:`silence_heartbeat`,
    :meth:`send_emergency`, :meth:`abort_sdo`, :meth:`slow_sdo`, :meth:`bus_off`, :meth:`power_cycle`.
    """

    thread_name = "canopen-nodes"
    idle_wait_s = IDLE_WAIT_S

    def __init__(
        self,
        bus: can.BusABC,
        nodes: Sequence[tuple[DriveMap, int]],
        *,
        dt_s: float | None = None,
        log: str | Path | None = None,
        clock: Clock | None = None,
    ) -> None:
        self._now = monotonic_s(clock)  # seconds
        self.log = open_log(log)  # every frame the nodes see and send, python-can format by suffix
        self.bus: Any = bus if self.log is None else LoggedBus(bus, self.log)
        self.dt_s = dt_s
        self.nodes: dict[int, CanopenNode] = {}
        ids = [node_id for _, node_id in nodes]
        if len(set(ids)) != len(ids):
            raise ValueError(f"node id {next(i for i in ids if ids.count(i) > 1)} used twice")
        # every CiA 402 drive in one bank, stepped together on SYNC (slot k: the k-th drive axis; a
        # multi-axis node has one slot per axis, consecutive, each seeing its objects at +0x800 per axis)
        cia402 = [(drive, node_id) for drive, node_id in nodes if is_cia402_drive(drive)]
        self.bank = DriveBank([drive_params(drive) for drive, _ in cia402 for _k in range(drive.axes)])
        self._slot: dict[int, int] = {}  # node id -> its first axis's slot
        self._axes: dict[int, tuple[int, ...]] = {}  # node id -> its axes' object offsets
        first = 0
        for drive, node_id in cia402:
            self._slot[node_id], self._axes[node_id] = first, drive.object_offsets
            first += drive.axes
        for drive, node_id in nodes:
            k = self._slot.get(node_id)
            app: App | None = None
            if k is not None:
                bank_drives = self.bank.drives[k : k + drive.axes]
                app = (
                    bank_drives[0]
                    if drive.axes == 1
                    else MultiAxisDrive(list(bank_drives), drive.object_offsets)
                )
            self.nodes[node_id] = CanopenNode(drive, node_id, app)
        self._views: dict[int, tuple[object, list[tuple[int, ObjectStore]]]] = {}  # node id -> (OD, per axis)
        self._active = np.zeros(first, dtype=np.bool_)  # drive slots stepping on this SYNC
        self.errors: list[str] = []
        self.syncs = 0
        self.sync_cpu_s = 0.0  # thread CPU time on SYNCs (RPDOs applied, drives stepped, TPDOs sent)
        super().__init__()
        self._lock = threading.Lock()
        self._last_sync: float | None = None
        self._next_hb: dict[int, float] = {}
        self._next_tick = 0.0
        self._routes: dict[int, list[CanopenNode]] | None = None  # RPDO COB-ID -> consumers
        self._corrupt: dict[int, int] = {}  # node id -> TPDOs still to send inverted
        self._sdo_delay: dict[int, int] = {}  # node id -> SYNCs its SDO server takes per request
        self._sdo_held: list[tuple[int, int, bytes]] = []  # (SYNC count when served, node id, request)

    def node(self, node_id: int) -> CanopenNode:
        return self.nodes[node_id]

    def boot(self) -> None:
        """Boot every node (boot-up messages), as :meth:`start` does, without a thread."""
        self._on_start()

    def deliver(self, msg: can.Message | None) -> None:
        """One frame from the bus (None: none), then the timers that are due (without the thread)."""
        self._serve_locked(msg)

    # -- life cycle ---------------------------------------------------------------------
    def _on_start(self) -> None:
        """Boot every node (boot-up messages); then the thread serves the bus."""
        with self._lock:
            for n in self.nodes.values():
                self._send(n.boot())

    # -- fault hooks ------------------------------------------------------------------------
    def drop_tpdos(self, node_id: int, count: int = 1) -> None:
        """The node's next ``count`` TPDOs are not sent."""
        with self._lock:
            self.nodes[node_id].drop_tpdos += count

    def silence_heartbeat(self, node_id: int, silent: bool = True) -> None:
        """The node stops (or resumes) producing heartbeats; everything else goes on."""
        self.nodes[node_id].heartbeat_silent = silent

    def send_emergency(self, node_id: int, code: int, register: int = 0x01, data: bytes = b"") -> None:
        """The node sends an EMCY (not when STOPPED or bus-off, as CiA 301 says)."""
        with self._lock:
            n = self.nodes[node_id]
            if not n.bus_off and n.state != NmtState.STOPPED:
                self._send([n.emergency(code, register, data)])

    def abort_sdo(self, node_id: int, index: int, sub: int | None, code: int) -> None:
        """Every SDO access to ``index:sub`` (None: any sub-index) of the node aborts with ``code``."""
        with self._lock:
            self.nodes[node_id].od.inject_abort(index, sub, code)

    def slow_sdo(self, node_id: int, syncs: int) -> None:
        """The node's SDO server takes ``syncs`` SYNCs (cycles) per request: it serves each request, and
        answers, only after that many SYNCs, with the objects as they are then (0: at once again)."""
        with self._lock:
            self._sdo_delay[node_id] = max(0, int(syncs))

    def _serve_held_sdo(self) -> None:
        """Serve the held SDO requests whose time has come (after a SYNC)."""
        due = [h for h in self._sdo_held if h[0] <= self.syncs]
        if not due:
            return
        self._sdo_held = [h for h in self._sdo_held if h[0] > self.syncs]
        for _, node_id, req in due:
            node = self.nodes.get(node_id)
            if node is not None and not node.bus_off:
                reply = node.sdo(req)
                if reply is not None:
                    self._send([reply])

    def bus_off(self, node_id: int, off: bool = True) -> None:
        """The node stops sending and receiving (CAN bus-off); back on: it boots again (reset node)."""
        with self._lock:
            n = self.nodes[node_id]
            n.bus_off = off
            if not off:
                self._send(n.nmt(0x81))
            self._routes = None

    def corrupt_tpdos(self, node_id: int, count: int = 1) -> None:
        """The node's next ``count`` TPDOs go out with every data bit inverted (length and COB-ID intact)."""
        with self._lock:
            self._corrupt[node_id] = self._corrupt.get(node_id, 0) + count

    def clear_faults(self) -> None:
        """Undo every injection: dropped and corrupted TPDOs, silent heartbeats, SDO aborts."""
        with self._lock:
            self._corrupt.clear()
            self._sdo_delay.clear()
            for node in self.nodes.values():
                node.drop_tpdos = 0
                node.heartbeat_silent = False
                node.od.clear_aborts()

    def power_cycle(self, node_id: int) -> None:
        """Reset node: object dictionary to defaults, drive restarts, boot-up message."""
        with self._lock:
            self._send(self.nodes[node_id].nmt(0x81))
            self._routes = None

    # -- the thread --------------------------------------------------------------------------
    def _send(self, frames: list[Frame]) -> None:
        for cob, data in frames:
            self.bus.send(can.Message(arbitration_id=cob, data=data, is_extended_id=False))

    def serve(self, timeout: float) -> bool:
        msg = self.bus.recv(timeout=timeout)
        self._serve_locked(msg)
        return msg is not None

    def idle(self) -> None:
        self._serve_locked(None)

    def _serve_locked(self, msg: can.Message | None) -> None:
        """``msg`` (None: no frame), then the timers that are due; an error is kept in :attr:`errors`."""
        with self._lock:
            try:
                if msg is not None and not msg.is_extended_id and not msg.is_remote_frame:
                    self.handle(msg.arbitration_id, bytes(msg.data))
                now = self._now()
                if now >= self._next_tick:
                    self._next_tick = now + TIMER_TICK_S
                    self.tick(now)
            except Exception as exc:  # keep serving; tests read .errors
                self.errors.append(f"{type(exc).__name__}: {exc}")

    def handle(self, cob: int, data: bytes) -> None:
        """One frame from the bus (without the thread: tests and fuzzing call this directly)."""
        if cob == COB_SYNC:
            t0 = time.thread_time()
            now = self._now()
            dt = self.dt_s
            if dt is None:
                dt = 0.001 if self._last_sync is None else min(0.01, max(1e-4, now - self._last_sync))
            self._last_sync = now
            self.syncs += 1
            self._sync(dt, now)
            if self._sdo_held:
                self._serve_held_sdo()
            self.sync_cpu_s += time.thread_time() - t0
            return
        if cob == COB_NMT:
            self._routes = None
            if len(data) < 2:
                return
            targets = (
                list(self.nodes.values())
                if data[1] == 0
                else [self.nodes[data[1]]]
                if data[1] in self.nodes
                else []
            )
            for n in targets:
                if not n.bus_off:
                    self._send(n.nmt(data[0]))
            return
        if COB_RSDO < cob <= COB_RSDO + 127:
            self._routes = None
            target = self.nodes.get(cob - COB_RSDO)
            delay = self._sdo_delay.get(cob - COB_RSDO, 0) if self._sdo_delay else 0
            if target is not None and not target.bus_off and delay:
                self._sdo_held.append((self.syncs + delay, target.node_id, data))
            elif target is not None and not target.bus_off:
                reply = target.sdo(data)
                if reply is not None:
                    self._send([reply])
            return
        routes = self._routes
        if routes is None:
            routes = self._routes = self._build_routes()
        consumers = routes.get(cob)
        if consumers is not None:
            for n in consumers:
                n.rpdo(cob, data)

    def _stores(self, n: CanopenNode, k: int) -> list[tuple[int, ObjectStore]]:
        """(bank slot, the objects it sees) per axis of node ``n`` (first slot ``k``); rebuilt for a new OD."""
        cached = self._views.get(n.node_id)
        if cached is None or cached[0] is not n.od:
            offsets = self._axes[n.node_id]
            stores: list[tuple[int, ObjectStore]] = [
                (k + j, n.od if off == 0 else AxisObjects(n.od, off)) for j, off in enumerate(offsets)
            ]
            cached = self._views[n.node_id] = (n.od, stores)
        return cached[1]

    def _sync(self, dt: float, now: float) -> None:
        """Every OPERATIONAL node's RPDOs applied, their drives stepped as runs of the bank, TPDOs sent."""
        bank, active, slot = self.bank, self._active, self._slot
        active.fill(False)
        taking_part: list[tuple[CanopenNode, list[tuple[int, ObjectStore]]]] = []  # node, its axes' slots
        for node_id, n in self.nodes.items():
            if n.sync_inputs():
                k = slot.get(node_id)
                stores = [] if k is None else self._stores(n, k)
                taking_part.append((n, stores))
                for s, store in stores:
                    bank.load_inputs(s, store)
                    active[s] = True
        for a, b in runs(np.flatnonzero(active)):  # the drives that take part (a stopped node's stands still)
            bank.step(a, b, dt)
        for n, stores in taking_part:
            for s, store in stores:
                bank.store_outputs(s, store)
            frames = n.sync_outputs(now)
            if frames and self._corrupt.get(n.node_id):
                frames = self._corrupted(n.node_id, frames)
            if frames:
                self._send(frames)

    def _corrupted(self, node_id: int, frames: list[Frame]) -> list[Frame]:
        out = []
        for cob, data in frames:
            if self._corrupt.get(node_id, 0) > 0 and 0x180 <= cob < 0x580:  # a TPDO
                self._corrupt[node_id] -= 1
                data = bytes(b ^ 0xFF for b in data)
            out.append((cob, data))
        return out

    def _build_routes(self) -> dict[int, list[CanopenNode]]:
        routes: dict[int, list[CanopenNode]] = {}
        for n in self.nodes.values():
            for cob in n.rpdo_cob_ids():
                if cob not in (COB_NMT, COB_SYNC) and not COB_RSDO < cob <= COB_RSDO + 127:
                    routes.setdefault(cob, []).append(n)
        return routes

    def tick(self, now: float) -> None:
        """Heartbeats and event-timer TPDOs due at ``now`` (time.monotonic seconds)."""
        for node_id, n in self.nodes.items():
            frames = n.timers(now)
            if frames:
                self._send(frames)
            period = n.heartbeat_ms / 1000
            if period <= 0:
                continue
            due = self._next_hb.get(node_id, 0.0)
            if now >= due:
                self._next_hb[node_id] = now + period
                hb = n.heartbeat()
                if hb is not None:
                    self._send([hb])
