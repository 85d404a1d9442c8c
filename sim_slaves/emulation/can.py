"""CAN buses for :mod:`fieldbus.testing`: CANopen nodes and MIT-mode motors.

Three ways, as the emulation asks: on a virtual clock, in lockstep with the
master in one thread (:class:`~fieldbus.testing.lockstep.LockstepCanBus`:
the same frames in the same order every run); on the wall clock, on
python-can's ``virtual`` bus with the simulator's own thread; or in a child
process on ``fieldbus_udp`` (:mod:`sim_slaves.can_process`; no fault hooks:
the child has no control channel).
"""

from __future__ import annotations

import itertools
import os
from typing import Any

from fieldbus.core.network import Bus
from fieldbus.testing.provider import BusEmulator, EmulationContext, EmulationError, EmulationUnavailable

_channels = itertools.count()
SILENT_TPDOS = 1 << 30  # "every TPDO from now on"


def _can() -> Any:
    try:
        import can
    except ImportError:
        raise EmulationUnavailable("CAN emulation needs python-can: pip install 'fieldbus[can]'") from None
    return can


def start_canopen(context: EmulationContext, bus: Bus) -> BusEmulator:
    return CanBus(context, bus, "canopen")


def start_rawcan(context: EmulationContext, bus: Bus) -> BusEmulator:
    return CanBus(context, bus, "mit")


