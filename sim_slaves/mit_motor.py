"""Emulated MIT-mode motors on a python-can bus (one bus instance serves every motor).

Each motor answers every command frame addressed to it (CAN id
``command_id + node_id``) with one reply frame, as bgkatz/motorcontrol does.
Special frames: enter motor mode (FF x7 FC), exit (FD), set zero (FE).
Physics per motor: a rotor of inertia ``J`` (kg·m²) with viscous friction
``b`` (N·m·s/rad) driven by the MIT impedance law
``tau = kp*(p_des - p) + kd*(v_des - v) + tau_ff``, saturated to the torque
field's range. Physics run on the clock: every motor follows its last set-point (a :class:`Law`) in
fixed steps of ``STEP_S`` on a grid of the clock's time, up to the time a frame arrives and, between
frames, whenever the emulator wakes (:meth:`MitMotorSimulator.idle`: its thread's wait, or a virtual
clock's watcher), so a set-point is followed after the last frame as a real motor's loop does, and a
run on a virtual clock is the same, bit for bit, every time.
Fault hooks: ``drop_replies(node, n)``, ``corrupt_replies(node, n)``,
``silence(node)`` and ``power_cycle(node)``. ``clock``: the time the motors
read (a :class:`~fieldbus.platform.clock.Clock` or a function giving seconds;
default the machine's; ``dt_s`` given: the physics' time is ``dt_s`` per command instead, for tests
without a virtual clock); without a thread, :meth:`MitMotorSimulator.deliver`
takes each frame (virtual time, :mod:`fieldbus.testing`). A motor answers a CAN FD command with
a CAN FD reply (bit-rate switched as the command was): the FD variants of these motors.
"""

from __future__ import annotations

import math
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import can

from fieldbus.core.pdo.model import DriveMap
from fieldbus.platform.clock import Clock, monotonic_s
from fieldbus.wire.canlog import LoggedBus, open_log
from sim_slaves.busthread import BusThread


class MitFrame:
    """One frame layout of a rawcan map, coded with Python integers (independent of fieldbus's image codec).

    Fields in frame order, the first in the most significant bits of the big-endian frame; a field with
    ``min``/``max`` is ``raw = rint((x - min) * steps / (max - min))`` clamped to ``0..2**bits - 1``
    (``steps``: ``2**bits - 1``, or ``2**bits`` with ``span: power_of_two``), others are plain integers.
    Decode plus encode: about 4 us per frame, against some 120 us through a one-motor ProcessImage.
    """

    def __init__(self, fields: Any, span: str) -> None:
        total = sum(f.bits for f in fields)
        self.size = total // 8
        self.fields: list[tuple[str, int, int, float | None, float]] = []  # name, shift, mask, min, unit/raw
        pos = total
        for f in fields:
            pos -= f.bits
            mask = (1 << f.bits) - 1
            if f.min is None or f.max is None:
                self.fields.append((f.name, pos, mask, None, 1.0))
            else:
                steps = mask + (1 if span == "power_of_two" else 0)
                self.fields.append((f.name, pos, mask, f.min, (f.max - f.min) / steps))

    def decode(self, data: bytes) -> dict[str, float]:
        """Engineering values (plain integers as floats) of the frame ``data``."""
        x = int.from_bytes(data, "big")
        return {
            name: float((x >> shift) & mask) if lo is None else ((x >> shift) & mask) * per_raw + lo
            for name, shift, mask, lo, per_raw in self.fields
        }

    def encode(self, values: dict[str, float]) -> bytes:
        """The frame for ``values`` (a missing field is 0; out-of-range values saturate)."""
        return self.bits(values).to_bytes(self.size, "big")

    def bits(
        self, values: dict[str, float], fields: list[tuple[str, int, int, float | None, float]] | None = None
    ) -> int:
        """The frame as an integer, of ``fields`` (default: all; a subset of :attr:`fields` leaves the
        others' bits 0) from ``values``, as :meth:`encode`."""
        x = 0
        for name, shift, mask, lo, per_raw in self.fields if fields is None else fields:
            v = values.get(name, 0.0)
            raw = int(v) if lo is None else round((v - lo) / per_raw)
            x |= (0 if raw < 0 else mask if raw > mask else raw) << shift
        return x

    def pack(self, values: Sequence[float], fields: list[tuple[str, int, int, float | None, float]]) -> int:
        """As :meth:`bits`, ``values`` given in the order of ``fields`` (no dict per frame)."""
        x = 0
        for v, (_, shift, mask, lo, per_raw) in zip(values, fields, strict=True):
            raw = int(v) if lo is None else round((v - lo) / per_raw)
            x |= (0 if raw < 0 else mask if raw > mask else raw) << shift
        return x


STEP_S = 1e-4  # s: the physics' fixed step (semi-implicit Euler; stiff MIT gains stay stable)
MAX_CATCH_UP = 100_000  # steps (10 s) at most per wake-up: a stalled emulator's step stays bounded


