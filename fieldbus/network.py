"""The cyclic API: open a network file, bring it up in typed phases, exchange every cycle.

    with fieldbus.open_network("robot.yaml") as net:
        op = net.bring_up()                 # PRE-OP (SDO plans, read back) -> SAFE-OP -> OP
        legs = op["legs"]                   # ProcessImage: one row per axis
        while running:
            legs.outputs["target_position"][:] = q      # engineering units (rad)
            result = op.exchange()          # one call per cycle, every bus
            if result.fresh:
                q_meas = legs.inputs["position_actual_value"]

Only the phase objects have the verbs that are valid in that phase
(:class:`Network` -> :class:`PreOp` -> :class:`SafeOp` -> :class:`Operational`),
so a cycle cannot run before the process image exists. Leaving the ``with``
block (normally, on an exception or on Ctrl-C) quick-stops every CiA 402 drive,
disables it, and closes the buses.
"""

from __future__ import annotations

import contextlib
import threading
import time
import warnings
from collections.abc import Iterator, Mapping
from concurrent.futures import Future
from pathlib import Path
from types import TracebackType
from typing import TYPE_CHECKING, Any

import numpy as np
import numpy.typing as npt

from fieldbus.backends import backend_class
from fieldbus.backends.base import AxisGroup, Backend
from fieldbus.core import network as netfile
from fieldbus.core.hold import TransitionHold
from fieldbus.core.output_rules import OutputRules
from fieldbus.core.pdo.image import ProcessImage
from fieldbus.core.safestop import SafeStopWriter
from fieldbus.core.safety import DEFAULT_RELEASE_AFTER, OK, PolicyConfig, SafetyPolicy
from fieldbus.core.winddown import MAX_BUDGET_S, WindDownReport
from fieldbus.cycle.acyclic import MAX_SDO_BYTES, AcyclicService
from fieldbus.cycle.buscycle import MODES_DISPLAY, BusCycle
from fieldbus.cycle.motor_events import MotorEventPump
from fieldbus.cycle.status import (
    BusEvent,
    BusFault,
    BusStatus,
    BusView,
    CycleEvent,
    CycleObserver,
    CycleResult,
    FaultKind,
    SdoAbortEvent,
)
from fieldbus.cycle.status import reason as _reason
from fieldbus.cycle.stopping import CLOSE_CYCLES, SafeStopController
from fieldbus.errors import FieldbusError, PhaseError, RequestError
from fieldbus.platform import phases as ph
from fieldbus.platform.clock import WALL, Clock

if TYPE_CHECKING:
    from fieldbus.recording import Recorder

__all__ = [  # the parts' types are re-exported here, where they always were
    "CLOSE_CYCLES",
    "MAX_SDO_BYTES",
    "MODES_DISPLAY",
    "PER_BUS_OPTIONS",
    "BusEvent",
    "BusFault",
    "BusStatus",
    "BusView",
    "CycleEvent",
    "CycleObserver",
    "CycleResult",
    "FaultKind",
    "Network",
    "Operational",
    "PreOp",
    "SafeOp",
    "SdoAbortEvent",
    "open_network",
]

PER_BUS_OPTIONS = ("can_bus", "can_log", "pcap")  # options naming one bus's own instance or file


def open_network(
    source: str | Path | netfile.NetworkConfig,
    *,
    backend: str | None = None,
    bus_options: Mapping[str, Mapping[str, object]] | None = None,
    **backend_options: object,
) -> Network:
    """Load a network file (or use a loaded one) and create its backends; nothing is opened yet.

    ``backend`` overrides every bus's type. ``backend_options`` go to every
    bus; ``bus_options`` maps a bus name to options for that bus only (they
    win over the shared ones), e.g. ``bus_options={"arm": {"can_bus": bus}}``.
    """
    net = source if isinstance(source, netfile.NetworkConfig) else netfile.load_network(source)
    return Network(net, backend=backend, bus_options=bus_options, **backend_options)


class _Phase:
    def __init__(self, owner: Network) -> None:
        self._net = owner

    def _check(self) -> None:
        if self._net._phase is not self:
            raise PhaseError(
                f"this {type(self).__name__} phase is over (now {type(self._net._phase).__name__})"
            )


