"""The backend contract: one bus, driven through bring-up phases and the cycle.

Template method (as python-can's ``recv`` over ``_recv_internal``): the
:class:`~fieldbus.network.Network` applies the working-counter policy, CiA 402
safe stop and statistics; a backend only moves bytes and runs bus-specific
bring-up. Directions are named from the master's side: ``outputs`` are the
RxPDOs (master -> drive), ``inputs`` the TxPDOs (drive -> master).

Process data live in the axis groups' images: consecutive slaves with the same
map form one :class:`AxisGroup` whose :class:`ProcessImage` holds one row per
axis. A backend moves each slave's ``out_row(i)`` onto the bus and each reply
into ``in_row(i)``; both are contiguous uint8 views of that slave's wire bytes
(a slave with several CiA 402 axes fills one row per axis: its ``out_row`` is
then the (axes, bytes) view of those rows, each row contiguous).
"""

from __future__ import annotations

import abc
from collections import deque
from collections.abc import Callable, Generator, Sequence
from concurrent.futures import Future
from dataclasses import dataclass, field

import numpy as np
import numpy.typing as npt

from fieldbus.core import kernels
from fieldbus.core.drivefault import DriveFault
from fieldbus.core.esc_errors import CounterRise, ErrorWatch, LinkChange
from fieldbus.core.network import Bus, Slave
from fieldbus.core.pdo.image import DirectionImage, ProcessImage
from fieldbus.core.pdo.layout import MapLayout, layout
from fieldbus.errors import FieldbusError, StateTransitionError, WorkingCounterError

RECOVERY_LOG = 100  # recovery errors kept per backend (oldest dropped)
OP_CONFIRM_CYCLES = 20  # cycles after OP in which one must return the expected working counter
# the fault counters every backend has (0 where its bus has no such thing), as Backend.counters() gives them
COUNTERS = (
    "late_replies",
    "stale_frames",
    "late_frames",
    "extra_frames",
    "tx_errors",
    "rx_errors",
    "error_frames",
    "bus_off",
    "emcy_count",
    "motor_faults",
)


@dataclass(frozen=True)
class SlaveArea:
    """One slave on its bus: its layout and its row in its group's process image."""

    slave: Slave
    layout: MapLayout
    group: int  # index into Backend.groups
    row: int  # row in that group's image (its first axis's row)
    axes: int = 1  # rows of the image this slave fills (a multi-axis drive: one per axis)

    @property
    def out_size(self) -> int:
        return self.layout.outputs.size * self.axes

    @property
    def in_size(self) -> int:
        return self.layout.inputs.size * self.axes


@dataclass
class SdoRequest:
    """An SDO transfer asked for while the cycle runs; served by the cycle thread, answered through ``future``.

    ``data`` None: an upload (read), the future's result is the bytes read;
    otherwise a download (write) of ``data``, the result is None. ``slave`` is
    the index of the slave on its bus.
    """

    slave: int
    index: int
    sub_index: int
    data: bytes | None
    future: Future[bytes | None] = field(default_factory=Future)

    def finish(self, result: bytes | None = None, error: BaseException | None = None) -> None:
        """Hand the outcome to whoever waits on :attr:`future` (once)."""
        if self.future.done():
            return
        if error is not None:
            self.future.set_exception(error)
        else:
            self.future.set_result(result)


@dataclass
class AxisGroup:
    """Consecutive slaves of one bus sharing a drive map: one process image, one row per axis."""

    name: str
    slaves: tuple[Slave, ...]
    image: ProcessImage
    first: int  # index of the first slave on its bus