@dataclass(frozen=True)
class Law:
    """A motor's set-point, followed between frames: the impedance law
    ``tau = kp*(position - p) + kd*(v_des - v) + torque`` with ``v_des = velocity``, or, with a position
    loop (``gain`` > 0, 1/s), ``v_des = clamp(gain*(target - p) + velocity, ±vmax)``. ``compensate``: the
    speed loop adds the friction torque of its set-point (no steady-state speed error).
    ``torque_limit``: N·m, under the motor's own. Units rad, rad/s, N·m."""

    position: float = 0.0
    velocity: float = 0.0
    kp: float = 0.0
    kd: float = 0.0
    torque: float = 0.0
    gain: float = 0.0
    target: float = 0.0
    vmax: float = math.inf
    torque_limit: float | None = None
    compensate: bool = False


FREE = Law()  # no torque: a disabled motor coasts to rest on its friction


def seconds_of(clock: Any) -> Callable[[], float]:
    """Seconds on ``clock``: a :class:`~fieldbus.platform.clock.Clock`, a function giving seconds, or None
    (the machine's monotonic clock)."""
    if clock is None:
        return time.monotonic
    if isinstance(clock, Clock):
        return monotonic_s(clock)
    if callable(clock):
        return clock  # type: ignore[no-any-return]
    raise TypeError(f"not a clock: {clock!r}")


@dataclass
class MotorState:
    """One emulated motor. Angles in rad, speeds in rad/s, torque in N·m."""

    node_id: int
    position: float = 0.0
    velocity: float = 0.0
    torque: float = 0.0
    enabled: bool = False
    zero: float = 0.0
    inertia: float = 0.002
    friction: float = 0.01
    commands: int = 0
    drop: int = 0
    corrupt: int = 0  # replies still to send with every data bit inverted
    silent: bool = False
    step: int | None = None  # the physics' grid step (units of STEP_S on the clock) reached so far
    law: Law | None = None  # the set-point being followed (None: no torque)
    torque_limit: float = 1e9  # N·m, the command's torque field range
    history: list[tuple[float, float]] = field(default_factory=list)
    # the last command received, in engineering units: position, velocity, kp, kd, torque (feed-forward)
    command: tuple[float, float, float, float, float] | None = None