def _check_bus_cycles(model: netfile.NetworkConfig) -> None:
    """Every bus's cycle (µs) is a whole multiple of the shortest: a bus runs every n-th cycle of the fastest."""
    base = min(bus.cycle_time_us for bus in model.buses)
    for bus in model.buses:
        if bus.cycle_time_us % base:
            raise FieldbusError(
                f"{model.source}: bus '{bus.name}' cycle_time_us {bus.cycle_time_us} is not a whole multiple "
                f"of the shortest bus cycle ({base} us): a bus runs every n-th cycle of the fastest"
            )


class Network(_Phase):
    """Configured: the network file is loaded and its backends created, nothing opened yet."""

    def __init__(
        self,
        model: netfile.NetworkConfig,
        *,
        backend: str | None = None,
        bus_options: Mapping[str, Mapping[str, object]] | None = None,
        **backend_options: object,
    ) -> None:
        super().__init__(self)
        self.model = model
        names = [bus.name for bus in model.buses]
        unknown = sorted(set(bus_options or {}) - set(names))
        if unknown:
            raise FieldbusError(
                f"bus_options name no bus of the network: {', '.join(unknown)} (have {', '.join(names)})"
            )
        clock = self._take_network_options(backend_options)
        self.last_wind_down: WindDownReport | None = None  # the outcome of the last close() from OP
        self.close_errors: list[str] = []  # what the buses raised while closing (close() itself does not)
        per_instance = [k for k in backend_options if k in PER_BUS_OPTIONS]
        if per_instance and len(names) > 1:
            raise FieldbusError(
                f"option {per_instance[0]!r} is one bus's own (an interface instance) and this network has "
                f"{len(names)} buses: pass it per bus, bus_options={{'{names[0]}': {{'{per_instance[0]}': ...}}}}"
            )
        _check_bus_cycles(model)
        netfile.check_open_options(model, backend, backend_options, bus_options)
        self.backends = self._make_backends(backend, backend_options, bus_options, clock)
        self.policies = [
            SafetyPolicy(
                b.expected_wkc,
                b.n_slaves,
                PolicyConfig(b.bus.safe_stop_after, self.release_after),
                name=b.bus.name,
            )
            for b in self.backends
        ]
        self.groups: dict[str, AxisGroup] = {g.name: g for b in self.backends for g in b.groups}
        self._phase: _Phase = self
        self._opened = False
        self._closed = False
        self._open_backends: list[Backend] = []  # every backend whose close() has not succeeded yet
        self._close_lock = threading.Lock()  # one close() at a time: a second one waits for the first
        self._closing_thread: int | None = None  # the thread inside close() now

    def _take_network_options(self, backend_options: dict[str, object]) -> Clock | None:
        """Take the network's own options out of ``backend_options``: ``clock`` (a Clock), ``release_after``
        (cycles), ``wind_down_max_s`` (s); returns the clock given (None: the wall clock)."""
        # ``clock``: a fieldbus.platform.clock.Clock paces the close wind-down and is the time of every
        # backend that reads a clock (sim, CAN); a bare ``() -> ns`` callable is the sim backend's option
        clock = backend_options.get("clock")
        if clock is not None and hasattr(clock, "now_ns") and hasattr(clock, "sleep"):
            del backend_options["clock"]
        else:
            clock = None
        release_after = backend_options.pop("release_after", DEFAULT_RELEASE_AFTER)
        wind_down_cap_s = backend_options.pop("wind_down_max_s", MAX_BUDGET_S)
        if not isinstance(release_after, int) or isinstance(release_after, bool) or release_after < 1:
            raise FieldbusError(f"release_after must be a whole number of cycles >= 1, not {release_after!r}")
        if not isinstance(wind_down_cap_s, int | float) or not 0 < float(wind_down_cap_s) <= 60:
            raise FieldbusError(
                f"wind_down_max_s must be a number of seconds in (0, 60], not {wind_down_cap_s!r}"
            )
        self.clock: Clock = WALL if clock is None else clock
        self.release_after = release_after
        self.wind_down_cap_s = float(wind_down_cap_s)
        return None if clock is None else self.clock

    def _make_backends(
        self,
        backend: str | None,
        backend_options: Mapping[str, object],
        bus_options: Mapping[str, Mapping[str, object]] | None,
        clock: Clock | None,
    ) -> list[Backend]:
        """One backend per bus, all or none: one that fails to construct takes down the ones made before
        it (none has opened its interface yet). Every check ran before: nothing exists until here."""
        backends: list[Backend] = []
        try:
            for bus in self.model.buses:
                kind = backend or bus.type
                cls = backend_class(kind)
                opts = {**backend_options, **(bus_options or {}).get(bus.name, {})}
                if clock is not None and "clock" in (netfile.backend_options(kind) or ("clock",)):
                    opts.setdefault("clock", clock)
                backends.append(cls(bus, **opts))
        except BaseException:
            for made in backends:
                with contextlib.suppress(Exception):  # the construction error is the one to report
                    made.close()
            raise
        return backends

    def backend(self, bus: str) -> Backend:
        """The backend of bus ``bus`` (by name)."""
        for b in self.backends:
            if b.bus.name == bus:
                return b
        raise FieldbusError(f"no bus '{bus}' (have: {', '.join(b.bus.name for b in self.backends)})")

    # -- phases -------------------------------------------------------------------------
    def pre_op(self) -> PreOp:
        """Open every bus, check identities, apply and read back every SDO plan."""
        self._check()
        self._opened = True
        self._open_backends = list(self.backends)
        try:
            for b in self.backends:
                b.open()
            for b in self.backends:
                b.configure()
        except BaseException:
            self.close()
            raise
        phase = PreOp(self)
        self._phase = phase
        return phase

    def bring_up(self) -> Operational:
        """``pre_op().safe_op().op()``."""
        return self.pre_op().safe_op().op()

    # -- context manager ---------------------------------------------------------------
    def __enter__(self) -> Network:
        return self

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.close()

    def close(self) -> None:
        """Bring every drive down (a controlled stop, then disable voltage), leave OP, close every bus.

        Never raises for a bus fault (invariant S1): whatever a bus raises on
        the way, every bus is still stopped and closed, and the errors are kept
        in :attr:`close_errors` and warned about (``RuntimeWarning``). A
        KeyboardInterrupt or SystemExit meanwhile does not cut it short and is
        raised again at the end. Calling it again retries what did not close;
        once all closed it does nothing.

        Re-entrant and thread-safe: a close() from another thread while one
        runs waits for it to finish (the wind-down is never skipped, nor run
        twice); a close() from the same thread while it runs (a signal handler
        that interrupts it) returns at once and the first one completes the
        controlled stop.
        """
        me = threading.get_ident()
        if self._closing_thread == me:
            return  # re-entered (a signal handler): the close under way finishes the stop
        with self._close_lock:
            self._closing_thread = me
            try:
                self._close()
            finally:
                self._closing_thread = None

    def _close(self) -> None:
        if self._closed and not self._open_backends:
            return
        self._closed = True
        interrupt: BaseException | None = None
        errors: list[str] = []
        phase = self._phase
        self._phase = _Closed(self)  # no verb of the old phase runs from now on
        if isinstance(phase, Operational):
            for obs in phase._observers:
                try:
                    obs.close()  # a recording never raises: a failed write was already warned about
                except Exception as exc:
                    errors.append(f"observer {type(obs).__name__}: {_reason(exc)}")
            phase._fail_pending_sdo()
            try:
                phase._wind_down()
            except Exception as exc:
                errors.append(f"wind-down: {_reason(exc)}")
            except BaseException as exc:  # KeyboardInterrupt: keep going, re-raise at the end
                interrupt = exc
        for verb in ("stop", "close"):
            for b in list(self._open_backends):
                try:
                    if verb == "stop":
                        b.stop()
                    else:
                        b.close()
                    if verb == "close":
                        self._open_backends.remove(b)
                except Exception as exc:
                    errors.append(f"bus '{b.bus.name}' {verb}: {_reason(exc)}")
                except BaseException as exc:
                    interrupt = interrupt or exc
        self.close_errors.extend(errors)
        for text in errors:
            warnings.warn(f"fieldbus: closing the network: {text}", RuntimeWarning, stacklevel=2)
        if interrupt is not None:
            raise interrupt


