"""CANopen backend on python-can: CiA 301 bring-up, then a SYNC cycle packed with our layout.

Bring-up: NMT pre-operational to every node; identity (0x1018:1/2) per node
against its map; each node's CANopen SDO plan (CiA 301 order) written and
read back; NMT start. The SDO client is :mod:`fieldbus.backends.can_sdo`;
canopen's per-variable PDO objects are not used anywhere.

Cycle: ``send()`` copies each RPDO's bytes from the slave's output row into a
preallocated frame and sends it, then SYNC. ``receive()`` waits up to the
receive timeout for every synchronous TPDO and copies each into the slave's
input row. Its "working counter" is the number of expected TPDOs that came;
``arrived()`` says which nodes delivered all of theirs, so the shared policy
gives per-node freshness (a silent node is stale, the others fresh).

Heartbeat consumer: a node whose heartbeat is older than 1.5x its producer
time (``heartbeat_ms`` of its map) is reported in :attr:`heartbeat_lost` and
is stale. EMCY frames are decoded with their names into :attr:`emergencies`.
A node that reboots (boot-up message) or comes back after a heartbeat loss is
reconfigured and started again by :meth:`recover_step`, one SDO per cycle.
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Generator
from typing import Any

import numpy as np
import numpy.typing as npt

from fieldbus.backends.base import Backend
from fieldbus.backends.can_sdo import SdoClient
from fieldbus.backends.sdo_exec import apply_plan
from fieldbus.core.emcy import Emergency
from fieldbus.core.network import Bus
from fieldbus.core.sdo import canopen_plan
from fieldbus.errors import BackendUnavailableError, FieldbusError, SdoAbortError, StateTransitionError

try:
    import can
except ImportError as exc:  # pragma: no cover - depends on the install
    raise BackendUnavailableError(
        f"the canopen backend needs python-can ({exc}): pip install 'fieldbus[can]'"
    ) from None

NMT_START, NMT_STOP, NMT_PRE_OP, NMT_RESET_NODE, NMT_RESET_COMM = 0x01, 0x02, 0x80, 0x81, 0x82
COB_SYNC, COB_EMCY, COB_HEARTBEAT = 0x080, 0x080, 0x700
NMT_OPERATIONAL = 0x05  # heartbeat state byte
HEARTBEAT_FACTOR = 1.5  # consumer time = this x the producer time
BOOT_WAIT_S = 0.2
MAX_EMERGENCIES = 1000


class CanopenBackend(Backend):
    """CANopen nodes on one CAN bus (``interface`` = python-can channel, ``can_interface`` its type)."""

    kind = "canopen"
    pdo_align = 8

    def __init__(self, bus: Bus, **options: Any) -> None:
        super().__init__(bus, **options)
        self._bus: Any = options.get("can_bus")
        self._own_bus = self._bus is None
        self._timeout_s = bus.receive_timeout_us / 1e6
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
        self._rpdos: list[tuple[Any, npt.NDArray[np.uint8], npt.NDArray[np.uint8]]] = []
        self._tpdos: dict[int, tuple[int, npt.NDArray[np.uint8], int]] = {}  # cob -> (slave, row slice, k)
        self._tpdo_count = np.zeros(n, dtype=np.int32)  # expected TPDOs per node
        self._got = np.zeros(n, dtype=np.int32)
        self._seen = np.zeros(0, dtype=bool)  # per expected TPDO, this cycle
        self._arrived = np.zeros(n, dtype=bool)
        self.heartbeat_lost = np.zeros(n, dtype=bool)
        self.nmt_state = np.full(n, -1, dtype=np.int16)  # last heartbeat state byte per node
        self._last_hb = np.zeros(n)
        self._hb_limit = np.array(
            [
                HEARTBEAT_FACTOR * (a.slave.map.canopen.heartbeat_ms if a.slave.map.canopen else 0) / 1000
                for a in self.areas
            ]
        )
        self._needs_setup = np.zeros(n, dtype=bool)
        self.emergencies: list[Emergency] = []
        self.boots: list[int] = []  # node ids seen booting (in order)
        self._sync = can.Message(arbitration_id=COB_SYNC, data=b"", is_extended_id=False)
        self._sdo: SdoClient | None = None
        self._recovery: Generator[None, None, bool] | None = None
        self.recoveries = 0
        self.recovery_errors: list[str] = []
        self.late_tpdos = 0  # TPDOs that arrived after their cycle's receive timeout (discarded)
        self._operational = False

    @property
    def expected_wkc(self) -> int:
        """Synchronous TPDOs expected per SYNC (all nodes)."""
        return int(sum(len(a.slave.map.tpdo) for a in self.areas))

    # -- bring-up ---------------------------------------------------------------------
    def open(self) -> None:
        if self._bus is None:
            try:
                self._bus = can.Bus(
                    interface=self.bus.can_interface or "socketcan",
                    channel=self.bus.interface,
                    bitrate=self.bus.bitrate,
                )
            except Exception as exc:
                raise FieldbusError(
                    f"bus '{self.bus.name}': cannot open {self.bus.can_interface} channel {self.bus.interface}: {exc}"
                ) from None
        self._sdo = SdoClient(self._bus, on_other=self._other)
        self._nmt(NMT_PRE_OP)
        time.sleep(0.01)
        lines = []
        for i, a in enumerate(self.areas):
            node = self.node_ids[i]
            try:
                vendor = int.from_bytes(self._sdo.upload(node, 0x1018, 1), "little")
                product = int.from_bytes(self._sdo.upload(node, 0x1018, 2), "little")
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
        for i in range(self.n_slaves):
            self._configure_node(i)

    def _configure_node(self, i: int) -> None:
        a = self.areas[i]
        apply_plan(canopen_plan(a.slave.map, self.node_ids[i]), *self._sdo_pair(i), slave=a.slave.name)

    def _sdo_pair(self, i: int) -> tuple[Any, Any]:
        def write(index: int, sub: int, data: bytes) -> None:
            self.sdo_write(i, index, sub, data)

        def read(index: int, sub: int, _size: int) -> bytes:
            return self.sdo_read(i, index, sub)

        return write, read

    def safe_op(self) -> None:
        """Prepare the cycle's frames (the nodes stay PRE-OPERATIONAL: no PDOs yet)."""
        self._rpdos, self._tpdos = [], {}
        k = 0
        for i, a in enumerate(self.areas):
            node = self.node_ids[i]
            out, inp = self.out_row(i), self.in_row(i)
            for pdo, place in zip(a.slave.map.rpdo, a.layout.outputs.pdos, strict=True):
                assert pdo.canopen is not None
                msg = can.Message(
                    arbitration_id=pdo.canopen.cob_id_for(node),
                    data=bytearray(place.size),
                    is_extended_id=False,
                )
                view = out[place.byte_offset : place.byte_offset + place.size]
                self._rpdos.append((msg, view, np.frombuffer(msg.data, dtype=np.uint8)))
            for pdo, place in zip(a.slave.map.tpdo, a.layout.inputs.pdos, strict=True):
                assert pdo.canopen is not None
                cob = pdo.canopen.cob_id_for(node)
                self._tpdos[cob] = (i, inp[place.byte_offset : place.byte_offset + place.size], k)
                k += 1
            self._tpdo_count[i] = len(a.slave.map.tpdo)
        self._seen = np.zeros(k, dtype=bool)

    def op(self) -> None:
        """NMT start; every node with a heartbeat must report OPERATIONAL within two periods."""
        self._drain()
        self.nmt_state.fill(-1)
        self._nmt(NMT_START)
        watched = self._hb_limit > 0
        deadline = time.monotonic() + max(0.3, 2 * float(self._hb_limit.max()) / HEARTBEAT_FACTOR)
        while time.monotonic() < deadline and not np.all(self.nmt_state[watched] == NMT_OPERATIONAL):
            msg = self._bus.recv(timeout=0.01)
            if msg is not None:
                self._other(msg)
        late = [
            self.areas[i].slave.name
            for i in range(self.n_slaves)
            if watched[i] and self.nmt_state[i] != NMT_OPERATIONAL
        ]
        if late:
            self._nmt(NMT_PRE_OP)
            raise StateTransitionError(
                f"bus '{self.bus.name}': no OPERATIONAL heartbeat after NMT start from {', '.join(late)}"
            )
        self._last_hb[:] = time.monotonic()
        self._operational = True

    # -- cycle ------------------------------------------------------------------------------
    def send(self) -> None:
        bus = self._bus
        # TPDOs still queued answer an earlier SYNC (late): they must not pass for this cycle's.
        # Heartbeats and EMCYs among them are kept.
        while (msg := bus.recv(timeout=0)) is not None:
            if msg.arbitration_id in self._tpdos:
                self.late_tpdos += 1
            else:
                self._other(msg)
        for msg, row, data in self._rpdos:
            np.copyto(data, row)
            bus.send(msg)
        bus.send(self._sync)

    def receive(self) -> int | None:
        self._seen.fill(False)
        self._got.fill(0)
        expected = self._seen.size
        count = 0
        deadline = time.perf_counter() + self._timeout_s
        bus = self._bus
        while count < expected:
            remaining = deadline - time.perf_counter()
            if remaining <= 0:
                break
            msg = bus.recv(timeout=remaining)
            if msg is None:
                break
            hit = self._tpdos.get(msg.arbitration_id)
            if hit is None or msg.is_extended_id:
                self._other(msg)
                continue
            i, row, k = hit
            if self._seen[k] or len(msg.data) != row.size:
                continue
            row[:] = np.frombuffer(msg.data, dtype=np.uint8)
            self._seen[k] = True
            self._got[i] += 1
            count += 1
        self._check_heartbeats()
        np.equal(self._got, self._tpdo_count, out=self._arrived)
        self._arrived &= ~self.heartbeat_lost
        if self._recovery is not None:
            self.recover_step()
        return count if count else None

    def _other(self, msg: Any) -> None:
        """Heartbeats, boot-ups and EMCYs (any time a frame is not the one awaited)."""
        if msg is None or msg.is_extended_id:
            return
        cob = msg.arbitration_id
        if COB_HEARTBEAT < cob <= COB_HEARTBEAT + 127 and len(msg.data) >= 1:
            i = self._index.get(cob - COB_HEARTBEAT)
            if i is None:
                return
            state = msg.data[0] & 0x7F
            if state == 0 and self._operational:  # boot-up: the node was reset
                self.boots.append(self.node_ids[i])
                self._needs_setup[i] = True
                if self._recovery is None:
                    self._recovery = self._recover()
            self.nmt_state[i] = state
            self._last_hb[i] = time.monotonic()
        elif COB_EMCY < cob <= COB_EMCY + 127:
            node = cob - COB_EMCY
            if node in self._index:
                if len(self.emergencies) >= MAX_EMERGENCIES:
                    del self.emergencies[: MAX_EMERGENCIES // 2]
                self.emergencies.append(Emergency.decode(node, bytes(msg.data), time.monotonic()))

    def _check_heartbeats(self) -> None:
        now = time.monotonic()
        for i in range(self.n_slaves):
            limit = self._hb_limit[i]
            lost = bool(limit) and now - self._last_hb[i] > limit
            if lost and not self.heartbeat_lost[i]:
                self._needs_setup[i] = True  # when it answers again, it is configured again
            self.heartbeat_lost[i] = lost

    def arrived(self) -> npt.NDArray[np.bool_]:
        return self._arrived

    def recover_step(self) -> bool:
        """One step (one SDO or NMT) of bringing rebooted or returning nodes back; never raises."""
        if not self._needs_setup.any():
            return True
        if self._recovery is None:
            self._recovery = self._recover()
        try:
            next(self._recovery)
        except StopIteration as stop:
            self._recovery = None
            return bool(stop.value)
        except FieldbusError as exc:
            self._recovery = None
            self.recovery_errors.append(f"{type(exc).__name__}: {exc}")
        return False

    def _recover(self) -> Generator[None, None, bool]:
        while True:
            todo = [i for i in range(self.n_slaves) if self._needs_setup[i] and not self.heartbeat_lost[i]]
            if not todo:
                return not self._needs_setup.any()
            i = todo[0]
            node = self.node_ids[i]
            self._nmt(NMT_PRE_OP, node)
            yield
            plan = canopen_plan(self.areas[i].slave.map, node)
            write, read = self._sdo_pair(i)
            for step in plan.steps:
                apply_plan(
                    dataclasses.replace(plan, steps=(step,)), write, read, slave=self.areas[i].slave.name
                )
                yield
            self._nmt(NMT_START, node)
            self._needs_setup[i] = False
            self.recoveries += 1
            yield

    # -- shut-down ------------------------------------------------------------------------------
    def stop(self) -> None:
        self._recovery = None
        if self._bus is not None and self._operational:
            self._operational = False
            self._nmt(NMT_PRE_OP)

    def close(self) -> None:
        if self._bus is not None and self._own_bus:
            self._bus.shutdown()
        self._bus = None

    # -- acyclic ------------------------------------------------------------------------------
    def _nmt(self, command: int, node: int = 0) -> None:
        self._bus.send(can.Message(arbitration_id=0x000, data=bytes([command, node]), is_extended_id=False))

    def _drain(self) -> None:
        while True:
            msg = self._bus.recv(timeout=0)
            if msg is None:
                return
            self._other(msg)

    def _client(self) -> SdoClient:
        if self._sdo is None:
            raise FieldbusError(f"bus '{self.bus.name}': not open")
        return self._sdo

    def sdo_read(self, slave: int, index: int, sub_index: int) -> bytes:
        try:
            return self._client().upload(self.node_ids[slave], index, sub_index)
        except SdoAbortError as exc:
            raise self._named(exc, slave) from None

    def sdo_write(self, slave: int, index: int, sub_index: int, data: bytes) -> None:
        try:
            self._client().download(self.node_ids[slave], index, sub_index, data)
        except SdoAbortError as exc:
            raise self._named(exc, slave) from None

    def _named(self, exc: SdoAbortError, slave: int) -> SdoAbortError:
        detail = f"node {self.node_ids[slave]}" + (f", {exc.detail}" if exc.detail else "")
        return SdoAbortError(
            exc.code,
            index=exc.index,
            subindex=exc.subindex,
            slave=self.areas[slave].slave.name,
            detail=detail,
        )
