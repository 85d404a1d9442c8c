"""The served bus: one axis-group state out and one command in per cycle, over DDS, in the cycle's thread.

:class:`BusServer` wraps a running :class:`fieldbus.Operational`. Its
:meth:`BusServer.step` is the cycle: answer requests, take the newest
commands, pass them through each group's :class:`~fieldbus.dds.gate.CommandGate`,
step the CiA 402 state machine, ``exchange()``, publish. Every DDS entity is
created and used in the thread that runs the cycle.
"""

from __future__ import annotations

import json
import math
import time
from collections.abc import Callable
from concurrent.futures import Future
from dataclasses import dataclass, field
from typing import Any, TypedDict

import numpy as np
import numpy.typing as npt
from cyclonedds.topic import Topic

from fieldbus.core.cia402 import (
    Cia402Controller,
    Goal,
    Homing,
    HomingPhase,
    Mode,
    State402,
    decode_states,
)
from fieldbus.core.drivefault import DriveFault
from fieldbus.core.network import row_names
from fieldbus.core.pdo.image import ProcessImage
from fieldbus.core.pdo.names import CONTROLWORD, STATUSWORD
from fieldbus.core.safestop import SafeStopWriter
from fieldbus.dds import messages as m
from fieldbus.dds.base_service import BaseService
from fieldbus.dds.bus_values import bus_values
from fieldbus.dds.callers import Caller, Callers, publication_handle
from fieldbus.dds.cdr import PlainReader, PlainWriter
from fieldbus.dds.gate import VERBS, ClaimError, CommandGate, Deadline, GateState
from fieldbus.dds.participant import (
    COMMANDS,
    DIAGNOSTICS,
    REALTIME,
    RELIABLE,
    Participant,
    service_names,
    topic_names,
)
from fieldbus.dds.service_host import ServiceHost
from fieldbus.dds.stalls import StallWatch
from fieldbus.dds.state_bytes import AxisStateBytes, JointStateBytes
from fieldbus.dds.topic_control import TopicControl
from fieldbus.errors import FieldbusError
from fieldbus.network import CycleResult, Network, Operational

# command fields -> the output channel they drive: a CiA 402 object, else a channel of that name (MIT maps)
OUTPUT_ROLES = {"position": 0x607A, "velocity": 0x60FF, "torque": 0x6071, "kp": None, "kd": None}
# JointState fields <- the input channel they come from
INPUT_ROLES = {
    "position": (0x6064, "position"),
    "velocity": (0x606C, "velocity"),
    "effort": (0x6077, "torque"),
}
MODES_OUT, MODES_DISPLAY = 0x6060, 0x6061
ENABLE_TIMEOUT_CYCLES = 3000
DIAGNOSTICS_DEFER_MAX = 100  # cycles a due DiagnosticArray waits for a cycle with half its period left
SERVICE_POLL_EVERY = 10  # cycles between looks at the ROS 2 service requests (10 ms at 1 kHz)
Respond = Callable[["dict[str, Any] | FieldbusError | None"], None]  # a service call's answer
Check = Callable[[], "dict[str, Any] | None"]  # a request under way: its detail once it has ended
LEVEL_OK, LEVEL_WARN, LEVEL_ERROR = 0, 1, 2
# why a command was not applied (a counter each, in the diagnostics as refused/<reason>)
REFUSALS = ("wrong_length", "not_finite", "not_owner", "before_transition")


@dataclass(frozen=True)
class ServeOptions:
    """How a bus is served: names, deadline (cycles), publishing rates (every n-th cycle)."""

    namespace: str
    deadline: Deadline = field(default_factory=Deadline)
    base_namespace: str = ""  # the wheeled base's topics (cmd_vel, odom...) under it; "": ROS 2 global names
    ros2_control: tuple[str, str] | None = None  # (commands, states) topics of topic-based ros2_control
    publish_every: int = 1
    diagnostics_every: int = 1000

    def __post_init__(self) -> None:
        for what, v in (("publish_every", self.publish_every), ("diagnostics_every", self.diagnostics_every)):
            if not isinstance(v, int) or isinstance(v, bool) or v < 1:
                raise FieldbusError(f"{what} must be a whole number of cycles >= 1, not {v!r}")


def _unscaled(image: ProcessImage, direction: str, index: int) -> str | None:
    lay = image.layout.outputs if direction == "out" else image.layout.inputs
    e = lay.find(index)
    return e.name if e is not None and not e.channel.scaled else None


def _dtype_fields(values: npt.NDArray[Any]) -> list[list[str]]:
    fields: dict[str, Any] = dict(values.dtype.fields or {})
    return [[name, fields[name][0].str] for name in values.dtype.names or ()]


class _AxisCounts(TypedDict):
    """AxisState's fields after the arrays, as one served cycle leaves them."""

    cycle: int
    safe_stop: bool
    gate: int
    command_sequence: int
    command_age: int
    owner: str
    dropped_sequences: int
    refused_commands: int


