"""A served bus (``fieldbus serve``) from another process or machine, with the face of the in-process API.

    with fieldbus.remote.connect("demo", interface="lo") as op:   # the served namespace
        legs = op["joints"]                 # inputs / outputs: numpy, the dtypes of the in-process image
        op.claim("joints")                  # one commanding client per group; others get ClaimError
        op.enable("joints")                 # CiA 402: the server runs the state machine
        while running:
            legs.outputs["target_position"][:] = q
            result = op.exchange()          # send the command, wait for the state that applied it

Commands carry the channels the server names in its description (position,
velocity, torque, kp, kd: ``op.command_channels(group)``); the other output
channels (controlword, modes) belong to the server. See ``docs/dds.md``.
"""

from __future__ import annotations

import contextlib
import json
import time
import uuid
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field
from types import TracebackType
from typing import Any

import numpy as np
import numpy.typing as npt

from fieldbus.core.cia402 import State402
from fieldbus.dds import require
from fieldbus.dds.cdr import PlainReader, PlainWriter
from fieldbus.dds.gate import ClaimError, GateState
from fieldbus.errors import BusTimeoutError, FieldbusError

require()

from cyclonedds.core import InstanceState, ReadCondition, SampleState, ViewState, WaitSet  # noqa: E402
from cyclonedds.topic import Topic  # noqa: E402

from fieldbus.dds import messages as m  # noqa: E402
from fieldbus.dds.participant import REALTIME, RELIABLE, Participant, check_namespace, service_names  # noqa: E402

__all__ = ["ClaimError", "GateState", "Remote", "RemoteError", "RemoteGroup", "RemoteResult", "connect"]

NEW = SampleState.NotRead | ViewState.Any | InstanceState.Any
RETRY_S = 0.5  # a request not answered within this is sent again (every verb is idempotent)


class RemoteError(FieldbusError):
    """The served bus answered a request with an error, or did not answer in time."""


class RemoteDirection:
    """One direction of a remote group: ``values`` (structured array, one row per axis) and ``[name]``."""

    def __init__(self, fields: Sequence[Sequence[str]], n_axes: int) -> None:
        self.values: npt.NDArray[Any] = np.zeros(n_axes, dtype=np.dtype([(n, s) for n, s in fields]))
        self.names = tuple(n for n, _ in fields)

    def __getitem__(self, name: str) -> npt.NDArray[Any]:
        try:
            return self.values[name]
        except (ValueError, KeyError):
            raise FieldbusError(f"no channel '{name}' (have: {', '.join(self.names)})") from None

    def __setitem__(self, name: str, value: Any) -> None:
        self[name]  # the same error for an unknown name
        self.values[name] = value


class RemoteGroup:
    """One served axis group: ``inputs`` / ``outputs`` as the in-process :class:`fieldbus.ProcessImage`."""

    def __init__(self, name: str, desc: dict[str, Any]) -> None:
        self.name = name
        self.axes: tuple[str, ...] = tuple(desc["axes"])
        self.n_axes = len(self.axes)
        self.inputs = RemoteDirection(desc["inputs"], self.n_axes)
        self.outputs = RemoteDirection(desc["outputs"], self.n_axes)
        self.command_channels: dict[str, str] = dict(desc["command"])  # command field -> output channel
        self.joint_state: dict[str, str] = dict(desc["joint_state"])  # JointState field <- input channel
        self.cia402 = bool(desc["cia402"])
        self.topics: dict[str, str] = dict(desc["topics"])
        self.state = m.AxisState()  # the newest state received
        self.drive_state = np.full(self.n_axes, -1, dtype=np.int8)
        self.fresh = np.zeros(self.n_axes, dtype=bool)

    def accept(self, st: m.AxisState) -> None:
        """Take a state: inputs, freshness and drive states from it."""
        self.state = st
        n = self.n_axes
        flat = np.asarray(st.inputs, dtype=np.float64)
        if flat.size == n * len(self.inputs.names):
            cols = flat.reshape(n, -1)
            for j, name in enumerate(self.inputs.names):
                self.inputs.values[name] = cols[:, j]
        if len(st.fresh) == n:
            self.fresh[:] = st.fresh
        if len(st.drive_state) == n:
            self.drive_state[:] = st.drive_state


