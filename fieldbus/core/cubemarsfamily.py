"""The CubeMars AK family (``rawcan: family: cubemars``) on the family protocol (:mod:`fieldbus.core.canfamily`).

The map section is the classic ``rawcan:`` one with its ``cubemars:`` part (:mod:`fieldbus.core.cubemars`);
the packets' and the status frame's numbers are channels of the process image, so ``to_wire`` /
``from_wire`` are their only encoders and decoders:

- ``protocol: servo``: each command channel a packet takes (``from``) is one big-endian number of the
  packet's type at its scale (``raw = scale x value``: position in 1e-4 deg, ...); a channel travels in one
  type and scale in every packet that takes it. The image's ``mode_field`` names the packet a cycle sends
  (29-bit id ``packet << 8 | id``; a number that names no packet sends nothing); the status frame
  (``status_packet << 8 | id``) is the input row, each field's bytes reversed into the image's
  little-endian numbers (``value = scale x raw``).
- ``protocol: mit``: the MIT frame of :mod:`fieldbus.core.mitfamily`; replies of the reply's length or of
  ``short_reply`` bytes. The wrapping position is unwrapped into ``unwrap.into``, an int32 channel of raw
  counts at the wrapped field's scale: ``raw + turns x steps``, counted in integers.
"""

from __future__ import annotations

from collections.abc import Iterator, Sequence
from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from fieldbus.core import cubemars
from fieldbus.core.canfamily import ClassicSection, FamilyMotor, Frame, FrameTime, Request, Steps
from fieldbus.core.mitfamily import MitFamily, field_place, safe_patch
from fieldbus.core.pdo.model import Channel
from fieldbus.core.rawcan import COMMAND_OBJECT, REPLY_OBJECT, RawCanConfig, field_channel
from fieldbus.core.yamlsrc import PathT
from fieldbus.errors import FieldbusError

SERVO_CURRENT = 1  # servo packet: current loop (the stop sends 0 A)
KINDS = {"int32": ("int", 32), "int16": ("int", 16), "int8": ("int", 8), "uint8": ("uint", 8)}


@dataclass(eq=False)
class ServoFrame:
    """One servo packet of one motor: its 29-bit id and data, filled from the output row through ``take``."""

    can_id: int
    extended: bool
    data: bytearray
    take: Any  # row byte of each data byte (big-endian numbers: each field's bytes reversed)
    target: Any


@dataclass
class _Servo:
    """A servo motor: its packets by number, the mode byte's and error byte's place, the status routing."""

    frames: dict[int, ServoFrame]
    mode_at: int
    error_at: int
    status_take: Any  # row byte k = status byte status_take[k]
    status_size: int


@dataclass
class _Unwrap:
    """Multi-turn counting of an MIT reply's wrapping position, in raw counts."""

    shift: int
    mask: int
    steps: int
    total: Any  # the int32 channel's bytes in the input row, as an int32 array of 1
    turns: int = 0
    last: int | None = None

    def __call__(self, frame: int) -> None:
        raw = (frame >> self.shift) & self.mask
        if self.last is not None:
            if raw - self.last > self.steps // 2:
                self.turns -= 1
            elif self.last - raw > self.steps // 2:
                self.turns += 1
        self.last = raw
        self.total[0] = raw + self.turns * self.steps


def _swap(fields: Sequence[cubemars.ServoField]) -> list[int]:
    """Byte k of a frame of big-endian ``fields`` <-> byte ``out[k]`` of the little-endian image row."""
    out: list[int] = []
    at = 0
    for f in fields:
        n = cubemars.TYPES[f.type][1]
        out += [at + n - 1 - j for j in range(n)]
        at += n
    return out


def _packed(cfg: RawCanConfig) -> dict[str, cubemars.ServoField]:
    """Each command channel a servo packet takes, as the first packet that takes it carries it."""
    assert cfg.cubemars is not None
    out: dict[str, cubemars.ServoField] = {}
    for mode in cfg.cubemars.modes:
        for f in mode.fields:
            out.setdefault(f.channel, f)
    return out


def _row_offsets(cfg: RawCanConfig) -> dict[str, int]:
    """Byte offset of each command channel in a servo motor's output row."""
    assert cfg.cubemars is not None
    packed, out, at = _packed(cfg), {}, 0
    for f in cfg.command:
        out[f.name] = at
        p = packed.get(f.name)
        at += (
            cubemars.TYPES[p.type][1] if p is not None and f.name != cfg.cubemars.mode_field else f.bits // 8
        )
    return out


