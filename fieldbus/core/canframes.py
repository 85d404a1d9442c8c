"""The declarative raw-CAN family: a motor's CAN protocol described in data only (``rawcan: family: frames``).

A map of this family names a command frame and a feedback frame, each either per motor (CAN id
``id + node_id``) or shared (one frame for ``motors`` motors: motor ``node_id`` k takes the k-th slot of
``stride`` bytes, k = 1..motors), with its fields in frame order::

    rawcan:
      family: frames
      command:  {id: 0x200, motors: 2, fields: [{name: velocity, type: int, bits: 16, byte_order: little,
                                                 scale: 9.5493, unit: rad/s, safe_value: 0}]}
      feedback: {id: 0x300, motors: 2, fields: [{name: position, type: int, bits: 16, byte_order: big,
                                                 scale: 13037.97, unit: rad}]}
      enable: [0x01]       # optional byte patterns, sent on the command id (per motor: to each)
      disable: [0x00]
      zero: [0x02]
      clear: [0x03]        # clears a fault (recovery: clear, then enable)

A field: ``type`` ``uint`` / ``int`` (8, 16 or 32 bits, or a ``uint`` bit field of 1..31 bits, least
significant bit first) or ``float32``; ``byte_order`` ``little`` or ``big`` (whole-byte fields; default
the frame's ``byte_order``, else little); ``scale`` (raw counts per engineering unit) and ``offset`` (raw
at 0): ``raw = scale * value + offset``, so the image shows engineering units; ``safe_value`` (command
fields): what the safe stop sends. ``fault`` names a feedback field and its code table
(``codes: {0: ok, 3: over-current}``, ``ok: [0]``): a code outside ``ok`` is a motor fault.

The fields compile into the process image (command = outputs, feedback = inputs), so the image's
``to_wire``/``from_wire`` are the only encoders and decoders and its NaN and saturation rules hold: the
image row is the motor's slot with every big-endian field's bytes reversed (:attr:`FrameSpec.swap`),
and the frame is the slots of its motors, each the row taken through that permutation.
Semantics for the emulator (:mod:`sim_slaves.frames_motor`) come from the field names: command
``velocity`` (rad/s), ``position`` (rad), ``torque`` (N·m); feedback ``position``, ``velocity``,
``torque`` and the fault field.
"""

from __future__ import annotations

import math
import struct
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

from fieldbus.core import datatypes
from fieldbus.core.canfamily import CanFamily, FamilyMotor, Frame, FrameTime
from fieldbus.core.pdo.model import Channel, Pdo
from fieldbus.core.rawcan import field_channel
from fieldbus.core.yamlsrc import PathT

SECTION_KEYS = ("family", "command", "feedback", "enable", "disable", "zero", "clear", "fault")
FRAME_KEYS = ("id", "motors", "extended", "byte_order", "length", "fields")
FIELD_KEYS = ("name", "type", "bits", "byte_order", "scale", "offset", "unit", "safe_value", "description")
TYPES = ("uint", "int", "float32")
FD_LENGTHS = (12, 16, 20, 24, 32, 48, 64)  # CAN FD data lengths past 8 bytes
COMMAND_OBJECT, FEEDBACK_OBJECT = 0x2000, 0x2001  # pseudo object indices: the fields have no dictionary


@dataclass(frozen=True)
class FrameField:
    """One field of a frame slot: ``offset_bits`` from the slot's start (LSB-first bit numbering for
    bit fields; whole-byte fields start on a byte)."""

    name: str
    type: str
    bits: int
    offset_bits: int
    byte_order: str = "little"
    scale: float | None = None  # raw per engineering unit
    offset: float = 0.0  # raw at 0
    unit: str | None = None
    safe_value: float | None = None
    description: str = ""

    @property
    def scaled(self) -> bool:
        return self.scale is not None or self.offset != 0.0

    def pack(self, value: float) -> int:
        """The raw wire integer of ``value`` (engineering units), NaN-safe: NaN sends 0, out of range
        saturates (for frames built outside the image: safe stops, emulators)."""
        raw = value * (self.scale if self.scale is not None else 1.0) + self.offset
        if self.type == "float32":
            f = 0.0 if math.isnan(raw) else max(-3.4028234663852886e38, min(3.4028234663852886e38, raw))
            return int.from_bytes(struct.pack("<f", f), "little")
        lo, hi = (
            (-(1 << (self.bits - 1)), (1 << (self.bits - 1)) - 1)
            if self.type == "int"
            else (0, (1 << self.bits) - 1)
        )
        r = (
            0
            if math.isnan(raw)
            else max(lo, min(hi, round(raw) if math.isfinite(raw) else (hi if raw > 0 else lo)))
        )
        return r & ((1 << self.bits) - 1)

    def unpack(self, raw: int) -> float:
        """Engineering value of the wire integer ``raw``."""
        if self.type == "float32":
            x = float(struct.unpack("<f", raw.to_bytes(4, "little"))[0])
        elif self.type == "int" and raw >= 1 << (self.bits - 1):
            x = float(raw - (1 << self.bits))
        else:
            x = float(raw)
        return (x - self.offset) / (self.scale if self.scale is not None else 1.0)


