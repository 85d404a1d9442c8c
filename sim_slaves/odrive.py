"""Emulated ODrive controllers speaking CANSimple on a python-can bus (one bus instance serves every axis).

The rotor physics are :class:`sim_slaves.mit_motor.MitMotorSimulator`'s (inherited, not copied; the
rotor's state is in rad there, CANSimple speaks turns); what is ODrive's comes from the drive map's
``rawcan.odrive`` section (:mod:`fieldbus.core.odrive`):

- ids ``node << 5 | command``; Set_Axis_State (IDLE lets go, CLOSED_LOOP_CONTROL holds, refused while an
  error is set), Set_Controller_Mode, Set_Input_Pos / Vel / Torque (the one of the current control mode
  acts, as the firmware's controller does), Clear_Errors, Reboot (back to IDLE, errors gone);
- remote frames ask for Get_Encoder_Estimates (turns, turn/s), the heartbeat or (0.6) Get_Error;
- RxSdo (0.6): endpoints held as 4 bytes, answered with TxSdo; ``watchdog=(timeout, enable)`` names the
  endpoints of ``axis0.config.watchdog_timeout`` (float32 s) and ``enable_watchdog`` (bool) of the firmware
  being emulated, else ``watchdog_ms`` sets it;
- a heartbeat every ``heartbeat_ms`` of ``clock`` (the map's rate unless given), and one at once when the
  axis state changes (an emulator convenience: a test's virtual clock need not run for a state change);
- a set-point carrying a NaN or infinite float32 is refused (counted in ``AxisState.refused``): the
  rotor keeps its state and the watchdog is not fed;
- the watchdog: an axis in closed loop whose last set-point is older than the timeout sets
  WATCHDOG_TIMER_EXPIRED and goes IDLE; ``inject_error(node, bits)`` sets any error (IDLE too).

Control in closed loop: position mode ``v = POSITION_GAIN * (p_set - p) + v_ff`` then the velocity loop
``t = VELOCITY_GAIN * (v - v_est) + t_ff``; velocity mode the velocity loop; torque mode the torque; the
set-point is followed on ``clock`` until the next (the physics of :mod:`sim_slaves.mit_motor`); arming
holds no set-point (no torque) until one comes.
"""

from __future__ import annotations

import math
import struct
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import can

from fieldbus.core import odrive
from fieldbus.core.pdo.model import DriveMap
from fieldbus.platform.clock import Clock
from sim_slaves.mit_motor import Law, MitMotorSimulator

POSITION_GAIN = 20.0  # (turn/s) per turn of position error
VELOCITY_GAIN = 1.0  # N·m per rad/s of speed error
TURN = 2.0 * math.pi  # rad per turn
WATCHDOG = "WATCHDOG_TIMER_EXPIRED"


@dataclass
class AxisState:
    """What an ODrive axis has beyond the rotor."""

    state: int = 1  # 1 IDLE, 8 CLOSED_LOOP_CONTROL
    error: int = 0  # axis error bits (the heartbeat's)
    disarm_reason: int = 0
    control_mode: int = 3
    input_mode: int = 1
    setpoint: dict[int, dict[str, float]] = field(default_factory=dict)  # by command id
    last_setpoint_t: float | None = None
    last_heartbeat_t: float | None = None
    endpoints: dict[int, bytes] = field(default_factory=dict)
    watchdog_s: float = 0.0
    frames: list[tuple[int, bytes, bool]] = field(default_factory=list)  # (command id, data, remote)
    reboots: int = 0
    refused: int = 0  # set-points refused for a NaN or infinite number (they feed neither rotor nor watchdog)


