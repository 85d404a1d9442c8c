"""Emulated CubeMars AK motors on a python-can bus: servo mode (29-bit ids, status frames) and MIT mode.

The rotor physics are :class:`sim_slaves.mit_motor.MitMotorSimulator`'s (inherited, not copied); what is
CubeMars' comes from the drive map's ``rawcan.cubemars`` section (:mod:`fieldbus.core.cubemars`):

- :class:`CubemarsServoSimulator` (``protocol: servo``): a packet on ``packet << 8 | id`` (extended id)
  sets what the motor does until the next one: duty (torque ``duty * STALL_TORQUE`` less a back-EMF term
  reaching 0 at ``NO_LOAD_SPEED``), current (torque ``KT * A``), current brake (holds the position where
  braking began with at most ``KT * A``), speed (a velocity loop of ``VELOCITY_GAIN``), position (a
  position loop of ``POSITION_GAIN`` under the manual's default speed, 12,000 erpm) and position-speed (the
  same under the packet's speed limit), set origin (position 0 here). Each packet is answered with a status
  frame on ``status_packet << 8 | id`` (the real firmware uploads at the rate set in CubeMars' tool; this
  emulator as a firmware set to answer every command).
- :class:`CubemarsMitSimulator` (``protocol: mit``): the MIT emulator with CubeMars' reply: the position
  counter wraps at ±PMAX, temperature + 40 and error code in bytes 6-7, or 6-byte replies
  (``short_replies``) as older firmware sends.

``inject_error(node, code)`` puts a motor in a fault (it lets go, as the firmware does). A CAN FD command is
answered in CAN FD.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import can

from fieldbus.core import cubemars
from fieldbus.core.pdo.model import DriveMap
from fieldbus.platform.clock import Clock
from sim_slaves.mit_motor import Law, MitFrame, MitMotorSimulator, MotorState

KT = 0.091 * 9  # N·m/A at the output: AK80-9's Kt 0.091 times its 9:1 gear (TMotorCANControl servo_can.py)
TORQUE_LIMIT = 18.0  # N·m, AK80-9 peak torque (the manual's MIT limits table)
STALL_TORQUE = 18.0  # N·m at duty 1 and standstill (an emulator's choice)
NO_LOAD_SPEED = 25.0  # rad/s at duty 1 (an emulator's choice)
POSITION_GAIN = 20.0  # 1/s: speed command per rad of position error (position modes)
VELOCITY_GAIN = 2.0  # N·m·s/rad: torque per rad/s of speed error
BRAKE_GAIN = 200.0  # N·m/rad, the current brake's stiffness (limited to KT x the brake current)
DEFAULT_SPEED = 12000 / (21 * 9) * 2 * math.pi / 60  # rad/s: the manual's default 12,000 erpm, AK80-9


class CubemarsServoSimulator(MitMotorSimulator):
    """CubeMars motors in servo mode ``motors = [(drive_map, node_id), ...]`` on ``bus``."""

    thread_name = "cubemars-servo"
    corrupts_replies = False  # its own replies: corrupt_replies() does not reach them

    def __init__(
        self,
        bus: can.BusABC,
        motors: list[tuple[DriveMap, int]],
        *,
        dt_s: float | None = None,
        log: str | Path | None = None,
        clock: Clock | None = None,
    ) -> None:
        super().__init__(bus, motors, dt_s=dt_s, log=log, clock=clock)
        self.proto: dict[int, cubemars.CubemarsProtocol] = {}
        self.error: dict[int, int] = {}
        self.temperature: dict[int, float] = {}
        self.packets: dict[int, list[tuple[int, bytes]]] = {}  # per node: (packet, data) of every command
        self._hold: dict[int, float] = {}  # brake: the position braking began at
        for drive, node in motors:
            cfg = drive.rawcan
            if cfg is None or cfg.cubemars is None or cfg.cubemars.protocol != "servo":
                raise ValueError(f"{drive.name} is not a CubeMars servo map (rawcan family cubemars)")
            self.proto[node] = cfg.cubemars
            self.error[node], self.temperature[node], self.packets[node] = 0, 30.0, []
            st = self.motor(node)
            st.enabled, st.torque_limit = True, TORQUE_LIMIT

    def inject_error(self, node_id: int, code: int) -> None:
        """Motor ``node_id`` reports ``code`` (e.g. 2 over-current) in its status frames and lets go."""
        with self._lock:
            self.error[node_id] = code
            self.motor(node_id).enabled = False

    def power_cycle(self, node_id: int) -> None:
        """Power lost and back: the rotor's reset, no error, and (servo mode) running again at once."""
        super().power_cycle(node_id)
        with self._lock:
            self.error[node_id] = 0
            self.motor(node_id).enabled = True
            self._hold.pop(node_id, None)

    def deliver(self, msg: can.Message) -> None:
        try:
            with self._lock:
                self._tick()
                if (
                    msg.is_extended_id
                    and not msg.is_remote_frame
                    and (msg.arbitration_id & 0xFF) in self.proto
                ):
                    self.handle(msg)
        except Exception as exc:  # keep serving; a test reads .errors
            self.errors.append(f"{type(exc).__name__}: {exc}")

    def handle(self, msg: can.Message) -> can.Message | None:
        """One servo packet: answered with a status frame (returned), then followed until the next."""
        node, packet, data = msg.arbitration_id & 0xFF, msg.arbitration_id >> 8, bytes(msg.data)
        proto, st = self.proto[node], self.motor(node)
        self.packets[node].append((packet, data))
        if packet == proto.origin_packet:
            st.zero += st.position
            st.position = 0.0
            return self._status(node, st, msg)
        mode = proto.mode_of_packet(packet)
        if mode is None or len(data) < sum(cubemars.TYPES[f.type][1] for f in mode.fields):
            return None
        v = cubemars.decode_command(mode.fields, data)
        st.commands += 1
        reply = self._status(node, st, msg)
        if packet != 2:
            self._hold.pop(node, None)
        st.law = self._law(node, st, packet, v)
        return reply

    def _law(self, node: int, st: MotorState, packet: int, v: dict[str, float]) -> Law:
        """The packet's control law (the MIT law with the packet's gains)."""
        if packet == 0:  # duty: a voltage; the torque falls with speed (back-EMF)
            duty = max(-1.0, min(1.0, v["duty"]))
            return Law(kd=STALL_TORQUE / NO_LOAD_SPEED, torque=duty * STALL_TORQUE)
        if packet == 1:
            return Law(torque=KT * v["current"])
        if packet == 2:
            hold = self._hold.setdefault(node, st.position)
            limit = KT * abs(v["brake_current"])
            return Law(position=hold, kp=BRAKE_GAIN, kd=VELOCITY_GAIN, torque_limit=limit)
        if packet == 3:
            return Law(velocity=v["velocity"], kd=VELOCITY_GAIN)
        # position (4), position-speed (6): a position loop under a speed limit
        vmax = abs(v["speed_limit"]) if "speed_limit" in v else DEFAULT_SPEED
        return Law(kd=VELOCITY_GAIN, gain=POSITION_GAIN, target=v["position"], vmax=vmax)

    def _status(self, node: int, st: MotorState, cmd: can.Message) -> can.Message | None:
        if st.drop:
            st.drop -= 1
            return None
        if st.silent:
            return None
        proto = self.proto[node]
        values = {
            "position": st.position,
            "velocity": st.velocity,
            "current": st.torque / KT,
            "temperature": self.temperature[node],
            proto.error_field: float(self.error[node]),
        }
        reply = can.Message(
            arbitration_id=cubemars.servo_id(proto.status_packet, node),
            data=cubemars.encode_status(proto.status, values),
            is_extended_id=True,
            is_fd=cmd.is_fd,
            bitrate_switch=cmd.bitrate_switch,
        )
        self.bus.send(reply)
        return reply