@dataclass(frozen=True)
class FrameSpec:
    """A command or feedback frame: CAN id, motors per frame (1: per motor, id + node_id), slot size."""

    can_id: int
    motors: int  # 1: one frame per motor on id + node_id; > 1: one shared frame, slot k = node k
    extended: bool
    stride: int  # bytes per motor slot
    length: int  # data bytes of the frame
    fields: tuple[FrameField, ...]
    swap: tuple[int, ...]  # slot byte j travels as row byte swap[j] (big-endian fields reversed)

    @property
    def shared(self) -> bool:
        return self.motors > 1

    def frame_id(self, node: int) -> int:
        return self.can_id if self.shared else self.can_id + node

    def slot(self, node: int) -> int:
        """Byte offset of motor ``node``'s slot in its frame."""
        return (node - 1) * self.stride if self.shared else 0

    def encode(self, values: Mapping[str, float]) -> bytes:
        """One slot from engineering values with Python integers (independent of the image codec)."""
        out = bytearray(self.stride)
        for f in self.fields:
            raw = f.pack(float(values.get(f.name, 0.0)))
            if f.bits % 8 == 0 and f.offset_bits % 8 == 0:
                o, n = f.offset_bits // 8, f.bits // 8
                out[o : o + n] = raw.to_bytes(n, "big" if f.byte_order == "big" else "little")
            else:
                x = int.from_bytes(out, "little") | raw << f.offset_bits
                out[:] = x.to_bytes(self.stride, "little")
        return bytes(out)

    def decode(self, slot: bytes) -> dict[str, float]:
        """Engineering values of one slot (Python integers, independent of the image codec)."""
        values: dict[str, float] = {}
        for f in self.fields:
            if f.bits % 8 == 0 and f.offset_bits % 8 == 0:
                o, n = f.offset_bits // 8, f.bits // 8
                raw = int.from_bytes(slot[o : o + n], "big" if f.byte_order == "big" else "little")
            else:
                raw = (int.from_bytes(slot, "little") >> f.offset_bits) & ((1 << f.bits) - 1)
            values[f.name] = f.unpack(raw)
        return values


@dataclass(frozen=True)
class FramesProtocol:
    """A declarative family's protocol: its two frames, special frames and fault table."""

    command: FrameSpec
    feedback: FrameSpec
    enable: bytes | None = None
    disable: bytes | None = None
    zero: bytes | None = None
    clear: bytes | None = None
    fault_field: str | None = None
    fault_codes: tuple[tuple[int, str], ...] = ()
    ok_codes: tuple[int, ...] = (0,)

    def fault_code(self, row: Any) -> int | None:
        """The fault field's code in a feedback image row (its fields little-endian in place), or None
        when the map has no fault field."""
        if self.fault_field is None:
            return None
        f = next(g for g in self.feedback.fields if g.name == self.fault_field)
        x = int.from_bytes(bytes(row[: self.feedback.stride]), "little")
        return (x >> f.offset_bits) & ((1 << f.bits) - 1)

    def fault_name(self, code: int) -> str:
        return dict(self.fault_codes).get(code, f"code {code}")

    def safe_slot(self) -> bytes:
        """The command slot of the safe stop: every field's ``safe_value`` (0 where it has none)."""
        return self.command.encode({f.name: f.safe_value or 0.0 for f in self.command.fields})


