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
from collections import deque
from collections.abc import Callable, Iterator, Mapping
from concurrent.futures import CancelledError, Future, wait
from dataclasses import dataclass, field, replace
from pathlib import Path
from types import TracebackType
from typing import TYPE_CHECKING, Any, Protocol

import numpy as np
import numpy.typing as npt

from fieldbus.backends import backend_class
from fieldbus.backends.base import AxisGroup, Backend, SdoRequest
from fieldbus.core import network as netfile
from fieldbus.core.cia402 import SafeStop
from fieldbus.core.drivefault import DriveFault, DriveFaultWatch, FaultFollowUp
from fieldbus.core.esc_errors import describe_change
from fieldbus.core.hold import TransitionHold
from fieldbus.core.output_rules import OutputClamp, OutputRules, channel_limits, slave_limits
from fieldbus.core.pdo.image import ProcessImage
from fieldbus.core.pdo.names import STATUSWORD
from fieldbus.core.safestop import SafeStopWriter, safe_stop_plan
from fieldbus.core.safety import DEFAULT_RELEASE_AFTER, PolicyConfig, SafetyPolicy, Verdict
from fieldbus.core.winddown import DISABLE_CYCLES, MAX_BUDGET_S, WindDown, WindDownReport
from fieldbus.errors import (
    BusTimeoutError,
    FieldbusError,
    PhaseError,
    RequestError,
    SdoAbortError,
    abort_name,
)
from fieldbus.runtime import phases as ph
from fieldbus.runtime.clock import WALL, Clock

if TYPE_CHECKING:
    from fieldbus.recording import Recorder

MODES_DISPLAY = 0x6061  # CiA 402 modes of operation display: the output path's step rule holds in 8-10
CLOSE_CYCLES = DISABLE_CYCLES  # cycles of disable voltage sent on close, after the quick stop is done
PER_BUS_OPTIONS = ("can_bus", "can_log", "pcap")  # options naming one bus's own instance or file
MAX_SDO_BYTES = 1 << 20  # the largest SDO download accepted at submit, bytes


@dataclass(frozen=True)
class BusEvent:
    """Something a bus did in one cycle: ``safe_stop`` latched, ``released``, ``bus_error``, ``acyclic_error``."""

    cycle: int
    bus: str
    kind: str
    detail: str = ""

    def __str__(self) -> str:
        return f"cycle {self.cycle} bus '{self.bus}': {self.kind}" + (
            f" ({self.detail})" if self.detail else ""
        )


class CycleObserver(Protocol):
    """What :meth:`Operational.add_observer` takes: a recording, a monitor, a test's probe.

    ``capture`` runs in the cycle's thread at the end of every ``exchange()``
    (keep it short and allocation-free); ``note_events`` gets the cycle's
    events when there are any, before ``capture``; ``close`` runs when the
    network closes.
    """

    def capture(self, res: CycleResult, t0_ns: int) -> None: ...

    def note_events(self, events: list[BusEvent | DriveFault | OutputClamp]) -> None: ...

    def close(self) -> None: ...


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
class BusView:
    """One bus as an observer sees it (:attr:`Operational.buses`): its status, statistics and counters.

    The public face of a running bus for monitors, reports and recordings; it
    reads the backend's counters on demand, never in the cycle.
    """

    backend: Backend
    policy: SafetyPolicy
    status: BusStatus
    rules: tuple[OutputRules, ...] = ()  # the output path's rules of its groups (S11)

    @property
    def name(self) -> str:
        return self.backend.bus.name

    @property
    def kind(self) -> str:
        return self.backend.kind

    @property
    def slaves(self) -> tuple[str, ...]:
        return tuple(a.slave.name for a in self.backend.areas)

    def counters(self) -> dict[str, int]:
        """Faults the bus absorbed since bring-up: late replies, stale and extra frames, transmit errors,
        bus-off events, emergencies (0 where the bus has no such thing), the policy's misses and errors,
        and the command values the output path refused (``output_clamps``).
        """
        out = {name: int(getattr(self.backend, name, 0) or 0) for name in COUNTERS}
        st = self.policy.stats
        out.update(misses=st.misses, timeouts=st.timeouts, short=st.short, errors=st.errors)
        out.update(safe_stops=st.safe_stops, releases=st.releases, recoveries=self.backend.recoveries)
        out["output_clamps"] = sum(int(r.counts.sum()) for r in self.rules)  # command values refused (S11)
        return out

    def slave_state(self, i: int) -> str:
        """Slave ``i``'s state: ``OP`` when its EtherCAT process data were fresh this cycle (a full
        working counter proves every slave processed the LRW in OP), else what the backend last read."""
        if self.backend.pdo_align == 1 and self.policy.fresh[i]:
            return "OP"
        state_of = getattr(self.backend, "slave_state", None)
        return str(state_of(i)) if state_of is not None else "-"