class MitMotorSimulator(BusThread):
    """Motors with maps ``motors = [(drive_map, node_id), ...]`` on ``bus`` (python-can)."""

    thread_name = "mit-motors"
    corrupts_replies = (
        True  # corrupt_replies() inverts the next replies (a subclass with its own replies: False)
    )

    def __init__(
        self,
        bus: can.BusABC,
        motors: list[tuple[DriveMap, int]],
        *,
        dt_s: float | None = None,
        log: str | Path | None = None,
        clock: Clock | Callable[[], float] | None = None,
    ) -> None:
        self._now = seconds_of(clock)  # seconds
        self.log = open_log(log)  # every frame the motors see and send, python-can format by suffix
        self.bus: Any = bus if self.log is None else LoggedBus(bus, self.log)
        self.dt_s = dt_s
        self._by_id: dict[int, tuple[MotorState, tuple[MitFrame, MitFrame], Any]] = {}
        for drive, node in motors:
            cfg = drive.rawcan
            if cfg is None:
                raise ValueError(f"{drive.name} has no rawcan section")
            frames = (MitFrame(cfg.command, cfg.span), MitFrame(cfg.reply, cfg.span))
            tmax = next((f.max for f in cfg.command if f.name == "torque" and f.max is not None), 1e9)
            self._by_id[cfg.command_id + node] = (MotorState(node, torque_limit=tmax), frames, cfg)
        super().__init__()
        self._lock = threading.Lock()  # fault hooks (test thread) against the serving thread
        self.errors: list[str] = []

    def motor(self, node_id: int) -> MotorState:
        for st, _, _ in self._by_id.values():
            if st.node_id == node_id:
                return st
        raise KeyError(node_id)

    # fault hooks
    def drop_replies(self, node_id: int, n: int) -> None:
        """The motor does not answer its next ``n`` commands (it still applies them)."""
        with self._lock:
            self.motor(node_id).drop += n

    def corrupt_replies(self, node_id: int, n: int) -> None:
        """The motor's next ``n`` replies go out with every data bit inverted (length and id intact)."""
        with self._lock:
            self.motor(node_id).corrupt += n

    def silence(self, node_id: int, silent: bool = True) -> None:
        """The motor stops (or resumes) answering; it still applies commands."""
        with self._lock:
            self.motor(node_id).silent = silent

    def power_cycle(self, node_id: int) -> None:
        """Power lost and back: out of motor mode, at rest, zero offset and faults gone (position kept)."""
        with self._lock:
            st = self.motor(node_id)
            st.enabled = False
            st.velocity = st.torque = 0.0
            st.position += st.zero
            st.zero = 0.0
            st.drop = st.corrupt = 0
            st.command, st.law = None, None

    # -- time ----------------------------------------------------------------------------------------
    def idle(self) -> None:
        """What is due without a frame: the physics up to now (and a family's timers)."""
        with self._lock:
            self._tick()

    def _tick(self) -> None:
        """Under the lock: every motor's physics up to the clock's now (a family adds its timers)."""
        self.advance(self._physics_now())

    def _physics_now(self) -> float:
        """The physics' time, s: the clock's; with ``dt_s``, ``dt_s`` per command of the most commanded
        motor (a test's deterministic pace without a virtual clock; no time passes between frames)."""
        if self.dt_s is None:
            return self._now()
        return self.dt_s * max(st.commands for st, _, _ in self._by_id.values())

    def advance(self, now: float) -> None:
        """Every motor's physics up to ``now`` (s, the emulator's clock), in whole steps of ``STEP_S``."""
        k = int(now / STEP_S + 1e-6)
        for st, _, _ in self._by_id.values():
            self._integrate(st, k)

    def _integrate(self, st: MotorState, k: int) -> None:
        """Motor ``st``'s law from its grid step to ``k`` (semi-implicit Euler; ``st.torque``: the last
        step's torque). A disabled motor gets no torque; the first call only sets the grid."""
        if st.step is None or k <= st.step:
            st.step = k if st.step is None else st.step
            return
        n, st.step = min(k - st.step, MAX_CATCH_UP), k
        law = st.law if st.enabled and st.law is not None else FREE
        if law == FREE:  # no torque: the n steps in closed form (an idle emulator costs no loop)
            a = 1.0 - STEP_S * st.friction / st.inertia  # the speed's factor per step
            an = a**n
            moved = a * (1.0 - an) / (1.0 - a) if a != 1.0 else float(n)  # sum of a**1 .. a**n
            st.position += STEP_S * st.velocity * moved
            st.velocity *= an
            st.torque = 0.0
            return
        tmax = st.torque_limit if law.torque_limit is None else min(st.torque_limit, law.torque_limit)
        p, v, t = st.position, st.velocity, 0.0
        h, h_j, damp = STEP_S, STEP_S / st.inertia, st.friction
        kp, kd, p_des, tau_ff, v_ff = law.kp, law.kd, law.position, law.torque, law.velocity
        gain, target, vmax, comp = law.gain, law.target, law.vmax, damp if law.compensate else 0.0
        for _ in range(n):
            v_des = v_ff
            if gain:
                v_des = gain * (target - p) + v_ff
                v_des = -vmax if v_des < -vmax else (vmax if v_des > vmax else v_des)
            t = kp * (p_des - p) + kd * (v_des - v) + tau_ff + comp * v_des
            t = -tmax if t < -tmax else (tmax if t > tmax else t)
            v += h_j * (t - damp * v)
            p += h * v
        st.position, st.velocity, st.torque = p, v, t

    # -- frames ---------------------------------------------------------------------------------------
    def serve(self, timeout: float) -> bool:
        msg = self.bus.recv(timeout=timeout)
        if msg is None:
            self.idle()
            return False
        self.deliver(msg)
        return True

    def deliver(self, msg: can.Message) -> None:
        """One frame from the bus (the thread's :meth:`serve`, or a caller without the thread); the
        physics first run up to now, so the reply tells the state when the frame arrived."""
        try:
            with self._lock:
                self._tick()
                if not msg.is_extended_id and msg.arbitration_id in self._by_id:
                    self.handle(msg)
        except Exception as exc:  # keep serving; a test reads .errors
            self.errors.append(f"{type(exc).__name__}: {exc}")

    def handle(self, msg: can.Message) -> can.Message | None:
        """Process one command frame; returns (and sends) the reply, if any.

        As a motor's firmware does, the reply carries the state measured when the command arrives (the
        caller ran the physics up to now); the command is followed from then on, until the next.
        """
        st, (command, reply_frame), cfg = self._by_id[msg.arbitration_id]
        data = bytes(msg.data)
        new: Law | None = None  # a set-point to follow from now on
        if data == cfg.enter:
            if not st.enabled:
                st.law = None  # enabling starts no motion: no torque until a command comes
            st.enabled = True
        elif data == cfg.exit:
            st.enabled = False
        elif data == cfg.zero:
            st.zero += st.position
            st.position = 0.0
        elif len(data) == command.size:
            v = command.decode(data)
            st.command = (v["position"], v["velocity"], v["kp"], v["kd"], v["torque"])
            new = Law(*st.command)
            st.commands += 1
        else:
            return None
        reply = None
        if st.drop:
            st.drop -= 1
        elif not st.silent:
            reply_id = cfg.reply_id if cfg.reply_id is not None else msg.arbitration_id
            data = self._reply_data(st, cfg, reply_frame)
            if st.corrupt:
                st.corrupt -= 1
                data = bytes(b ^ 0xFF for b in data)
            reply = can.Message(
                arbitration_id=reply_id,
                data=data,
                is_extended_id=False,
                is_fd=msg.is_fd,
                bitrate_switch=msg.bitrate_switch,
            )
            self.bus.send(reply)
        if new is not None:
            st.law = new
        return reply

    def _reply_data(self, st: MotorState, cfg: Any, frame: MitFrame) -> bytes:
        """The reply's data for motor ``st`` (a family's emulator adds its fields)."""
        values = {"position": st.position, "velocity": st.velocity, "torque": st.torque}
        if cfg.node_field:
            values[cfg.node_field] = st.node_id
        return frame.encode(values)