def parse_frames(
    r: Any, m: Mapping[Any, Any], path: PathT
) -> tuple[FramesProtocol, tuple[Pdo, ...], tuple[Pdo, ...]]:
    """Validate a ``rawcan:`` section of family ``frames`` (``m``: its mapping); returns protocol, rpdo, tpdo."""
    r.mapping(m, path, SECTION_KEYS, required=("command", "feedback"))
    command = _frame(r, m["command"], (*path, "command"), outputs=True)
    feedback = _frame(r, m["feedback"], (*path, "feedback"), outputs=False)
    if not any(f.safe_value is not None for f in command.fields):
        raise r.err(
            (*path, "command", "fields"), "no command field has a safe_value: say what the safe stop sends"
        )
    special = {
        k: _pattern(r, m[k], (*path, k)) if k in m else None for k in ("enable", "disable", "zero", "clear")
    }
    fault_field: str | None = None
    codes: tuple[tuple[int, str], ...] = ()
    ok: tuple[int, ...] = (0,)
    if "fault" in m:
        fp: PathT = (*path, "fault")
        fm = r.mapping(m["fault"], fp, ("field", "codes", "ok"), required=("field",))
        fault_field = r.string(fm["field"], (*fp, "field"))
        found = next((f for f in feedback.fields if f.name == fault_field), None)
        if found is None or found.scaled or found.type != "uint" or found.bits > 16:
            raise r.err(
                (*fp, "field"), f"'{fault_field}' is not an unscaled uint feedback field of 1..16 bits"
            )
        table = r.mapping(fm.get("codes", {}), (*fp, "codes"), [k for k in fm.get("codes", {})])
        codes = tuple(
            (r.integer(k, (*fp, "codes", k), 0, 2**32 - 1), r.string(v, (*fp, "codes", k)))
            for k, v in table.items()
        )
        ok = tuple(
            r.integer(v, (*fp, "ok", i), 0, 2**32 - 1)
            for i, v in enumerate(r.sequence(fm.get("ok", [0]), (*fp, "ok")))
        )
    proto = FramesProtocol(
        command,
        feedback,
        special["enable"],
        special["disable"],
        special["zero"],
        special["clear"],
        fault_field,
        codes,
        ok,
    )
    rpdo = (Pdo(0x1600, _channels(command, COMMAND_OBJECT, outputs=True)),)
    tpdo = (Pdo(0x1A00, _channels(feedback, FEEDBACK_OBJECT, outputs=False)),)
    return proto, rpdo, tpdo


def _pattern(r: Any, raw: Any, path: PathT) -> bytes:
    items = r.sequence(raw, path)
    if not 0 < len(items) <= 8:
        raise r.err(path, f"a classic CAN frame has 1..8 bytes, not {len(items)}")
    return bytes(r.integer(v, (*path, i), 0, 255) for i, v in enumerate(items))


def _frame(r: Any, raw: Any, path: PathT, *, outputs: bool) -> FrameSpec:
    m = r.mapping(raw, path, FRAME_KEYS, required=("id", "fields"))
    extended = r.boolean(m["extended"], (*path, "extended")) if "extended" in m else False
    can_id = r.integer(m["id"], (*path, "id"), 0, 0x1FFFFFFF if extended else 0x7FF)
    motors = r.integer(m.get("motors", 1), (*path, "motors"), 1, 64)
    order = r.choice(m.get("byte_order", "little"), (*path, "byte_order"), ("little", "big"))
    fields: list[FrameField] = []
    bit = 0
    for i, item in enumerate(r.sequence(m["fields"], (*path, "fields"))):
        fp: PathT = (*path, "fields", i)
        f = r.mapping(item, fp, FIELD_KEYS, required=("name", "bits"))
        name = r.name(f["name"], (*fp, "name"))
        if any(g.name == name for g in fields):
            raise r.err((*fp, "name"), f"duplicate field name '{name}'")
        kind = r.choice(f.get("type", "uint"), (*fp, "type"), TYPES)
        bits = r.integer(f["bits"], (*fp, "bits"), 1, 32)
        whole = bits in (8, 16, 32)
        if kind == "float32" and bits != 32:
            raise r.err((*fp, "bits"), "a float32 field has 32 bits")
        if kind == "int" and not whole:
            raise r.err((*fp, "bits"), "an int field has 8, 16 or 32 bits (bit fields are uint)")
        if whole and bit % 8:
            raise r.err(
                (*fp, "bits"), f"a {bits}-bit field starts on a byte; the fields before it end at bit {bit}"
            )
        f_order = r.choice(f.get("byte_order", order), (*fp, "byte_order"), ("little", "big"))
        if f_order == "big" and not whole:
            raise r.err((*fp, "byte_order"), "a bit field is little-endian (least significant bit first)")
        scale = r.number(f["scale"], (*fp, "scale")) if "scale" in f else None
        if scale is not None and not (math.isfinite(scale) and scale != 0.0):
            raise r.err((*fp, "scale"), "scale (raw counts per unit) must be a finite non-zero number")
        offset = r.number(f["offset"], (*fp, "offset")) if "offset" in f else 0.0
        safe = r.number(f["safe_value"], (*fp, "safe_value")) if "safe_value" in f else None
        if safe is not None and not outputs:
            raise r.err((*fp, "safe_value"), "safe_value belongs to command fields (outputs)")
        unit = r.string(f["unit"], (*fp, "unit")) if "unit" in f else None
        text = r.string(f["description"], (*fp, "description")) if "description" in f else ""
        fields.append(FrameField(name, kind, bits, bit, f_order, scale, offset, unit, safe, text))
        bit += bits
    if not fields:
        raise r.err((*path, "fields"), "a frame needs at least one field")
    stride = (bit + 7) // 8
    length = r.integer(m.get("length", stride * motors), (*path, "length"), 1, 64)
    if stride * motors > length:
        raise r.err(
            (*path, "fields"),
            f"{motors} motor(s) of {stride} bytes do not fit a {length}-byte frame (classic CAN: 8 bytes)",
        )
    if length > 8 and length not in FD_LENGTHS:
        raise r.err(
            (*path, "fields") if "length" not in m else (*path, "length"),
            f"{motors} motor(s) of {stride} bytes make a {length}-byte frame: classic CAN carries 8 bytes, "
            f"CAN FD {', '.join(map(str, FD_LENGTHS))}",
        )
    swap = list(range(stride))
    for f in fields:
        if f.byte_order == "big" and f.bits > 8:
            o, n = f.offset_bits // 8, f.bits // 8
            swap[o : o + n] = range(o + n - 1, o - 1, -1)
    return FrameSpec(can_id, motors, extended, stride, length, tuple(fields), tuple(swap))