class OdriveSimulator(MitMotorSimulator):
    """ODrive axes ``motors = [(drive_map, node_id), ...]`` on ``bus``."""

    thread_name = "odrive-axes"
    corrupts_replies = False  # its own replies: corrupt_replies() does not reach them

    def __init__(
        self,
        bus: can.BusABC,
        motors: list[tuple[DriveMap, int]],
        *,
        dt_s: float | None = None,
        log: str | Path | None = None,
        clock: Clock | Callable[[], float] | None = None,
        heartbeat_ms: float | None = None,
        watchdog_ms: float = 0.0,
        watchdog: tuple[int, int] | None = None,
    ) -> None:
        super().__init__(bus, motors, dt_s=dt_s, log=log, clock=clock)
        self.clock = self._now
        self.axes: dict[int, AxisState] = {}
        self._proto: dict[int, odrive.OdriveProtocol] = {}
        self._watchdog_ep = watchdog
        self._hb_s: dict[int, float] = {}
        for drive, node in motors:
            cfg = drive.rawcan
            if cfg is None or cfg.odrive is None:
                raise ValueError(f"{drive.name} is not an ODrive map (rawcan family odrive)")
            self._proto[node] = cfg.odrive
            ax = AxisState(watchdog_s=watchdog_ms / 1000)
            ax.control_mode = cfg.odrive.mode_named(cfg.odrive.mode).control_mode
            if watchdog is not None:
                ax.endpoints[watchdog[0]] = struct.pack("<f", 0.0)
                ax.endpoints[watchdog[1]] = struct.pack("<I", 0)
            self.axes[node] = ax
            self._hb_s[node] = (cfg.odrive.heartbeat_ms if heartbeat_ms is None else heartbeat_ms) / 1000

    # -- fault hooks -------------------------------------------------------------------------------
    def inject_error(self, node_id: int, bits: int) -> None:
        """Axis ``node_id`` sets error ``bits`` and goes IDLE (the next heartbeat tells)."""
        with self._lock:
            ax = self.axes[node_id]
            ax.error |= bits
            ax.disarm_reason = bits
            self._set_state(node_id, self._proto[node_id].idle)

    def power_cycle(self, node_id: int) -> None:
        """Power lost and back: the rotor's reset, errors gone, IDLE in the map's control mode (a heartbeat)."""
        super().power_cycle(node_id)
        with self._lock:
            ax, proto = self.axes[node_id], self._proto[node_id]
            ax.error = ax.disarm_reason = 0
            ax.setpoint.clear()
            ax.last_setpoint_t = None
            ax.control_mode = proto.mode_named(proto.mode).control_mode
            self._set_state(node_id, proto.idle)

    def _tick(self) -> None:
        super()._tick()
        self.check_timers()

    def check_timers(self) -> None:
        """Watchdogs, then the heartbeats that are due."""
        now = self.clock()
        for node, ax in self.axes.items():
            proto = self._proto[node]
            if (
                ax.state == proto.closed_loop
                and self._watchdog(ax) > 0
                and ax.last_setpoint_t is not None
                and now - ax.last_setpoint_t > self._watchdog(ax)
            ):
                ax.error |= next(bit for bit, name in proto.errors if name == WATCHDOG)
                self._set_state(node, proto.idle)
            if ax.last_heartbeat_t is None or now - ax.last_heartbeat_t >= self._hb_s[node]:
                self._heartbeat(node)

    def _watchdog(self, ax: AxisState) -> float:
        if self._watchdog_ep is None:
            return ax.watchdog_s
        timeout_ep, enable_ep = self._watchdog_ep
        if not struct.unpack("<I", ax.endpoints[enable_ep])[0]:
            return 0.0
        return float(struct.unpack("<f", ax.endpoints[timeout_ep])[0])

    # -- serving -----------------------------------------------------------------------------------
    def serve(self, timeout: float) -> bool:
        msg = self.bus.recv(timeout=timeout)
        with self._lock:
            self._tick()
            if msg is None:
                return False
            if not msg.is_extended_id and not msg.is_error_frame:
                try:
                    self.handle(msg)
                except Exception as exc:  # keep serving; a test reads .errors
                    self.errors.append(f"{type(exc).__name__}: {exc}")
        return True

    def _send(self, node: int, command: str, data: bytes) -> can.Message:
        msg = can.Message(
            arbitration_id=self._proto[node].can_id(node, command), data=data, is_extended_id=False
        )
        self.bus.send(msg)
        return msg

    def _heartbeat(self, node: int) -> None:
        ax = self.axes[node]
        ax.last_heartbeat_t = self.clock()
        if not self.motor(node).silent:
            self._send(node, "heartbeat", odrive.heartbeat_frame(ax.error, ax.state))

    def _set_state(self, node: int, state: int) -> None:
        ax, proto = self.axes[node], self._proto[node]
        if state == proto.closed_loop and ax.error:
            return  # the firmware refuses to arm with an error set
        changed = state != ax.state
        ax.state = state
        st = self.motor(node)
        st.enabled = state == proto.closed_loop
        if st.enabled:
            ax.last_setpoint_t = self.clock()
            ax.setpoint.clear()
        if changed:
            st.law = None  # arming (or letting go) holds no set-point: no torque until one comes
        if changed:
            self._heartbeat(node)

    def handle(self, msg: can.Message) -> can.Message | None:
        """One frame addressed to an axis; returns the answer sent, if any."""
        node, cmd = msg.arbitration_id >> 5, msg.arbitration_id & 0x1F
        proto = self._proto.get(node)
        if proto is None:
            return None
        ax, st = self.axes[node], self.motor(node)
        data = bytes(msg.data)
        ax.frames.append((cmd, data, bool(msg.is_remote_frame)))
        c = proto.commands
        if msg.is_remote_frame:
            if cmd == c["get_encoder_estimates"]:
                if st.drop:
                    st.drop -= 1
                    return None
                if st.silent:
                    return None
                return self._send(
                    node, "get_encoder_estimates", struct.pack("<ff", st.position / TURN, st.velocity / TURN)
                )
            if cmd == c["heartbeat"]:
                self._heartbeat(node)
            elif cmd == c.get("get_error"):
                return self._send(node, "get_error", struct.pack("<II", ax.error, ax.disarm_reason))
            return None
        if cmd == c["set_axis_state"] and len(data) >= 4:
            self._set_state(node, struct.unpack_from("<I", data)[0])
        elif cmd == c["set_controller_mode"] and len(data) == 8:
            ax.control_mode, ax.input_mode = struct.unpack("<II", data)
        elif cmd == c["clear_errors"]:
            ax.error = ax.disarm_reason = 0
        elif cmd == c["reboot"]:
            ax.reboots += 1
            ax.error = ax.disarm_reason = 0
            self._set_state(node, proto.idle)
        elif cmd == c.get("rxsdo") and len(data) == 8:
            opcode, endpoint = data[0], struct.unpack_from("<H", data, 1)[0]
            if endpoint not in ax.endpoints:
                return None
            if opcode == odrive.SDO_WRITE:
                ax.endpoints[endpoint] = data[4:8]
                return None
            return self._send(node, "txsdo", bytes([0]) + data[1:3] + bytes([0]) + ax.endpoints[endpoint])
        else:
            for mode in proto.modes:
                if cmd == mode.command:
                    self._setpoint(node, mode, data)
        return None

    def _setpoint(self, node: int, mode: odrive.OdriveMode, data: bytes) -> None:
        """A set-point feeds the watchdog; the one of the active control mode is followed from now on."""
        ax, st = self.axes[node], self.motor(node)
        values = odrive.decode_setpoint(mode, data)
        if not all(math.isfinite(v) for v in values.values()):
            ax.refused += 1  # a NaN or infinite set-point: refused, the rotor's state never turns NaN
            return
        ax.setpoint[mode.command] = values
        ax.last_setpoint_t = self.clock()
        st.commands += 1
        if ax.state != self._proto[node].closed_loop or mode.control_mode != ax.control_mode:
            return
        v_ff, t_ff = values.get("velocity", 0.0), values.get("torque", 0.0)
        if mode.control_mode == 3:  # position
            target = values.get("position", 0.0) * TURN
            st.law = Law(
                velocity=v_ff * TURN, kd=VELOCITY_GAIN, torque=t_ff, gain=POSITION_GAIN, target=target
            )
        elif mode.control_mode == 2:  # velocity
            st.law = Law(velocity=v_ff * TURN, kd=VELOCITY_GAIN, torque=t_ff)
        else:  # torque
            st.law = Law(torque=t_ff)

    def endpoint(self, node: int, endpoint: int, fmt: str = "<f") -> Any:
        """An endpoint's value as the axis holds it (``fmt``: struct format)."""
        return struct.unpack(fmt, self.axes[node].endpoints[endpoint])[0]
