"""CANopen backend on python-can: CiA 301 bring-up, then a SYNC cycle packed with our layout.

Bring-up (blocking, outside the cycle): NMT pre-operational to every node;
identity (0x1018:1/2) per node against its map; each node's CANopen SDO plan
(CiA 301 order, :func:`fieldbus.core.sdo.canopen_plan`) written and read back
through :func:`~fieldbus.backends.sdo_exec.apply_plan`; NMT start, confirmed by
each node's heartbeat. The SDO client is this module's own (expedited and
segmented, :func:`sdo_upload` / :func:`sdo_download` as sans-IO generators);
the ``canopen`` package is not used, and no per-variable PDO object anywhere.

Cycle (the hot path): ``send()`` copies each RPDO's bytes from the slave's
output row into a preallocated frame and sends it, then SYNC. ``receive()``
waits up to the receive timeout for every *awaited* TPDO - those with
transmission type 1, due at every SYNC - and copies each into the slave's
input row, then takes whatever else has come. Its "working counter" is the
number of awaited TPDOs that came. TPDOs of other transmission types are
copied into the input row whenever they come, without being waited for.

Every input has a deadline (:mod:`fieldbus.core.liveness`): an awaited TPDO
this cycle; a TPDO of type 2-240 within its n SYNCs; an event-driven TPDO
(254/255) within its event timer (0x1800 + n sub 5) plus one cycle; the node
itself within its heartbeat consumer time. ``arrived()`` is False for a node
that missed any of them, so the shared policy never calls it fresh. A node
that could die unnoticed (no heartbeat, no TPDO with a deadline) is refused.
Counted (:class:`~fieldbus.backends.canfaults.CanFaults`): late and extra
awaited TPDOs, driver errors on send and receive (raised as
:class:`~fieldbus.errors.BusIoError`), error frames and bus-off.

Directions from the master's side: outputs are RPDOs (master -> node), inputs
TPDOs (node -> master). ``open()`` takes the CAN channel's lock
(:mod:`fieldbus.backends.buslock`): one master per channel.

Heartbeat consumer: a node whose heartbeat is older than its consumer time
(1.5 x the producer time ``heartbeat_ms`` of its map, or the backend option
``heartbeat_consumer_ms``) is flagged in :attr:`heartbeat_lost` and stale.
EMCY frames are decoded with their names into :attr:`emergencies` (and the
last one per node in :attr:`last_emergency`).

Recovery: a node that boots (boot-up message), or whose heartbeat comes back
in a state other than OPERATIONAL, is put in PRE-OPERATIONAL, its identity
checked, its plan written and read back, and started again - by
:meth:`recover_step`, which never waits: each call sends at most one frame
and the answer is picked up by the cycle's own receive path.
"""

from __future__ import annotations

import struct
import time
from collections.abc import Generator
from typing import Any

import numpy as np
import numpy.typing as npt

from fieldbus.backends.base import Backend, SdoRequest, SlaveArea
from fieldbus.backends.buslock import InterfaceLock, lock_can_bus
from fieldbus.backends.canbus import attach_can_bus, release_can_bus
from fieldbus.backends.canfaults import CanFaults
from fieldbus.backends.sdo_exec import apply_plan
from fieldbus.core.candecode import NMT_STATES
from fieldbus.core.emcy import Emergency
from fieldbus.core.liveness import tpdo_deadline, unwatched_reason
from fieldbus.core.network import Bus
from fieldbus.core.sdo import StepKind, canopen_plan
from fieldbus.core.sdo.canopen_client import ABORT_TIMEOUT, SdoSteps, sdo_download, sdo_upload
from fieldbus.errors import (
    BackendUnavailableError,
    BusTimeoutError,
    FieldbusError,
    SdoAbortError,
    SdoMismatchError,
    StateTransitionError,
)
from fieldbus.platform.clock import monotonic_s
from fieldbus.wire.canlog import open_log

try:
    import can
except ImportError as exc:  # pragma: no cover - depends on the install
    raise BackendUnavailableError(
        f"the canopen backend needs python-can ({exc}): pip install 'fieldbus[can]'"
    ) from None

