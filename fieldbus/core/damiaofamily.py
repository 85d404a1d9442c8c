"""The Damiao DM-J family (``rawcan: family: damiao``) on the family protocol (:mod:`fieldbus.core.canfamily`).

The map section is the classic ``rawcan:`` one with its ``damiao:`` part (:mod:`fieldbus.core.damiao`).
Every mode's command fields are channels of the process image, so the image's ``to_wire`` is their only
encoder (NaN keeps the value sent last, out of range saturates, S11): the MIT frame's fields under their
own names (``position``, ``velocity``, ``kp``, ``kd``, ``torque``), then each other mode's fields as
``<mode>.<field>`` (float64 engineering values in the image, as the MIT frame's; on the wire
little-endian in frame order), e.g. ``position_velocity.position`` (float32, rad),
``position_velocity.velocity`` (float32, rad/s, the speed limit), ``velocity.velocity`` (float32, rad/s),
``position_force.position`` / ``.velocity`` (uint16, x 100) / ``.torque`` (uint16, per unit of TMAX x
10000). A uint16 field is a magnitude (a limit): its window is 0..max. Each takes its unit, its window
and its safe value from the MIT field it is ``from`` (speed and torque 0: the safe stop holds).

One cycle sends each motor one frame: its mode's wire bytes on ``node + id_offset`` (zero-padded to 8
bytes), and awaits its status reply on MST_ID (``node + reply_id_offset``). Bring-up
(:meth:`DamiaoFamily.configure`) is a generator of register requests and their answers: MST_ID checked,
PMAX/VMAX/TMAX compared with the map, CTRL_MODE and TIMEOUT written and read back. The reply's error
nibble outside ``ok_codes`` is a named fault; recovery is the clear-error frame, then enable, both
answered, the code then 1 (enabled).
"""

from __future__ import annotations

from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, replace
from typing import Any, ClassVar

import numpy as np

from fieldbus.core import damiao, damiao_registers
from fieldbus.core.canfamily import ClassicSection, FamilyMotor, Frame, FrameTime, Request, Steps
from fieldbus.core.mitfamily import MitFamily, field_place, safe_patch
from fieldbus.core.pdo.model import Channel
from fieldbus.core.rawcan import COMMAND_OBJECT, RawCanConfig, field_channel
from fieldbus.core.yamlsrc import PathT
from fieldbus.errors import BusTimeoutError, FieldbusError, StateTransitionError

REGISTER_TIMEOUT_S = 0.2  # a register answer (bring-up, mode switches; never in the cycle)
SAVE_REGISTER = 1  # the register byte of a save request (the damiao-motor package's store_parameters)
FRAME_BYTES = 8  # every command frame is zero-padded to 8 data bytes
ENABLED = 1  # the reply's code of an enabled motor


def mode_channel(mode: str, source: str) -> str:
    """The image channel of mode ``mode``'s field taken from MIT field ``source``."""
    return f"{mode}.{source}"


def mode_windows(cfg: RawCanConfig) -> list[tuple[str, float, float]]:
    """``(channel, min, max)`` of every mode field: the MIT field's range (a uint16 magnitude: 0..max)."""
    assert cfg.damiao is not None
    by_name = {f.name: f for f in cfg.command}
    out = []
    for mode in cfg.damiao.modes:
        for f in mode.fields:
            src = by_name[f.source]
            if src.min is None or src.max is None:
                continue
            lo = 0.0 if f.type == "uint16" else src.min
            out.append((mode_channel(mode.name, f.source), lo, src.max))
    return out


def _mode_channels(cfg: RawCanConfig) -> tuple[Channel, ...]:
    """The image channels of the non-MIT modes' fields, after the MIT frame's (raw = factor x value)."""
    assert cfg.damiao is not None
    by_name = {f.name: f for f in cfg.command}
    out: list[Channel] = []
    sub = len(cfg.command)
    for mode in cfg.damiao.modes:
        for f in mode.fields:
            src = by_name[f.source]
            factor = f.scale / src.max if f.per_unit and src.max else f.scale
            kind, bits = {"float32": ("float32", 32), "uint16": ("uint", 16), "int16": ("int", 16)}[f.type]
            sub += 1
            name = mode_channel(mode.name, f.source)
            # every one scaled, float32 too (factor 1): the image holds them as float64 engineering values
            # beside the MIT frame's, so the output rules see one block and the C codec writes the wire
            out.append(
                field_channel(
                    COMMAND_OBJECT, sub, name, kind, bits, True, factor, 0.0, src.unit, True, src.safe_value
                )
            )
    return tuple(out)