def _servo_outputs(r: Any, cfg: RawCanConfig, path: PathT) -> tuple[Channel, ...]:
    """The command channels: the mode byte, then each channel as the packets carry it."""
    assert cfg.cubemars is not None
    kinds: dict[str, cubemars.ServoField] = {}
    for mode in cfg.cubemars.modes:
        for p in mode.fields:
            seen = kinds.setdefault(p.channel, p)
            if (seen.type, seen.scale) != (p.type, p.scale):
                raise r.err(
                    (*path, "cubemars", "modes"),
                    f"'{p.channel}' travels as {seen.type} x {seen.scale:g} and {p.type} x {p.scale:g}: "
                    "give a channel one type and scale in every packet",
                )
    out: list[Channel] = []
    for sub, f in enumerate(cfg.command, start=1):
        packed = kinds.get(f.name)
        if f.name == cfg.cubemars.mode_field or packed is None:
            kind, bits, factor, scaled = f.type, f.bits, 1.0, False
        else:
            (kind, bits), factor, scaled = KINDS[packed.type], packed.scale, True
        out.append(
            field_channel(
                COMMAND_OBJECT, sub, f.name, kind, bits, True, factor, 0.0, f.unit, scaled, f.safe_value
            )
        )
    return tuple(out)


def _servo_inputs(cfg: RawCanConfig) -> tuple[Channel, ...]:
    """The status frame's fields as input channels, in frame order (``value = scale x raw``)."""
    assert cfg.cubemars is not None
    units = {f.name: f.unit for f in cfg.reply}
    return tuple(
        field_channel(
            REPLY_OBJECT,
            sub,
            f.channel,
            *KINDS[f.type],
            True,
            f.scale,
            0.0,
            units.get(f.channel),
            f.scale != 1.0,
            None,
        )
        for sub, f in enumerate(cfg.cubemars.status, start=1)
    )


def _unwrapped(cfg: RawCanConfig, channels: tuple[Channel, ...]) -> tuple[Channel, ...]:
    """The ``unwrap.into`` channel as int32 raw counts at the wrapped field's scale."""
    assert cfg.cubemars is not None and cfg.cubemars.unwrap is not None
    src, into = cfg.cubemars.unwrap
    f = next(f for f in cfg.reply if f.name == src)
    assert f.min is not None and f.max is not None
    steps = (1 << f.bits) - (1 if cfg.span == "full" else 0)
    per_raw = (f.max - f.min) / steps
    return tuple(
        field_channel(c.index, c.sub_index, c.name, "int", 32, True, per_raw, f.min, f.unit, True, None)
        if c.name == into
        else c
        for c in channels
    )