NMT_START, NMT_STOP, NMT_PRE_OP, NMT_RESET_NODE, NMT_RESET_COMM = 0x01, 0x02, 0x80, 0x81, 0x82
COB_NMT, COB_SYNC, COB_EMCY, COB_TSDO, COB_RSDO, COB_HEARTBEAT = 0x000, 0x080, 0x080, 0x580, 0x600, 0x700
NMT_OPERATIONAL = 0x05  # heartbeat state byte
HEARTBEAT_FACTOR = 1.5  # consumer time = this x the producer time
SDO_TIMEOUT_S = 0.5  # per SDO request / response
RETRY_AFTER_S = 1.0  # a node whose recovery failed is tried again after this
MAX_EMERGENCIES = 1000
MAX_BOOTS = 1000
NEVER = np.iinfo(np.int64).max  # a SYNC count no cycle reaches


class CanopenBackend(CanFaults, Backend):
    """CANopen nodes on one CAN bus (``interface`` = python-can channel, ``can_interface`` its type).

    Options: ``can_bus`` (a python-can bus instance to use instead of opening
    one), ``heartbeat_consumer_ms`` (consumer time for every node; 0 turns the
    check off; default 1.5 x each map's ``heartbeat_ms``), ``sdo_timeout_s``.
    """

    kind = "canopen"
    pdo_align = 8

    def __init__(self, bus: Bus, **options: Any) -> None:
        super().__init__(bus, **options)
        self._bus: Any = options.get("can_bus")
        self._own_bus = self._bus is None
        self._timeout_s = bus.receive_timeout_us / 1e6
        # seconds; in tests a virtual clock's (fieldbus.testing)
        self._now = monotonic_s(options.get("clock"))
        self._sdo_timeout_s = float(options.get("sdo_timeout_s", SDO_TIMEOUT_S))
        n = self.n_slaves
        self.node_ids: list[int] = []
        for a in self.areas:
            if a.slave.node_id is None:
                raise FieldbusError(f"bus '{bus.name}': slave {a.slave.name} has no node_id")
            if a.slave.map.canopen is None:
                raise FieldbusError(
                    f"bus '{bus.name}': slave {a.slave.name} map {a.slave.map.name} has no canopen section"
                )
            self.node_ids.append(a.slave.node_id)
        self._index = {node: i for i, node in enumerate(self.node_ids)}
        self._init_tpdo_tables(n)
        self._lock: InterfaceLock | None = None
        self._init_heartbeat_consumer(bus, options.get("heartbeat_consumer_ms"))
        # EMCY, boot-ups
        self.emergencies: list[Emergency] = []
        self.last_emergency: dict[int, Emergency] = {}  # node id -> its last EMCY
        self.boots: list[int] = []  # node ids seen booting while OPERATIONAL (in order)
        # recovery
        self._needs_setup = np.zeros(n, dtype=bool)
        self._retry_at = np.zeros(n)
        self._recovering: int | None = None  # node id whose SDO answer the recovery (or acyclic) awaits
        self._acyclic: Generator[None, None, bytes] | None = None  # an SDO asked for in OP, under way
        self._acyclic_request: SdoRequest | None = None
        self._reply: bytes | None = None
        self.sdo_transfers = 0
        self._sync = can.Message(arbitration_id=COB_SYNC, data=b"", is_extended_id=False)
        self._open = False
        self._operational = False
        # last: a refused configuration above leaves no file open
        self._log = open_log(options.get("can_log"))  # every frame to a python-can log file

    def _init_tpdo_tables(self, n: int) -> None:
        """The cycle's tables: RPDOs to send, TPDOs awaited per SYNC, and the deadlines of the others."""
        # filled by safe_op
        self._rpdos: list[tuple[Any, npt.NDArray[np.uint8], npt.NDArray[np.uint8]]] = []
        # TPDO COB-ID -> (slave, its bytes in the input row, k: index among awaited TPDOs or -1,
        # j: its deadline slot in the slave's row or -1)
        self._tpdos: dict[int, tuple[int, npt.NDArray[np.uint8], int, int]] = {}
        self._tpdo_count = np.zeros(n, dtype=np.int32)  # expected TPDOs per node per SYNC
        for i, a in enumerate(self.areas):
            self._tpdo_count[i] = sum(1 for p in a.slave.map.bus_map.tpdo if tpdo_deadline(p).every_sync)
        self._got = np.zeros(n, dtype=np.int32)
        self._seen = np.zeros(0, dtype=bool)  # per expected TPDO, this cycle
        self._arrived = np.zeros(n, dtype=bool)
        self._ok = np.zeros(n, dtype=bool)  # scratch of the judgement
        self.other_tpdos = 0  # TPDOs of other transmission types received (copied, not awaited)
        # deadlines of the TPDOs not awaited (types 2-240 in SYNCs, 254/255 by event timer): per node a
        # row of slots, each the time (time.monotonic s) or SYNC count after which its data are stale
        self._syncs = 0  # SYNCs sent since open
        self._quiet_t = 0.0  # time.monotonic when the receive queue was last seen empty
        self._due_t = np.full((n, 1), np.inf)
        self._due_s = np.full((n, 1), NEVER, dtype=np.int64)
        self._limit_t = np.zeros((n, 1))  # s: event timer + one cycle
        self._limit_s = np.zeros((n, 1), dtype=np.int64)  # SYNCs: the transmission type
        self._min_t = np.zeros(n)
        self._min_s = np.zeros(n, dtype=np.int64)
        self._timed = self._counted = False

    def _init_heartbeat_consumer(self, bus: Bus, consumer: Any) -> None:
        """Heartbeat consumer: per node the time (s) without a heartbeat after which it is lost
        (``consumer``: the ``heartbeat_consumer_ms`` option, else a factor of the producer's period)."""
        n = self.n_slaves
        self.heartbeat_lost = np.zeros(n, dtype=bool)
        self.nmt_state: npt.NDArray[np.int16] = np.full(
            n, -1, dtype=np.int16
        )  # last heartbeat state byte per node
        self._last_hb = np.zeros(n)
        self._hb_limit = np.array(
            [
                float(consumer) / 1000 if consumer is not None else HEARTBEAT_FACTOR * _producer_ms(a) / 1000
                for a in self.areas
            ]
        )
        self._hb_watched = self._hb_limit > 0
        for i, a in enumerate(self.areas):  # the network file refuses these; an option may still switch off
            why = unwatched_reason(a.slave.map, float(self._hb_limit[i]))
            if why is not None:
                raise FieldbusError(
                    f"bus '{bus.name}': node {self.node_ids[i]} ({a.slave.name}, heartbeat consumer "
                    f"{self._hb_limit[i] * 1e3:g} ms): {why}"
                )

    @property
    def expected_wkc(self) -> int:
        """TPDOs expected per SYNC (transmission type 1, all nodes)."""
        return int(self._tpdo_count.sum())

    def slave_state(self, i: int) -> str:
        """Node ``i``'s NMT state from its last heartbeat ("-" before any, "lost" when it went silent)."""
        if self.heartbeat_lost[i]:
            return "lost"
        return NMT_STATES.get(int(self.nmt_state[i]), "-")

    def last_emergency_name(self, i: int) -> str | None:
        """The name of node ``i``'s last EMCY (None: none received)."""
        emcy = self.last_emergency.get(self.node_ids[i])
        return None if emcy is None else str(emcy.name)

    # -- bring-up ---------------------------------------------------------------------
    def open(self) -> None:
        """Lock the channel (:class:`~fieldbus.errors.InterfaceInUseError` when another master has it),
        open the CAN bus, NMT pre-operational to all, identity 0x1018:1/2 of every node against its map."""
        if self._lock is None:
            self._lock = lock_can_bus(self.bus)
        self._bus = attach_can_bus(self.bus, self._bus, self._log)
        self._open = True
        self._nmt(NMT_PRE_OP)
        time.sleep(0.01)
        lines = []
        for i, a in enumerate(self.areas):
            node = self.node_ids[i]
            try:
                vendor = int.from_bytes(self._sdo_blocking(node, sdo_upload(0x1018, 1)), "little")
                product = int.from_bytes(self._sdo_blocking(node, sdo_upload(0x1018, 2)), "little")
            except FieldbusError as exc:
                lines.append(f"  node {node} ({a.slave.name}): no identity ({exc})")
                continue
            if (vendor, product) != (a.slave.map.vendor_id, a.slave.map.product_id):
                lines.append(
                    f"  node {node} ({a.slave.name}): expected {a.slave.map.name} vendor 0x{a.slave.map.vendor_id:08X} "
                    f"product 0x{a.slave.map.product_id:08X}, found vendor 0x{vendor:08X} product 0x{product:08X}"
                )
        if lines:
            raise StateTransitionError(f"bus '{self.bus.name}': identity check failed:\n" + "\n".join(lines))

    def configure(self) -> None:
        """Every node's CiA 301 plan, written and read back; the first abort or mismatch stops bring-up.

        No node has been started then (all stay PRE-OPERATIONAL, no drive is enabled).
        """
        for i in range(self.n_slaves):
            a = self.areas[i]
            write, read = self.plan_io(i)
            apply_plan(canopen_plan(a.slave.map, self.node_ids[i]), write, read, slave=a.slave.name)

    def safe_op(self) -> None:
        """Prepare the cycle's frames and deadlines (the nodes stay PRE-OPERATIONAL: no PDOs yet)."""
        self._rpdos, self._tpdos = [], {}
        k = 0
        n = self.n_slaves
        slots = [[tpdo_deadline(p) for p in a.slave.map.bus_map.tpdo] for a in self.areas]
        width = max([sum(1 for d in row if d.any and not d.every_sync) for row in slots] + [1])
        self._due_t = np.full((n, width), np.inf)
        self._due_s = np.full((n, width), NEVER, dtype=np.int64)
        self._limit_t = np.zeros((n, width))
        self._limit_s = np.zeros((n, width), dtype=np.int64)
        margin_s = self.bus.cycle_time_us / 1e6
        for i, a in enumerate(self.areas):
            node = self.node_ids[i]
            # a multi-axis node: axis k's PDOs (bus_map order: axis by axis) into its row of the image
            out = self.out_row(i).reshape(a.axes, -1)
            inp = self.in_row(i).reshape(a.axes, -1)
            out_places = [(k, pl) for k in range(a.axes) for pl in a.layout.outputs.pdos]
            in_places = [(k, pl) for k in range(a.axes) for pl in a.layout.inputs.pdos]
            for pdo, (ax, place) in zip(a.slave.map.bus_map.rpdo, out_places, strict=True):
                assert pdo.canopen is not None
                msg = can.Message(
                    arbitration_id=pdo.canopen.cob_id_for(node),
                    data=bytearray(place.size),
                    is_extended_id=False,
                )
                view = out[ax, place.byte_offset : place.byte_offset + place.size]
                self._rpdos.append((msg, view, np.frombuffer(msg.data, dtype=np.uint8)))
            j = 0
            for pdo, (ax, place), due in zip(a.slave.map.bus_map.tpdo, in_places, slots[i], strict=True):
                assert pdo.canopen is not None
                cob = pdo.canopen.cob_id_for(node)
                if cob in self._tpdos:
                    raise FieldbusError(f"bus '{self.bus.name}': two TPDOs use COB-ID 0x{cob:03X}")
                row = inp[ax, place.byte_offset : place.byte_offset + place.size]
                if due.every_sync:
                    self._tpdos[cob] = (i, row, k, -1)
                    k += 1
                elif due.any:
                    self._tpdos[cob] = (i, row, -1, j)
                    if due.event_ms:
                        self._limit_t[i, j] = due.event_ms / 1e3 + margin_s
                    else:
                        self._limit_s[i, j] = due.syncs
                    j += 1
                else:
                    self._tpdos[cob] = (i, row, -1, -1)
        self._seen = np.zeros(k, dtype=bool)
        self._timed = bool((self._limit_t > 0).any())  # some TPDO has an event-timer deadline
        self._counted = bool((self._limit_s > 0).any())  # some TPDO is due every n > 1 SYNCs

    def op(self) -> None:
        """NMT start; every node with a heartbeat must report OPERATIONAL within two periods."""
        self._drain()
        self.nmt_state.fill(-1)
        self._nmt(NMT_START)
        watched = self._hb_watched
        wait = max(0.3, 2 * float(self._hb_limit.max(initial=0.0)) / HEARTBEAT_FACTOR)
        deadline = self._now() + wait
        while self._now() < deadline and not np.all(self.nmt_state[watched] == NMT_OPERATIONAL):
            msg = self._recv(0.01)
            if msg is not None:
                self._other(msg)
        late = [
            f"{self.areas[i].slave.name} (node {self.node_ids[i]}, state {int(self.nmt_state[i])})"
            for i in range(self.n_slaves)
            if watched[i] and self.nmt_state[i] != NMT_OPERATIONAL
        ]
        if late:
            self._nmt(NMT_PRE_OP)
            raise StateTransitionError(
                f"bus '{self.bus.name}': no OPERATIONAL heartbeat within {wait * 1e3:.0f} ms of NMT start "
                f"from {', '.join(late)}"
            )
        now = self._quiet_t = self._now()
        self._last_hb[:] = now
        # the first of each TPDO is due one deadline after the start (a type-n TPDO at the n-th SYNC)
        timed = self._limit_t > 0
        self._due_t[timed] = now + self._limit_t[timed]
        counted = self._limit_s > 0
        self._due_s[counted] = self._syncs + self._limit_s[counted]
        self._operational = True

    # -- cycle ------------------------------------------------------------------------------
    def send(self) -> None:
        """RPDOs, then SYNC. Raises :class:`~fieldbus.errors.BusIoError` when the driver refuses a frame."""
        bus = self._bus
        # What is still queued came after the last receive(): an awaited TPDO there answers an
        # earlier SYNC (late) and must not pass for this cycle's; other frames are handled.
        try:
            while (msg := bus.recv(timeout=0)) is not None:
                self._take(msg, on_time=False)
        except (can.CanError, OSError) as exc:
            raise self._io_failed("receive", exc) from exc
        self._quiet_t = self._now()
        try:
            for msg, row, data in self._rpdos:
                np.copyto(data, row)
                bus.send(msg)
            bus.send(self._sync)
        except (can.CanError, OSError) as exc:
            raise self._io_failed("send", exc) from exc
        self._syncs += 1

    def receive(self) -> int | None:
        """Awaited TPDOs until all came or the receive timeout, then whatever else is queued; judge.

        Raises :class:`~fieldbus.errors.BusIoError` (every node not arrived) when the driver fails.
        """
        self._seen.fill(False)
        self._got.fill(0)
        expected = self._seen.size
        count = 0
        deadline = self._now() + self._timeout_s
        bus = self._bus
        take = self._take
        try:
            while count < expected:
                remaining = deadline - self._now()
                if remaining <= 0:
                    break
                msg = bus.recv(timeout=remaining)
                if msg is None:
                    break
                count += take(msg, on_time=True)
            # what else came (event-driven TPDOs, heartbeats): an awaited TPDO now is late
            while (msg := bus.recv(timeout=0)) is not None:
                take(msg, on_time=False)
        except (can.CanError, OSError) as exc:
            self._arrived.fill(False)
            raise self._io_failed("receive", exc) from exc
        self._quiet_t = self._now()
        self._judge(self._quiet_t)
        if expected == 0:
            return 0
        return count if count else None

    def _take(self, msg: Any, *, on_time: bool) -> int:
        """One frame from the cycle's queue; returns 1 when it is an awaited TPDO taken for this cycle."""
        if msg.is_error_frame:
            self._error_frame(msg)
            return 0
        if msg.is_extended_id or msg.is_remote_frame:
            return 0
        hit = self._tpdos.get(msg.arbitration_id)
        if hit is None:
            self._other(msg)
            return 0
        i, row, k, j = hit
        if k < 0:
            self._unawaited(msg, i, row, j)
            return 0
        if self._seen[k]:  # (in send(): the one of the last cycle came already)
            self.extra_frames += 1
            return 0
        if not on_time:
            self.late_frames += 1
            return 0
        data = msg.data
        if len(data) != row.size:
            return 0
        row[:] = np.frombuffer(data, dtype=np.uint8)
        self._seen[k] = True
        self._got[i] += 1
        return 1

    def _unawaited(self, msg: Any, i: int, row: npt.NDArray[np.uint8], j: int) -> None:
        """A TPDO the cycle does not wait for: copied; its deadline, if it has one, starts again."""
        data = msg.data
        if len(data) != row.size:
            return
        row[:] = np.frombuffer(data, dtype=np.uint8)
        self.other_tpdos += 1
        if j >= 0:
            limit = self._limit_t[i, j]
            if limit > 0:
                self._due_t[i, j] = self._frame_time(msg) + limit
            else:
                self._due_s[i, j] = self._syncs + self._limit_s[i, j]

    def _frame_time(self, msg: Any) -> float:
        """When ``msg`` came (time.monotonic s): its timestamp where that is plausible, else the last
        moment the queue was seen empty (it came after that: never later than it really came)."""
        now = self._now()
        age = time.time() - float(msg.timestamp)
        if 0.0 <= age <= now - self._quiet_t:
            return now - age
        return self._quiet_t

    def _judge(self, now: float) -> None:
        """Per node: every awaited TPDO this cycle, every other deadline kept, heartbeat not lost."""
        self._check_heartbeats(now)
        arrived, ok = self._arrived, self._ok
        np.equal(self._got, self._tpdo_count, out=arrived)
        np.logical_not(self.heartbeat_lost, out=ok)
        arrived &= ok
        if self._timed:
            np.min(self._due_t, axis=1, out=self._min_t)
            np.greater_equal(self._min_t, now, out=ok)
            arrived &= ok
        if self._counted:
            np.min(self._due_s, axis=1, out=self._min_s)
            np.greater_equal(self._min_s, self._syncs, out=ok)
            arrived &= ok

    @property
    def late_tpdos(self) -> int:
        """Older name of :attr:`late_frames`."""
        return self.late_frames

    @property
    def extra_tpdos(self) -> int:
        """Older name of :attr:`other_tpdos`."""
        return self.other_tpdos

    def _other(self, msg: Any) -> None:
        """Heartbeats, boot-ups, EMCYs and SDO answers (any frame that is not an awaited TPDO)."""
        if msg is None:
            return
        if msg.is_error_frame:
            self._error_frame(msg)
            return
        if msg.is_extended_id or msg.is_remote_frame:
            return
        cob = msg.arbitration_id
        if COB_HEARTBEAT < cob <= COB_HEARTBEAT + 127:
            i = self._index.get(cob - COB_HEARTBEAT)
            if i is None or len(msg.data) < 1:
                return
            state = msg.data[0] & 0x7F
            if state == 0 and self._operational:  # boot-up: the node was reset
                if len(self.boots) >= MAX_BOOTS:
                    del self.boots[: MAX_BOOTS // 2]
                self.boots.append(self.node_ids[i])
                self._needs_setup[i] = True
                self._retry_at[i] = 0.0
            elif self.heartbeat_lost[i] and state != NMT_OPERATIONAL and self._operational:
                self._needs_setup[i] = True  # back, but not as we left it
            self.nmt_state[i] = state
            self._last_hb[i] = self._frame_time(msg)
        elif COB_EMCY < cob <= COB_EMCY + 127:
            node = cob - COB_EMCY
            if node in self._index:
                if len(self.emergencies) >= MAX_EMERGENCIES:
                    del self.emergencies[: MAX_EMERGENCIES // 2]
                emcy = Emergency.decode(node, bytes(msg.data), self._now())
                self.emergencies.append(emcy)
                self.emcy_count += 1
                self.last_emergency[node] = emcy
        elif self._recovering is not None and cob == COB_TSDO + self._recovering:
            self._reply = bytes(msg.data)

    def _check_heartbeats(self, now: float) -> None:
        lost = self.heartbeat_lost
        np.subtract(now, self._last_hb, out=self._min_t)
        np.greater(self._min_t, self._hb_limit, out=lost)
        lost &= self._hb_watched

    def arrived(self) -> npt.NDArray[np.bool_]:
        return self._arrived

    def heartbeat_lost_slaves(self) -> list[str]:
        """Names of the slaves whose heartbeat is older than their consumer time (as of the last cycle)."""
        return [self.areas[i].slave.name for i in np.flatnonzero(self.heartbeat_lost)]

    # -- recovery -------------------------------------------------------------------------------
    def recover_step(self) -> bool:
        """One step of bringing rebooted nodes back: sends at most one frame, never waits, never raises.

        Returns True when no node needs it.
        """
        if self._recovery is None:
            if not self._needs_setup.any():
                return True
            self._abort_acyclic("a node is being configured again (recovery)")
        done = super().recover_step()
        if self._recovery is None:  # finished or failed (the node is tried again after RETRY_AFTER_S)
            self._recovering = None
        return done

    @property
    def recovering(self) -> bool:
        return self._recovery is not None or bool(self._needs_setup.any())

    def _recover(self) -> Generator[None, None, bool]:
        while True:
            now = self._now()
            todo = [
                i
                for i in range(self.n_slaves)
                if self._needs_setup[i] and not self.heartbeat_lost[i] and now >= self._retry_at[i]
            ]
            if not todo:
                return not self._needs_setup.any()
            i = todo[0]
            self._retry_at[i] = now + RETRY_AFTER_S  # until it succeeds
            a = self.areas[i]
            node = self.node_ids[i]
            self._nmt(NMT_PRE_OP, node)
            yield
            try:
                ident = []
                for sub in (1, 2):
                    raw = yield from self._sdo_async(node, sdo_upload(0x1018, sub))
                    ident.append(int.from_bytes(raw, "little"))
                if tuple(ident) != (a.slave.map.vendor_id, a.slave.map.product_id):
                    raise StateTransitionError(
                        f"bus '{self.bus.name}': node {node} ({a.slave.name}) came back as vendor "
                        f"0x{ident[0]:08X} product 0x{ident[1]:08X}, expected {a.slave.map.name}"
                    )
                plan = canopen_plan(a.slave.map, node)
                for step in plan.steps:  # as apply_plan: every write, then every read-back
                    if step.kind is StepKind.WRITE:
                        yield from self._sdo_async(node, sdo_download(step.index, step.sub_index, step.data))
                for step in plan.checks:
                    assert step.readback is not None
                    got = yield from self._sdo_async(node, sdo_upload(step.index, step.sub_index))
                    want = step.readback
                    if got[: len(want)] != want or any(got[len(want) :]):
                        raise SdoMismatchError(
                            index=step.index,
                            sub_index=step.sub_index,
                            expected=want,
                            received=got,
                            slave=a.slave.name,
                        )
            except SdoAbortError as exc:
                raise self._named(exc, i) from None
            self._nmt(NMT_START, node)
            self._needs_setup[i] = False
            self.recoveries += 1
            yield

    # -- acyclic SDO in OP -------------------------------------------------------------------------
    def acyclic_step(self, request: SdoRequest) -> bool:
        """Advance an SDO asked for in OP by at most one frame, never waiting; True when finished.

        The answer is picked up by the cycle's own receive path; a node that
        does not answer within ``sdo_timeout_s`` fails the request with
        :class:`BusTimeoutError`.
        """
        if self._acyclic is None:
            node = self.node_ids[request.slave]
            steps = (
                sdo_upload(request.index, request.sub_index)
                if request.data is None
                else sdo_download(request.index, request.sub_index, request.data)
            )
            self._acyclic, self._acyclic_request = self._sdo_async(node, steps), request
        try:
            next(self._acyclic)
            return False
        except StopIteration as stop:
            request.finish(None if request.data is not None else bytes(stop.value))
        except SdoAbortError as exc:
            request.finish(error=self._named(exc, request.slave))
        except FieldbusError as exc:
            request.finish(error=exc)
        self._acyclic = self._acyclic_request = None
        return True

    def _abort_acyclic(self, why: str) -> None:
        if self._acyclic is not None and self._acyclic_request is not None:
            self._acyclic_request.finish(
                error=FieldbusError(f"bus '{self.bus.name}': SDO transfer cut short: {why}")
            )
        self._acyclic = self._acyclic_request = None
        self._recovering = None

    def _sdo_async(self, node: int, steps: SdoSteps) -> Generator[None, None, bytes]:
        """Run an SDO transfer without waiting: yields until each answer has come in through ``_other``."""
        req = next(steps)
        while True:
            self._reply = None
            self._recovering = node
            self._send_sdo(node, req)
            deadline = self._now() + self._sdo_timeout_s
            while self._reply is None:
                if self._now() > deadline:
                    self._recovering = None
                    self._send_sdo_abort(node, req, ABORT_TIMEOUT)
                    raise BusTimeoutError(
                        f"bus '{self.bus.name}': node {node}: no SDO answer within "
                        f"{self._sdo_timeout_s * 1e3:.0f} ms"
                    )
                yield
            resp, self._reply, self._recovering = self._reply, None, None
            try:
                req = steps.send(resp)
            except StopIteration as stop:
                return bytes(stop.value)
            except SdoAbortError as exc:
                if resp[:1] != b"\x80":  # our side gave up: tell the server
                    self._send_sdo_abort(node, req, exc.code)
                raise

    # -- shut-down ------------------------------------------------------------------------------
    def stop(self) -> None:
        """NMT pre-operational to every node (they stop their PDOs; drives react per CiA 402).

        Never raises: a failing bus is kept in :attr:`last_error`.
        """
        self._recovery = None
        self._recovering = None
        if self._bus is not None and self._operational:
            self._operational = False
            try:
                self._nmt(NMT_PRE_OP)
            except Exception as exc:
                self._shut_failed("stop", exc)

    def close(self) -> None:
        """Close the bus (if this backend opened it) and its log, release the channel's lock.

        Idempotent; never raises: a failure is kept in :attr:`last_error`.
        """
        port, self._bus = self._bus, None
        try:
            release_can_bus(port, self._own_bus, self._log)
        except Exception as exc:
            self._shut_failed("close", exc)
        finally:
            self._open = False
            if self._lock is not None:
                self._lock.release()
                self._lock = None

    # -- acyclic ------------------------------------------------------------------------------
    def _send_frame(self, msg: Any) -> None:
        """One frame outside the cycle; :class:`~fieldbus.errors.BusIoError` when the driver refuses it."""
        try:
            self._bus.send(msg)
        except (can.CanError, OSError) as exc:
            raise self._io_failed("send", exc) from exc

    def _recv(self, timeout: float) -> Any:
        try:
            return self._bus.recv(timeout=timeout)
        except (can.CanError, OSError) as exc:
            raise self._io_failed("receive", exc) from exc

    def _nmt(self, command: int, node: int = 0) -> None:
        self._send_frame(
            can.Message(arbitration_id=COB_NMT, data=bytes([command, node]), is_extended_id=False)
        )

    def _send_sdo(self, node: int, payload: bytes) -> None:
        self._send_frame(can.Message(arbitration_id=COB_RSDO + node, data=payload, is_extended_id=False))
        self.sdo_transfers += 1

    def _send_sdo_abort(self, node: int, req: bytes, code: int) -> None:
        self._send_sdo(node, b"\x80" + req[1:4] + struct.pack("<I", code))

    def _drain(self) -> None:
        while True:
            msg = self._recv(0)
            if msg is None:
                return
            self._other(msg)

    def _sdo_blocking(self, node: int, steps: SdoSteps) -> bytes:
        """Run an SDO transfer, waiting for each answer (bring-up and the user's SDO verbs)."""
        if self._bus is None or not self._open:
            raise FieldbusError(f"bus '{self.bus.name}': not open")
        if self._recovering == node:
            raise FieldbusError(f"bus '{self.bus.name}': node {node} is being configured again (recovery)")
        req = next(steps)
        while True:
            self._send_sdo(node, req)
            deadline = self._now() + self._sdo_timeout_s
            while True:
                remaining = deadline - self._now()
                if remaining <= 0:
                    self._send_sdo_abort(node, req, ABORT_TIMEOUT)
                    raise BusTimeoutError(
                        f"bus '{self.bus.name}': node {node}: no SDO answer within "
                        f"{self._sdo_timeout_s * 1e3:.0f} ms"
                    )
                msg = self._recv(remaining)
                if msg is None:
                    continue
                if msg.is_error_frame or msg.is_extended_id or msg.is_remote_frame:
                    self._other(msg)
                    continue
                if msg.arbitration_id == COB_TSDO + node:
                    break
                hit = self._tpdos.get(msg.arbitration_id)
                if hit is None:
                    self._other(msg)
                elif hit[2] < 0:
                    self._unawaited(msg, hit[0], hit[1], hit[3])
            resp = bytes(msg.data)
            try:
                req = steps.send(resp)
            except StopIteration as stop:
                return bytes(stop.value)
            except SdoAbortError as exc:
                if resp[:1] != b"\x80":
                    self._send_sdo_abort(node, req, exc.code)
                raise

    def sdo_read(self, slave: int, index: int, sub_index: int) -> bytes:
        """Upload ``index:sub_index`` of slave ``slave`` (an index into this bus's slaves)."""
        try:
            return self._sdo_blocking(self.node_ids[slave], sdo_upload(index, sub_index))
        except SdoAbortError as exc:
            raise self._named(exc, slave) from None

    def sdo_write(self, slave: int, index: int, sub_index: int, data: bytes) -> None:
        """Download ``data`` to ``index:sub_index`` of slave ``slave``."""
        try:
            self._sdo_blocking(self.node_ids[slave], sdo_download(index, sub_index, data))
        except SdoAbortError as exc:
            raise self._named(exc, slave) from None

    def _named(self, exc: SdoAbortError, slave: int) -> SdoAbortError:
        detail = f"node {self.node_ids[slave]}" + (f", {exc.detail}" if exc.detail else "")
        return SdoAbortError(
            exc.code,
            index=exc.index,
            sub_index=exc.sub_index,
            slave=self.areas[slave].slave.name,
            detail=detail,
        )


def _producer_ms(area: SlaveArea) -> int:
    cfg = area.slave.map.canopen
    return cfg.heartbeat_ms if cfg is not None else 0