class _Closed(_Phase):
    pass


class PreOp(_Phase):
    """PRE-OP: SDO plans applied; acyclic SDO access allowed; no process data yet."""

    def sdo_read(self, bus: str, slave: str, index: int, sub_index: int) -> bytes:
        """Upload ``index:sub_index`` from slave ``slave`` of bus ``bus`` (blocking; raw bytes)."""
        self._check()
        b = self._net.backend(bus)
        return b.sdo_read(b.slave_index(slave), index, sub_index)

    def sdo_write(self, bus: str, slave: str, index: int, sub_index: int, data: bytes) -> None:
        """Download ``data`` to ``index:sub_index`` of slave ``slave`` of bus ``bus`` (blocking)."""
        self._check()
        b = self._net.backend(bus)
        b.sdo_write(b.slave_index(slave), index, sub_index, data)

    def safe_op(self) -> SafeOp:
        self._check()
        try:
            for b in self._net.backends:
                b.safe_op()
        except BaseException:
            self._net.close()
            raise
        phase = SafeOp(self._net)
        self._net._phase = phase
        return phase


class SafeOp(_Phase):
    """SAFE-OP: process image mapped; drives ignore outputs."""

    def op(self) -> Operational:
        """Every bus to OP: CAN buses first (their op() waits for the nodes' NMT state), EtherCAT last,
        so that no EtherCAT slave sits in OP without process data while another bus waits (its
        SyncManager watchdog would trip before the first cycle)."""
        self._check()
        try:
            for b in sorted(self._net.backends, key=lambda b: b.pdo_align == 1):
                b.op()
        except BaseException:
            self._net.close()
            raise
        phase = Operational(self._net)
        self._net._phase = phase
        return phase