class ServedGroup:
    """One axis group as served: its gate, its CiA 402 controller, its messages and topics."""

    def __init__(
        self,
        server: BusServer,
        name: str,
        image: ProcessImage,
        axes: tuple[str, ...],
        maps: tuple[Any, ...] = (),
    ) -> None:
        self.name = name
        self.bus = ""  # the bus it is on, from attach()
        self.maps = maps  # one drive map per slave (homing time-outs; a multi-axis map for each of its axes)
        self.homing: Homing | None = None  # a home request under way
        self.image = image
        self.axes = axes
        self.n = len(axes)
        self.fresh = np.zeros(self.n, dtype=bool)  # per axis (row), from the bus's per-slave freshness
        self.slave_fresh: npt.NDArray[np.bool_] | None = None  # the bus's per-slave rows, from attach()
        # rows per slave: a multi-axis slave (``axes:``) has one joint per axis, named ``<slave>.axis<k>``
        self.rows_per_slave = np.array([mp.axes for mp in maps] or [1] * self.n, dtype=np.intp)
        # an SDO to a joint goes to its slave, at its axis's object (0x6041 -> 0x6841 for axis 2)
        self.sdo_targets: dict[str, tuple[str, Any, int]] = {}
        self.writer: SafeStopWriter | None = None  # the group's safe outputs, from attach()
        self.gate = CommandGate(server.options.deadline)
        out, inp = image.outputs, image.inputs
        self.out_roles = {
            r: c for r, i in OUTPUT_ROLES.items() if (c := image.layout.outputs.channel_for(i, r))
        }
        self.in_roles = {
            r: c for r, (i, n) in INPUT_ROLES.items() if (c := image.layout.inputs.channel_for(i, n))
        }
        self.input_names = list(inp.values.dtype.names or ())
        self._inputs = np.zeros((self.n, len(self.input_names)))
        cw, sw = _unscaled(image, "out", CONTROLWORD), _unscaled(image, "in", STATUSWORD)
        self.ctrl: Cia402Controller | None = None
        self._cia: tuple[Any, ...] = ()
        if cw is not None and sw is not None:
            mo, md = _unscaled(image, "out", MODES_OUT), _unscaled(image, "in", MODES_DISPLAY)
            mode = Mode(int(out.values[mo][0])) if mo is not None and int(out.values[mo][0]) else Mode.CSP
            self.ctrl = Cia402Controller(self.n, mode=mode, timeout_cycles=ENABLE_TIMEOUT_CYCLES)
            self._cia = (
                inp.values[sw],
                out.values[cw],
                inp.values[md] if md is not None else None,
                out.values[mo] if mo is not None else None,
            )
        self.no_state = np.full(self.n, -1, dtype=np.int8)
        self.drive_errors: list[str] = [""] * self.n  # per axis its newest drive fault, by name
        self.refusals = dict.fromkeys(REFUSALS, 0)  # commands not applied, per reason
        self.last_refusal = ""  # the newest refusal, said for people
        self.latched_by = ""  # why the gate latched its safe stop (deadline, bus, drive fault, owner left)
        self.callers = server.callers
        self.owner_writers: list[tuple[Any, int]] = []  # (reader, writer handle) the owner was seen on
        self.stopped = False  # the group's drives are held by safe outputs (the gate's or the bus's latch)
        self._scratch = np.zeros(self.n, dtype=np.intp)
        topics = topic_names(server.options.namespace, name)
        dp = server.participant.dp
        self.js_writer = PlainWriter(dp, Topic(dp, topics["joint_states"], m.JointState), qos=REALTIME)
        self.st_writer = PlainWriter(dp, Topic(dp, topics["axis_state"], m.AxisState), qos=REALTIME)
        self.cmd_reader = PlainReader(dp, Topic(dp, topics["command"], m.JointCommand), qos=COMMANDS)
        self.topics = topics
        # the per-cycle messages encoded in place, where the writers take bytes (cyclonedds's serializer
        # otherwise: 0.1-0.2 ms of every served step)
        fast = self.js_writer.fast and self.st_writer.fast
        self._js_bytes = JointStateBytes(list(axes), list(self.in_roles)) if fast else None
        self._st_bytes = AxisStateBytes(self.n, len(self.input_names)) if fast else None

    def describe(self) -> dict[str, Any]:
        return {
            "axes": list(self.axes),
            "inputs": _dtype_fields(self.image.inputs.values),
            "outputs": _dtype_fields(self.image.outputs.values),
            "command": self.out_roles,
            "joint_state": self.in_roles,
            "cia402": self.ctrl is not None,
            "topics": self.topics,
        }

    # -- the cycle, before exchange() --
    def refuse(self, reason: str, why: str) -> None:
        """A command not applied: counted under ``reason``; ``why`` is published in the diagnostics."""
        self.refusals[reason] += 1
        if reason != "before_transition":
            self.gate.refused += 1
        self.last_refusal = why

    def discard_pending(self) -> None:
        """A transition (claim, clear, enable): commands received before it are not applied after it."""
        for cmd in self.cmd_reader.take(N=64):
            if isinstance(cmd, m.JointCommand):
                self.refuse(
                    "before_transition", f"sequence {cmd.sequence} came before a claim, clear or enable"
                )

    def take_commands(self) -> None:
        """Offer every command received since the last cycle to the gate; apply the newest accepted one.

        Refused, with the reason counted: a sequence of the wrong length, a
        value that is not finite (NaN, inf: it never counts as a live command),
        a writer whose DDS participant is not the owner's (whatever client_id it
        names)."""
        newest: m.JointCommand | None = None
        gate = self.gate
        for cmd in self.cmd_reader.take(N=64):
            if not isinstance(cmd, m.JointCommand):
                continue  # an instance disposed by a departed writer
            given = [(r, v) for r in OUTPUT_ROLES if (v := getattr(cmd, r))]
            if any(len(v) != self.n for _, v in given):
                lengths = {r: len(v) for r, v in given}
                self.refuse("wrong_length", f"sequence {cmd.sequence}: lengths {lengths}, want 0 or {self.n}")
                continue
            if not all(math.isfinite(x) for _, v in given for x in v):
                self.refuse("not_finite", f"sequence {cmd.sequence}: a value is NaN or infinite")
                continue
            who = self.callers.of(self.cmd_reader, cmd)
            if who is None or who != gate.owner:
                self.refuse(
                    "not_owner",
                    f"sequence {cmd.sequence} (client_id {cmd.client_id!r}) from DDS participant {who}, "
                    f"not the owner's",
                )
                continue
            if gate.offer(who, cmd.sequence):
                newest = cmd
                self.note_owner_writer(self.cmd_reader, publication_handle(cmd))
        if newest is not None:
            out = self.image.outputs.values
            for role, chan in self.out_roles.items():
                seq = getattr(newest, role)
                if seq:
                    out[chan] = seq

    def note_owner_writer(self, reader: Any, handle: int) -> None:
        """The owner wrote on ``reader`` with writer ``handle``: its liveliness is watched there."""
        if handle and (reader, handle) not in self.owner_writers:
            self.owner_writers.append((reader, handle))

    def latch(self, why: str, *, edge: bool = False) -> None:
        """Latch the group's safe stop now (``edge``: the gate has just latched it itself); the drives'
        goal is DISABLE until an enable after the clear."""
        if edge or not self.gate.latched:
            self.latched_by = why
        self.gate.latch()
        if self.ctrl is not None:
            self.ctrl.set_goal(Goal.DISABLE)

    def seed(self) -> None:
        """No command applies: position target = the joint's actual position, velocity and torque 0."""
        out, inp = self.image.outputs.values, self.image.inputs.values
        pos_out, pos_in = self.out_roles.get("position"), self.in_roles.get("position")
        if pos_out is not None and pos_in is not None:
            out[pos_out] = inp[pos_in]
        for role in ("velocity", "torque"):
            chan = self.out_roles.get(role)
            if chan is not None:
                out[chan] = 0.0

    def before_exchange(self, bus_stopped: bool) -> None:
        was = self.gate.state
        state = self.gate.tick()
        if state is GateState.SAFE_STOP and was is not GateState.SAFE_STOP:
            self.latch(f"no command for {self.gate.deadline.stop_after} cycles", edge=True)
        self.stopped = state is GateState.SAFE_STOP or bus_stopped
        if self.ctrl is not None:
            if self.stopped:  # the safe outputs own the controlword: no fault reset is spent against them
                decode_states(self._cia[0], self.ctrl.state, self._scratch)
            else:
                self.ctrl.step(*self._cia)
            if self.homing is not None:
                self.homing.step(self._cia[0], self._cia[1])
        if state is GateState.IDLE or self.stopped:
            # no command applies: the targets hold the joint, so an enable or a first command starts from here
            self.seed()
        if state is GateState.SAFE_STOP and self.writer is not None:
            self.writer.apply()

    # -- after exchange() --
    def publish(self, res: CycleResult, stamp_ns: int) -> None:
        """JointState and AxisState of this cycle, stamped ``stamp_ns`` (ns since the Unix epoch)."""
        inp = self.image.inputs.values
        if self.slave_fresh is not None and self.fresh is not self.slave_fresh:  # each slave's, per axis
            self.fresh[:] = np.repeat(self.slave_fresh, self.rows_per_slave)
        for j, name in enumerate(self.input_names):
            self._inputs[:, j] = inp[name]
        g = self.gate
        drive_state = self.ctrl.state if self.ctrl is not None else self.no_state
        counts: _AxisCounts = {
            "cycle": res.cycle,
            "safe_stop": res.safe_stop or g.latched,
            "gate": int(g.state),
            "command_sequence": g.applied_sequence,
            "command_age": g.age,
            "owner": g.label if g.owner is not None else "",
            "dropped_sequences": g.dropped,
            "refused_commands": g.refused,
        }
        if self._js_bytes is not None and self._st_bytes is not None:  # encoded in place (state_bytes)
            values = {r: inp[c] for r, c in self.in_roles.items()}
            self.js_writer.write_encoded(self._js_bytes.encode(stamp_ns, values))
            self.st_writer.write_encoded(
                self._st_bytes.encode(
                    stamp_ns, fresh=self.fresh, drive_state=drive_state, inputs=self._inputs, **counts
                )
            )
            return
        header = m.Header(stamp=m.Time.of_ns(stamp_ns), frame_id="")
        js = m.JointState(header=header, name=list(self.axes))
        for field_name, chan in self.in_roles.items():
            setattr(js, field_name, inp[chan].astype(np.float64).tolist())
        self.js_writer.write(js)
        st = m.AxisState(
            header=header,
            fresh=self.fresh.tolist(),
            drive_state=drive_state.tolist(),
            inputs=self._inputs.ravel().tolist(),
            all_fresh=bool(self.fresh.all()),
            **counts,
        )
        self.st_writer.write(st)