class CubemarsFamily(MitFamily):
    """The CubeMars motors of one bus (servo or MIT by each map's ``protocol``); a motor's ``config`` is
    its :class:`~fieldbus.core.rawcan.RawCanConfig` with ``cubemars`` set."""

    name = "cubemars"
    emulator = "sim_slaves.cubemars:simulator"
    section = "cubemars"
    max_bits = 256  # servo: the image holds every mode's fields; MIT: the frame plus the unwrapped position
    tail_float32 = True  # MIT: a float32 reply field after the frame holds the multi-turn position

    @classmethod
    def parse_section(cls, r: Any, classic: ClassicSection) -> Any:
        """``rawcan.cubemars``: protocol servo or mit (:func:`fieldbus.core.cubemars.parse_cubemars`)."""
        path = classic.path
        if "cubemars" not in classic.mapping:
            raise r.err(path, "family cubemars needs its 'cubemars' section (protocol servo or mit)")
        proto = cubemars.parse_cubemars(
            r, classic.mapping["cubemars"], (*path, "cubemars"), classic.command, classic.reply
        )
        if proto.protocol == "servo" and classic.byte_order != "little":
            raise r.err(path, "a CubeMars servo map's image is little-endian: give byte_order: little")
        wire = sum(f.bits for f in classic.command)
        if proto.protocol == "mit" and wire > 64:
            raise r.err(
                (*path, "command"), f"fields add up to {wire} bits; a classic CAN frame is 8..64 bits"
            )
        return proto

    def __init__(self, motors: Sequence[FamilyMotor]) -> None:
        mit = [m for m in motors if m.config.cubemars.protocol == "mit"]
        super().__init__(mit)
        self.motors = {m.index: m for m in motors}
        self._servo: dict[int, _Servo] = {}
        self._by_status: dict[int, int] = {}  # status frame id -> motor index
        self._sending: list[Any] = []
        self._lengths: dict[int, tuple[int, int]] = {}  # MIT motor -> reply lengths taken
        self._unwrap: dict[int, _Unwrap] = {}
        self._error_at: dict[int, tuple[int, int, int]] = {}
        self._safe = {m.index: safe_patch(m.config) for m in mit}
        for m in mit:
            proto: cubemars.CubemarsProtocol = m.config.cubemars
            self._lengths[m.index] = (proto.reply_bytes, proto.short_reply or proto.reply_bytes)
            self._error_at[m.index] = field_place(m.config, proto.error_field)
            if proto.unwrap is not None:
                self._unwrap[m.index] = self._unwrapper(m, proto.unwrap[0])
        for m in motors:
            proto = m.config.cubemars
            if proto.protocol != "servo":
                continue
            if not 0 <= m.node <= 0xFF:
                raise ValueError(f"{m.name}: a CubeMars motor id is 0..255")
            at = _row_offsets(m.config)
            frames = {}
            for mode in proto.modes:
                take = [at[f.channel] + b for f in mode.fields for b in range(cubemars.TYPES[f.type][1])]
                rows = np.array(take, dtype=np.intp)
                order = np.array(_swap(mode.fields), dtype=np.intp)
                data = bytearray(len(take))
                frames[mode.packet] = ServoFrame(
                    cubemars.servo_id(mode.packet, m.node),
                    True,
                    data,
                    rows[order],
                    np.frombuffer(data, np.uint8),
                )
            status = [s.channel for s in proto.status]
            size = sum(cubemars.TYPES[s.type][1] for s in proto.status)
            err = sum(cubemars.TYPES[s.type][1] for s in proto.status[: status.index(proto.error_field)])
            self._servo[m.index] = _Servo(
                frames, at[proto.mode_field], err, np.array(_swap(proto.status), dtype=np.intp), size
            )
            self._by_status[cubemars.servo_id(proto.status_packet, m.node)] = m.index

    def _unwrapper(self, m: FamilyMotor, source: str) -> _Unwrap:
        bit, bits = 0, 0
        for f in m.config.reply:
            if f.name == source:
                bits = f.bits
                break
            bit += f.bits
        wire = 8 * m.config.cubemars.reply_bytes
        steps = (1 << bits) - (1 if m.config.span == "full" else 0)
        return _Unwrap(wire - bit - bits, (1 << bits) - 1, steps, m.inputs[:4].view(np.int32))

    # -- the map ---------------------------------------------------------------------------------
    @classmethod
    def emulator_kind(cls, config: Any) -> str:
        """``cubemars-servo`` or ``cubemars-mit``: one emulator per protocol."""
        return f"{cls.name}-{config.cubemars.protocol}"

    @classmethod
    def parse(cls, r: Any, raw: Any, path: PathT) -> tuple[Any, tuple[Any, ...], tuple[Any, ...]]:
        from fieldbus.core.rawcan import parse_classic

        cfg, (rpdo,), (tpdo,) = parse_classic(r, raw)
        if cfg.cubemars is None:
            raise r.err(path, "family cubemars needs its 'cubemars' section (protocol servo or mit)")
        if cfg.cubemars.protocol == "servo":
            rpdo = replace(rpdo, channels=_servo_outputs(r, cfg, path))
            tpdo = replace(tpdo, channels=_servo_inputs(cfg))
        elif cfg.cubemars.unwrap is not None:
            tpdo = replace(tpdo, channels=_unwrapped(cfg, tpdo.channels))
        return cfg, (rpdo,), (tpdo,)

    @classmethod
    def wire_frames(cls, name: str, config: Any, node: int) -> list[FrameTime]:
        """Servo: the map's packet (29-bit) and the status frame; MIT: the command and its reply."""
        proto: cubemars.CubemarsProtocol = config.cubemars
        if proto.protocol == "mit":
            return [
                FrameTime(
                    config.command_id + node, sum(f.bits for f in config.command) // 8, f"{name} command"
                ),
                FrameTime(
                    config.reply_can_id(node), proto.reply_bytes, f"{name} reply", after=f"{name} command"
                ),
            ]
        mode = proto.mode_named(proto.mode)
        out = sum(cubemars.TYPES[f.type][1] for f in mode.fields)
        status = sum(cubemars.TYPES[f.type][1] for f in proto.status)
        return [
            FrameTime(cubemars.servo_id(mode.packet, node), out, f"{name} command", True),
            FrameTime(
                cubemars.servo_id(proto.status_packet, node), status, f"{name} reply", True, f"{name} command"
            ),
        ]

    @classmethod
    def fault_codes(cls, config: Any) -> dict[int, str] | None:
        return {code: name for code, name in config.cubemars.errors if code != 0}

    # -- the cycle -------------------------------------------------------------------------------
    def cycle(self) -> list[Any]:
        out = self._sending
        out.clear()
        out += super().cycle()
        for i, s in self._servo.items():
            row = self.motors[i].outputs
            f = s.frames.get(int(row[s.mode_at]))
            if f is not None:  # a number that names no packet: nothing sent (its status missing tells)
                np.take(row, f.take, out=f.target)
                out.append(f)
        return out

    def carries(self, can_id: int, extended: bool, data: bytes) -> list[int]:
        if extended:
            i = self._by_status.get(can_id)
            return [i] if i is not None and len(data) >= self._servo[i].status_size else []
        byte = self._node_byte.get(can_id)
        if byte is None:
            return []
        node = (data[byte] if byte < len(data) else -2) if byte >= 0 else -1
        i = self._route.get((can_id, node))
        return [i] if i is not None and len(data) in self._lengths[i] else []

    def route(self, can_id: int, extended: bool, data: bytes) -> list[int]:
        motors = self.carries(can_id, extended, data)
        for i in motors:
            raw = np.frombuffer(data, dtype=np.uint8)
            if extended:
                s = self._servo[i]
                np.take(raw, s.status_take, out=self.motors[i].inputs[: s.status_size])
                continue
            self._replies[i][: len(data)] = raw
            unwrap = self._unwrap.get(i)
            if unwrap is not None:
                unwrap(int.from_bytes(data.ljust(self._lengths[i][0], b"\0"), "big"))
        return motors

    def error(self, motor: int) -> tuple[int, str | None] | None:
        s = self._servo.get(motor)
        if s is not None:
            code = int(self.motors[motor].inputs[s.error_at])
        else:
            byte, shift, mask = self._error_at[motor]
            code = (int(self._replies[motor][byte]) >> shift) & mask
        return code, (None if code == 0 else self.motors[motor].config.cubemars.error_name(code))

    # -- transitions -----------------------------------------------------------------------------
    def commands(self, which: str, motor: int | None = None) -> list[Frame]:
        """MIT: the map's enter / exit / zero frames; servo: set origin (``zero``, temporary) only."""
        out: list[Frame] = []
        for m in self.motors.values():
            if motor is not None and m.index != motor:
                continue
            if m.index not in self._servo:
                out += super().commands(which, m.index)
            elif which == "zero":  # set origin: 0 = temporary (until power-off), no answer
                out.append((cubemars.servo_id(m.config.cubemars.origin_packet, m.node), True, b"\0"))
        return out

    def stop_frames(self) -> list[Frame]:
        """Servo: a current of 0 A; MIT: the frame sent last with kp = kd = torque = 0."""
        out: list[Frame] = []
        for frame in self._frames:
            data = bytearray(frame.data)
            i = self._route_of_command(frame.can_id)
            self._safe[i](data)
            out.append((frame.can_id, False, bytes(data)))
        for s in self._servo.values():
            off = s.frames.get(SERVO_CURRENT)
            if off is not None:
                out.append((off.can_id, True, bytes(len(off.data))))
        return out

    def _route_of_command(self, can_id: int) -> int:
        return next(m.index for m in self.motors.values() if m.config.command_id + m.node == can_id)

    def bring_up(self, which: str) -> Iterator[Request]:
        if which == "exit":
            yield from (Request(f) for f in self.stop_frames())
        if which == "enter":  # servo: the map's packet from the first cycle
            for i, s in self._servo.items():
                proto = self.motors[i].config.cubemars
                self.motors[i].outputs[s.mode_at] = proto.mode_named(proto.mode).packet
        if which == "zero":
            for unwrap in self._unwrap.values():
                unwrap.turns, unwrap.last = 0, None
        kind = {"enter": "enable", "exit": "disable"}.get(which, which)
        for m in self.motors.values():
            awaits = () if m.index in self._servo else (m.index,)
            yield from (Request(f, awaits) for f in self.commands(kind, m.index))

    def recover(self, motor: int) -> Iterator[Request]:
        """MIT: enter motor mode, answered; servo: nothing to send (no clear command)."""
        yield from (Request(f, (motor,)) for f in self.commands("enable", motor))

    def enabled(self, motor: int) -> bool:
        """A servo has no clear command: enabled again only when its code is 0 (after a power cycle)."""
        if motor not in self._servo:
            return True
        err = self.error(motor)
        return err is not None and err[0] == 0

    def set_mode(self, motor: int, name: str) -> Steps:
        """Servo: the image's mode byte names the packet ``name`` from the next cycle."""
        proto: cubemars.CubemarsProtocol = self.motors[motor].config.cubemars
        s = self._servo.get(motor)
        if s is None:
            raise FieldbusError(
                f"{self.motors[motor].name}: a CubeMars motor in MIT mode has no other mode over CAN "
                "(servo or MIT is chosen in CubeMars' tool)"
            )
        try:
            packet = proto.mode_named(name).packet
        except KeyError:
            have = ", ".join(m.name for m in proto.modes)
            raise FieldbusError(f"{self.motors[motor].name}: no mode '{name}' (have: {have})") from None
        self.motors[motor].outputs[s.mode_at] = packet
        return
        yield

    def mode(self, motor: int) -> str | None:
        s = self._servo.get(motor)
        if s is None:
            return None
        found = self.motors[motor].config.cubemars.mode_of_packet(int(self.motors[motor].outputs[s.mode_at]))
        return found.name if found is not None else None
