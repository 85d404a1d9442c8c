"""Emulated MIT-mode motors on a python-can bus (one bus instance serves every motor).

Each motor answers every command frame addressed to it (CAN id
``command_id + node_id``) with one reply frame, as bgkatz/motorcontrol does.
Special frames: enter motor mode (FF x7 FC), exit (FD), set zero (FE).
Physics per motor: a rotor of inertia ``J`` (kg·m²) with viscous friction
``b`` (N·m·s/rad) driven by the MIT impedance law
``tau = kp*(p_des - p) + kd*(v_des - v) + tau_ff``, saturated to the torque
field's range, integrated over the time between commands (``dt_s`` if given).
Fault hooks: ``drop_replies(node, n)``, ``corrupt_replies(node, n)``,
``silence(node)`` and ``power_cycle(node)``. ``clock``: the time the motors
read when a frame has no timestamp (a :class:`~fieldbus.runtime.clock.Clock`;
default the machine's); without a thread, :meth:`MitMotorSimulator.deliver`
takes each frame (virtual time, :mod:`fieldbus.testing`). A motor answers a CAN FD command with
a CAN FD reply (bit-rate switched as the command was): the FD variants of these motors.
"""

from __future__ import annotations

import threading
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import can

from fieldbus.core.pdo.model import DriveMap
from fieldbus.runtime.clock import Clock, monotonic_s
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
        x = 0
        for name, shift, mask, lo, per_raw in self.fields:
            v = values.get(name, 0.0)
            raw = int(v) if lo is None else round((v - lo) / per_raw)
            x |= min(mask, max(0, raw)) << shift
        return x.to_bytes(self.size, "big")


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
    last_t: float | None = None
    torque_limit: float = 1e9  # N·m, the command's torque field range
    history: list[tuple[float, float]] = field(default_factory=list)
    # the last command received, in engineering units: position, velocity, kp, kd, torque (feed-forward)
    command: tuple[float, float, float, float, float] | None = None


class MitMotorSimulator(BusThread):
    """Motors with maps ``motors = [(drive_map, node_id), ...]`` on ``bus`` (python-can)."""

    thread_name = "mit-motors"

    def __init__(
        self,
        bus: can.BusABC,
        motors: list[tuple[DriveMap, int]],
        *,
        dt_s: float | None = None,
        log: str | Path | None = None,
        clock: Clock | None = None,
    ) -> None:
        self._now = monotonic_s(clock)  # seconds
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
            st.last_t = None
            st.command = None

    def serve(self, timeout: float) -> bool:
        msg = self.bus.recv(timeout=timeout)
        if msg is None:
            return False
        self.deliver(msg)
        return True

    def deliver(self, msg: can.Message) -> None:
        """One frame from the bus (the thread's :meth:`serve`, or a caller without the thread)."""
        if not msg.is_extended_id and msg.arbitration_id in self._by_id:
            try:
                with self._lock:
                    self.handle(msg)
            except Exception as exc:  # keep serving; a test reads .errors
                self.errors.append(f"{type(exc).__name__}: {exc}")

    def handle(self, msg: can.Message) -> can.Message | None:
        """Process one command frame; returns (and sends) the reply, if any.

        As a motor's firmware does, the reply carries the state measured when the
        command arrives; the command then acts for ``dt_s`` (or as long as the time since
        the command before), so a reply never tells of a time still to come.
        """
        st, (command, reply_frame), cfg = self._by_id[msg.arbitration_id]
        data = bytes(msg.data)
        now = msg.timestamp or self._now()
        new: tuple[float, float, float, float, float] | None = None  # a command to act from now on
        if data == cfg.enter:
            st.enabled = True
        elif data == cfg.exit:
            st.enabled = False
        elif data == cfg.zero:
            st.zero += st.position
            st.position = 0.0
        elif len(data) == command.size:
            v = command.decode(data)
            new = st.command = (v["position"], v["velocity"], v["kp"], v["kd"], v["torque"])
            st.commands += 1
        else:
            return None
        dt = (
            self.dt_s
            if self.dt_s is not None
            else (0.001 if st.last_t is None else min(0.01, now - st.last_t))
        )
        st.last_t = now
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
            self._step(st, *new, dt)
        return reply

    def _reply_data(self, st: MotorState, cfg: Any, frame: MitFrame) -> bytes:
        """The reply's data for motor ``st`` (a family's emulator adds its fields)."""
        values = {"position": st.position, "velocity": st.velocity, "torque": st.torque}
        if cfg.node_field:
            values[cfg.node_field] = st.node_id
        return frame.encode(values)

    @staticmethod
    def _step(
        st: MotorState, p_des: float, v_des: float, kp: float, kd: float, tau_ff: float, dt: float
    ) -> None:
        """Integrate ``dt`` s of the impedance law (semi-implicit Euler in 0.1 ms sub-steps: stiff gains
        stay stable); ``st.torque`` is the last sub-step's torque."""
        tmax, p, v = st.torque_limit, st.position, st.velocity
        if not st.enabled:
            kp = kd = tau_ff = 0.0
        n = max(1, int(dt / 1e-4))
        h = dt / n
        h_j, damp = h / st.inertia, st.friction
        t = 0.0
        for _ in range(n):
            t = kp * (p_des - p) + kd * (v_des - v) + tau_ff
            t = -tmax if t < -tmax else (tmax if t > tmax else t)
            v += h_j * (t - damp * v)
            p += h * v
        st.position, st.velocity, st.torque = p, v, t