class Operational(_Phase):
    """OP: call :meth:`exchange` once per cycle.

    A façade over parts with one job each (:mod:`fieldbus.cycle`): per bus a
    :class:`~fieldbus.cycle.buscycle.BusCycle` (encode, send, receive, judge,
    accept, decode, recovery step), the
    :class:`~fieldbus.cycle.acyclic.AcyclicService` (SDO queue, drive-fault
    follow-up reads, diagnostics), the
    :class:`~fieldbus.cycle.stopping.SafeStopController` (writers, latch,
    wind-down) and the :class:`~fieldbus.cycle.motor_events.MotorEventPump`.
    """

    def __init__(self, owner: Network) -> None:
        super().__init__(owner)
        net = owner
        # a bus runs every n-th call: n = its cycle_time_us / the shortest one (the call rate)
        self.cycle_time_us = min(b.bus.cycle_time_us for b in net.backends)
        self._cycles = [
            BusCycle(b, p, b.bus.cycle_time_us // self.cycle_time_us)
            for b, p in zip(net.backends, net.policies, strict=True)
        ]
        statuses = tuple(bc.status for bc in self._cycles)
        self.result = CycleResult(statuses, _by_name={s.name: s for s in statuses})
        self._acyclic = AcyclicService(net.backends, net.groups)
        self._stop = SafeStopController(net.groups, self._cycles, self.result)
        self._motor = MotorEventPump(net.backends)
        self.safe_stops: dict[str, SafeStopWriter] = (
            self._stop.writers
        )  # what the safe stop writes, per group
        # the one output path: every group's command values pass its rules before any codec (S11)
        self.output_rules: dict[str, OutputRules] = {}
        for k, bc in enumerate(self._cycles):
            self.output_rules.update((r.group, r) for r in bc.rules)
            for watch, _ in bc.watches:
                self.result.drive_faults[watch.group] = watch.faults
            bc.on_drive_fault = lambda fault, k=k: self._acyclic.read_code(k, fault)
        # raw-CAN groups: their hold command after a transition (S12, fieldbus.core.hold)
        self.holds: dict[str, TransitionHold] = {}
        for bc in self._cycles:
            self.holds.update(bc.holds)
            if bc.holds:
                bc.backend.on_hold = bc.hold_hook
        self._observers: tuple[CycleObserver, ...] = ()  # recordings and probes, called every cycle
        # where exchange() spends its time, phase by phase (fieldbus.platform.phases); None: not timed
        self.phases: ph.PhaseTimer | None = None
        self.buses: tuple[BusView, ...] = tuple(
            BusView(bc.backend, bc.policy, bc.status, bc.rules) for bc in self._cycles
        )

    @property
    def groups(self) -> dict[str, AxisGroup]:
        return self._net.groups

    def fault_code_pending(self, group: str) -> npt.NDArray[np.bool_]:
        """Per row of ``group``: its fault's error code (0x603F) is still being read acyclically.

        Pass it to ``Cia402Controller.step(..., hold_reset=...)`` (or ``step_image``) so the fault
        reset waits for the read: a drive clears 0x603F on reset. The same array every cycle, updated
        by :meth:`exchange` (read it, do not keep a copy).
        """
        return self._acyclic.code_pending(group)

    def __getitem__(self, group: str) -> ProcessImage:
        """The process image of axis group ``group`` (a bus name when the bus has one map)."""
        try:
            return self._net.groups[group].image
        except KeyError:
            raise FieldbusError(f"no axis group '{group}' (have: {', '.join(self._net.groups)})") from None

    def __iter__(self) -> Iterator[str]:
        return iter(self._net.groups)

    def exchange(self) -> CycleResult:
        """One cycle on every bus that is due: encode outputs, send, receive, judge, accept fresh inputs.

        Never raises for a bus fault (invariant S1): an exception from a
        backend's send or receive becomes that bus's verdict ERROR, with the
        reason in :attr:`BusStatus.error` (and its :attr:`BusStatus.fault`), and
        latches the safe stop. While a safe stop is latched, every group's safe
        outputs overwrite what the controller wrote. Inputs of a slave that is
        not fresh are not touched (S2). Recovery of lost slaves advances here -
        its one caller - by one bounded step per bus per cycle, after a miss and
        while the bus reports it is recovering. Raises only for caller errors
        (:class:`PhaseError` after close).
        """
        if self._net._phase is not self:
            self._check()  # raises PhaseError
        t0 = time.perf_counter_ns()
        if self._acyclic.cycle_thread is None:
            self._acyclic.cycle_thread = threading.get_ident()
        res = self.result
        cycle = res.cycle
        pt = self.phases
        if pt is not None:
            pt.start(t0)
        if res.events:
            res.events = []  # a new list only after a cycle that had events: the caller may keep the old one
        if res.safe_stop:
            self._stop.before_cycle()  # latched: the safe outputs over the controller's (S4)
        for bc in self._cycles:
            if bc.due(cycle):
                bc.send(cycle, res.events, pt)
        all_fresh = True
        any_stop = False
        for k, bc in enumerate(self._cycles):
            if bc.status.ran:
                self._receive(k, cycle)
            all_fresh = all_fresh and bc.status.verdict is OK
            any_stop = any_stop or bc.policy.safe_stop
        if self._acyclic.follow_ups:
            self._acyclic.collect(cycle, res.events)
            if pt is not None:
                pt.mark(ph.ACYCLIC)
        res.fresh = all_fresh
        latched = self._stop.after_cycle(any_stop)
        res.cycle = cycle + 1
        res.exchange_ns = time.perf_counter_ns() - t0
        if res.events:
            for obs in self._observers:
                obs.note_events(res.events)
        for obs in self._observers:  # before the safe outputs below: it records what this cycle sent
            obs.capture(res, t0)
        if latched:
            self._stop.apply()  # effective from the next cycle's outputs
        elif self._stop.released:  # raw-CAN motors hold where they are until the controller writes (S12)
            self._stop.seed_holds()
        if pt is not None:
            pt.mark(ph.OBSERVERS)
        return res

    def _receive(self, k: int, cycle: int) -> None:
        """Bus ``k`` after its send: receive, judge and accept; motor events; recovery and acyclic steps.
        Never raises (S1)."""
        bc, events, pt = self._cycles[k], self.result.events, self.phases
        bc.receive(cycle, events, pt)
        if self._motor.reporting[k]:  # raw-CAN motor faults (Damiao error codes, ODrive axis errors)
            self._motor.pump(k, cycle, events)
        if pt is not None:
            pt.mark(ph.ACCEPT)
        st, b, ac = bc.status, bc.backend, self._acyclic
        # the clean cycle (fresh, not recovering) has no recovery step due and no recovery status to copy
        if st.verdict is not OK or st.error is not None or st.recovering or b.recovering:
            bc.recover()
        if pt is not None:
            pt.mark(ph.CONTRACT)
        if ac.current[k] is not None or ac.pending[k] or b.error_watch is not None:
            ac.step(k, st, cycle, events)  # an SDO transfer to serve, or a diagnostic read (diag_step)
        if pt is not None:
            pt.mark(ph.ACYCLIC)

    def record(self, path: str | Path, *, raw: bool = False, **options: Any) -> Recorder:
        """Record every cycle from now on to the MCAP file ``path`` (see :mod:`fieldbus.recording`).

        Inputs and outputs of every axis group in engineering units (``raw``: also
        the wire bytes), per bus the working counter, verdict and per-slave
        freshness, cycle times, and events. The cycle copies into a preallocated
        ring, a writer thread writes the file. Stops on ``recorder.close()`` or
        :meth:`close`. Raises :class:`FieldbusError` naming the file when it cannot
        be written. ``options``: ``block_cycles``, ``ring_blocks``, ``open_file``.
        """
        self._check()
        from fieldbus.recording import Recorder

        return Recorder(self, path, raw=raw, **options)

    @property
    def recorders(self) -> tuple[Recorder, ...]:
        """The recordings running on this network (:meth:`record`)."""
        from fieldbus.recording import Recorder

        return tuple(o for o in self._observers if isinstance(o, Recorder))

    @property
    def network(self) -> Network:
        """The network this phase belongs to (its model, backends and last wind-down)."""
        return self._net

    def add_observer(self, observer: CycleObserver) -> None:
        """Call ``observer`` every cycle from now on (see :class:`CycleObserver`)."""
        self._check()
        self._observers = (*self._observers, observer)

    def remove_observer(self, observer: CycleObserver) -> None:
        """Stop calling ``observer`` (no error if it was not added)."""
        self._observers = tuple(o for o in self._observers if o is not observer)

    # -- acyclic access in OP --------------------------------------------------------------
    def submit_sdo_read(self, bus: str, slave: str, index: int, sub_index: int) -> Future[bytes | None]:
        """Queue an SDO upload for the running cycle to serve; its future gives the bytes read.

        Any thread may call it. The cycle serves one transfer per bus at a time,
        one bounded step per cycle, never while the bus is recovering.
        """
        return self._submit(bus, slave, index, sub_index, None)

    def submit_sdo_write(
        self, bus: str, slave: str, index: int, sub_index: int, data: bytes
    ) -> Future[bytes | None]:
        """Queue an SDO download of ``data`` for the running cycle to serve (see :meth:`submit_sdo_read`)."""
        if not isinstance(data, bytes | bytearray | memoryview):
            raise RequestError(f"SDO data must be bytes, not {type(data).__name__}")
        return self._submit(bus, slave, index, sub_index, bytes(data))

    def sdo_read(self, bus: str, slave: str, index: int, sub_index: int, *, timeout_s: float = 2.0) -> bytes:
        """Read an object while the cycle runs in another thread: waits until the cycle has served it."""
        data = self._acyclic.wait(self.submit_sdo_read(bus, slave, index, sub_index), timeout_s)
        assert data is not None
        return data

    def sdo_write(
        self, bus: str, slave: str, index: int, sub_index: int, data: bytes, *, timeout_s: float = 2.0
    ) -> None:
        """Write an object while the cycle runs in another thread: waits until the cycle has served it."""
        self._acyclic.wait(self.submit_sdo_write(bus, slave, index, sub_index, data), timeout_s)

    def _submit(
        self, bus: str, slave: str, index: int, sub_index: int, data: bytes | None
    ) -> Future[bytes | None]:
        """Check the request at the door (S5): a malformed one raises here and nothing is queued."""
        self._check()
        b = self._net.backend(bus)
        return self._acyclic.submit(self._net.backends.index(b), slave, index, sub_index, data)

    def _fail_pending_sdo(self) -> None:
        self._acyclic.fail_pending()

    def dc_correction_ns(self) -> int:
        """Nanoseconds to add to the next cycle deadline so the host follows DC time (0 without DC).

        The host follows one clock: the reference clock of the first bus with
        DC (each other bus keeps its own slaves in step with its reference slave).
        Pass it to :func:`fieldbus.run_cycles` as ``adjust``.
        """
        for b in self._net.backends:
            if b.dc_time_ns is not None:
                return b.dc_correction_ns()
        return 0

    def clear_safe_stop(self) -> bool:
        """Ask to release a latched safe stop (S4); True when every bus's latch is open now.

        Refused with :class:`~fieldbus.core.safety.SafeStopClearError` while a
        latched bus is still missing (nothing is changed then). Otherwise each
        latched bus opens once it has had ``release_after`` fresh cycles in a
        row (at once if it already has; a miss meanwhile cancels the request);
        until then its safe outputs keep overwriting the controller's. The
        controller then re-enables its drives through CiA 402.
        """
        self._check()
        return self._stop.clear()

    def close(self) -> None:
        self._net.close()

    def _wind_down(self) -> None:
        """A controlled stop (S6), on close from OP: see :meth:`SafeStopController.wind_down`. The
        outcome is in :attr:`Network.last_wind_down`."""
        net = self._net

        def keep(report: WindDownReport) -> None:
            net.last_wind_down = report

        self._stop.wind_down(self._receive, self.cycle_time_us, net.wind_down_cap_s, net.clock.sleep, keep)