def _channels(spec: FrameSpec, obj: int, *, outputs: bool) -> tuple[Channel, ...]:
    """The image channels of one motor's slot: every field little-endian at its place (the row)."""
    chans: list[Channel] = []
    for sub, f in enumerate(spec.fields, start=1):
        aligned = f.bits in (8, 16, 32) and f.offset_bits % 8 == 0
        factor, offset = 1.0, 0.0
        if f.scaled:
            s = f.scale if f.scale is not None else 1.0
            factor, offset = (s, f.offset) if outputs else (1.0 / s, -f.offset / s)
        chans.append(
            field_channel(
                obj,
                sub,
                f.name,
                f.type,
                f.bits,
                aligned,
                factor,
                offset,
                f.unit,
                f.scaled,
                f.safe_value,
                f.description,
            )
        )
    pad = spec.stride * 8 - sum(f.bits for f in spec.fields)
    if pad:  # whole bytes per row: a gap entry fills the last one
        gap = datatypes.lookup(f"bit{pad}")
        assert gap is not None
        chans.append(Channel(index=0, sub_index=0, type=gap, name=f"_pad{obj:X}"))
    return tuple(chans)


@dataclass
class _Slot:
    motor: int  # the backend's slave index
    offset: int  # byte offset in the frame
    row: Any  # the motor's image row (numpy uint8 view): outputs for commands, receive scratch for feedback
    swap: Any  # numpy index array: slot byte j is row byte swap[j]


@dataclass
class WireFrame:
    """One frame of a cycle: id, data (written in place each cycle) and the motors' slots in it."""

    can_id: int
    extended: bool
    data: bytearray
    slots: list[_Slot]