@dataclass
class RemoteResult:
    """What :meth:`Remote.exchange` returns: the served cycle whose state came back, as CycleResult does."""

    cycle: int = 0  # the bus's cycle number of the newest state
    fresh: bool = False  # a state that applied this command came back in time, every axis fresh
    safe_stop: bool = False  # a bus or a group's deadline safe stop is latched
    late: bool = False  # no state applied this command within the deadline
    round_trip_ns: int = 0  # command written -> its state taken, ns
    gate: dict[str, GateState] = field(default_factory=dict)


class _Link:
    """A group's topics: its state reader and command writer."""

    def __init__(self, dp: Any, group: RemoteGroup, ws: WaitSet) -> None:
        self.reader = PlainReader(dp, Topic(dp, group.topics["axis_state"], m.AxisState), qos=REALTIME)
        self.writer = PlainWriter(dp, Topic(dp, group.topics["command"], m.JointCommand), qos=REALTIME)
        self.cond = ReadCondition(self.reader, NEW)
        ws.attach(self.cond)


class Remote:
    """A connection to a served bus; see :func:`connect`. Use it from one thread."""

    def __init__(
        self,
        namespace: str,
        *,
        domain: int | None = None,
        interface: str | None = None,
        peers: Sequence[str] = (),
        client_id: str | None = None,
        deadline_s: float = 0.1,
        timeout_s: float = 10.0,
    ) -> None:
        self.namespace = check_namespace(namespace)
        self.client_id = client_id or f"fieldbus-{uuid.uuid4().hex[:12]}"
        self.deadline_s = deadline_s
        self.participant = Participant(domain, interface, peers)
        dp = self.participant.dp
        names = service_names(self.namespace)
        self._req = PlainWriter(dp, Topic(dp, names["request"], m.Request), qos=RELIABLE)
        self._rep = PlainReader(dp, Topic(dp, names["reply"], m.Reply), qos=RELIABLE)
        self._rep_ws = WaitSet(dp)
        self._rep_ws.attach(ReadCondition(self._rep, NEW))
        self._request_id = 0
        self.description = self.request("describe", timeout_s=timeout_s) or {}
        self.cycle_time_us = float(self.description["cycle_time_us"])
        self.groups = {n: RemoteGroup(n, d) for n, d in self.description["groups"].items()}
        self._ws = WaitSet(dp)
        self._links = {n: _Link(dp, g, self._ws) for n, g in self.groups.items()}
        self.claimed: set[str] = set()
        self.sequence = 0
        self.misses = 0  # exchanges whose state did not come back within the deadline
        self.result = RemoteResult()
        self._wait_first_state(timeout_s)

    # -- the in-process face --
    def __getitem__(self, group: str) -> RemoteGroup:
        try:
            return self.groups[group]
        except KeyError:
            raise FieldbusError(f"no axis group '{group}' (have: {', '.join(self.groups)})") from None

    def __iter__(self) -> Iterator[str]:
        return iter(self.groups)

    def __enter__(self) -> Remote:
        return self

    def __exit__(
        self, tp: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.close()

    def close(self) -> None:
        """Give up every claimed group (its last command stays applied, no deadline) and leave the domain."""
        for g in sorted(self.claimed):
            with contextlib.suppress(FieldbusError):  # the server is gone, or the claim was taken over
                self.request("release", g, timeout_s=1.0)
        self.claimed.clear()

    # -- requests --
    def request(
        self,
        verb: str,
        group: str = "",
        *,
        argument: dict[str, Any] | None = None,
        timeout_s: float = 5.0,
    ) -> dict[str, Any] | None:
        """Send a request and wait for its reply; the reply's detail (JSON) or None.

        Raises :class:`ClaimError` when the group belongs to another client,
        :class:`RemoteError` for any other refusal and when no reply came.
        """
        self._request_id += 1
        rid = self._request_id
        text = json.dumps(argument) if argument is not None else ""
        req = m.Request(client_id=self.client_id, request_id=rid, group=group, verb=verb, argument=text)
        end = time.monotonic() + timeout_s
        while time.monotonic() < end:
            self._req.write(req)
            resend = min(end, time.monotonic() + RETRY_S)
            while (now := time.monotonic()) < resend:
                self._rep_ws.wait(int((resend - now) * 1e9))
                for rep in self._rep.take(N=32):
                    if isinstance(rep, m.Reply) and rep.client_id == self.client_id and rep.request_id == rid:
                        return self._reply(verb, group, rep)
        raise RemoteError(
            f"no reply to '{verb}' from namespace '{self.namespace}' on DDS domain "
            f"{self.participant.domain_id} within {timeout_s:g} s: is 'fieldbus serve' running there?"
        )

    @staticmethod
    def _reply(verb: str, group: str, rep: m.Reply) -> dict[str, Any] | None:
        if not rep.ok:
            kind, _, text = rep.error.partition(": ")
            what = f"'{verb}'" + (f" for group '{group}'" if group else "")
            if kind == "ClaimError":
                raise ClaimError(f"{what} refused: {text}")
            raise RemoteError(f"{what} refused: {rep.error}")
        detail: dict[str, Any] | None = json.loads(rep.detail) if rep.detail else None
        return detail

    def claim(self, group: str) -> None:
        """Become the one client that commands ``group`` (:class:`ClaimError` if another owns it).

        The position command starts at the measured position, velocity and torque at 0: the first exchange
        holds the joints. The server knows this client by its DDS participant, not by ``client_id``.
        """
        g = self[group]
        self.request("claim", group)
        self._hold(g)
        self.claimed.add(group)

    def release(self, group: str) -> None:
        self.request("release", group)
        self.claimed.discard(group)

    def enable(self, group: str, *, wait_s: float = 5.0) -> None:
        """Enable ``group``'s CiA 402 drives; waits until every axis reports OPERATION ENABLED (the server
        answers then, or with the axes that stayed in FAULT). The joints hold until the next command."""
        self.request("enable", group, timeout_s=wait_s)
        self._wait_states(group, State402.OPERATION_ENABLED, wait_s)

    def disable(self, group: str, *, wait_s: float = 5.0) -> None:
        self.request("disable", group)
        self._wait_states(group, State402.SWITCHED_ON, wait_s, at_most=True)

    def clear_safe_stop(self, group: str) -> None:
        """Open the group's latched safe stop (and the bus's, when it is latched and the bus is back)."""
        self.request("clear_safe_stop", group)
        for st in self._links[group].reader.take(
            N=8
        ):  # states from before the clear: not the answer to later
            if isinstance(st, m.AxisState):
                self.groups[group].accept(st)

    def reset_faults(self, group: str, axis: str | None = None) -> list[str]:
        """Re-arm the fault-reset budget of ``axis`` (a joint; default every joint of ``group``), for a
        drive that stayed in FAULT after its automatic resets; the joints that had given up."""
        detail = self.request("reset_faults", group, argument={"axis": axis} if axis else None) or {}
        return list(detail.get("re_armed", []))

    def home(self, group: str, *, timeout_s: float = 60.0) -> dict[str, Any]:
        """Home every axis of ``group`` (enabled, claimed) with the drives' homing method (0x6098); waits
        for the end. Refused with the axes and phases when an axis failed or timed out. While homing,
        the deadline is paused; afterwards the position command starts at the new measured position."""
        detail = self.request("home", group, timeout_s=timeout_s) or {}
        self._reseed(group)
        return detail

    def set_mode(self, group: str, mode: str | int, *, timeout_s: float = 10.0) -> None:
        """Switch ``group``'s drives to ``mode`` (a name of :class:`fieldbus.Mode`, e.g. "CSV", or its
        number); waits until every drive shows it. The position command restarts at the joints."""
        self.request("mode", group, argument={"mode": mode}, timeout_s=timeout_s)
        self._reseed(group)

    def sdo_read(
        self, group: str, axis: str, index: int, sub_index: int = 0, *, timeout_s: float = 5.0
    ) -> bytes:
        """Read object ``index:sub_index`` of joint ``axis`` through the served bus's cycle."""
        arg = {"axis": axis, "index": index, "sub_index": sub_index}
        detail = self.request("sdo_read", group, argument=arg, timeout_s=timeout_s) or {}
        return bytes.fromhex(str(detail.get("data", "")))

    def sdo_write(
        self, group: str, axis: str, index: int, sub_index: int, data: bytes, *, timeout_s: float = 5.0
    ) -> None:
        """Write ``data`` to object ``index:sub_index`` of joint ``axis`` (the group must be claimed)."""
        arg = {"axis": axis, "index": index, "sub_index": sub_index, "data": bytes(data).hex()}
        self.request("sdo_write", group, argument=arg, timeout_s=timeout_s)

    def _reseed(self, group: str, timeout_s: float = 2.0) -> None:
        """Take a state newer than the reply, then start the position command at the measured position."""
        g, link = self[group], self._links[group]
        seen = g.state.cycle
        end = time.monotonic() + timeout_s
        while g.state.cycle <= seen and time.monotonic() < end:
            self._ws.wait(int(0.05 * 1e9))
            for st in link.reader.take(N=8):
                if isinstance(st, m.AxisState) and st.cycle > g.state.cycle:
                    g.accept(st)
        self._hold(g)

    @staticmethod
    def _hold(g: RemoteGroup) -> None:
        """The next command holds the joints: position at the measured one, velocity and torque 0 (what the
        server applies while no command does)."""
        out, inp = g.command_channels.get("position"), g.joint_state.get("position")
        if out is not None and inp is not None:
            g.outputs.values[out] = g.inputs.values[inp]
        for role in ("velocity", "torque"):
            chan = g.command_channels.get(role)
            if chan is not None:
                g.outputs.values[chan] = 0.0

    def command_channels(self, group: str) -> dict[str, str]:
        """Which output channel each command field carries (the rest belong to the server)."""
        return dict(self[group].command_channels)

    # -- the cycle --
    def send(self) -> int:
        """Send the outputs of every claimed group as one command now, without waiting; its sequence.

        For a client that keeps its own pace (free-running): :meth:`poll` then tells which command the
        bus applied last. :meth:`exchange` is ``send`` and a wait for the state that applied it."""
        self.sequence += 1
        seq = self.sequence
        for name in self.claimed:
            g = self.groups[name]
            cmd = m.JointCommand(client_id=self.client_id, sequence=seq)
            for role, chan in g.command_channels.items():
                setattr(cmd, role, g.outputs.values[chan].astype(np.float64).tolist())
            self._links[name].writer.write(cmd)
        return seq

    def poll(self, wait_s: float = 0.0) -> int:
        """Take the states that have arrived (waiting up to ``wait_s`` seconds for one when none has): the
        inputs are the newest; returns the newest command sequence every claimed group has applied (0:
        none yet)."""
        if wait_s > 0.0:
            self._ws.wait(int(wait_s * 1e9))
        applied = []
        for name in self.claimed or self.groups:
            g = self.groups[name]
            for st in self._links[name].reader.take(N=16):
                if isinstance(st, m.AxisState) and st.cycle > g.state.cycle:
                    g.accept(st)
            applied.append(int(g.state.command_sequence))
        return min(applied) if applied else 0

    def exchange(self, deadline_s: float | None = None) -> RemoteResult:
        """Send the outputs of every claimed group as a command; wait for the state that applied it.

        Without claimed groups: wait for the next state of every group. Never
        raises for a late state: ``result.late`` (and :attr:`misses`) say so and
        the inputs keep the newest state received.
        """
        t0 = time.perf_counter_ns()
        seq = self.send()
        waiting = dict.fromkeys(self.claimed or self.groups, False)
        last_cycle = {n: self.groups[n].state.cycle for n in waiting}
        end = t0 + int((self.deadline_s if deadline_s is None else deadline_s) * 1e9)
        res = self.result
        while not all(waiting.values()):
            now = time.perf_counter_ns()
            if now >= end:
                break
            self._ws.wait(end - now)
            for name in waiting:
                for st in self._links[name].reader.take(N=8):
                    if not isinstance(st, m.AxisState):
                        continue
                    g = self.groups[name]
                    if (
                        st.cycle > g.state.cycle or st.cycle < last_cycle[name]
                    ):  # newer (or a restarted server)
                        g.accept(st)
                    if name in self.claimed:  # a latched group applies no command: its state is the answer
                        done = st.command_sequence >= seq or st.gate == GateState.SAFE_STOP
                    else:
                        done = st.cycle != last_cycle[name]
                    waiting[name] = waiting[name] or done
        res.round_trip_ns = time.perf_counter_ns() - t0
        res.late = not all(waiting.values())
        self.misses += res.late
        states = [self.groups[n].state for n in waiting]
        res.cycle = max(s.cycle for s in states)
        res.safe_stop = any(s.safe_stop for s in states)
        res.fresh = not res.late and all(s.all_fresh for s in states)
        res.gate = {n: GateState(self.groups[n].state.gate) for n in waiting}
        return res

    def _wait_first_state(self, timeout_s: float) -> None:
        end = time.monotonic() + timeout_s
        pending = set(self.groups)
        while pending and time.monotonic() < end:
            self._ws.wait(int(0.1 * 1e9))
            for name in list(pending):
                for st in self._links[name].reader.take(N=8):
                    if isinstance(st, m.AxisState):
                        self.groups[name].accept(st)
                        pending.discard(name)
        if pending:
            raise RemoteError(f"no state from group(s) {', '.join(sorted(pending))} within {timeout_s:g} s")

    def _wait_states(self, group: str, state: int, wait_s: float, *, at_most: bool = False) -> None:
        """Exchange (without claiming anything new) until every axis of ``group`` reports ``state``."""
        g = self[group]
        end = time.monotonic() + wait_s
        while time.monotonic() < end:
            self.exchange(deadline_s=0.05)
            if (
                ((g.drive_state <= state) & (g.drive_state >= 0)).all()
                if at_most
                else (g.drive_state == state).all()
            ):
                return
        raise BusTimeoutError(
            f"group '{group}' did not reach drive state {state} within {wait_s:g} s "
            f"(states {g.drive_state.tolist()})"
        )


def connect(
    namespace: str,
    *,
    domain: int | None = None,
    interface: str | None = None,
    peers: Sequence[str] = (),
    client_id: str | None = None,
    deadline_s: float = 0.1,
    timeout_s: float = 10.0,
) -> Remote:
    """Connect to the bus served under ``namespace`` (``fieldbus serve --namespace``, default the network's name).

    ``domain``, ``interface``, ``peers``: as ``fieldbus serve`` chooses them.
    ``client_id``: the name claims are made under (default a random one).
    ``deadline_s``: how long :meth:`Remote.exchange` waits for the state.
    ``timeout_s``: how long to wait for the server to answer at first.
    """
    return Remote(
        namespace,
        domain=domain,
        interface=interface,
        peers=peers,
        client_id=client_id,
        deadline_s=deadline_s,
        timeout_s=timeout_s,
    )