class CanBus(BusEmulator):
    """The nodes (``kind`` canopen) or motors (``kind`` mit) of one CAN bus, with their fault hooks."""

    def __init__(self, context: EmulationContext, bus: Bus, kind: str) -> None:
        super().__init__(bus)
        can = _can()
        self.kind = kind
        if any(s.node_id is None for s in bus.slaves):
            raise EmulationError(f"bus '{bus.name}': every slave needs a node_id")
        self.node_ids = [int(s.node_id or 0) for s in bus.slaves]
        nodes = [(s.map, n) for s, n in zip(bus.slaves, self.node_ids, strict=True)]
        self.sim: Any = None
        self.lockstep: Any = None
        self._changes: dict[str, Any] = {}
        self._options: dict[str, Any] = {}
        self._own: list[Any] = []  # python-can buses this emulator opened
        if context.can == "udp":
            self._start_process(context, bus, nodes)
            return
        if kind == "canopen":
            from sim_slaves.canopen import CanopenSimulator as simulator
        else:
            from sim_slaves.mit_motor import MitMotorSimulator as simulator  # type: ignore[assignment]
        if context.virtual:
            from fieldbus.testing.lockstep import LockstepCanBus

            clock: Any = context.clock
            self.lockstep = LockstepCanBus(clock, bus.name)
            self.sim = simulator(self.lockstep.peer, nodes, clock=clock)
            self.lockstep.handlers.append(self.sim.deliver)
            if kind == "canopen":  # heartbeats and event timers run as time passes
                self._watch = lambda _t: self.sim.deliver(None)
                clock.watch(self._watch)
                self._clock = clock
                self.sim.boot()
            self._options = {"can_bus": self.lockstep}
        else:
            channel = f"fieldbus-testing-{os.getpid()}-{next(_channels)}"
            theirs = can.Bus(interface="virtual", channel=channel)
            ours = can.Bus(interface="virtual", channel=channel)
            self._own = [ours, theirs]
            self.sim = simulator(theirs, nodes).start()
            self._options = {"can_bus": ours}

    def _start_process(self, context: EmulationContext, bus: Bus, nodes: list[tuple[Any, int]]) -> None:
        from sim_slaves.can_process import can_emulator_process, udp_bus

        maps = {id(m) for m, _ in nodes}
        if len(maps) != 1:
            raise EmulationError(
                f"bus '{bus.name}': over udp every node of a bus must share one drive map (the child "
                "process takes one); use can='virtual'"
            )
        source = nodes[0][0].source
        if not source:
            raise EmulationError(f"bus '{bus.name}': over udp the drive map must be a file")
        where = udp_bus(next(_channels), "fieldbus_udp")
        try:
            context.cleanup.enter_context(
                can_emulator_process(self.kind, source, [n for _, n in nodes], where)
            )
        except RuntimeError as exc:
            raise EmulationError(f"bus '{bus.name}': {exc}") from None
        self._changes = {
            "interface": where.channel,
            "can_interface": where.interface,
            "can_options": where.options,
        }

    # -- bring-up -------------------------------------------------------------------------
    def bus_changes(self) -> dict[str, Any]:
        return dict(self._changes)

    def backend_options(self) -> dict[str, Any]:
        return dict(self._options)

    def close(self) -> None:
        if self.lockstep is not None:
            if self.kind == "canopen":
                self._clock.unwatch(self._watch)
            self.lockstep.shutdown()
        elif self.sim is not None:
            self.sim.stop()
        for b in self._own:
            b.shutdown()
        self._own = []

    # -- faults ------------------------------------------------------------------------------
    def _need_sim(self, what: str) -> Any:
        if self.sim is None:
            raise self._unsupported(
                what, "the emulator runs in a child process (can='udp') without fault hooks"
            )
        return self.sim

    def _tpdos(self, node: int) -> int:
        return len(self.sim.node(node).drive.tpdo)

    def drive_states(self) -> list[int]:
        sim = self._need_sim("drive_states")
        if self.kind != "canopen":
            return [-1] * len(self.node_ids)
        return [int(getattr(sim.node(n).app, "state", -1)) for n in self.node_ids]

    def lose_cycles(self, cycles: int) -> None:
        sim = self._need_sim("lose_cycles")
        for n in self.node_ids:
            if self.kind == "canopen":
                sim.drop_tpdos(n, cycles * self._tpdos(n))
            else:
                sim.drop_replies(n, cycles)

    def short_wkc(self, cycles: int, slave: int) -> None:
        sim = self._need_sim("short_wkc")
        n = self.node_ids[slave]
        if self.kind == "canopen":
            sim.drop_tpdos(n, cycles * self._tpdos(n))
        else:
            sim.drop_replies(n, cycles)

    def delay(self, seconds: float, cycles: int) -> None:
        raise self._unsupported("delay", "an EtherCAT fault (a CAN frame is on time or lost)")

    def corrupt_inputs(self, slave: int, cycles: int) -> None:
        sim = self._need_sim("corrupt_inputs")
        n = self.node_ids[slave]
        if self.kind == "canopen":
            sim.corrupt_tpdos(n, cycles * self._tpdos(n))
        else:
            sim.corrupt_replies(n, cycles)

    def power_cycle(self, slave: int) -> None:
        self._need_sim("power_cycle").power_cycle(self.node_ids[slave])

    def drive_fault(self, slave: int, code: int) -> None:
        sim = self._need_sim("drive_fault")
        if self.kind != "canopen":
            raise self._unsupported("drive_fault", "MIT-mode motors report no error code")
        n = self.node_ids[slave]
        app = sim.node(n).app
        if not hasattr(app, "inject_fault"):
            raise self._unsupported("drive_fault", f"node {n} is not a CiA 402 drive")
        app.inject_fault(code)
        sim.send_emergency(n, code, 0x01)

    def silence(self, slave: int, silent: bool) -> None:
        sim = self._need_sim("silence")
        n = self.node_ids[slave]
        if self.kind == "canopen":
            sim.silence_heartbeat(n, silent)
            node = sim.node(n)
            node.drop_tpdos = SILENT_TPDOS if silent else 0
        else:
            sim.silence(n, silent)

    def error_frames(self, count: int) -> None:
        self._need_sim("error_frames")
        can = _can()
        for _ in range(count):
            frame = can.Message(arbitration_id=0, is_error_frame=True, dlc=0, is_extended_id=False)
            if self.lockstep is not None:
                self.lockstep.inject(frame)
            else:
                self.sim.bus.send(frame)

    def bus_off(self, slave: int, off: bool) -> None:
        sim = self._need_sim("bus_off")
        n = self.node_ids[slave]
        if self.kind == "canopen":
            sim.bus_off(n, off)
        else:
            if not off:
                sim.power_cycle(n)
            sim.silence(n, off)

    def sdo_abort(self, slave: int, index: int, sub_index: int | None, code: int) -> None:
        sim = self._need_sim("sdo_abort")
        if self.kind != "canopen":
            raise self._unsupported("sdo_abort", "MIT-mode motors have no object dictionary")
        sim.abort_sdo(self.node_ids[slave], index, sub_index, code)

    def clear_faults(self) -> None:
        sim = self._need_sim("clear_faults")
        if self.kind == "canopen":
            sim.clear_faults()
        else:
            for n in self.node_ids:
                st = sim.motor(n)
                st.drop = st.corrupt = 0
                st.silent = False