def _reason(exc: BaseException) -> str:
    """An exception as a reason kept in BusStatus: its type and text."""
    t = type(exc)
    name = t.__name__ if t.__module__ == "builtins" else f"{t.__module__.split('.')[0]}.{t.__name__}"
    text = str(exc)
    return f"{name}: {text}" if text else name


@dataclass
class BusStatus:
    """One bus in one cycle (updated in place each cycle)."""

    name: str
    expected_wkc: int
    fresh: npt.NDArray[np.bool_]  # per slave, True: inputs decoded this cycle
    verdict: Verdict = Verdict.OK
    wkc: int = -1
    consecutive_misses: int = 0
    safe_stop: bool = False
    dc_time_ns: int | None = None  # DC system time of this cycle's frame (EtherCAT with DC), ns
    dc_sync_error_ns: int | None = None  # host phase error against the DC cycle, ns
    ran: bool = True  # the bus exchanged this cycle (a bus with a longer cycle_time_us skips cycles)
    recovering: bool = False  # a slave is being brought back to OP
    recoveries: int = 0  # slaves / passes brought back to OP since bring-up
    recovery_error: str | None = None  # the last failed recovery attempt, if any
    error: str | None = None  # this cycle: the exception the bus raised (type: text); None: none
    errors: int = 0  # cycles whose bus raised since bring-up (each one a miss that latches the safe stop)
    last_error: str | None = None  # the newest bus error, kept after the bus is back
    release_pending: bool = False  # clear_safe_stop() was asked; the latch opens after enough fresh cycles