class BusServer:
    """Serve a network over DDS: create it before bring-up (topics take a while to create: the slaves'
    watchdogs would expire), :meth:`attach` the running phase, then call :meth:`step` once per cycle."""

    def __init__(
        self,
        net: Network,
        participant: Participant,
        options: ServeOptions,
        *,
        clock: Callable[[], int] = time.monotonic_ns,
    ) -> None:
        self._op: Operational | None = None
        self._clock = clock  # when each cycle starts (ns): the gaps between cycles, for the stall watch
        # the cycle whose DiagnosticArray (0.1-0.2 ms of Python) is due, -1: none; it goes out in the first
        # cycle since then whose own work took less than half the period (a slow spell of the CPU does not
        # get it on top), at the latest DIAGNOSTICS_DEFER_MAX cycles late
        self._diagnostics_due = -1
        self.stalls = StallWatch(1_000_000)
        self.participant = participant
        self.options = options
        self.callers = Callers()
        self._bus_stopped = False  # the bus's safe stop was latched at the end of the last cycle
        self.groups: dict[str, ServedGroup] = {
            name: ServedGroup(self, name, g.image, row_names(g.slaves), tuple(s.map for s in g.slaves))
            for name, g in net.groups.items()
        }
        for name, g in net.groups.items():
            rows = iter(self.groups[name].axes)
            self.groups[name].sdo_targets = {
                next(rows): (s.name, s.map, k) for s in g.slaves for k in range(s.map.axes)
            }
        # requests answered in a later cycle: (request, a check returning the detail or None while under way)
        self._pending: list[tuple[m.Request, Callable[[], dict[str, Any] | None], Respond | None]] = []
        self._answered: dict[str, tuple[int, m.Reply]] = {}  # per client its newest reply (a resend)
        dp = participant.dp
        names = service_names(options.namespace)
        self.req_reader = PlainReader(dp, Topic(dp, names["request"], m.Request), qos=RELIABLE)
        self.reply_writer = PlainWriter(dp, Topic(dp, names["reply"], m.Reply), qos=RELIABLE)
        self.diag_writer = PlainWriter(
            dp, Topic(dp, names["diagnostics"], m.DiagnosticArray), qos=DIAGNOSTICS
        )
        self.requests = 0
        self.services = ServiceHost(
            participant, options.namespace, list(self.groups), self._answer, self.callers
        )
        # the network file's wheeled base: cmd_vel in, odom/tf out (fieldbus.dds.base_service)
        self.base: BaseService | None = None
        if net.model.base is not None:
            self.base = BaseService(self, net.model.base, options.base_namespace)
        # ros2_control's topic-based hardware interface (fieldbus.dds.topic_control), on the other groups
        self.topic_control: TopicControl | None = None
        if options.ros2_control is not None:
            wheels = tuple(g.name for g in self.base.groups) if self.base is not None else ()
            self.topic_control = TopicControl(self, *options.ros2_control, exclude=wheels)

    def attach(self, op: Operational) -> None:
        """Serve ``op`` (the network's running phase) from the next :meth:`step` on."""
        for bv in op.buses:
            for g in bv.backend.groups:
                served = self.groups[g.name]
                served.slave_fresh = bv.status.fresh[g.first : g.first + len(g.slaves)]
                if len(g.slaves) == served.n:  # one row per slave: the bus's own rows
                    served.fresh = served.slave_fresh
                served.bus = bv.name
                served.writer = op.safe_stops[g.name]
        self.stalls = StallWatch(int(op.cycle_time_us * 1000))
        self._op = op
        if self.base is not None:
            self.base.attach(op)

    @property
    def op(self) -> Operational:
        if self._op is None:
            raise FieldbusError("BusServer.attach(op) first: the network is not up")
        return self._op

    def describe(self) -> dict[str, Any]:
        o = self.options
        return {
            "namespace": o.namespace,
            "cycle_time_us": self.op.cycle_time_us,
            "publish_every": o.publish_every,
            "hold_after": o.deadline.hold_after,
            "stop_after": o.deadline.stop_after,
            "groups": {name: g.describe() for name, g in self.groups.items()},
            **({"base": self.base.topics} if self.base is not None else {}),
            **({"ros2_control": self.topic_control.describe()} if self.topic_control is not None else {}),
        }

    def step(self, k: int) -> bool:
        """One cycle: requests, commands, gates, ``exchange()``, publish (every n-th cycle). Never stops early."""
        self.stalls.tick(self._clock(), self.op.result.cycle)
        for req in self.req_reader.take(N=16):
            if isinstance(req, m.Request):
                self._answer(req, None, Caller.of(self.callers, self.req_reader, req, req.client_id))
        if k % SERVICE_POLL_EVERY == 0:
            self.services.poll()
        if self._pending:
            self._advance_pending()
        if k % SERVICE_POLL_EVERY == 5:
            self._watch_owners()
        start_ns = self._clock()
        if self.base is not None:
            self.base.take(start_ns / 1e9)
        if self.topic_control is not None:
            self.topic_control.take()
        for g in self.groups.values():
            g.take_commands()
            g.before_exchange(self._bus_stopped)
        res = self.op.exchange()
        self.stalls.result(res.cycle, res.safe_stop)
        if res.safe_stop and not self._bus_stopped:
            for g in self.groups.values():
                g.latch("the bus's safe stop")
        self._bus_stopped = res.safe_stop
        if res.events:
            self._note_faults(res)
        o = self.options
        if self.base is not None:
            self.base.after(res, start_ns / 1e9, self.op.cycle_time_us / 1e6, time.time_ns())
        if k % o.publish_every == 0:
            now = time.time_ns()
            for g in self.groups.values():
                g.publish(res, now)
            if self.topic_control is not None:
                self.topic_control.publish(now)
        if k % o.diagnostics_every == 0 and self._diagnostics_due < 0:
            self._diagnostics_due = k
        if self._diagnostics_due >= 0 and (
            self._clock() - start_ns < self.op.cycle_time_us * 500  # this cycle has half its period left
            or k - self._diagnostics_due >= DIAGNOSTICS_DEFER_MAX
        ):
            self._diagnostics_due = -1
            self.diag_writer.write(self.diagnostics())
        return False

    def _note_faults(self, res: CycleResult) -> None:
        """Keep each axis's newest drive fault (0x603F by name) for the diagnostics."""
        for ev in res.events:
            if isinstance(ev, DriveFault) and ev.group in self.groups:
                g = self.groups[ev.group]
                code = f"0x{ev.code:04X} " if ev.code is not None else ""
                g.drive_errors[ev.axis] = f"{code}{ev.name} (cycle {ev.cycle})"
                # no automatic re-enable on the last command: the owner clears and enables again
                g.latch(f"drive fault on {g.axes[ev.axis]} (its drive_error says which)")

    def _watch_owners(self) -> None:
        """A group whose owner's participant has left the domain (no writer of it matched) latches."""
        for g in self.groups.values():
            if g.gate.owner is None or g.gate.latched or not g.owner_writers:
                continue
            if not any(self.callers.alive(reader, h) for reader, h in g.owner_writers):
                g.latch(f"the owner '{g.gate.label}' left the DDS domain")

    def _answer(self, req: m.Request, respond: Respond | None, caller: Caller) -> None:
        """Carry out ``req`` for ``caller``; its outcome goes to ``respond`` (a ROS 2 service call), else as
        a Reply."""
        if respond is None:
            done = self._answered.get(req.client_id)
            if done is not None and done[0] == req.request_id:  # a resend of an answered request
                self.reply_writer.write(done[1])
                return
            if any(
                p.client_id == req.client_id and p.request_id == req.request_id and r is None
                for p, _, r in self._pending
            ):
                return  # a resend of a request under way: answered when it ends
        self.requests += 1
        try:
            detail = self._do(req, caller)
        except FieldbusError as exc:
            self._reply(req, exc, respond)
            return
        if callable(detail):
            self._pending.append((req, detail, respond))
        else:
            self._reply(req, detail, respond)

    def _advance_pending(self) -> None:
        """Once a cycle: the requests under way that have ended are answered."""
        still = []
        for req, check, respond in self._pending:
            try:
                detail = check()
            except FieldbusError as exc:
                self._reply(req, exc, respond)
                continue
            if detail is None:
                still.append((req, check, respond))
            else:
                self._reply(req, detail, respond)
        self._pending = still

    def _reply(
        self, req: m.Request, outcome: dict[str, Any] | FieldbusError | None, respond: Respond | None = None
    ) -> None:
        if respond is not None:
            respond(outcome)
            return
        reply = m.Reply(client_id=req.client_id, request_id=req.request_id, ok=True)
        if isinstance(outcome, FieldbusError):
            reply.ok = False
            reply.error = f"{type(outcome).__name__}: {outcome}"
        elif outcome:
            reply.detail = json.dumps(outcome)
        self._answered[req.client_id] = (req.request_id, reply)
        self.reply_writer.write(reply)

    def _do(self, req: m.Request, caller: Caller) -> dict[str, Any] | Check | None:
        """Carry out ``req``: its detail, or a check the cycle calls until it gives the detail.

        The caller is its DDS participant (``caller.who``), not the client_id it names."""
        verb = req.verb
        if verb not in VERBS:
            raise FieldbusError(f"unknown request '{verb}' (have: {', '.join(VERBS)})")
        if verb == "describe":
            return self.describe()
        if verb == "set_odometry":
            return self._set_odometry(_argument(req))
        g = self.groups.get(req.group)
        if g is None:
            raise FieldbusError(f"no axis group '{req.group}' (have: {', '.join(self.groups)})")
        if not req.client_id:
            raise ClaimError("a request needs a client_id")
        if caller.who is None:
            raise ClaimError(f"client '{req.client_id}': its DDS participant is not known (yet): ask again")
        client = caller.who
        gate = g.gate
        gate.heard_from(client)
        if verb == "claim":
            was = gate.owner
            gate.claim(client, req.client_id)
            if was != client:
                g.owner_writers = []
                g.note_owner_writer(caller.reader, caller.handle)
                g.discard_pending()
        elif verb == "release":
            gate.release(client)
            g.owner_writers = []
        elif verb == "disable":  # anyone may stop the drives
            self._cia402(g).set_goal(Goal.DISABLE)
        elif verb == "enable":
            return self._enable(g, client)
        elif verb == "reset_faults":
            return self._reset_faults(g, client, _argument(req))
        elif verb == "clear_safe_stop":
            gate.check_owner(client)
            if self.op.result.safe_stop:
                self.op.clear_safe_stop()  # SafeStopClearError while a bus is still missing
            gate.clear(client)
            g.latched_by = ""
            g.discard_pending()
        elif verb == "home":
            return self._home(g, client)
        elif verb == "mode":
            return self._mode(g, client, _argument(req))
        elif verb in ("sdo_read", "sdo_write"):
            return self._sdo(g, client, verb, _argument(req))
        return None

    def _enable(self, g: ServedGroup, client: str) -> Check:
        """Enable ``g``'s drives (the owner): IDLE first (targets on the joints, commands sent before
        discarded), each axis's fault-reset budget re-armed; answered once every axis is OPERATION
        ENABLED, or with the axes that are not. While the bus's latch waits for its release (after a
        clear), the goal waits too."""
        ctrl, gate = self._cia402(g), g.gate
        gate.check_owner(client)
        bus = self.op.result.safe_stop
        if gate.latched or (bus and not any(bv.status.release_pending for bv in self.op.buses)):
            raise FieldbusError("safe stop latched: send clear_safe_stop first")
        gate.pause(client)  # IDLE, no deadline until enabled
        g.discard_pending()
        ctrl.reset_fault_budget()
        end = self.op.result.cycle + ENABLE_TIMEOUT_CYCLES
        started = False

        def check() -> dict[str, Any] | None:
            nonlocal started
            if gate.latched or gate.owner != client:
                raise FieldbusError(
                    f"group '{g.name}': {g.latched_by or 'the claim was lost'} while enabling"
                )
            if self.op.result.cycle > end:
                raise FieldbusError(
                    f"group '{g.name}' not enabled within {ENABLE_TIMEOUT_CYCLES} cycles (states {_names(ctrl)})"
                )
            if not started:
                if self.op.result.safe_stop:
                    return None  # the bus's latch opens after its release cycles
                ctrl.set_goal(Goal.ENABLE)
                started = True
            if ctrl.gave_up.any():
                bad = ", ".join(a for a, x in zip(g.axes, ctrl.gave_up, strict=True) if x)
                raise FieldbusError(f"group '{g.name}': {bad} stayed in FAULT after its fault resets")
            if not (ctrl.state == State402.OPERATION_ENABLED).all():
                return None
            gate.restart(client)  # IDLE, the no-command deadline counts from now
            g.discard_pending()
            return {}

        return self._resuming(g, check)

    def _reset_faults(self, g: ServedGroup, client: str, arg: dict[str, Any]) -> dict[str, Any]:
        """Re-arm the fault-reset budget of ``arg['axis']`` (a joint; default every joint of ``g``)."""
        ctrl = self._cia402(g)
        g.gate.check_owner(client)
        axis = arg.get("axis")
        if axis is not None and axis not in g.axes:
            raise FieldbusError(
                f"reset_faults: no axis {axis!r} in group '{g.name}' (have: {', '.join(g.axes)})"
            )
        axes = [g.axes.index(axis)] if axis is not None else list(range(g.n))
        re_armed = [g.axes[i] for i in axes if ctrl.gave_up[i]]
        ctrl.reset_fault_budget(axes)
        return {"re_armed": re_armed}

    @staticmethod
    def _resuming(g: ServedGroup, check: Check) -> Check:
        """``check``, and once it has ended (answer or error) the gate's no-command deadline counts again."""

        def wrapped() -> dict[str, Any] | None:
            try:
                detail = check()
            except FieldbusError:
                g.gate.resume()
                raise
            if detail is not None:
                g.gate.resume()
            return detail

        return wrapped

    def _home(self, g: ServedGroup, client: str) -> Callable[[], dict[str, Any] | None]:
        """Home every axis of ``g`` (the drive's method 0x6098, the map's homing time-out)."""
        ctrl = self._cia402(g)
        g.gate.check_owner(client)
        if g.homing is not None and not g.homing.done:
            raise FieldbusError(f"group '{g.name}' is homing already")
        if not (ctrl.state == State402.OPERATION_ENABLED).all():
            raise FieldbusError(f"group '{g.name}': enable the drives before homing (states {_names(ctrl)})")
        g.gate.pause(client)  # the target follows the joints while the drives home
        homing = g.homing = Homing.from_maps(ctrl, g.maps, int(self.op.cycle_time_us))
        homing.start()

        def check() -> dict[str, Any] | None:
            display = g._cia[2]
            back = display is None or bool((display == ctrl.mode_request).all())
            if not homing.done or not back:  # answered once every drive shows its previous mode again
                return None
            g.homing = None
            phases = [HomingPhase(int(p)).name for p in homing.phase]
            bad = [f"{a}: {p}" for a, p in zip(g.axes, phases, strict=True) if p != "DONE"]
            if bad:
                raise FieldbusError(f"homing of group '{g.name}' did not end: {', '.join(bad)}")
            return {"phases": phases, "cycles": homing.cycles.tolist()}

        return self._resuming(g, check)

    def _mode(self, g: ServedGroup, client: str, arg: dict[str, Any]) -> Callable[[], dict[str, Any] | None]:
        """Switch ``g``'s drives to ``arg['mode']`` (a name such as "CSV" or a CiA 402 number)."""
        ctrl = self._cia402(g)
        g.gate.check_owner(client)
        want = arg.get("mode")
        try:
            mode = Mode[want.upper()] if isinstance(want, str) else Mode(int(want))  # type: ignore[arg-type]
        except (KeyError, ValueError, TypeError):
            have = ", ".join(x.name for x in Mode)
            raise FieldbusError(f"unknown mode {want!r} (have: {have}, or their numbers)") from None
        if g._cia[2] is None or g._cia[3] is None:
            raise FieldbusError(f"group '{g.name}' maps no modes of operation (0x6060/0x6061)")
        if g.homing is not None and not g.homing.done:
            raise FieldbusError(f"group '{g.name}' is homing: wait for its reply first")
        g.gate.pause(client)  # the targets follow the joints through the switch
        ctrl.request_mode(mode)
        display = g._cia[2]
        end = self.op.result.cycle + ENABLE_TIMEOUT_CYCLES

        def check() -> dict[str, Any] | None:
            if (display == int(mode)).all():
                return {"mode": mode.name}
            if self.op.result.cycle > end:
                raise FieldbusError(
                    f"group '{g.name}' did not switch to {mode.name} within {ENABLE_TIMEOUT_CYCLES} cycles "
                    f"(modes shown: {display.tolist()})"
                )
            return None

        return self._resuming(g, check)

    def _sdo(
        self, g: ServedGroup, client: str, verb: str, arg: dict[str, Any]
    ) -> Callable[[], dict[str, Any] | None]:
        """``arg``: axis (a joint name), index, sub_index, and for a write data (hex). Reading needs no
        claim; writing needs the group's claim."""
        axis = arg.get("axis")
        if axis not in g.axes:
            raise FieldbusError(f"SDO: no axis {axis!r} in group '{g.name}' (have: {', '.join(g.axes)})")
        index, sub = arg.get("index"), arg.get("sub_index", 0)
        if not isinstance(index, int) or not isinstance(sub, int):
            raise FieldbusError(f"SDO: index and sub_index must be whole numbers, not {index!r}, {sub!r}")
        slave, drive_map, k = g.sdo_targets[axis]
        index = drive_map.axis_index(index, k)  # 0x6000-0x67FF: that axis's object
        if verb == "sdo_read":
            future: Future[bytes | None] = self.op.submit_sdo_read(g.bus, slave, index, sub)
        else:
            g.gate.check_owner(client)
            try:
                data = bytes.fromhex(str(arg.get("data", "")))
            except ValueError:
                raise FieldbusError(f"SDO write: data must be hex text, not {arg.get('data')!r}") from None
            future = self.op.submit_sdo_write(g.bus, slave, index, sub, data)

        def check() -> dict[str, Any] | None:
            if not future.done():
                return None
            exc = future.exception()
            if exc is not None:
                if isinstance(exc, FieldbusError):
                    raise exc
                raise FieldbusError(f"SDO {axis} 0x{index:04X}:{sub:02X}: {type(exc).__name__}: {exc}")
            got = future.result()
            return {"data": got.hex() if got is not None else ""}

        return check

    def _set_odometry(self, arg: dict[str, Any]) -> dict[str, Any]:
        """The wheeled base's pose in the odometry frame: ``x``, ``y`` (m), ``yaw`` (rad); absent: 0.
        Moves nothing, so anyone may ask (as ``set_pose`` of a localisation node)."""
        if self.base is None or self.base.base is None:
            raise FieldbusError("set_odometry: this network has no base: section")
        pose = []
        for key in ("x", "y", "yaw"):
            v = arg.get(key, 0.0)
            if isinstance(v, bool) or not isinstance(v, int | float) or not math.isfinite(v):
                raise FieldbusError(f"set_odometry: {key} must be a finite number, not {v!r}")
            pose.append(float(v))
        self.base.base.odometry.reset(*pose)
        return dict(zip(("x", "y", "yaw"), pose, strict=True))

    @staticmethod
    def _cia402(g: ServedGroup) -> Cia402Controller:
        if g.ctrl is None:
            raise FieldbusError(f"group '{g.name}' has no CiA 402 drives (no controlword/statusword)")
        return g.ctrl

    def diagnostics(self) -> m.DiagnosticArray:
        """Per bus its verdict and counters, per group its gate, owner and drive states; the cycle's stalls."""
        w = self.stalls
        status = [
            m.DiagnosticStatus(
                level=LEVEL_ERROR if w.note else LEVEL_WARN if w.count else LEVEL_OK,
                name="fieldbus/cycle",
                message=w.note or (f"{w.count} stall(s)" if w.count else "OK"),
                hardware_id="cycle",
                values=[
                    m.KeyValue("stalls", str(w.count)),
                    m.KeyValue("longest_stall_us", str(w.longest_ns // 1000)),
                    m.KeyValue("last_stall_cycle", str(w.last_cycle) if w.last_cycle >= 0 else ""),
                ],
            )
        ]
        for bv in self.op.buses:
            st = bv.status
            level = LEVEL_ERROR if st.safe_stop else LEVEL_OK if st.verdict.name == "OK" else LEVEL_WARN
            values = bus_values(st, bv.counters())
            watch = bv.backend.error_watch  # EtherCAT, error_counters: ESC counters in OP
            if watch is not None:
                esc = watch.summary([a.slave.name for a in bv.backend.areas])
                values += [m.KeyValue(k, v) for k, v in esc.items()]
                if "suspect_link" in esc and level == LEVEL_OK:
                    level = LEVEL_WARN
            status.append(
                m.DiagnosticStatus(
                    level=level,
                    name=f"fieldbus/bus/{bv.name}",
                    message=f"{st.verdict.name}{' safe stop' if st.safe_stop else ''}",
                    hardware_id=bv.kind,
                    values=values,
                )
            )
        for g in self.groups.values():
            gate = g.gate
            states = g.ctrl.state.tolist() if g.ctrl is not None else []
            level = LEVEL_ERROR if gate.latched else LEVEL_WARN if gate.state is GateState.HOLD else LEVEL_OK
            values = [
                m.KeyValue("owner", gate.label if gate.owner is not None else ""),
                m.KeyValue("owner_participant", gate.owner or ""),
                m.KeyValue("command_sequence", str(gate.applied_sequence)),
                m.KeyValue("dropped_sequences", str(gate.dropped)),
                m.KeyValue("refused_commands", str(gate.refused)),
            ]
            values += [m.KeyValue(f"refused/{r}", str(n)) for r, n in g.refusals.items()]
            values += [m.KeyValue("last_refusal", g.last_refusal), m.KeyValue("latched_by", g.latched_by)]
            values += [
                m.KeyValue(f"{axis}/drive_state", _state_name(s))
                for axis, s in zip(g.axes, states, strict=False)
            ]
            faults = self.op.result.drive_faults.get(g.name)
            for i, axis in enumerate(g.axes):
                if g.drive_errors[i]:
                    n = int(faults[i]) if faults is not None else 1
                    values.append(m.KeyValue(f"{axis}/drive_error", f"{g.drive_errors[i]}, {n} fault(s)"))
            status.append(
                m.DiagnosticStatus(
                    level=level,
                    name=f"fieldbus/group/{g.name}",
                    message=gate.state.name + (f": {g.latched_by}" if gate.latched and g.latched_by else ""),
                    hardware_id=g.name,
                    values=values,
                )
            )
        return m.DiagnosticArray(header=m.Header(stamp=m.Time.of_ns(time.time_ns())), status=status)


def _argument(req: m.Request) -> dict[str, Any]:
    """A request's argument: a JSON object."""
    try:
        arg = json.loads(req.argument) if req.argument else {}
    except json.JSONDecodeError as exc:
        raise FieldbusError(
            f"'{req.verb}': argument is not JSON ({exc.msg} at character {exc.pos})"
        ) from None
    if not isinstance(arg, dict):
        raise FieldbusError(f"'{req.verb}': argument must be a JSON object")
    return arg


def _names(ctrl: Cia402Controller) -> str:
    return ", ".join(_state_name(int(s)) for s in ctrl.state)


def _state_name(code: int) -> str:
    try:
        return State402(code).name
    except ValueError:
        return "UNKNOWN"
