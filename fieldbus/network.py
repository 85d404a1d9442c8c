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
import time
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from types import TracebackType

import numpy as np
import numpy.typing as npt

from fieldbus.backends import backend_class
from fieldbus.backends.base import AxisGroup, Backend
from fieldbus.core import network as netfile
from fieldbus.core.pdo.image import ProcessImage
from fieldbus.core.pdo.names import CONTROLWORD
from fieldbus.core.wkc import PolicyConfig, Verdict, WkcPolicy
from fieldbus.errors import FieldbusError, PhaseError

QUICK_STOP = 0x0002  # CiA 402 controlword "quick stop" (bits 1=1, 2=0): leaves OPERATION ENABLED
DISABLE_VOLTAGE = 0x0000  # CiA 402 "disable voltage": to SWITCH ON DISABLED
CLOSE_CYCLES = 5  # cycles of quick stop, then of disable voltage, sent on close


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
    source: str | Path | netfile.Network, *, backend: str | None = None, **backend_options: object
) -> Network:
    """Load a network file (or use a loaded one); ``backend`` overrides every bus's type."""
    net = source if isinstance(source, netfile.Network) else netfile.load_network(source)
    return Network(net, backend=backend, **backend_options)


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
        self, model: netfile.Network, *, backend: str | None = None, **backend_options: object
    ) -> None:
        super().__init__(self)
        self.model = model
        self.backends: list[Backend] = []
        for bus in model.buses:
            cls = backend_class(backend or bus.type)
            self.backends.append(cls(bus, **backend_options))
        self.policies = [
            WkcPolicy(b.expected_wkc, b.n_slaves, PolicyConfig(b.bus.safe_stop_after)) for b in self.backends
        ]
        self.groups: dict[str, AxisGroup] = {g.name: g for b in self.backends for g in b.groups}
        self._phase: _Phase = self
        self._opened = False
        self._closed = False

    # -- phases -------------------------------------------------------------------------
    def pre_op(self) -> PreOp:
        """Open every bus, check identities, apply and read back every SDO plan."""
        self._check()
        self._opened = True
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
        """Bring every drive down (quick stop, disable voltage), leave OP, close. Idempotent."""
        if self._closed:
            return
        self._closed = True
        phase = self._phase
        if isinstance(phase, Operational):
            phase._wind_down()
        for b in self.backends:
            if self._opened:
                with contextlib.suppress(Exception):  # a dead bus must not keep the others open
                    b.stop()
        for b in self.backends:
            b.close()
        self._phase = _Closed(self)


class _Closed(_Phase):
    pass


class PreOp(_Phase):
    """PRE-OP: SDO plans applied; acyclic SDO access allowed; no process data yet."""

    def sdo_read(self, bus: str, slave: str, index: int, sub_index: int) -> bytes:
        self._check()
        b = self._net.backends[[x.bus.name for x in self._net.backends].index(bus)]
        return b.sdo_read(b.slave_index(slave), index, sub_index)

    def sdo_write(self, bus: str, slave: str, index: int, sub_index: int, data: bytes) -> None:
        self._check()
        b = self._net.backends[[x.bus.name for x in self._net.backends].index(bus)]
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
        self._pairs = list(zip(net.backends, net.policies, statuses, strict=True))
        # controlword views of CiA 402 groups (for the safe stop)
        self._controlwords: list[npt.NDArray[np.uint16]] = []
        self._safe_stop_applied = False
        for g in net.groups.values():
            e = g.image.layout.outputs.find(CONTROLWORD)
            if e is not None and not e.channel.scaled:
                self._controlwords.append(g.image.outputs.values[e.name])

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
        """One cycle on every bus: encode outputs, send, receive, judge, decode fresh inputs."""
        self._check()
        t0 = time.perf_counter_ns()
        res = self.result
        if res.safe_stop:
            for cw in self._controlwords:
                cw.fill(QUICK_STOP)
        for b, _, _ in self._pairs:
            for g in b.groups:
                g.image.outputs.to_wire()
            b.send()
        all_fresh = True
        any_stop = False
        for b, policy, st in self._pairs:
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
            if verdict is not Verdict.OK:
                all_fresh = False
                b.recover_step()
            any_stop = any_stop or policy.safe_stop
        res.fresh = all_fresh
        if any_stop and not res.safe_stop:
            for cw in self._controlwords:  # effective from the next cycle's outputs
                cw.fill(QUICK_STOP)
        res.safe_stop = any_stop
        res.cycle += 1
        res.exchange_ns = time.perf_counter_ns() - t0
        return res

    def dc_correction_ns(self) -> int:
        """Nanoseconds to add to the next cycle deadline so the host follows DC time (0 without DC).

        Pass it to :func:`fieldbus.runtime.loop.run_cycles` as ``adjust``.
        """
        return sum(b.dc_correction_ns() for b in self._net.backends)

    def clear_safe_stop(self) -> None:
        """Release a latched safe stop (the controller then re-enables drives through CiA 402)."""
        for _, policy, st in self._pairs:
            policy.clear_safe_stop()
            st.safe_stop = False
        self.result.safe_stop = False

    def close(self) -> None:
        self._net.close()

    def _wind_down(self) -> None:
        """Quick stop then disable voltage on every CiA 402 axis, a few cycles each; never raises."""
        for word in (QUICK_STOP, DISABLE_VOLTAGE):
            for _ in range(CLOSE_CYCLES):
                for cw in self._controlwords:
                    cw.fill(word)
                try:
                    for b, _, _ in self._pairs:
                        for g in b.groups:
                            g.image.outputs.to_wire()
                        b.send()
                    for b, _, _ in self._pairs:
                        b.receive()
                except Exception:
                    return
                time.sleep(self._net.model.cycle_time_us / 1e6)
