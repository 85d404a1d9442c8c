"""Emulated motors of the declarative raw-CAN family (``rawcan: family: frames``), from the map alone.

Everything comes from the map's description (:mod:`fieldbus.core.canframes`), coded here with Python
integers (:meth:`~fieldbus.core.canframes.FrameSpec.encode` / ``decode``, not the image codec):

- a command frame (per motor on ``id + node``, or shared: motor k's slot k) sets each motor's set-point
  by its field names: ``velocity`` (rad/s, a speed loop), ``position`` (rad, a position loop under
  ``velocity`` when both are there), ``torque`` (N·m, feed-forward); the physics are
  :mod:`sim_slaves.mit_motor`'s, on the clock, followed between frames;
- each command frame is answered with the feedback frame(s) of its motors (shared: one frame with
  every motor's slot): ``position``, ``velocity``, ``torque`` and the fault field (its code), other fields 0;
  an integer field wraps as a counter does (two's complement of its bits); a shared frame is one
  device's, sent whole or not at all (a silent or dropping motor silences its frame);
- ``enable`` / ``disable`` / ``zero`` / ``clear`` (the fault) patterns on the command id: a map without ``enable`` has its motors
  enabled from power-up; enabling starts no motion (no set-point until a command);
- fault hooks: ``inject_error(node, code)`` (the motor lets go, the fault field reports ``code``),
  ``clear_error(node)``, and the base's ``drop_replies``, ``silence``, ``power_cycle``.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any

import can

from fieldbus.core.canframes import FrameSpec, FramesProtocol
from fieldbus.core.pdo.model import DriveMap
from fieldbus.platform.clock import Clock
from sim_slaves.mit_motor import Law, MitMotorSimulator, MotorState

POSITION_GAIN = 20.0  # 1/s: speed per rad of position error (position set-points)
VELOCITY_GAIN = 0.5  # N·m·s/rad: the speed loop (with friction feed-forward: no steady-state error)


class FramesMotorSimulator(MitMotorSimulator):
    """Motors ``motors = [(drive_map, node_id), ...]`` of family ``frames`` on ``bus``."""

    thread_name = "frames-motors"
    corrupts_replies = False  # its own replies: corrupt_replies() does not reach them

    def __init__(
        self,
        bus: can.BusABC,
        motors: list[tuple[DriveMap, int]],
        *,
        dt_s: float | None = None,
        log: str | Path | None = None,
        clock: Clock | Callable[[], float] | None = None,
    ) -> None:
        super().__init__(bus, [], dt_s=dt_s, log=log, clock=clock)
        self.proto: dict[int, FramesProtocol] = {}
        self.error: dict[int, int] = {}
        self.frames: list[tuple[int, bytes]] = []  # (CAN id, data) of every frame received
        self.sent: list[tuple[int, bytes]] = []  # (CAN id, data) of every feedback frame sent
        self._commands: dict[tuple[int, bool], list[int]] = {}  # command frame -> its nodes
        for drive, node in motors:
            cfg = drive.rawcan
            if cfg is None or not isinstance(cfg.protocol, FramesProtocol):
                raise ValueError(f"{drive.name} is not a declarative map (rawcan family frames)")
            proto = cfg.protocol
            self.proto[node] = proto
            self.error[node] = 0
            key = (proto.command.frame_id(node), proto.command.extended)
            self._commands.setdefault(key, []).append(node)
            st = MotorState(node, enabled=proto.enable is None)
            self._by_id[node] = (st, None, cfg)  # type: ignore[assignment]  # physics only: frames are ours

    def inject_error(self, node_id: int, code: int) -> None:
        """Motor ``node_id`` reports ``code`` in its fault field and lets go until cleared."""
        with self._lock:
            self.error[node_id] = code
            self.motor(node_id).enabled = False

    def clear_error(self, node_id: int) -> None:
        with self._lock:
            self.error[node_id] = 0

    def deliver(self, msg: can.Message) -> None:
        try:
            with self._lock:
                self._tick()
                if not msg.is_error_frame and not msg.is_remote_frame:
                    self.handle(msg)
        except Exception as exc:  # keep serving; a test reads .errors
            self.errors.append(f"{type(exc).__name__}: {exc}")

    def handle(self, msg: can.Message) -> can.Message | None:
        """One frame: a pattern or a command frame; returns the last feedback frame sent."""
        nodes = self._commands.get((msg.arbitration_id, bool(msg.is_extended_id)))
        if nodes is None:
            return None
        data = bytes(msg.data)
        self.frames.append((msg.arbitration_id, data))
        proto = self.proto[nodes[0]]
        if data in (proto.enable, proto.disable, proto.zero, proto.clear):
            for node in nodes:
                st = self.motor(node)
                if data == proto.clear:
                    self.error[node] = 0
                elif data == proto.zero:
                    st.zero += st.position
                    st.position = 0.0
                elif data == proto.enable and not self.error[node]:
                    if not st.enabled:
                        st.law = None  # enabling starts no motion
                    st.enabled = True
                elif data == proto.disable:
                    st.enabled = False
            return None
        spec = proto.command
        if len(data) < spec.length:
            return None
        for node in nodes:
            st = self.motor(node)
            o = spec.slot(node)
            st.commands += 1
            st.law = _law(spec.decode(data[o : o + spec.stride]))
        return self._send_feedback(nodes)

    def _send_feedback(self, nodes: list[int]) -> can.Message | None:
        """The feedback frames of ``nodes`` (the state when the command came: physics ran up to it). A
        shared frame is one device's: it goes out whole, or not at all when one of its motors is silent
        or drops its reply."""
        last = None
        frames: dict[tuple[int, bool], bytearray] = {}
        quiet: set[tuple[int, bool]] = set()
        for node in nodes:
            st, spec = self.motor(node), self.proto[node].feedback
            key = (spec.frame_id(node), spec.extended)
            if st.silent or st.drop:
                st.drop = max(0, st.drop - 1)
                quiet.add(key)
                continue
            data = frames.setdefault(key, bytearray(spec.length))
            slot = spec.encode(self._values(node, st, spec))
            o = spec.slot(node)
            data[o : o + len(slot)] = slot
        for (can_id, ext), data in frames.items():
            if (can_id, ext) in quiet:
                continue
            last = can.Message(arbitration_id=can_id, data=bytes(data), is_extended_id=ext)
            self.sent.append((can_id, bytes(data)))
            self.bus.send(last)
        return last

    def _values(self, node: int, st: MotorState, spec: FrameSpec) -> dict[str, float]:
        values = {"position": st.position, "velocity": st.velocity, "torque": st.torque}
        fault = self.proto[node].fault_field
        if fault is not None:
            values[fault] = self.error[node]
        for f in spec.fields:  # a counter wraps: the value modulo its raw range
            if f.type != "float32" and f.name in values and f.scale is not None:
                span = (1 << f.bits) / abs(f.scale)
                half = span / 2 if f.type == "int" else 0.0
                values[f.name] = (values[f.name] + half) % span - half
        return values


def _law(v: dict[str, Any]) -> Law:
    """The set-point of one command slot, by its field names."""
    torque = float(v.get("torque", 0.0))
    if "position" in v:
        vmax = abs(float(v["velocity"])) if "velocity" in v else float("inf")
        return Law(
            kd=VELOCITY_GAIN,
            torque=torque,
            gain=POSITION_GAIN,
            target=float(v["position"]),
            vmax=vmax,
            compensate=True,
        )
    if "velocity" in v:
        return Law(velocity=float(v["velocity"]), kd=VELOCITY_GAIN, torque=torque, compensate=True)
    return Law(torque=torque)
