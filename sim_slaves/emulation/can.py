"""CAN buses for :mod:`fieldbus.testing`: CANopen nodes and raw-CAN motors of every family.

A raw-CAN bus gets the emulator of its maps' family (:mod:`sim_slaves.can_families`: MIT, Damiao,
ODrive, CubeMars servo or MIT); a bus mixing families is refused. Three ways, as the emulation asks: on
a virtual clock, in lockstep with the master in one thread
(:class:`~fieldbus.testing.lockstep.LockstepCanBus`: the same frames in the same order every run; the
emulators' timers - heartbeats, CAN timeouts, watchdogs - run as the clock does); on the wall clock, on
python-can's ``virtual`` bus with the emulator's own thread; or in a child process on ``fieldbus_udp``
(:mod:`sim_slaves.can_process`; no fault hooks: the child has no control channel).
"""

from __future__ import annotations

import itertools
import os
from collections import deque
from contextlib import ExitStack
from typing import Any

from fieldbus.core.canfamily import families
from fieldbus.core.network import Bus
from fieldbus.errors import FieldbusError
from fieldbus.testing.provider import BusEmulator, EmulationContext, EmulationError, EmulationUnavailable
from sim_slaves.ethercat.axes import app_states

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
    from sim_slaves.can_families import bus_family

    try:
        family = bus_family(s.map for s in bus.slaves)
    except ValueError as exc:
        raise EmulationError(f"bus '{bus.name}': {exc}") from None
    return CanBus(context, bus, family)


class _Inbox:
    """A raw-CAN emulator's end of a lockstep bus, as python-can's: ``recv`` gives the frame being delivered,
    ``send`` goes to the master's queue."""

    def __init__(self, peer: Any) -> None:
        self.peer = peer
        self.frames: deque[Any] = deque()
        self.channel_info = peer.channel_info

    def send(self, msg: Any, timeout: float | None = None) -> None:
        self.peer.send(msg)

    def recv(self, timeout: float | None = None) -> Any:
        return self.frames.popleft() if self.frames else None

    def shutdown(self) -> None:
        pass


class _UdpProcess:
    """One child process (:func:`sim_slaves.can_process.can_emulators_process`) for every CAN bus of a
    network on udp, each bus with its kind, map and nodes; started once, when the master's backends exist
    (every bus has joined by then), stopped with the emulation."""

    def __init__(self, context: EmulationContext) -> None:
        # stopped where the first bus joined: after the master closed (its exit frames still answered)
        self.stack = context.cleanup.enter_context(ExitStack())
        self.buses: list[tuple[str, Any]] = []  # (bus name, EmulatedBus)
        self.started = False

    def start(self) -> None:
        if self.started:
            return
        from sim_slaves.can_process import can_emulators_process

        self.started = True
        try:
            self.stack.enter_context(can_emulators_process([b for _, b in self.buses]))
        except RuntimeError as exc:
            names = ", ".join(f"'{name}'" for name, _ in self.buses)
            raise EmulationError(f"CAN buses {names}: {exc}") from None