class CubemarsMitSimulator(MitMotorSimulator):
    """CubeMars motors in MIT mode; ``short_replies``: answer with the first 6 bytes (older firmware)."""

    thread_name = "cubemars-mit"

    def __init__(
        self,
        bus: can.BusABC,
        motors: list[tuple[DriveMap, int]],
        *,
        dt_s: float | None = None,
        log: str | Path | None = None,
        clock: Clock | None = None,
        short_replies: bool = False,
    ) -> None:
        super().__init__(bus, motors, dt_s=dt_s, log=log, clock=clock)
        self.short_replies = short_replies
        self.error: dict[int, int] = {}
        self.temperature: dict[int, float] = {}
        for key, (st, (command, _), cfg) in list(self._by_id.items()):
            proto = cfg.cubemars
            if proto is None or proto.protocol != "mit":
                raise ValueError(f"map with command id 0x{key:X} is not a CubeMars MIT map (family cubemars)")
            wire = tuple(f for f in cfg.reply if proto.unwrap is None or f.name != proto.unwrap[1])
            self._by_id[key] = (st, (command, MitFrame(wire, cfg.span)), cfg)
            self.error[st.node_id], self.temperature[st.node_id] = 0, 30.0

    def inject_error(self, node_id: int, code: int) -> None:
        """Motor ``node_id`` reports ``code`` in its replies and lets go."""
        with self._lock:
            self.error[node_id] = code
            self.motor(node_id).enabled = False

    def power_cycle(self, node_id: int) -> None:
        """Power lost and back: the rotor's reset (out of motor mode), no error."""
        super().power_cycle(node_id)
        with self._lock:
            self.error[node_id] = 0

    def _reply_data(self, st: MotorState, cfg: Any, frame: MitFrame) -> bytes:
        """CubeMars' reply: the position counter wraps at ±PMAX; temperature and error code follow."""
        pos = next(f for f in cfg.reply if f.name == "position")
        assert pos.min is not None and pos.max is not None
        span = pos.max - pos.min
        wrapped = (st.position - pos.min) % span + pos.min
        values = {"position": wrapped, "velocity": st.velocity, "torque": st.torque}
        values.update(temperature=self.temperature[st.node_id], error=float(self.error[st.node_id]))
        if cfg.node_field:
            values[cfg.node_field] = st.node_id
        data = frame.encode(values)
        proto = cfg.cubemars
        return data[: proto.short_reply] if self.short_replies and proto.short_reply else data


def simulator(
    bus: can.BusABC,
    motors: list[tuple[DriveMap, int]],
    *,
    dt_s: float | None = None,
    log: str | Path | None = None,
    clock: Clock | None = None,
) -> MitMotorSimulator:
    """The emulator of family ``cubemars`` (its ``emulator``): servo or MIT by the maps' ``protocol``."""
    cfg = motors[0][0].rawcan if motors else None
    servo = cfg is not None and cfg.cubemars is not None and cfg.cubemars.protocol == "servo"
    kind = CubemarsServoSimulator if servo else CubemarsMitSimulator
    return kind(bus, motors, dt_s=dt_s, log=log, clock=clock)
