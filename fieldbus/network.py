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

import threading
import time
from collections import deque
from collections.abc import Iterator, Mapping
from concurrent.futures import Future, wait
from dataclasses import dataclass, field
from pathlib import Path
from types import TracebackType
from typing import TYPE_CHECKING, Any

import numpy as np
import numpy.typing as npt

from fieldbus.backends import backend_class
from fieldbus.backends.base import AxisGroup, Backend, SdoRequest
from fieldbus.core import network as netfile
from fieldbus.core.cia402 import SafeStop
from fieldbus.core.pdo.image import ProcessImage
from fieldbus.core.safestop import SafeStopWriter, safe_stop_plan
from fieldbus.core.wkc import PolicyConfig, Verdict, WkcPolicy
from fieldbus.errors import BusTimeoutError, FieldbusError, PhaseError, SdoAbortError, abort_name

if TYPE_CHECKING:
    from fieldbus.recording import Recorder

CLOSE_CYCLES = 5  # cycles of quick stop, then of disable voltage, sent on close
PER_BUS_OPTIONS = ("can_bus", "can_log", "pcap")  # options naming one bus's own instance or file


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


@dataclass
class CycleResult:
    """What :meth:`Operational.exchange` returns; the same object, updated every cycle."""

    buses: tuple[BusStatus, ...]
    cycle: int = 0
    fresh: bool = False  # every slave of every bus fresh
    safe_stop: bool = False  # any bus escalated to a safe stop (latched)
    exchange_ns: int = 0  # time spent in exchange(), ns
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
        per_instance = [k for k in backend_options if k in PER_BUS_OPTIONS]
        if per_instance and len(names) > 1:
            raise FieldbusError(
                f"option {per_instance[0]!r} is one bus's own (an interface instance) and this network has "
                f"{len(names)} buses: pass it per bus, bus_options={{'{names[0]}': {{'{per_instance[0]}': ...}}}}"
            )
        netfile.check_open_options(model, backend, backend_options, bus_options)
        self.backends: list[Backend] = []
        for bus in model.buses:
            cls = backend_class(backend or bus.type)
            self.backends.append(cls(bus, **{**backend_options, **(bus_options or {}).get(bus.name, {})}))
        self.policies = [
            WkcPolicy(b.expected_wkc, b.n_slaves, PolicyConfig(b.bus.safe_stop_after)) for b in self.backends
        ]
        base = min(bus.cycle_time_us for bus in model.buses)
        for bus in model.buses:
            if bus.cycle_time_us % base:
                raise FieldbusError(
                    f"{model.source}: bus '{bus.name}' cycle_time_us {bus.cycle_time_us} is not a whole multiple "
                    f"of the shortest bus cycle ({base} us): a bus runs every n-th cycle of the fastest"
                )
        self.groups: dict[str, AxisGroup] = {g.name: g for b in self.backends for g in b.groups}
        self._phase: _Phase = self
        self._opened = False
        self._closed = False
        self._open_backends: list[Backend] = []  # every backend whose close() has not succeeded yet

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
        """Bring every drive down (safe outputs, then disable voltage), leave OP, close every bus.

        Whatever raises on the way (a dead bus, a second Ctrl-C), every bus is
        still stopped and closed; afterwards the first error is raised again.
        Calling it again retries what did not close; once all closed it does nothing.
        """
        if self._closed and not self._open_backends:
            return
        self._closed = True
        first: BaseException | None = None
        phase = self._phase
        self._phase = _Closed(self)  # no verb of the old phase runs from now on
        if isinstance(phase, Operational):
            for rec in phase._recorders:
                rec.close()  # never raises: a failed recording was already warned about
            phase._fail_pending_sdo()
            try:
                phase._wind_down()
            except BaseException as exc:  # KeyboardInterrupt included: keep going, re-raise at the end
                first = exc
        for b in list(self._open_backends):
            try:
                b.stop()
            except BaseException as exc:
                first = first or exc
        for b in list(self._open_backends):
            try:
                b.close()
                self._open_backends.remove(b)
            except BaseException as exc:
                first = first or exc
        if first is not None:
            raise first


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
        self._check()
        try:
            for b in self._net.backends:
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
        self._recorders: tuple[Recorder, ...] = ()  # each copies every cycle into its ring (record())

    @property
    def groups(self) -> dict[str, AxisGroup]:
        return self._net.groups

    def __getitem__(self, group: str) -> ProcessImage:
        """The process image of axis group ``group`` (a bus name when the bus has one map)."""
        try:
            return self._net.groups[group].image
        except KeyError:
            raise FieldbusError(f"no axis group '{group}' (have: {', '.join(self._net.groups)})") from None

    def __iter__(self) -> Iterator[str]:
        return iter(self._net.groups)

    def exchange(self) -> CycleResult:
        """One cycle on every bus that is due: encode outputs, send, receive, judge, decode fresh inputs.

        While a safe stop is latched, every group's safe outputs overwrite what
        the controller wrote. Recovery of lost slaves advances here - its one
        caller - by one bounded step per bus per cycle, after a miss and while
        the bus reports it is recovering.
        """
        self._check()
        t0 = time.perf_counter_ns()
        if self._cycle_thread is None:
            self._cycle_thread = threading.get_ident()
        res = self.result
        cycle = res.cycle
        if res.safe_stop:
            for w in self._writers:
                w.apply()
        for b, _, st, every in self._pairs:
            st.ran = cycle % every == 0
            if st.ran:
                for g in b.groups:
                    g.image.outputs.to_wire()
                b.send()
        all_fresh = True
        any_stop = False
        for k, (b, policy, st, _) in enumerate(self._pairs):
            if st.ran:
                wkc = b.receive()
                verdict = policy.judge(wkc, b.arrived())
                st.verdict = verdict
                st.wkc = policy.last_wkc
                st.consecutive_misses = policy.consecutive_misses
                st.safe_stop = policy.safe_stop
                st.dc_time_ns = b.dc_time_ns
                st.dc_sync_error_ns = b.dc_sync_error_ns
                if verdict is Verdict.OK or (verdict is Verdict.SHORT and b.arrived() is not None):
                    for g in b.groups:
                        g.image.inputs.from_wire()  # CAN: rows of silent nodes still hold their last bytes
                if verdict is not Verdict.OK or b.recovering:
                    b.recover_step()
                st.recovering = b.recovering
                st.recoveries = b.recoveries
                st.recovery_error = b.last_recovery_error
                if not st.recovering and (self._sdo_current[k] is not None or self._sdo_pending[k]):
                    self._serve_sdo(k, b)
            all_fresh = all_fresh and st.verdict is Verdict.OK
            any_stop = any_stop or policy.safe_stop
        res.fresh = all_fresh
        latched = any_stop and not res.safe_stop
        res.safe_stop = any_stop
        res.cycle = cycle + 1
        res.exchange_ns = time.perf_counter_ns() - t0
        for rec in self._recorders:  # before the safe outputs below: it records what this cycle sent
            rec.capture(res, t0)
        if latched:
            for w in self._writers:  # effective from the next cycle's outputs
                w.apply()
        return res

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
        return self._recorders

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
        self._check()
        b = self._net.backend(bus)
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
            if self._recorders:
                self._note_sdo_abort(b, req)

    def _note_sdo_abort(self, b: Backend, req: SdoRequest) -> None:
        """An SDO transfer served in this cycle that the slave aborted: an event in every recording."""
        exc = req.future.exception(0) if req.future.done() else None
        if not isinstance(exc, SdoAbortError):
            return
        for rec in self._recorders:
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

    def clear_safe_stop(self) -> None:
        """Release a latched safe stop (the controller then re-enables drives through CiA 402)."""
        for _, policy, st, _ in self._pairs:
            policy.clear_safe_stop()
            st.safe_stop = False
        self.result.safe_stop = False

    def close(self) -> None:
        self._net.close()

    def _wind_down(self) -> None:
        """Safe outputs (CiA 402 quick stop), then disable voltage, a few cycles each, on every bus.

        A bus that fails on the way is left out of the remaining cycles; the
        others still get theirs. A KeyboardInterrupt meanwhile does not cut the
        wind-down short (it takes 2 x CLOSE_CYCLES cycles). Raises the first
        error or interrupt afterwards.
        """
        first: BaseException | None = None
        alive = [b for b, _, _, _ in self._pairs]
        for word in (SafeStop.QUICK_STOP, SafeStop.DISABLE_VOLTAGE):
            for _ in range(CLOSE_CYCLES):
                for w in self._writers:
                    w.apply(word)
                for b in list(alive):
                    try:
                        for g in b.groups:
                            g.image.outputs.to_wire()
                        b.send()
                        b.receive()
                    except Exception as exc:  # this bus failed: the others still get their cycles
                        first = first or exc
                        alive.remove(b)
                    except BaseException as exc:  # a second Ctrl-C: finish stopping the drives first
                        first = first or exc
                time.sleep(self.cycle_time_us / 1e6)
        if first is not None:
            raise first