def _by_slave(rows: npt.NDArray[np.uint8], slaves: int) -> npt.NDArray[np.uint8]:
    """``rows`` (one per axis) as (slave, axis, byte): a view, never a copy."""
    out: npt.NDArray[np.uint8] = rows.reshape(slaves, rows.shape[0] // slaves, rows.shape[1])
    return out


class Backend(abc.ABC):
    """One bus. Phases: ``open`` -> ``configure`` (PRE-OP, SDO plans) -> ``safe_op`` -> ``op``.

    Bring-up methods block (outside the cycle). ``send`` / ``receive`` are the
    hot path: no allocation that outlives the call, no blocking longer than the
    bus's receive timeout.
    """

    kind = "abstract"
    pdo_align = 1  # 1: EtherCAT bit packing inside a slave; 8: one CAN frame per PDO
    late_wkc: int | None = None  # WKC of the last reply receive() judged late (a miss); None: none

    # -- optional capabilities: every backend has them, with these defaults ("none of that on this
    # bus"); a backend that has one overrides it (an attribute it updates, or a method). Callers read
    # them directly, never probe for them by name (tests/unit/test_backend_contract.py).
    # Fault counters (COUNTERS), since open, only growing:
    late_replies = 0  # EtherCAT: replies that came back after the receive timeout
    stale_frames = 0  # EtherCAT: frames of earlier cycles discarded
    late_frames = 0  # CAN: awaited frames after their cycle's receive timeout
    extra_frames = 0  # CAN: awaited frames that came more than once in a cycle
    tx_errors = 0  # sends the driver refused
    rx_errors = 0  # receives the driver failed
    error_frames = 0  # CAN error frames received
    bus_off = 0  # CAN: bus-off reports; the cycle makes a rise a bus error (S1)
    emcy_count = 0  # emergencies received since open, ever (the kept list is bounded; this never falls)
    motor_faults = 0  # raw CAN: faults the motors reported
    # What the bus keeps (bounded, newest last): emergencies received, and faults the motors reported
    emergencies: Sequence[object] = ()
    faults: Sequence[object] = ()
    # Per slave: NMT state byte of its last heartbeat (-1: none yet), int16; None: the bus has no NMT
    nmt_state: npt.NDArray[np.int16] | None = None
    # ESC error counters watched in OP (EtherCAT with error_counters); None: not watched
    error_watch: ErrorWatch | None = None

    def __init__(self, bus: Bus, **options: object) -> None:
        """``options`` are backend specific (for example fault hooks of the sim backend)."""
        self.bus = bus
        self.options = options
        layouts = [layout(s.map, pdo_align=self.pdo_align) for s in bus.slaves]
        self.groups: list[AxisGroup] = []
        self.areas: list[SlaveArea] = []
        runs: list[list[int]] = []
        for i, s in enumerate(bus.slaves):
            if runs and bus.slaves[runs[-1][0]].map is s.map:
                runs[-1].append(i)
            else:
                runs.append([i])
        # receive scratch, one per group: backends write replies here, never into the image, so a
        # reply the policy rejects cannot change what the controller reads (invariant S2)
        self.rx: list[npt.NDArray[np.uint8]] = []
        for run in runs:
            first = bus.slaves[run[0]]
            name = bus.name if len(runs) == 1 else f"{bus.name}.{first.name}"
            axes = first.map.axes  # a multi-axis slave fills one row per axis, its axes' bytes in a row
            image = ProcessImage(layouts[run[0]], len(run) * axes)
            # inputs start as the decode of their (zero) wire bytes: a row never accepted then reads the
            # same before and after another row's first accepted cycle decodes the image (S2)
            image.inputs.from_wire()
            for row, i in enumerate(run):
                self.areas.append(SlaveArea(bus.slaves[i], layouts[i], len(self.groups), row * axes, axes))
            self.groups.append(AxisGroup(name, tuple(bus.slaves[i] for i in run), image, run[0]))
            self.rx.append(np.zeros(image.inputs.wire.shape, dtype=np.uint8))  # C-contiguous
        self.out_bytes = sum(a.out_size for a in self.areas)
        self.in_bytes = sum(a.in_size for a in self.areas)
        # recovery bookkeeping, bounded (the cycle reports it in BusStatus)
        self.recoveries = 0  # slaves (or whole passes, EtherCAT) brought back to OP
        self.recovery_errors: deque[str] = deque(maxlen=RECOVERY_LOG)  # newest last
        self.last_recovery_error: str | None = None
        self._recovery: Generator[None, None, bool] | None = None
        # set by the network in OP: called with a slave's index after the backend seeded its outputs
        # (a transition: raw-CAN recover, set_mode), so the output rules restart from the seed (S12)
        self.on_hold: Callable[[int], None] | None = None
        self._accept_plan: (
            list[tuple[DirectionImage, npt.NDArray[np.uint8], npt.NDArray[np.uint8], npt.NDArray[np.bool_]]]
            | None
        ) = None
        self._accept_src: npt.NDArray[np.bool_] | None = None
        self._accept_all: list[tuple[DirectionImage, Callable[[], object]]] = []  # every slave fresh
        self._expected_wkc: int | None = None

    def out_row(self, i: int) -> npt.NDArray[np.uint8]:
        """Slave ``i``'s output (RxPDO) wire bytes: a contiguous view into its group's image."""
        a = self.areas[i]
        wire = self.groups[a.group].image.outputs.wire
        # a multi-axis slave: its axes' rows, (axes, size) - rows are contiguous, not the rows together
        row: npt.NDArray[np.uint8] = wire[a.row] if a.axes == 1 else wire[a.row : a.row + a.axes]
        return row

    def in_row(self, i: int) -> npt.NDArray[np.uint8]:
        """Where slave ``i``'s input (TxPDO) wire bytes are received: a contiguous row of the receive scratch.

        The network copies a row into the image only when the policy accepts
        that slave's inputs for the cycle (:meth:`accept_inputs`).
        """
        a = self.areas[i]
        rx = self.rx[a.group]
        row: npt.NDArray[np.uint8] = rx[a.row] if a.axes == 1 else rx[a.row : a.row + a.axes].reshape(-1)
        return row

    def accept_inputs(self, fresh: npt.NDArray[np.bool_], every: bool = False) -> None:
        """Copy the rows of the slaves fresh this cycle (per slave, bus order) into the images and decode.

        Rows of stale slaves are not touched: their values stay bit-identical to
        the last accepted ones. ``every``: the caller knows every slave is fresh
        (a plain copy). Allocation-free (the masks are views made once).
        """
        if self._accept_plan is None or self._accept_src is not fresh:
            self._accept_src = fresh
            self._accept_plan = [  # (slave, axis, byte) views: a multi-axis slave's rows go together
                (
                    g.image.inputs,
                    _by_slave(g.image.inputs.wire, len(g.slaves)),
                    _by_slave(self.rx[k], len(g.slaves)),
                    fresh[g.first : g.first + len(g.slaves)].reshape(-1, 1, 1),
                )
                for k, g in enumerate(self.groups)
            ]
            self._accept_all = [
                (g.image.inputs, kernels.copier(g.image.inputs.wire, self.rx[k]))
                for k, g in enumerate(self.groups)
            ]
        if every:  # one copy per group (core.kernels), then decode
            for inputs, copy in self._accept_all:
                copy()
                inputs.from_wire()
            return
        for inputs, wire, rx, rows in self._accept_plan:
            if rows.any():
                np.copyto(wire, rx, where=rows)
            else:
                continue
            inputs.from_wire()

    @property
    def n_slaves(self) -> int:
        return len(self.areas)

    def counters(self) -> dict[str, int]:
        """The fault counters (:data:`COUNTERS`) since open: 0 for what the bus has no such thing of."""
        return {
            "late_replies": int(self.late_replies),
            "stale_frames": int(self.stale_frames),
            "late_frames": int(self.late_frames),
            "extra_frames": int(self.extra_frames),
            "tx_errors": int(self.tx_errors),
            "rx_errors": int(self.rx_errors),
            "error_frames": int(self.error_frames),
            "bus_off": int(self.bus_off),
            "emcy_count": int(self.emcy_count),
            "motor_faults": int(self.motor_faults),
        }

    def slave_state(self, i: int) -> str:
        """Slave ``i``'s state as the bus last read it (EtherCAT AL state, CANopen NMT state); "-": unknown."""
        return "-"

    def last_emergency_name(self, i: int) -> str | None:
        """The name of the last emergency slave ``i`` sent (CANopen EMCY); None: none, or no such thing."""
        return None

    def take_motor_events(self, cycle: int) -> tuple[DriveFault, ...]:
        """Faults the motors reported since the last call, as events of cycle ``cycle`` (raw CAN: their
        own error codes); the cycle calls it once per bus cycle after accepting inputs. Default: none."""
        return ()

    @property
    def expected_wkc(self) -> int:
        """Working counter a complete cycle returns (EtherCAT rule; CAN backends override). Computed once."""
        if self._expected_wkc is None:
            from fieldbus.core.wkc import expected_wkc

            self._expected_wkc = expected_wkc([a.layout for a in self.areas])
        return self._expected_wkc

    def check_identities(self, found: list[tuple[str, int, int] | None], where: str) -> None:
        """Compare what sits at each wire position, ``(name, vendor id, product id)``, with the maps.

        Raises :class:`StateTransitionError` listing every position that differs
        (expected map and identity, and what was found).
        """
        lines = []
        for i in range(max(len(found), len(self.areas))):
            have = found[i] if i < len(found) else None
            exp = self.areas[i].slave if i < len(self.areas) else None
            have_txt = f"'{have[0]}' vendor 0x{have[1]:08X} product 0x{have[2]:08X}" if have else "nothing"
            if exp is None:
                lines.append(f"  position {i}: found {have_txt}, not in the network file")
            elif have is None or have[1:] != (exp.map.vendor_id, exp.map.product_id):
                lines.append(
                    f"  position {i} ({exp.name}): expected {exp.map.name} vendor 0x{exp.map.vendor_id:08X} "
                    f"product 0x{exp.map.product_id:08X}, found {have_txt}"
                )
        if lines:
            raise StateTransitionError(
                f"bus '{self.bus.name}' {where}: {len(found)} slaves found, {len(self.areas)} expected; "
                "mismatches:\n" + "\n".join(lines)
            )

    def slave_index(self, name: str) -> int:
        for i, a in enumerate(self.areas):
            if a.slave.name == name:
                return i
        raise FieldbusError(f"no slave '{name}' on bus '{self.bus.name}'")

    # -- bring-up (blocking, outside the cycle) -----------------------------------
    @abc.abstractmethod
    def open(self) -> None:
        """Open the interface and find the slaves (checks identity against the maps)."""

    @abc.abstractmethod
    def configure(self) -> None:
        """PRE-OP / PRE-OPERATIONAL: apply every slave's SDO plan and read it back."""

    @abc.abstractmethod
    def safe_op(self) -> None:
        """Map process data and go to SAFE-OP (inputs valid, outputs ignored by the drives)."""

    @abc.abstractmethod
    def op(self) -> None:
        """Go to OP / OPERATIONAL; raise :class:`StateTransitionError` with the reason on failure."""

    def _confirm_wkc(self, cycles: int = OP_CONFIRM_CYCLES) -> None:
        """After OP: within ``cycles`` cycles one must return the expected working counter.

        Every slave can report OP while the process data still do not reach
        one of them (a mapping SOEM and the slave disagree on): bring-up stops
        here with :class:`WorkingCounterError` instead of starting a cycle that
        would never be fresh.
        """
        got: int | None = None
        for _ in range(cycles):
            self.send()
            got = self.receive()
            # a late reply is a miss in the cycle, but its WKC still shows the mapping reaches every slave
            if got == self.expected_wkc or self.late_wkc == self.expected_wkc:
                return
        raise WorkingCounterError(
            self.expected_wkc,
            -1 if got is None else got,
            f"bus '{self.bus.name}': every slave reports OP, but no cycle of {cycles} returned the expected "
            "working counter (None: no reply)",
        )

    # -- cycle ----------------------------------------------------------------------
    @abc.abstractmethod
    def send(self) -> None:
        """Put this cycle's outputs (every slave's ``out_row``) on the bus."""

    @abc.abstractmethod
    def receive(self) -> int | None:
        """Wait up to the receive timeout; copy replies into the slaves' ``in_row`` (the receive scratch).

        Returns the working counter (CAN: the number of expected frames that
        arrived) or None on timeout. The scratch may be partly written on a
        miss: the Network copies a slave's row into the image only when the
        policy calls that slave fresh. May raise on a bus fault: the Network
        turns any exception into this bus's verdict ERROR (never out of ``exchange()``).
        """

    def arrived(self) -> npt.NDArray[np.bool_] | None:
        """Per-slave arrival of this cycle's inputs when the bus can tell (CAN); else None."""
        return None

    def slaves_answered(self, wkc: int | None) -> npt.NDArray[np.bool_] | None:
        """Per slave, whether it answered in a cycle whose working counter ``wkc`` was short, when the
        bus can tell (CAN: :meth:`arrived`; EtherCAT: :func:`fieldbus.core.wkc.answered_slaves`); None:
        it cannot. Used by the wind-down on close (S6), not by the cycle's verdict."""
        return self.arrived()

    # distributed clocks (EtherCAT buses with DC slaves; None elsewhere)
    dc_time_ns: int | None = None  # DC system time read in this cycle's frame (reference clock), ns
    dc_sync_error_ns: int | None = None  # host cycle phase minus its target within the DC cycle, ns

    def dc_correction_ns(self) -> int:
        """Nanoseconds to add to the next cycle deadline so the host follows DC time (0: no DC)."""
        return 0

    @property
    def recovering(self) -> bool:
        """A recovery is under way (a slave is known not to be in OP, or is being configured again)."""
        return self._recovery is not None

    def recover_step(self) -> bool:
        """One bounded recovery step for slaves not in OP; True: nothing (more) to do. Never raises.

        Called by :meth:`fieldbus.network.Operational.exchange` - the only caller
        in the cycle - once per cycle after a miss and every cycle while
        :attr:`recovering`. Advances :meth:`_recover` by one step; a step that
        raises ends that attempt (recorded in :attr:`recovery_errors`), the
        next call starts another.
        """
        if self._recovery is None:
            self._recovery = self._recover()
            if self._recovery is None:
                return True
        try:
            next(self._recovery)
        except StopIteration as stop:
            self._recovery = None
            return bool(stop.value)
        except Exception as exc:
            self._recovery = None
            self._recovery_failed(exc)
        return False

    def _recover(self) -> Generator[None, None, bool] | None:
        """The bus's recovery as bounded steps (one per ``yield``), returning True when all are back; None: none."""
        return None

    def plan_io(self, i: int) -> tuple[Callable[[int, int, bytes], None], Callable[[int, int, int], bytes]]:
        """(write, read) of slave ``i`` for :func:`~fieldbus.backends.sdo_exec.apply_plan` (blocking SDOs)."""

        def write(index: int, sub: int, data: bytes) -> None:
            self.sdo_write(i, index, sub, data)

        def read(index: int, sub: int, size: int) -> bytes:
            return self.read_for_plan(i, index, sub, size)

        return write, read

    def read_for_plan(self, slave: int, index: int, sub_index: int, size: int) -> bytes:
        """A plan's read-back of ``size`` bytes (a backend whose reads need the size overrides it)."""
        return self.sdo_read(slave, index, sub_index)

    def _recovery_failed(self, exc: BaseException) -> None:
        """Record a failed recovery attempt (kept bounded in :attr:`recovery_errors`)."""
        self.last_recovery_error = f"{type(exc).__name__}: {exc}"
        self.recovery_errors.append(self.last_recovery_error)

    # -- shut-down ----------------------------------------------------------------------
    @abc.abstractmethod
    def stop(self) -> None:
        """Leave OP (SAFE-OP/INIT or NMT pre-operational). Must not raise on a dead bus."""

    @abc.abstractmethod
    def close(self) -> None:
        """Release the interface. Idempotent."""

    # -- acyclic access ---------------------------------------------------------------
    def acyclic_step(self, request: SdoRequest) -> bool:
        """Serve (or advance) an SDO transfer asked for in OP, from the cycle thread; True when finished.

        Called by :meth:`fieldbus.network.Operational.exchange` at most once per
        bus per cycle, never while the bus is recovering. This default runs the
        transfer at once (fine where it takes microseconds: the in-process
        emulator); a backend whose transfers wait on the wire overrides it with
        a bounded or non-blocking version. Never raises: the outcome goes to
        the request's future.
        """
        try:
            if request.data is None:
                request.finish(self.sdo_read(request.slave, request.index, request.sub_index))
            else:
                self.sdo_write(request.slave, request.index, request.sub_index, request.data)
                request.finish(None)
        except FieldbusError as exc:
            request.finish(error=exc)
        return True

    def diag_step(self) -> list[CounterRise | LinkChange]:
        """One bounded diagnostic read per cycle in OP (EtherCAT: ESC error counters); what changed.
        Called after the SDO step, never while recovering, and only while :attr:`error_watch` is set.
        Default: none."""
        return []

    def sdo_read(self, slave: int, index: int, sub_index: int) -> bytes:
        raise FieldbusError(f"{self.kind} backend has no SDO access")

    def sdo_write(self, slave: int, index: int, sub_index: int, data: bytes) -> None:
        raise FieldbusError(f"{self.kind} backend has no SDO access")
