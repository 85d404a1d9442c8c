"""Emulated Damiao DM-J motors on a python-can bus: registers, modes, ids, CAN timeout and error codes.

The rotor physics are :class:`sim_slaves.mit_motor.MitMotorSimulator`'s (inherited, not copied); what
is Damiao's comes from the drive map's ``rawcan.damiao`` section (:mod:`fieldbus.core.damiao`):

- commands on ESC_ID (the node id) + the mode's offset; a frame of a mode other than CTRL_MODE's is
  ignored (no reply), as the firmware does; each command is answered on MST_ID (register 7) with
  byte 0 = error << 4 | id, position, velocity, torque, MOS and rotor temperature (°C);
- enable / disable / set zero / clear error: seven 0xFF then FC / FD / FE / FB on ESC_ID;
- registers on 0x7FF ``[id lo, id hi, op, register, value LE]``: read (0x33) and write (0x55) are
  answered with the same layout on MST_ID, save (0xAA) only while disabled, refresh (0xCC) answers a
  status frame; an unknown register is not answered;
- modes: MIT (impedance law), position-velocity and position-force (a position loop of
  ``POSITION_GAIN`` 1/s under the speed limit; position-force also limits the torque to its per-unit
  current of TMAX), velocity (a velocity loop of ``VELOCITY_GAIN`` N·m·s/rad);
- TIMEOUT (register 9, units of 50 us, 0: off): an enabled motor with no command for that long
  reports 0xD (communication lost) and lets go; errors stay until the clear-error frame;
- ``inject_error(node, code)`` puts a motor in any error (it lets go, as the firmware does).

Time: ``clock`` (seconds, default :func:`time.monotonic`) decides the CAN timeout and runs the physics
(as in the MIT emulator: the mode's set-point is followed between frames, on the clock), so a test can
run it in virtual time. The speed loop of the non-MIT modes adds the friction torque of its set-point,
so a speed is reached without steady-state error.
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import can

from fieldbus.core import damiao
from fieldbus.core.pdo.model import DriveMap
from fieldbus.platform.clock import Clock
from sim_slaves.mit_motor import Law, MitFrame, MitMotorSimulator, MotorState

POSITION_GAIN = 20.0  # 1/s: speed command per rad of position error (position modes)
VELOCITY_GAIN = 0.5  # N·m·s/rad: torque per rad/s of speed error (velocity loop of the non-MIT modes)
COMM_LOST = 0xD
ENABLED, DISABLED = 0x1, 0x0
# registers held as floats (the others are uint32): UV, KT, OT, OC, ACC, DEC, MAX_SPD, limits, loop gains...
FLOAT_REGISTERS = frozenset({0, 1, 2, 3, 4, 5, 6, 11, 12, 17, 18, 19, 20, *range(21, 35)})
READ_ONLY = frozenset({11, 12, 13, 14, 15, 16, 17, 18, 19, 20, 36})
ROTOR_FIELDS = ("position", "velocity", "torque")  # the status reply's fields that change every frame
TIMEOUT_MARGIN_S = 1e-6  # the timeout check looks this much early (the bound's rounding, never late)
SPECIAL_PREFIX = b"\xff" * 7  # enable / disable / zero / clear: seven 0xFF, then the code
FRAMES_KEPT = 1000  # frames a motor keeps (DamiaoState.frames): a long run's memory stays bounded


@dataclass
class DamiaoState:
    """What a Damiao motor has beyond the rotor: registers (4 raw bytes each), error code, mode command."""

    registers: dict[int, bytes]
    error: int = DISABLED  # reply code: 0 disabled, 1 enabled, 8.. faults
    last_command_t: float | None = None
    mode_command: tuple[str, dict[str, float]] | None = None  # the last non-MIT command, by mode name
    t_mos: float = 30.0  # °C
    t_rotor: float = 32.0
    saves: int = 0
    # (CAN id, data) of the frames received, the last FRAMES_KEPT
    frames: deque[tuple[int, bytes]] = field(default_factory=lambda: deque(maxlen=FRAMES_KEPT))

    def reg(self, number: int) -> float:
        return damiao.unpack_register(self.registers[number], number in FLOAT_REGISTERS)


# a command CAN id's node, mode, protocol, rawcan section, rotor, state and MIT command layout
Route = tuple[int, damiao.Mode, damiao.DamiaoProtocol, Any, MotorState, DamiaoState, MitFrame]


class DamiaoSimulator(MitMotorSimulator):
    """Damiao motors ``motors = [(drive_map, node_id), ...]`` on ``bus``; ``registers`` overrides
    a motor's register values at power-up: ``{node_id: {register: value}}``."""

    corrupts_replies = False  # its own replies: corrupt_replies() does not reach them

    thread_name = "damiao-motors"

    def __init__(
        self,
        bus: can.BusABC,
        motors: list[tuple[DriveMap, int]],
        *,
        dt_s: float | None = None,
        log: str | Path | None = None,
        clock: Clock | Callable[[], float] | None = None,
        registers: dict[int, dict[int, float]] | None = None,
    ) -> None:
        super().__init__(bus, motors, dt_s=dt_s, log=log, clock=clock)
        self.clock = self._now
        self.state: dict[int, DamiaoState] = {}
        self._esc: dict[int, int] = {}  # ESC_ID -> node
        self._proto: dict[int, tuple[damiao.DamiaoProtocol, Any]] = {}
        for drive, node in motors:
            cfg = drive.rawcan
            if cfg is None or cfg.damiao is None:
                raise ValueError(f"{drive.name} is not a Damiao map (rawcan family damiao)")
            proto, regs = cfg.damiao, cfg.damiao.registers
            values: dict[int, float] = {
                0: 10.0, 1: 0.1, 2: 120.0, 3: 0.98, 4: 30.0, 5: -30.0, 6: 30.0,
                regs.master_id: cfg.reply_can_id(node), 8: node, regs.timeout: 0, regs.ctrl_mode: 1,
                13: 1, 14: 5013, 16: 14, 20: 10.0, 35: 4, 24: 1000.0, 25: 0.001, 26: 0.002, 27: 30.0,
                28: 0.0, 29: 30.0, 30: 0.9, 31: 5.0, 32: 100.0, 33: 1000.0, 34: 1000.0,
            }  # fmt: skip
            values.update({reg: limit for _, reg, limit in proto.limits})
            values.update((registers or {}).get(node, {}))
            self.state[node] = DamiaoState(
                {k: damiao.pack_register(v, k in FLOAT_REGISTERS) for k, v in values.items()}
            )
            self._esc[node] = node
            self._proto[node] = (proto, cfg)
        self._boot = {n: dict(ds.registers) for n, ds in self.state.items()}  # registers at power-up
        # a command's CAN id -> (node, mode): one look-up per frame, not a search over nodes and modes
        self._register_id = next(iter(self._proto.values()))[0].registers.can_id  # 0x7FF, every motor's
        self._motors = {node: self.motor(node) for node in self.state}  # node -> its rotor, per frame
        self._commands = {
            node + mode.id_offset: (node, mode)
            for node, (proto, _) in self._proto.items()
            for mode in proto.modes
        }
        self._mit = {node: self._by_id[node + cfg.command_id][1][0] for node, (_, cfg) in self._proto.items()}
        self._tmax = {  # the MIT frame's torque range per node: a position-force frame's current limit base
            node: next(f.max for f in cfg.command if f.name == "torque")
            for node, (_, cfg) in self._proto.items()
        }
        # node -> (TIMEOUT in s, MST_ID, CTRL_MODE): decoded when written, not per frame
        self._fixed: dict[int, tuple[float, int, int]] = {}
        self._timeout_due = -math.inf  # clock time before which no motor's TIMEOUT can have elapsed
        for node in self.state:
            self._refresh(node)
        # the status reply per node: its frame, the rotor's fields (every reply) and the others (error
        # field name, fields: encoded once per change of the error code or a temperature)
        self._status_frame: dict[int, tuple[MitFrame, Any, tuple[str, Any]]] = {}
        for node, (proto, cfg) in self._proto.items():
            frame = self._by_id[node + cfg.command_id][1][1]
            rotor = [next(f for f in frame.fields if f[0] == name) for name in ROTOR_FIELDS]  # in order
            rest = [f for f in frame.fields if f[0] not in ROTOR_FIELDS]
            self._status_frame[node] = (frame, rotor, (proto.error_field, rest))
        self._status_rest: dict[int, tuple[tuple[int, float, float], int]] = {}
        self._maxima = {
            node: {f.name: f.max for f in cfg.command if f.max is not None}
            for node, (_, cfg) in self._proto.items()
        }
        # a command's CAN id -> what its frame needs: node, mode, protocol, rawcan section, rotor, state
        # and the MIT command's layout (one look-up per frame)
        self._routes: dict[int, Route] = {
            can_id: (node, mode, *self._proto[node], self._motors[node], self.state[node], self._mit[node])
            for can_id, (node, mode) in self._commands.items()
        }
        self._fd = (False, False)  # the last frame's (CAN FD, bit-rate switch): its reply's
        self._tick_s = -math.inf  # the clock at the last tick (s): a command's arrival time

    # -- fault hooks -------------------------------------------------------------------------------
    def inject_error(self, node_id: int, code: int) -> None:
        """Motor ``node_id`` reports ``code`` (e.g. 0x8 over-voltage) and lets go until cleared."""
        with self._lock:
            self.state[node_id].error = code
            self.motor(node_id).enabled = False

    def power_cycle(self, node_id: int) -> None:
        """Power lost and back: the rotor's reset, registers as at power-up (RAM writes lost), disabled."""
        super().power_cycle(node_id)
        with self._lock:
            ds = self.state[node_id]
            ds.registers = dict(self._boot[node_id])
            ds.error, ds.last_command_t, ds.mode_command = DISABLED, None, None
            self._refresh(node_id)

    def set_temperatures(self, node_id: int, mos: float, rotor: float) -> None:
        with self._lock:
            st = self.state[node_id]
            st.t_mos, st.t_rotor = mos, rotor

    def _tick(self) -> None:
        """The physics and the CAN timeouts up to now, on one reading of the clock."""
        now = self._tick_s = self.clock()
        self.advance(now if self.dt_s is None else self._physics_now())
        if now >= self._timeout_due:
            self.check_timeouts(now)

    def _refresh(self, node: int) -> None:
        """The registers every frame reads (TIMEOUT, MST_ID, CTRL_MODE), decoded once after each write."""
        ds, regs = self.state[node], self._proto[node][0].registers
        timeout, mst, mode = (int(ds.reg(r)) for r in (regs.timeout, regs.master_id, regs.ctrl_mode))
        self._fixed[node] = (timeout * 50e-6, mst, mode)
        self._timeout_due = -math.inf  # a TIMEOUT written: the next tick looks at every motor

    def check_timeouts(self, now: float | None = None) -> None:
        """Every enabled motor whose TIMEOUT elapsed since its last command: error 0xD, torque off.

        Before ``_timeout_due`` (the earliest such time seen at the last look, a little early) none can
        have elapsed: commands only move a motor's time later; enabling a motor or writing TIMEOUT makes
        the next tick look again. ``now``: the clock's time (s; default: read it)."""
        now = self.clock() if now is None else now
        if now < self._timeout_due:
            return
        due = math.inf
        for node, ds in self.state.items():
            limit = self._fixed[node][0]
            last = ds.last_command_t
            if limit and ds.error == ENABLED and last is not None:
                if now - last > limit:
                    ds.error = COMM_LOST
                    self._motors[node].enabled = False
                else:
                    due = min(due, last + limit - TIMEOUT_MARGIN_S)
        self._timeout_due = due

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

    def handle(self, msg: can.Message) -> can.Message | None:
        """One frame: a register request, a special frame or a command of some mode; returns the reply sent.
        The caller ticks first (:meth:`serve`, :meth:`deliver`): a command arrives at that tick's time."""
        can_id, data = msg.arbitration_id, bytes(msg.data)
        self._fd = (bool(msg.is_fd), bool(msg.bitrate_switch))  # a CAN FD variant answers in FD
        route = self._routes.get(can_id)
        if route is None:
            return self._register(data) if can_id == self._register_id else None
        route[5].frames.append((can_id, data))
        return self._command(route, data)

    def _reply(self, node: int, data: bytes) -> can.Message:
        fd, brs = self._fd
        reply = can.Message(
            arbitration_id=self._fixed[node][1], data=data, is_extended_id=False, is_fd=fd, bitrate_switch=brs
        )
        self.bus.send(reply)
        return reply

    def _status(self, node: int) -> can.Message | None:
        return self._status_of(node, self._motors[node], self.state[node])

    def _status_of(self, node: int, st: MotorState, ds: DamiaoState) -> can.Message | None:
        """Motor ``node``'s status reply (rotor ``st``, state ``ds``), sent unless dropped or silenced."""
        if st.drop:
            st.drop -= 1
            return None
        if st.silent:
            return None
        frame, rotor, rest = self._status_frame[node]
        key = (ds.error, ds.t_mos, ds.t_rotor)
        cached = self._status_rest.get(node)
        if cached is None or cached[0] != key:  # error code, temperatures, id: encoded when they change
            values = {"t_mos": ds.t_mos, "t_rotor": ds.t_rotor, "motor_id": node & 0xF, rest[0]: ds.error}
            cached = self._status_rest[node] = (key, frame.bits(values, rest[1]))
        x = cached[1] | frame.pack((st.position, st.velocity, st.torque), rotor)
        return self._reply(node, x.to_bytes(frame.size, "big"))

    def _register(self, data: bytes) -> can.Message | None:
        if len(data) != 8:
            return None
        node = self._esc.get(data[0] | data[1] << 8)
        if node is None:
            return None
        proto, _ = self._proto[node]
        regs, ds, op, number = proto.registers, self.state[node], data[2], data[3]
        if op == regs.refresh:
            return self._status(node)
        if op == regs.save:
            if ds.error == ENABLED:
                return None  # the firmware saves only while the motor is disabled
            ds.saves += 1
            return self._reply(node, data[:4] + bytes([1, 0, 0, 0]))
        if number not in ds.registers:
            return None
        if op == regs.write and number not in READ_ONLY:
            ds.registers[number] = data[4:8]
            self._refresh(node)
            return self._reply(node, data[:4] + ds.registers[number])
        if op == regs.read:
            return self._reply(node, data[:4] + ds.registers[number])
        return None

    def _command(self, route: Route, data: bytes) -> can.Message | None:
        node, mode, proto, cfg, st, ds, frame = route
        now = self._tick_s  # the frame's arrival: the tick before it
        if mode.mit and data[:7] == SPECIAL_PREFIX and len(data) == 8:
            if data == cfg.enter:
                if ds.error in (ENABLED, DISABLED):
                    if not st.enabled:
                        st.law = None  # enabling starts no motion: no torque until a command comes
                    ds.error, st.enabled = ENABLED, True
                    ds.last_command_t = now
                    self._timeout_due = -math.inf  # an enabled motor more to watch
            elif data == cfg.exit:
                if ds.error == ENABLED:
                    ds.error = DISABLED
                st.enabled = False
            elif data == cfg.zero:
                st.zero += st.position
                st.position = 0.0
            elif data == proto.clear and ds.error not in (ENABLED, DISABLED):
                ds.error = DISABLED
            return self._status_of(node, st, ds)
        if self._fixed[node][2] != mode.ctrl_mode:
            return None  # not the mode the motor is in: ignored
        ds.last_command_t = now
        st.commands += 1
        if mode.mit:
            v = frame.decode(data)
            st.command = (v["position"], v["velocity"], v["kp"], v["kd"], v["torque"])
            reply = self._status_of(node, st, ds)
            st.law = Law(*st.command)
            return reply
        v = damiao.decode_mode(mode, data, self._maxima[node])
        ds.mode_command = (mode.name, v)
        reply = self._status_of(node, st, ds)
        limit = (
            v.get("torque", self._tmax[node]) if mode.fields[-1].per_unit else None
        )  # position-force: its share
        if "position" in v:  # position loop under the speed limit
            vmax = abs(v.get("velocity", 0.0))
            st.law = Law(
                kd=VELOCITY_GAIN,
                gain=POSITION_GAIN,
                target=v["position"],
                vmax=vmax,
                torque_limit=limit,
                compensate=True,
            )
        else:
            st.law = Law(velocity=v.get("velocity", 0.0), kd=VELOCITY_GAIN, compensate=True)
        return reply