class FramesFamily(CanFamily):
    """The declarative family's frames of one bus, sans I/O: the cycle's command frames from the image's
    output rows (:meth:`cycle`), feedback frames routed into the input rows (:meth:`route`), the special
    and safe-stop frames; a motor's ``config`` is its :class:`FramesProtocol`."""

    name = "frames"
    emulator = "sim_slaves.frames_motor:FramesMotorSimulator"

    def __init__(self, motors: Sequence[FamilyMotor]) -> None:
        import numpy as np

        super().__init__(motors)
        self._np = np
        self._commands: list[WireFrame] = []
        self.feedback: dict[tuple[int, bool], WireFrame] = {}
        self.protocols: dict[int, FramesProtocol] = {m.index: m.config for m in motors}
        by_id: dict[tuple[int, bool], WireFrame] = {}
        for m in motors:
            i, node, proto = m.index, m.node, m.config
            for spec, row, table in (
                (proto.command, m.outputs, by_id),
                (proto.feedback, m.inputs, self.feedback),
            ):
                if spec.shared and not 1 <= node <= spec.motors:
                    raise ValueError(
                        f"node_id {node} has no slot in frame 0x{spec.can_id:X} ({spec.motors} motors: 1..{spec.motors})"
                    )
                key = (spec.frame_id(node), spec.extended)
                frame = table.setdefault(key, WireFrame(key[0], key[1], bytearray(spec.length), []))
                offset = spec.slot(node)
                if any(s.offset == offset for s in frame.slots):
                    raise ValueError(f"two motors in slot {node} of frame 0x{key[0]:X}")
                frame.slots.append(_Slot(i, offset, row, np.array(spec.swap, dtype=np.intp)))
        self._commands = list(by_id.values())

    @classmethod
    def parse(cls, r: Any, raw: Any, path: PathT) -> tuple[FramesProtocol, tuple[Pdo, ...], tuple[Pdo, ...]]:
        return parse_frames(r, raw, path)

    @classmethod
    def wire_frames(cls, name: str, config: Any, node: int) -> list[FrameTime]:
        """The motor's command frame and the feedback that answers it (a shared frame is named by its id:
        it carries several motors)."""
        out: list[FrameTime] = []
        for spec, what in ((config.command, "command"), (config.feedback, "feedback")):
            cid = spec.frame_id(node)
            label = f"0x{cid:X} {what}" if spec.shared else f"{name} {what}"
            after = out[0].label if out else None
            out.append(FrameTime(cid, spec.length, label, spec.extended, after, spec.shared))
        return out

    @classmethod
    def max_motors(cls, config: Any) -> int | None:
        """The slots of a shared frame (the fewer of command and feedback); None when none is shared."""
        shared = [s.motors for s in (config.command, config.feedback) if s.shared]
        return min(shared) if shared else None

    def cycle(self) -> list[WireFrame]:
        """The cycle's command frames, their data taken from the output rows (the image's ``to_wire``)."""
        np = self._np
        for frame in self._commands:
            data = np.frombuffer(frame.data, dtype=np.uint8)
            for s in frame.slots:
                np.take(s.row, s.swap, out=data[s.offset : s.offset + len(s.swap)])
        return self._commands

    def route(self, can_id: int, extended: bool, data: bytes) -> list[int]:
        """Copy a feedback frame's slots into their motors' input rows; the motors it carried (none when
        it is not feedback or too short)."""
        frame = self.feedback.get((can_id, extended))
        if frame is None or len(data) < len(frame.data):
            return []
        np = self._np
        raw = np.frombuffer(data, dtype=np.uint8)
        for s in frame.slots:
            np.take(raw[s.offset : s.offset + len(s.swap)], s.swap, out=s.row[: len(s.swap)])
        return [s.motor for s in frame.slots]

    def carries(self, can_id: int, extended: bool, data: bytes) -> list[int]:
        frame = self.feedback.get((can_id, extended))
        if frame is None or len(data) < len(frame.data):
            return []
        return [s.motor for s in frame.slots]

    def commands(self, which: str, motor: int | None = None) -> list[Frame]:
        """The ``enable`` / ``disable`` / ``zero`` / ``clear`` pattern on each command frame whose motors have
        one (``motor``: on that motor's frame only)."""
        out = []
        for frame in self._commands:
            if motor is not None and all(s.motor != motor for s in frame.slots):
                continue
            pattern = getattr(self.protocols[frame.slots[0].motor if motor is None else motor], which)
            if pattern is not None:
                out.append((frame.can_id, frame.extended, pattern))
        return out

    def stop_frames(self) -> list[Frame]:
        """Command frames of the safe stop: every motor's slot at its fields' ``safe_value``, the rest 0
        (NaN-free: built from the map, not from the image)."""
        out = []
        for frame in self._commands:
            data = bytearray(len(frame.data))
            for s in frame.slots:
                slot = self.protocols[s.motor].safe_slot()
                data[s.offset : s.offset + len(slot)] = slot
            out.append((frame.can_id, frame.extended, bytes(data)))
        return out

    def error(self, motor: int) -> tuple[int, str | None] | None:
        """The fault field's code in the motor's input row and its name (None for an ``ok`` code)."""
        proto = self.protocols[motor]
        code = proto.fault_code(self.motors[motor].inputs)
        if code is None:
            return None
        return code, None if code in proto.ok_codes else proto.fault_name(code)