class CanBus(BusEmulator):
    """The nodes (``kind`` canopen) or motors (``kind``: their family, :func:`~sim_slaves.can_families.
    family_of`) of one CAN bus, with their fault hooks."""

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
        self._process: _UdpProcess | None = None
        if context.can == "udp":
            self._start_process(context, bus, nodes)
            return
        self._watch: Any = None
        if kind == "canopen":
            from sim_slaves.canopen import CanopenSimulator

            def make(port: Any, clock: Any = None) -> Any:
                return CanopenSimulator(port, nodes, clock=clock) if clock else CanopenSimulator(port, nodes)
        else:
            from sim_slaves.can_families import simulator

            # every family's physics run on the clock (virtual in lockstep), between frames too

            def make(port: Any, clock: Any = None) -> Any:
                return simulator(port, nodes, clock=clock)

        # the master's channel: this process's own (its lock is in-process), never the robot's can0, which
        # another test or the robot's master may hold at the same time
        channel = f"fieldbus-testing-{os.getpid()}-{next(_channels)}"
        self._changes = {"interface": channel, "can_interface": "virtual"}
        if context.virtual:
            from fieldbus.testing.lockstep import LockstepCanBus

            clock: Any = context.clock
            self._clock = clock
            self.lockstep = LockstepCanBus(clock, bus.name)
            if kind == "canopen":
                self.sim = make(self.lockstep.peer, clock)
                self.lockstep.handlers.append(self.sim.deliver)
                self._watch = lambda _t: self.sim.deliver(None)  # heartbeats, event timers
                self.sim.boot()
            else:
                inbox = _Inbox(self.lockstep.peer)
                self.sim = make(inbox, clock)

                def deliver(msg: Any) -> None:
                    inbox.frames.append(msg)
                    self.sim.serve(0.0)

                self.lockstep.handlers.append(deliver)
                self._watch = lambda _t: self.sim.idle()  # CAN timeouts, heartbeats, watchdogs
            clock.watch(self._watch)
            self._options = {"can_bus": self.lockstep}
        else:
            theirs = can.Bus(interface="virtual", channel=channel)
            ours = can.Bus(interface="virtual", channel=channel)
            self._own = [ours, theirs]
            self.sim = make(theirs).start()
            self._options = {"can_bus": ours}

    def _start_process(self, context: EmulationContext, bus: Bus, nodes: list[tuple[Any, int]]) -> None:
        """Join the network's one emulator process (:class:`_UdpProcess`; started at the first attach)."""
        from sim_slaves.can_process import EmulatedBus, udp_bus

        maps = {id(m) for m, _ in nodes}
        if len(maps) != 1:
            raise EmulationError(
                f"bus '{bus.name}': over udp every node of a bus must share one drive map (the child "
                "process takes one per bus); use can='virtual'"
            )
        source = nodes[0][0].source
        if not source:
            raise EmulationError(f"bus '{bus.name}': over udp the drive map must be a file")
        where = udp_bus(next(_channels), "fieldbus_udp")
        if "can_udp_process" not in context.extra:
            context.extra["can_udp_process"] = _UdpProcess(context)
        process: _UdpProcess = context.extra["can_udp_process"]
        kind = "canopen" if self.kind == "canopen" else "auto"
        process.buses.append((bus.name, EmulatedBus(kind, source, [n for _, n in nodes], where)))
        self._process = process
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

    def attach(self, backend: Any) -> None:
        if self._process is not None:
            self._process.start()  # every bus of the network is known by now

    def close(self) -> None:
        if self.lockstep is not None:
            if self._watch is not None:
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
        return len(self.sim.node(node).drive.bus_map.tpdo)

    def drive_states(self) -> list[int]:
        sim = self._need_sim("drive_states")
        if self.kind != "canopen":
            return [-1] * len(self.node_ids)
        return [st for n in self.node_ids for st in app_states(sim.node(n).app)]  # per axis

    def drive_positions(self) -> list[float]:
        sim = self._need_sim("drive_positions")
        if self.kind == "canopen":
            raise self._unsupported("drive_positions", "the CANopen emulator's drives are read by SDO")
        return [float(sim.motor(n).position) for n in self.node_ids]

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
        elif getattr(sim, "corrupts_replies", False):  # the emulator says whether it can
            sim.corrupt_replies(n, cycles)
        else:
            raise self._unsupported("corrupt_inputs", f"the {self.kind} emulator sends no corrupted replies")

    def power_cycle(self, slave: int) -> None:
        self._need_sim("power_cycle").power_cycle(self.node_ids[slave])

    def drive_fault(self, slave: int, code: int, axis: int = 0) -> None:
        sim = self._need_sim("drive_fault")
        n = self.node_ids[slave]
        if self.kind == "canopen":
            app = sim.node(n).app
            if not hasattr(app, "inject_fault"):
                raise self._unsupported("drive_fault", f"node {n} is not a CiA 402 drive")
            if axis:
                if not hasattr(app, "drives"):
                    raise self._unsupported("drive_fault", f"node {n} runs one axis")
                app.inject_fault(code, axis=axis)
            else:
                app.inject_fault(code)
            # a multi-axis node says which axis faulted: manufacturer-specific byte 0 = the axis, 1-based
            # (CiA 301 leaves the 5 bytes to the manufacturer; this emulator's convention)
            data = bytes([axis + 1]) if hasattr(app, "drives") else b""
            sim.send_emergency(n, code, 0x01, data)
            return
        if self.kind == "mit":
            raise self._unsupported("drive_fault", "MIT-mode motors (family mit) report no error code")
        if axis:
            raise self._unsupported("drive_fault", f"a {self.kind} motor has one axis")
        cfg = self.bus.slaves[slave].map.rawcan
        assert cfg is not None
        registered = families().get(cfg.family) if cfg.protocol is not None else None
        faults = registered.fault_codes(cfg.protocol) if registered is not None else None
        if faults is not None:  # the family's table (Damiao: the reply's error nibble)
            if code not in faults:
                have = ", ".join(f"0x{c:X} {name}" for c, name in faults.items())
                raise FieldbusError(f"drive_fault: a {cfg.family} fault code is one of {have}; got {code:#x}")
        elif cfg.frames is not None and cfg.frames.fault_field is None:
            raise self._unsupported(
                "drive_fault", f"map {self.bus.slaves[slave].map.name} has no fault field"
            )
        sim.inject_error(n, code)  # ODrive: axis error bits (up to 32)

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
            raise self._unsupported("sdo_abort", "raw-CAN motors have no object dictionary")
        sim.abort_sdo(self.node_ids[slave], index, sub_index, code)

    def slow_sdo(self, slave: int, cycles: int) -> None:
        sim = self._need_sim("slow_sdo")
        if self.kind != "canopen":
            raise self._unsupported("slow_sdo", "raw-CAN motors have no SDO server")
        sim.slow_sdo(self.node_ids[slave], cycles)

    def clear_faults(self) -> None:
        sim = self._need_sim("clear_faults")
        if self.kind == "canopen":
            sim.clear_faults()
        else:
            for n in self.node_ids:
                st = sim.motor(n)
                st.drop = st.corrupt = 0
                st.silent = False