@dataclass
class CycleResult:
    """What :meth:`Operational.exchange` returns; the same object, updated every cycle."""

    buses: tuple[BusStatus, ...]
    cycle: int = 0
    fresh: bool = False  # every slave of every bus fresh
    safe_stop: bool = False  # any bus escalated to a safe stop (latched)
    exchange_ns: int = 0  # time spent in exchange(), ns
    events: list[BusEvent | DriveFault | OutputClamp] = field(
        default_factory=list
    )  # what happened in this cycle (new list each)
    drive_faults: dict[str, npt.NDArray[np.int64]] = field(
        default_factory=dict
    )  # per group, fault edges per axis
    _by_name: dict[str, BusStatus] = field(default_factory=dict, repr=False)

    def bus(self, name: str) -> BusStatus:
        return self._by_name[name]


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
        # ``clock``: a fieldbus.runtime.clock.Clock paces the close wind-down and is the time of every
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
        self.last_wind_down: WindDownReport | None = None  # the outcome of the last close() from OP
        self.close_errors: list[str] = []  # what the buses raised while closing (close() itself does not)
        per_instance = [k for k in backend_options if k in PER_BUS_OPTIONS]
        if per_instance and len(names) > 1:
            raise FieldbusError(
                f"option {per_instance[0]!r} is one bus's own (an interface instance) and this network has "
                f"{len(names)} buses: pass it per bus, bus_options={{'{names[0]}': {{'{per_instance[0]}': ...}}}}"
            )
        base = min(bus.cycle_time_us for bus in model.buses)
        for bus in model.buses:
            if bus.cycle_time_us % base:
                raise FieldbusError(
                    f"{model.source}: bus '{bus.name}' cycle_time_us {bus.cycle_time_us} is not a whole multiple "
                    f"of the shortest bus cycle ({base} us): a bus runs every n-th cycle of the fastest"
                )
        netfile.check_open_options(model, backend, backend_options, bus_options)
        # atomic construction: every check above ran before anything exists; a backend that fails to
        # construct takes down the ones made before it (none has opened its interface yet)
        self.backends: list[Backend] = []
        try:
            for bus in model.buses:
                kind = backend or bus.type
                cls = backend_class(kind)
                opts = {**backend_options, **(bus_options or {}).get(bus.name, {})}
                if clock is not None and "clock" in (netfile.backend_options(kind) or ("clock",)):
                    opts.setdefault("clock", clock)
                self.backends.append(cls(bus, **opts))
        except BaseException:
            for made in self.backends:
                with contextlib.suppress(Exception):  # the construction error is the one to report
                    made.close()
            raise
        self.policies = [
            SafetyPolicy(
                b.expected_wkc,
                b.n_slaves,
                PolicyConfig(b.bus.safe_stop_after, release_after),
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
                    getattr(b, verb)()
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
    """OP: call :meth:`exchange` once per cycle."""

    def __init__(self, owner: Network) -> None:
        super().__init__(owner)
        net = owner
        statuses = tuple(
            BusStatus(b.bus.name, b.expected_wkc, p.fresh)
            for b, p in zip(net.backends, net.policies, strict=True)
        )
        self.result = CycleResult(statuses, _by_name={s.name: s for s in statuses})
        # a bus runs every n-th call: n = its cycle_time_us / the shortest one (the call rate)
        self.cycle_time_us = min(b.bus.cycle_time_us for b in net.backends)
        self._every = [b.bus.cycle_time_us // self.cycle_time_us for b in net.backends]
        self._pairs = list(zip(net.backends, net.policies, statuses, self._every, strict=True))
        # SDO transfers asked for while the cycle runs (any thread), served by the cycle, one per bus at a time
        self._sdo_pending: list[deque[SdoRequest]] = [deque() for _ in net.backends]
        self._sdo_current: list[SdoRequest | None] = [None] * len(net.backends)
        self._cycle_thread: int | None = None
        # what the safe stop writes, per axis group (chosen by its drive map)
        self.safe_stops: dict[str, SafeStopWriter] = {}
        for name, g in net.groups.items():
            plan = safe_stop_plan(g.slaves[0].map, g.image.layout)
            self.safe_stops[name] = SafeStopWriter(plan, g.image)
        self._writers = list(self.safe_stops.values())
        # the one output path: every group's command values pass the rules before any codec (output_rules)
        self.output_rules: dict[str, OutputRules] = {}
        self.holds: dict[str, TransitionHold] = {}  # raw-CAN groups: their hold command (fieldbus.core.hold)
        self._encoders: list[list[tuple[OutputRules, ProcessImage]]] = []
        for b in net.backends:
            enc = []
            for g in b.groups:
                lay = g.image.layout
                sw, md = lay.inputs.find(STATUSWORD), lay.inputs.find(MODES_DISPLAY)
                rules = OutputRules(
                    g.name,
                    g.image.outputs,
                    channel_limits(g.slaves[0].map, lay.outputs, b.bus.cycle_time_us / 1e6),
                    g.image.inputs.values[sw.name] if sw is not None and not sw.channel.scaled else None,
                    g.image.inputs.values[md.name] if md is not None and not md.channel.scaled else None,
                    slave_limits(g.slaves, lay.outputs, b.bus.cycle_time_us / 1e6),  # the network's narrowing
                )
                self.output_rules[g.name] = rules
                enc.append((rules, g.image))
                if g.slaves[0].map.rawcan is not None:  # raw-CAN motors hold after a transition (S12)
                    self.holds[g.name] = TransitionHold(g.image, rules)
            self._encoders.append(enc)
            if any(g.slaves[0].map.rawcan is not None for g in b.groups):
                b.on_hold = self._hold_hook(b)
        self._observers: tuple[CycleObserver, ...] = ()  # recordings and probes, called every cycle
        # where exchange() spends its time, phase by phase (fieldbus.runtime.phases); None: not timed
        self.phases: ph.PhaseTimer | None = None
        self.buses: tuple[BusView, ...] = tuple(
            BusView(b, p, st, tuple(r for r, _ in enc))
            for (b, p, st, _), enc in zip(self._pairs, self._encoders, strict=True)
        )
        self._bus_off: list[int | None] = [
            int(getattr(b, "bus_off", 0)) if hasattr(b, "bus_off") else None for b in net.backends
        ]
        # drive faults (CiA 402 statusword bit 3), watched on the rows each cycle accepted; per bus
        self._faults: list[list[tuple[DriveFaultWatch, npt.NDArray[np.bool_]]]] = []
        for b, p in zip(net.backends, net.policies, strict=True):
            watches = []
            for g in b.groups:
                w = DriveFaultWatch(g.name, g.image, tuple(s.name for s in g.slaves))
                if w.active:
                    watches.append((w, p.fresh[g.first : g.first + len(g.slaves)]))
                    self.result.drive_faults[g.name] = w.faults
            self._faults.append(watches)
        self._code_reads: list[FaultFollowUp] = []  # 0x603F read when not in a PDO, 0x10F3 when kept
        # per group and row: its fault's 0x603F read is not served yet (a reset now would clear the code)
        self._code_pending: dict[str, npt.NDArray[np.bool_]] = {
            name: np.zeros(g.image.n_axes, dtype=bool) for name, g in net.groups.items()
        }
        # raw-CAN motor faults (Damiao error codes, ODrive axis errors): the backend's onsets, as events
        self._motor_events: list[Any] = [  # Callable[[int], tuple[DriveFault, ...]] | None
            getattr(b, "take_motor_events", None) for b in net.backends
        ]

    @property
    def groups(self) -> dict[str, AxisGroup]:
        return self._net.groups

    def fault_code_pending(self, group: str) -> npt.NDArray[np.bool_]:
        """Per row of ``group``: its fault's error code (0x603F) is still being read acyclically.

        Pass it to ``Cia402Controller.step(..., hold_reset=...)`` (or ``step_image``) so the fault
        reset waits for the read: a drive clears 0x603F on reset. The same array every cycle, updated
        by :meth:`exchange` (read it, do not keep a copy).
        """
        return self._code_pending[group]

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
        reason in :attr:`BusStatus.error`, and latches the safe stop. While a
        safe stop is latched, every group's safe outputs overwrite what the
        controller wrote. Inputs of a slave that is not fresh are not touched
        (S2). Recovery of lost slaves advances here - its one caller - by one
        bounded step per bus per cycle, after a miss and while the bus reports
        it is recovering. Raises only for caller errors (:class:`PhaseError`
        after close).
        """
        self._check()
        t0 = time.perf_counter_ns()
        if self._cycle_thread is None:
            self._cycle_thread = threading.get_ident()
        res = self.result
        cycle = res.cycle
        pt = self.phases
        if pt is not None:
            pt.start(t0)
        if res.events:
            res.events = []  # a new list only after a cycle that had events: the caller may keep the old one
        if res.safe_stop:
            for w in self._writers:
                w.apply()
        for k, (b, _, st, every) in enumerate(self._pairs):
            st.ran = cycle % every == 0
            st.error = None
            if st.ran:
                try:
                    self._encode(k, cycle)
                    if pt is not None:
                        pt.mark(ph.ENCODE)
                    b.send()
                except Exception as exc:
                    st.error = _reason(exc)
                if pt is not None:
                    pt.mark(ph.SEND)
        all_fresh = True
        any_stop = False
        for k, (b, policy, st, _) in enumerate(self._pairs):
            if st.ran:
                self._receive(k, b, policy, st, cycle)
            all_fresh = all_fresh and st.verdict is Verdict.OK
            any_stop = any_stop or policy.safe_stop
        if self._code_reads:
            self._collect_codes(cycle)
            if pt is not None:
                pt.mark(ph.ACYCLIC)
        res.fresh = all_fresh
        latched = any_stop and not res.safe_stop
        released = res.safe_stop and not any_stop
        res.safe_stop = any_stop
        res.cycle = cycle + 1
        res.exchange_ns = time.perf_counter_ns() - t0
        if res.events:
            for obs in self._observers:
                obs.note_events(res.events)
        for obs in self._observers:  # before the safe outputs below: it records what this cycle sent
            obs.capture(res, t0)
        if latched:
            for w in self._writers:  # effective from the next cycle's outputs
                w.apply()
        if released:  # raw-CAN motors hold where they are until the controller writes again (S12)
            for hold in self.holds.values():
                hold.seed()
        if pt is not None:
            pt.mark(ph.OBSERVERS)
        return res

    def _encode(self, k: int, cycle: int) -> None:
        """The one output path of bus ``k``: each group's outputs pass the rules, then are encoded.

        A refused value (NaN, infinity, out of the map's window, too big a step) is replaced in the image
        before ``to_wire()`` and before a raw-CAN family reads it; its streak's first cycle is an
        :class:`~fieldbus.core.output_rules.OutputClamp` event.
        """
        for rules, image in self._encoders[k]:
            if rules.apply():
                self.result.events.extend(rules.events(cycle))
            else:
                rules.settle()
            image.outputs.to_wire()

    def _receive(self, k: int, b: Backend, policy: SafetyPolicy, st: BusStatus, cycle: int) -> None:
        """Receive, judge and accept one bus's cycle; recovery and acyclic steps. Never raises (S1)."""
        wkc: int | None = None
        arrived = None
        pt = self.phases
        if st.error is None:
            try:
                wkc = b.receive()
                arrived = b.arrived()
            except Exception as exc:
                st.error = _reason(exc)
        if pt is not None:
            pt.mark(ph.WAIT)
        off_before = self._bus_off[k]
        if off_before is not None:  # a CAN controller that reported bus-off: a bus error (S1)
            off = int(getattr(b, "bus_off", 0))
            if off > off_before and st.error is None:
                st.error = f"bus-off reported by the CAN controller ({off} since bring-up)"
            self._bus_off[k] = off
        verdict = policy.judge(wkc, arrived, st.error)
        st.verdict = verdict
        st.wkc = policy.last_wkc
        st.consecutive_misses = policy.consecutive_misses
        st.safe_stop = policy.safe_stop
        st.release_pending = policy.clear_requested
        st.dc_time_ns = b.dc_time_ns
        st.dc_sync_error_ns = b.dc_sync_error_ns
        events = self.result.events
        if st.error is not None:
            st.errors += 1
            st.last_error = st.error
            events.append(BusEvent(cycle, st.name, "bus_error", st.error))
        if policy.latched_now:
            events.append(BusEvent(cycle, st.name, "safe_stop", f"{policy.consecutive_misses} misses"))
        if policy.released_now:
            events.append(BusEvent(cycle, st.name, "released"))
        if pt is not None:
            pt.mark(ph.JUDGE)
        if verdict is Verdict.OK or (arrived is not None and policy.fresh.any()):
            b.accept_inputs(
                policy.fresh, verdict is Verdict.OK
            )  # stale rows keep their last accepted bytes (S2)
            for watch, rows in self._faults[k]:
                for fault in watch.step(rows, cycle):
                    events.append(fault)
                    drive = b.areas[b.slave_index(fault.slave)].slave.map
                    if fault.code is None or drive.ethercat.diagnosis_history:
                        self._read_code(b, fault)
        take = self._motor_events[k]
        if take is not None:
            events.extend(take(cycle))
        if pt is not None:
            pt.mark(ph.ACCEPT)
        if st.error is None and (verdict is not Verdict.OK or b.recovering):
            try:
                b.recover_step()
            except Exception as exc:  # recover_step never raises by contract; a backend bug is a miss reason
                st.last_error = _reason(exc)
        st.recovering = b.recovering
        st.recoveries = b.recoveries
        st.recovery_error = b.last_recovery_error
        if pt is not None:
            pt.mark(ph.CONTRACT)
        if not st.recovering and (self._sdo_current[k] is not None or self._sdo_pending[k]):
            try:
                self._serve_sdo(k, b)
            except Exception as exc:  # fails that transfer only, with its cause (S5)
                req = self._sdo_current[k]
                self._sdo_current[k] = None
                text = _reason(exc)
                if req is not None:
                    req.finish(error=FieldbusError(f"SDO transfer failed in the cycle: {text}"))
                st.last_error = text
                events.append(BusEvent(cycle, st.name, "acyclic_error", text))
        if not st.recovering:
            try:
                changes = b.diag_step()  # one diagnostic datagram at most, in a cycle nothing else used
            except Exception as exc:  # diag_step never raises by contract; a backend bug is a reason
                changes, st.last_error = [], _reason(exc)
            if changes:
                names = [a.slave.name for a in b.areas]
                events.extend(BusEvent(cycle, st.name, *describe_change(c, names)) for c in changes)
        if pt is not None:
            pt.mark(ph.ACYCLIC)

    def _bus_of(self, group: str) -> str:
        return next(b.bus.name for b in self._net.backends if any(g.name == group for g in b.groups))

    def _read_code(self, b: Backend, fault: DriveFault) -> None:
        """Ask for 0x603F of a faulted drive whose map does not have it in a PDO, and for its diagnosis
        history 0x10F3 when its map says it keeps one (served by the cycle, one upload at a time)."""
        k = self._net.backends.index(b)
        slave = b.slave_index(fault.slave)
        drive = b.areas[slave].slave.map
        pending = self._sdo_pending[k]

        def submit(index: int, sub_index: int) -> Future[bytes | None]:
            req = SdoRequest(slave, index, sub_index, None)
            pending.append(req)
            return req.future

        code = drive.axis_index(0x603F, fault.slave_axis) if fault.code is None else None
        if code is not None and fault.group in self._code_pending:
            self._code_pending[fault.group][fault.axis] = True
        self._code_reads.append(
            FaultFollowUp(fault, submit, code_index=code, history=drive.ethercat.diagnosis_history)
        )

    def _collect_codes(self, cycle: int) -> None:
        """Drive faults whose follow-up reads finished: the fault again, with its code (and history), as an event."""
        keep = []
        for follow in self._code_reads:
            try:
                done = follow.poll()
            except Exception as exc:  # never silent: the fault stays reported without its code, and why
                why = "cancelled" if isinstance(exc, CancelledError) else _reason(exc)
                fault = follow.fault
                self._release_reset(fault)
                self.result.events.append(
                    BusEvent(
                        cycle, self._bus_of(fault.group), "acyclic_error", f"0x603F of {fault.slave}: {why}"
                    )
                )
                continue
            if not follow.code_pending:
                self._release_reset(follow.fault)
            if done is None:
                keep.append(follow)
                continue
            self.result.events.append(replace(done, cycle=cycle))
            if follow.error is not None:
                self.result.events.append(
                    BusEvent(cycle, self._bus_of(done.group), "acyclic_error", follow.error)
                )
        self._code_reads = keep
        for follow in keep:  # a second fault of an axis whose first read just ended: still pending
            pending = self._code_pending.get(follow.fault.group)
            if pending is not None and follow.code_pending:
                pending[follow.fault.axis] = True

    def _release_reset(self, fault: DriveFault) -> None:
        """The 0x603F read of ``fault`` is over (served or failed): its axis may be reset."""
        pending = self._code_pending.get(fault.group)
        if pending is not None:
            pending[fault.axis] = False

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
        data = self._wait(self.submit_sdo_read(bus, slave, index, sub_index), timeout_s)
        assert data is not None
        return data

    def sdo_write(
        self, bus: str, slave: str, index: int, sub_index: int, data: bytes, *, timeout_s: float = 2.0
    ) -> None:
        """Write an object while the cycle runs in another thread: waits until the cycle has served it."""
        self._wait(self.submit_sdo_write(bus, slave, index, sub_index, data), timeout_s)

    def _submit(
        self, bus: str, slave: str, index: int, sub_index: int, data: bytes | None
    ) -> Future[bytes | None]:
        """Check the request at the door (S5): a malformed one raises here and nothing is queued."""
        self._check()
        b = self._net.backend(bus)
        for what, value, top in (("index", index, 0xFFFF), ("sub_index", sub_index, 0xFF)):
            if not isinstance(value, int) or isinstance(value, bool) or not 0 <= value <= top:
                shown = (
                    f"0x{value:X}" if isinstance(value, int) and not isinstance(value, bool) else repr(value)
                )
                raise RequestError(
                    f"SDO {what} {shown} out of range 0..0x{top:X} (bus '{bus}' slave '{slave}')"
                )
        if data is not None and not 1 <= len(data) <= MAX_SDO_BYTES:
            raise RequestError(
                f"SDO download to 0x{index:04X}:{sub_index:02X} of '{slave}': {len(data)} bytes "
                f"(1..{MAX_SDO_BYTES} accepted)"
            )
        req = SdoRequest(b.slave_index(slave), index, sub_index, data)
        self._sdo_pending[self._net.backends.index(b)].append(req)
        return req.future

    def _wait(self, future: Future[bytes | None], timeout_s: float) -> bytes | None:
        if threading.get_ident() == self._cycle_thread:
            future.cancel()
            raise FieldbusError(
                "sdo_read/sdo_write in OP wait for the cycle, and this thread runs the cycle: call them from "
                "another thread, or use submit_sdo_read/submit_sdo_write and look at the future in later cycles"
            )
        # wait() reports done or not without raising, so the transfer's own BusTimeoutError (a
        # TimeoutError, as the future's timeout is) cannot be taken for "not served"
        if not wait((future,), timeout_s).done and future.cancel():
            # withdrawn: it cannot run after the caller was told it failed (a write applied late)
            raise BusTimeoutError(
                f"SDO transfer not served within {timeout_s:g} s (withdrawn): is exchange() being called?"
            )
        if not wait((future,), timeout_s).done:  # the cycle took it up meanwhile: as long again
            raise BusTimeoutError(
                f"SDO transfer started but not finished within {2 * timeout_s:g} s: it may still be applied"
            )
        return future.result()

    def _serve_sdo(self, k: int, b: Backend) -> None:
        req = self._sdo_current[k]
        if req is None:
            req = self._sdo_current[k] = self._sdo_pending[k].popleft()
            if not req.future.set_running_or_notify_cancel():
                self._sdo_current[k] = None
                return
        if b.acyclic_step(req):
            self._sdo_current[k] = None
            if self._observers:
                self._note_sdo_abort(b, req)

    def _note_sdo_abort(self, b: Backend, req: SdoRequest) -> None:
        """An SDO transfer served in this cycle that the slave aborted: an event in every recording."""
        exc = req.future.exception(0) if req.future.done() else None
        if not isinstance(exc, SdoAbortError):
            return
        for rec in self.recorders:
            rec.ring.note(
                self.result.cycle,  # this cycle's index (exchange() counts it when done)
                "sdo_abort",
                bus=b.bus.name,
                slave=b.areas[req.slave].slave.name,
                access="read" if req.data is None else "write",
                index=req.index,
                sub_index=req.sub_index,
                code=exc.code,
                name=abort_name(exc.code),
                detail=str(exc),
            )

    def _fail_pending_sdo(self) -> None:
        for k, pending in enumerate(self._sdo_pending):
            cur = self._sdo_current[k]
            if cur is not None:
                cur.finish(error=PhaseError("the network left OP before this SDO transfer finished"))
                self._sdo_current[k] = None
            while pending:
                req = pending.popleft()
                if req.future.set_running_or_notify_cancel():
                    req.finish(error=PhaseError("the network left OP before this SDO transfer was served"))

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
        for _, policy, _, _ in self._pairs:
            if policy.safe_stop and policy.last_verdict is not Verdict.OK:
                policy.clear_safe_stop()  # raises SafeStopClearError with this bus's reason
        for _, policy, st, _ in self._pairs:
            policy.clear_safe_stop()
            st.safe_stop = policy.safe_stop
            st.release_pending = policy.clear_requested
        was = self.result.safe_stop
        self.result.safe_stop = any(p.safe_stop for _, p, _, _ in self._pairs)
        if was and not self.result.safe_stop:  # opened at once: the next cycle sends the hold (S12)
            for hold in self.holds.values():
                hold.seed()
        return not self.result.safe_stop

    def _hold_hook(self, b: Backend) -> Callable[[int], None]:
        """What a backend calls after it seeded motor ``i``'s outputs (recover, set_mode): its group's
        output rules restart from the seed (:meth:`~fieldbus.core.output_rules.OutputRules.rebase`)."""

        def held(i: int) -> None:
            a = b.areas[i]
            hold = self.holds.get(b.groups[a.group].name)
            if hold is not None:
                rows = np.zeros(hold.image.n_axes, dtype=bool)
                rows[a.row : a.row + a.axes] = True
                hold.rules.rebase(rows)

        return held

    def close(self) -> None:
        self._net.close()

    def _wind_down(self) -> None:
        """A controlled stop (S6): quick stop until every drive reports it done, then disable voltage.

        Each cycle goes through the same never-raising path as :meth:`exchange`
        (a bus that fails keeps its miss; the others still get their cycles).
        The quick stop lasts until every CiA 402 axis is done
        (:class:`~fieldbus.core.winddown.WindDown`), at most its budget; then
        ``CLOSE_CYCLES`` cycles of disable voltage. A KeyboardInterrupt
        meanwhile does not cut it short; it is raised again afterwards. The
        outcome is in :attr:`Network.last_wind_down`.
        """
        net = self._net
        # per bus, its slaves heard not to answer in this wind-down cycle (S6: a slave is given up alone)
        self._unheard = [np.zeros(b.n_slaves, dtype=bool) for b in net.backends]
        groups = []
        group_bus: list[int] = []
        for k, (b, p, _, _) in enumerate(self._pairs):
            for g in b.groups:
                rows = slice(g.first, g.first + len(g.slaves))
                groups.append((g.name, g.image, g.slaves[0].map, p.fresh[rows], self._unheard[k][rows]))
                group_bus.append(k)
        dead_after = min(p.config.safe_stop_after for _, p, _, _ in self._pairs)
        wd = WindDown(groups, self.cycle_time_us, cap_s=net.wind_down_cap_s, dead_after=dead_after)
        net.last_wind_down = wd.report
        first: BaseException | None = None
        period_s = self.cycle_time_us / 1e6
        done = False
        statuses = [st for _, _, st, _ in self._pairs]
        for _ in range(wd.budget_cycles + 1):
            try:
                self._wind_down_cycle(SafeStop.QUICK_STOP)
                done = wd.step([statuses[k].ran for k in group_bus])
            except BaseException as exc:  # a second Ctrl-C: finish stopping the drives first
                first = first or exc
            if done:
                break
            net.clock.sleep(period_s)
        wd.finish()
        for _ in range(CLOSE_CYCLES):
            try:
                self._wind_down_cycle(SafeStop.DISABLE_VOLTAGE)
                wd.report.disable_cycles += 1
            except BaseException as exc:
                first = first or exc
            net.clock.sleep(period_s)
        if first is not None:
            raise first

    def _wind_down_cycle(self, word: SafeStop) -> None:
        """One cycle of the wind-down on every bus that is due (each at its own rate, as in
        :meth:`exchange`), the safe outputs with ``word`` written first.

        A bus whose reply came back short is judged per slave here (S6): the
        slaves the backend can tell answered (``Backend.slaves_answered``) are
        fresh and their inputs accepted, so a healthy drive is watched to its
        stop beside a power-cycled one; those it can tell did not are marked
        unheard. A bus with no reply (timeout, error) leaves every slave unheard.
        """
        for w in self._writers:
            w.apply(word)
        res = self.result
        cycle = res.cycle
        for k, (b, _, st, every) in enumerate(self._pairs):
            st.ran, st.error = cycle % every == 0, None
            if not st.ran:
                continue
            try:
                self._encode(k, cycle)
                b.send()
            except Exception as exc:
                st.error = _reason(exc)
        for k, (b, policy, st, _) in enumerate(self._pairs):
            if not st.ran:
                continue
            self._receive(k, b, policy, st, cycle)
            unheard = self._unheard[k]
            unheard.fill(st.verdict in (Verdict.TIMEOUT, Verdict.ERROR))  # no reply: nobody heard
            if st.verdict is not Verdict.SHORT:
                continue
            try:
                answered = b.slaves_answered(policy.last_wkc)
            except Exception:  # a backend bug: nothing attributed
                answered = None
            if answered is None:
                continue  # a short reply nobody can attribute: every slave stale, none given up
            np.logical_not(answered, out=unheard)
            if not np.array_equal(answered, policy.fresh):
                np.copyto(policy.fresh, answered)
                b.accept_inputs(policy.fresh)  # only the slaves that answered (S2 for the others)
        res.cycle = cycle + 1