@dataclass
class DamiaoFrame:
    """A motor's command frame of the cycle: id and data rewritten from its mode's image bytes."""

    can_id: int
    extended: bool
    data: bytearray


@dataclass
class _ModeWire:
    """Where mode ``mode``'s frame comes from: ``source`` (its bytes in the output row, frame order) into
    ``target`` (the first bytes of the frame), and the safe stop's patches ``(offset, bytes)``."""

    mode: damiao.Mode
    can_id: int
    source: Any
    target: Any
    safe: Callable[[bytearray], None]


class DamiaoFamily(MitFamily):
    """The Damiao motors of one bus; a motor's ``config`` is its :class:`~fieldbus.core.rawcan.RawCanConfig`
    (with its :class:`~fieldbus.core.damiao.DamiaoProtocol` as ``damiao``)."""

    name = "damiao"
    emulator = "sim_slaves.damiao:DamiaoSimulator"
    register_table: ClassVar[Any] = damiao_registers
    section = "damiao"

    @classmethod
    def parse_section(cls, r: Any, classic: ClassicSection) -> Any:
        """``rawcan.damiao``: modes, registers, errors (:func:`fieldbus.core.damiao.parse_damiao`)."""
        if "damiao" not in classic.mapping:
            raise r.err(classic.path, "family damiao needs its 'damiao' section (modes, registers, errors)")
        path = (*classic.path, "damiao")
        return damiao.parse_damiao(r, classic.mapping["damiao"], path, classic.command, classic.reply)

    def __init__(self, motors: Sequence[FamilyMotor]) -> None:
        super().__init__(motors)
        self._frames = []  # the MIT family's, replaced: one frame per motor, its id following the mode
        self._wire: dict[int, dict[str, _ModeWire]] = {}
        self._mode: dict[int, _ModeWire] = {}
        self._frame_of: dict[int, DamiaoFrame] = {}
        self._error_at: dict[int, tuple[int, int, int]] = {}
        self._fault_names: dict[int, dict[int, str]] = {}  # per motor: the map's error codes by name
        self._cycle: list[tuple[DamiaoFrame, Any]] = []  # per motor: frame, its mode (kept current)
        for m in motors:
            cfg: RawCanConfig = m.config
            proto = cfg.damiao
            if proto is None:
                raise ValueError(f"motor {m.name or m.node}: family damiao needs the map's damiao section")
            frame = DamiaoFrame(m.node, False, bytearray(FRAME_BYTES))
            data = np.frombuffer(frame.data, dtype=np.uint8)
            mit_bytes = sum(f.bits for f in cfg.command) // 8
            wires: dict[str, _ModeWire] = {}
            at = mit_bytes
            for mode in proto.modes:
                if mode.mit:
                    mit = m.outputs[:mit_bytes]
                    src = mit if cfg.byte_order == "little" else mit[::-1]
                    wires[mode.name] = _ModeWire(
                        mode, m.node + mode.id_offset, src, data[:mit_bytes], safe_patch(cfg)
                    )
                    continue
                n = sum(damiao.MODE_TYPES[f.type][1] for f in mode.fields)
                wires[mode.name] = _ModeWire(
                    mode, m.node + mode.id_offset, m.outputs[at : at + n], data[:n], _mode_safe(cfg, mode)
                )
                at += n
            self._wire[m.index] = wires
            self._frame_of[m.index] = frame
            self._frames.append(frame)  # type: ignore[arg-type]
            self._error_at[m.index] = field_place(cfg, proto.error_field)
            self._fault_names[m.index] = dict(proto.errors)
            self._select(m.index, proto.mode)

    # -- the map ---------------------------------------------------------------------------------
    @classmethod
    def parse(cls, r: Any, raw: Any, path: PathT) -> tuple[Any, tuple[Any, ...], tuple[Any, ...]]:
        """The classic section (family damiao); the modes' fields appended to the command's channels."""
        from fieldbus.core.rawcan import parse_classic

        cfg, rpdo, tpdo = parse_classic(r, raw)
        if cfg.damiao is None:
            raise r.err(path, "family damiao needs its 'damiao' section (modes, registers, errors)")
        (command,) = rpdo
        return cfg, (replace(command, channels=(*command.channels, *_mode_channels(cfg))),), tpdo

    @classmethod
    def fault_codes(cls, config: Any) -> dict[int, str] | None:
        """The reply's error codes outside ``ok_codes`` (the states disabled, enabled)."""
        proto = config.damiao
        return {code: name for code, name in proto.errors if code not in proto.ok_codes}

    @classmethod
    def max_motors(cls, config: Any) -> int | None:
        """Replies come on id + ``reply_id_offset`` (MST_ID): ids 1 .. offset - 1 keep clear of them."""
        offset = config.reply_id_offset
        return offset - 1 if offset else None

    @classmethod
    def command_limits(cls, config: Any) -> list[tuple[str, float, float]]:
        return mode_windows(config)

    @classmethod
    def wire_frames(cls, name: str, config: Any, node: int, mode: str | None = None) -> list[FrameTime]:
        """The command of ``mode`` (default: the map's, written to CTRL_MODE at bring-up) on ``node +
        id_offset``, 8 bytes, and its 8-byte status reply on MST_ID."""
        proto = config.damiao
        m = proto.mode_named(mode or proto.mode)
        command = FrameTime(node + m.id_offset, FRAME_BYTES, f"{name} {m.name} command")
        reply = FrameTime(config.reply_can_id(node), 8, f"{name} reply", after=command.label)
        return [command, reply]

    # -- the cycle -------------------------------------------------------------------------------
    def _select(self, motor: int, name: str) -> None:
        wire = self._wire[motor][name]
        self._mode[motor] = wire
        frame = self._frame_of[motor]
        frame.can_id = wire.can_id
        frame.data[:] = bytes(FRAME_BYTES)
        np.copyto(wire.target, wire.source)

    def cycle(self) -> list[DamiaoFrame]:  # type: ignore[override]
        for w in self._mode.values():
            np.copyto(w.target, w.source)
        return self._frames  # type: ignore[return-value]

    def stop_frames(self) -> list[Frame]:
        """Each motor's frame in its mode with the map's safe values (MIT: kp = kd = torque = 0; speed and
        current limits 0); the position is the one sent last (the frame's bytes, never the image's)."""
        out: list[Frame] = []
        for i, w in self._mode.items():
            data = bytearray(self._frame_of[i].data)
            w.safe(data)
            out.append((w.can_id, False, bytes(data)))
        return out

    def error(self, motor: int) -> tuple[int, str | None] | None:
        byte, shift, mask = self._error_at[motor]
        code = (int(self._replies[motor][byte]) >> shift) & mask
        proto = self.motors[motor].config.damiao
        if code in proto.ok_codes:
            return code, None
        name = self._fault_names[motor].get(code)  # every cycle while a motor is in fault: no dict built
        return code, (name if name is not None else proto.error_name(code))

    # -- transitions -----------------------------------------------------------------------------
    def commands(self, which: str, motor: int | None = None) -> list[Frame]:
        if which != "clear":
            return super().commands(which, motor)
        return [
            (m.config.command_id + m.node, False, m.config.damiao.clear)
            for m in self.motors.values()
            if motor is None or m.index == motor
        ]

    def bring_up(self, which: str) -> Iterator[Request]:
        """Enter / exit / zero / clear: the frame to each motor, its status reply awaited; exit sends the
        safe stop frames first."""
        if which == "exit":
            yield from (Request(f) for f in self.stop_frames())
        kind = {"enter": "enable", "exit": "disable"}.get(which, which)
        for m in self.motors.values():
            yield from (Request(f, (m.index,)) for f in self.commands(kind, m.index))

    def clear(self, motor: int) -> Iterator[Request]:
        yield from (Request(f, (motor,)) for f in self.commands("clear", motor))

    def recover(self, motor: int) -> Iterator[Request]:
        """The clear-error frame, then enable, each answered by a status reply."""
        for kind in ("clear", "enable"):
            yield from (Request(f, (motor,)) for f in self.commands(kind, motor))

    def enabled(self, motor: int) -> bool:
        err = self.error(motor)
        return err is not None and err[0] == ENABLED

    # -- registers and modes (outside the cycle) ---------------------------------------------------
    def register(self, motor: int, number: int, value: float | None = None, is_float: bool = False) -> Steps:
        """Read (``value`` None) or write a register; returns the value the motor answers."""
        regs = self.motors[motor].config.damiao.registers
        if value is None:
            op, data = regs.read, bytes(4)
        else:
            op, data = regs.write, damiao.pack_register(value, is_float)
        what = f"{'read' if value is None else 'write'} of register {number}"
        got = yield from self._request(motor, op, number, data, what)
        return damiao.unpack_register(got, is_float)

    def save(self, motor: int) -> Steps:
        """Store the registers to flash (op save); the motor answers only while disabled."""
        regs = self.motors[motor].config.damiao.registers
        what = "save to flash (a motor saves only while disabled)"
        yield from self._request(motor, regs.save, SAVE_REGISTER, bytes(4), what)

    def _request(self, motor: int, op: int, number: int, data: bytes, what: str) -> Steps:
        m = self.motors[motor]
        regs = m.config.damiao.registers
        reply_id = m.config.reply_can_id(m.node)

        def answers(can_id: int, extended: bool, got: bytes) -> bool:
            if extended or can_id != reply_id:
                return False
            found = damiao.register_reply(m.node, got, (op,))
            return found is not None and found[1] == number

        frame = (regs.can_id, False, damiao.register_frame(m.node, op, number, data))
        # unanswered: the backend names the motor (awaits) and the request (what) and ends the transaction
        answer = yield Request(frame, (motor,), answers, timeout_s=REGISTER_TIMEOUT_S, what=f"the {what}")
        if answer is None:  # a runner that sends None back instead
            raise BusTimeoutError(
                f"{m.name} (node {m.node}) did not answer the {what} within {REGISTER_TIMEOUT_S * 1000:.0f} ms"
            )
        return bytes(answer[4:8])

    def _write_checked(self, motor: int, name: str, number: int, value: float) -> Steps:
        yield from self.register(motor, number, value)
        back = yield from self.register(motor, number)
        if back != value:
            m = self.motors[motor]
            raise StateTransitionError(
                f"{m.name} register {name} ({number}) reads back {back:g} after writing {value:g}",
                slave=m.name,
            )

    def configure(self) -> Steps:
        """Per motor: MST_ID checked; PMAX/VMAX/TMAX compared with the map; CTRL_MODE and TIMEOUT written
        and read back."""
        for i, m in self.motors.items():
            cfg: RawCanConfig = m.config
            proto = cfg.damiao
            assert proto is not None
            regs, node, want_id = proto.registers, m.node, cfg.reply_can_id(m.node)
            mst = yield from self.register(i, regs.master_id)
            if int(mst) != want_id:
                raise StateTransitionError(
                    f"{m.name} (node {node}) answers with MST_ID (register {regs.master_id}) = 0x{int(mst):X}; "
                    f"its map expects 0x{want_id:X}",
                    slave=m.name,
                )
            for reg_name, reg, want in proto.limits:
                have = yield from self.register(i, reg, is_float=True)
                if have != damiao.float32(want):
                    raise StateTransitionError(
                        f"{m.name} (node {node}) has {reg_name} (register {reg}) = {have:g}, the map says "
                        f"{want:g}: the MIT frame would be scaled wrongly; set the motor's register (Damiao "
                        "tool) or use the map of this motor",
                        slave=m.name,
                    )
            yield from self._write_checked(i, "CTRL_MODE", regs.ctrl_mode, self._mode[i].mode.ctrl_mode)
            yield from self._write_checked(i, "TIMEOUT", regs.timeout, proto.timeout_units)

    def set_mode(self, motor: int, name: str) -> Steps:
        """CTRL_MODE written and read back, then the motor's frames go out in mode ``name``."""
        wires = self._wire[motor]
        if name not in wires:
            raise FieldbusError(f"{self.motors[motor].name}: no mode '{name}' (have: {', '.join(wires)})")
        regs = self.motors[motor].config.damiao.registers
        yield from self._write_checked(motor, "CTRL_MODE", regs.ctrl_mode, wires[name].mode.ctrl_mode)
        self._select(motor, name)

    def mode(self, motor: int) -> str | None:
        return self._mode[motor].mode.name


def _mode_safe(cfg: RawCanConfig, mode: damiao.Mode) -> Callable[[bytearray], None]:
    """Puts the safe values into a mode frame (each field from the MIT field's ``safe_value``)."""
    by_name = {f.name: f for f in cfg.command}
    patches: list[tuple[int, bytes]] = []
    at = 0
    for f in mode.fields:
        size = damiao.MODE_TYPES[f.type][1]
        safe = by_name[f.source].safe_value
        if safe is not None:
            maxima = {f.source: by_name[f.source].max or 1.0}
            patches.append((at, damiao.encode_fields((f,), {f.source: safe}, maxima, size)))
        at += size

    def put(data: bytearray) -> None:
        for offset, raw in patches:
            data[offset : offset + len(raw)] = raw

    return put
