"""Raw-CAN motor frames (MIT-mode style actuators) described in a drive map's ``rawcan:`` section.

MIT-mode frames (bgkatz/motorcontrol, and the MIT mode of the actuators built on it) pack fields
most-significant bit first, big-endian: the 8-byte command is
``[p15-8][p7-0][v11-4][v3-0|kp11-8][kp7-0][kd11-4][kd3-0|t11-8][t7-0]``.
Reversing the frame's bytes turns that into an ordinary least-significant-bit
first layout with the fields in reverse order, so a ``rawcan`` map compiles
into the same PDO model (command = RxPDO = master outputs; reply = TxPDO =
master inputs) and uses the same vectorised process image; the backend
reverses bytes on the wire.

A field with ``min``/``max`` is a float sent as an unsigned integer over its
range: ``raw = (x - min) * steps / (max - min)`` with ``steps = 2**bits - 1``
(bgkatz's ``float_to_uint``) or ``2**bits`` (``span: power_of_two``, as some vendors'
libraries scale). That is an affine map, i.e. a ``factor``/``offset`` of the PDO model.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import replace
from typing import Any

from fieldbus.core import datatypes
from fieldbus.core.canfamily import CanFamily, ClassicSection, families
from fieldbus.core.pdo.model import Channel, Pdo
from fieldbus.core.rawcan_config import MIT_ENTER as MIT_ENTER
from fieldbus.core.rawcan_config import MIT_EXIT as MIT_EXIT
from fieldbus.core.rawcan_config import MIT_ZERO as MIT_ZERO
from fieldbus.core.rawcan_config import SECTION_FIELDS
from fieldbus.core.rawcan_config import RawCanConfig as RawCanConfig
from fieldbus.core.rawcan_config import RawCanField as RawCanField
from fieldbus.core.yamlsrc import PathT

#: The classic section's own keys; a registered family adds the key of its own part (CanFamily.section)
RAWCAN_KEYS = (
    "family", "command_id", "reply_id", "reply_id_offset", "node_field", "span", "enter", "exit", "zero",
    "command", "reply", "byte_order",
)  # fmt: skip
FAMILIES = (
    "mit",
    "frames",
)  # mit: the MIT frame alone; frames: any protocol described in data (fieldbus.core.canframes). The
# other families on the protocol (fieldbus.core.canfamily.families) are chosen from their table; the
# part of the classic section a family owns (rawcan.<CanFamily.section>) is parsed by the family.
FIELD_KEYS = ("name", "bits", "min", "max", "unit", "description", "safe_value", "type")
FIELD_TYPES = ("uint", "int", "float32")  # float32 and int: byte_order little only
# MIT-mode safe stop when the map names no safe_value: no stiffness, no damping, no torque
MIT_SAFE_FIELDS = ("kp", "kd", "torque", "t_ff", "tau", "tau_ff")
COMMAND_OBJECT = 0x2000  # pseudo object indices: the fields have no object dictionary
REPLY_OBJECT = 0x2001


def parse_rawcan(r: Any, raw: Any) -> tuple[RawCanConfig, tuple[Pdo, ...], tuple[Pdo, ...]]:
    """Validate a ``rawcan:`` section (``r`` is the map loader's Reader); returns config, rpdo, tpdo."""
    path: PathT = ("rawcan",)
    registered = families()
    name = raw.get("family", "mit") if isinstance(raw, Mapping) else None
    if isinstance(name, str) and name in registered:  # a family on the protocol (fieldbus.core.canfamily)
        proto, rpdo, tpdo = registered[name].parse(r, raw, path)
        if isinstance(proto, RawCanConfig):  # a family of the classic section (mit)
            return replace(proto, protocol=proto), rpdo, tpdo
        cfg = RawCanConfig(command=(), reply=(), enter=b"", exit=b"", zero=b"", family=name, protocol=proto)
        if name == "frames":  # its ids and patterns where the emulators and tools look for them
            cfg = replace(
                cfg, command_id=proto.command.can_id, reply_id=proto.feedback.can_id, enter=proto.enable or b"",
                exit=proto.disable or b"", zero=proto.zero or b"", frames=proto,
            )  # fmt: skip
        return cfg, rpdo, tpdo
    return parse_classic(r, raw)


def parse_classic(r: Any, raw: Any) -> tuple[RawCanConfig, tuple[Pdo, ...], tuple[Pdo, ...]]:
    """A classic ``rawcan:`` section (command and reply fields): family mit, or a registered family that
    adds its own part (:attr:`CanFamily.section <fieldbus.core.canfamily.CanFamily.section>`)."""
    path: PathT = ("rawcan",)
    registered = families()
    owners = section_owners(registered)
    m: Mapping[Any, Any] = r.mapping(raw, path, (*RAWCAN_KEYS, *owners), required=("command", "reply"))
    span = r.choice(m.get("span", "full"), (*path, "span"), ("full", "power_of_two"))
    family = r.choice(m.get("family", "mit"), (*path, "family"), (*FAMILIES, *registered))
    order = r.choice(m.get("byte_order", "big"), (*path, "byte_order"), ("big", "little"))
    kind = registered[family]
    command = _fields(r, m["command"], (*path, "command"), order, kind.max_bits)
    reply = _fields(r, m["reply"], (*path, "reply"), order, kind.max_bits, kind.tail_float32)
    for i, f in enumerate(reply):
        if f.safe_value is not None:
            raise r.err((*path, "reply", i, "safe_value"), "safe_value belongs to command fields (outputs)")
    node_field = None
    if "node_field" in m:
        node_field = r.string(m["node_field"], (*path, "node_field"))
        if node_field not in {f.name for f in reply} or any(f.scaled for f in reply if f.name == node_field):
            raise r.err((*path, "node_field"), f"'{node_field}' is not an unscaled reply field")
    command = _safe_defaults(r, command, (*path, "command"))
    sections = _own_sections(r, owners, family, ClassicSection(path, m, command, reply, order))
    if "reply_id" in m and "reply_id_offset" in m:
        raise r.err((*path, "reply_id_offset"), "give reply_id or reply_id_offset, not both", key=True)
    cfg = RawCanConfig(
        command=command,
        reply=reply,
        command_id=r.integer(m.get("command_id", 0), (*path, "command_id"), 0, 0x7FF),
        reply_id=r.integer(m["reply_id"], (*path, "reply_id"), 0, 0x7FF) if "reply_id" in m else None,
        node_field=node_field,
        span=span,
        enter=_frame(r, m.get("enter"), (*path, "enter"), MIT_ENTER),
        exit=_frame(r, m.get("exit"), (*path, "exit"), MIT_EXIT),
        zero=_frame(r, m.get("zero"), (*path, "zero"), MIT_ZERO),
        family=family,
        reply_id_offset=(
            r.integer(m["reply_id_offset"], (*path, "reply_id_offset"), 0, 0x7FF)
            if "reply_id_offset" in m
            else None
        ),
        byte_order=order,
        sections=tuple(sections.items()),
        **{key: part for key, part in sections.items() if key in SECTION_FIELDS},
    )
    little = order == "little"
    rpdo = (Pdo(0x1600, _channels(command, COMMAND_OBJECT, span, outputs=True, little=little)),)
    tpdo = (Pdo(0x1A00, _channels(reply, REPLY_OBJECT, span, outputs=False, little=little)),)
    return cfg, rpdo, tpdo


def section_owners(registered: Mapping[str, type[CanFamily]]) -> dict[str, type[CanFamily]]:
    """The registered families that own a part of the classic section, by its key. ``TypeError`` for a
    key the classic section has already or two families claim (a family's mistake, not the map's)."""
    owners: dict[str, type[CanFamily]] = {}
    for name, kind in registered.items():
        key = kind.section
        if key is None:
            continue
        if key in RAWCAN_KEYS or key in owners:
            raise TypeError(
                f"family {name}'s section '{key}' is a key of the classic section or another family's"
            )
        owners[key] = kind
    return owners


def _own_sections(
    r: Any, owners: Mapping[str, type[CanFamily]], family: str, classic: ClassicSection
) -> dict[str, Any]:
    """The family's own part of the section, parsed by the family; another family's part is refused."""
    out: dict[str, Any] = {}
    for key, kind in owners.items():
        if kind.name == family:
            out[key] = kind.parse_section(r, classic)
        elif key in classic.mapping:
            article = "an" if key[:1] in "aeiou" else "a"
            raise r.err(
                (*classic.path, key), f"{article} '{key}' section needs family: {kind.name}", key=True
            )
    return out


def _safe_defaults(r: Any, fields: tuple[RawCanField, ...], path: PathT) -> tuple[RawCanField, ...]:
    """The MIT default merged with the map's own safe values: kp, kd and torque fields go to 0 unless
    they have a ``safe_value`` of their own; other fields' ``safe_value`` is added to that, never
    instead of it. A default field whose min..max leaves out 0 needs a ``safe_value``."""
    mit = [i for i, f in enumerate(fields) if f.name in MIT_SAFE_FIELDS]
    if not mit and not any(f.safe_value is not None for f in fields):
        raise r.err(
            path,
            "no command field has a safe_value and none is named "
            f"{'/'.join(MIT_SAFE_FIELDS)}: say what the safe stop sends (safe_value on the fields)",
        )
    out = list(fields)
    for i in mit:
        f = fields[i]
        if f.safe_value is not None:
            continue
        if not _holds_zero(f):
            raise r.err(
                (*path, i),
                f"the safe stop sends {f.name} = 0 (MIT default), outside min..max ({f.min:g}..{f.max:g}): "
                "give this field a safe_value",
            )
        out[i] = replace(f, safe_value=0.0)
    return tuple(out)


def _holds_zero(f: RawCanField) -> bool:
    return f.min is None or f.max is None or f.min <= 0.0 <= f.max


def _frame(r: Any, raw: Any, path: PathT, default: bytes) -> bytes:
    if raw is None:
        return default
    items = r.sequence(raw, path)
    if not 0 < len(items) <= 8:
        raise r.err(path, f"a classic CAN frame has 1..8 bytes, not {len(items)}")
    return bytes(r.integer(v, (*path, i), 0, 255) for i, v in enumerate(items))


def _fields(
    r: Any, raw: Any, path: PathT, order: str = "big", max_bits: int = 64, float_big: bool = False
) -> tuple[RawCanField, ...]:
    out: list[RawCanField] = []
    seen: set[str] = set()
    for i, item in enumerate(r.sequence(raw, path)):
        fp: PathT = (*path, i)
        f = r.mapping(item, fp, FIELD_KEYS, required=("name", "bits"))
        name = r.name(f["name"], (*fp, "name"))
        if name in seen:
            raise r.err((*fp, "name"), f"duplicate field name '{name}'")
        seen.add(name)
        bits = r.integer(f["bits"], (*fp, "bits"), 1, 32)
        lo = r.number(f["min"], (*fp, "min")) if "min" in f else None
        hi = r.number(f["max"], (*fp, "max")) if "max" in f else None
        if (lo is None) != (hi is None):
            raise r.err(fp, "give both min and max (or neither)")
        if lo is not None and hi is not None and not hi > lo:
            raise r.err((*fp, "max"), f"max {hi:g} must be greater than min {lo:g}")
        unit = r.string(f["unit"], (*fp, "unit")) if "unit" in f else None
        safe = r.number(f["safe_value"], (*fp, "safe_value")) if "safe_value" in f else None
        kind = r.choice(f.get("type", "uint"), (*fp, "type"), FIELD_TYPES)
        big_ok = float_big and kind == "float32"  # a value computed after the frame (CanFamily.tail_float32)
        if kind != "uint" and (
            (order != "little" and not big_ok) or bits not in (8, 16, 32) or lo is not None
        ):
            raise r.err(
                (*fp, "type"), f"a {kind} field needs byte_order: little, 8/16/32 bits and no min/max"
            )
        if kind == "float32" and bits != 32:
            raise r.err((*fp, "bits"), "a float32 field has 32 bits")
        if safe is not None and lo is not None and hi is not None and not lo <= safe <= hi:
            raise r.err((*fp, "safe_value"), f"safe_value {safe:g} is outside min..max ({lo:g}..{hi:g})")
        out.append(RawCanField(name, bits, lo, hi, unit, safe, kind))
    total = sum(f.bits for f in out)
    if not out or total % 8 or total > max_bits:
        what = (
            "a classic CAN frame is 8..64 bits" if max_bits == 64 else f"the image takes 8..{max_bits} bits"
        )
        raise r.err(path, f"fields add up to {total} bits; {what} in whole bytes")
    return tuple(out)


def _channels(
    fields: tuple[RawCanField, ...], obj: int, span: str, *, outputs: bool, little: bool = False
) -> tuple[Channel, ...]:
    """PDO channels of the byte-reversed frame: fields in reverse order, LSB first (``little``: the frame
    as it is, fields in order)."""
    chans: list[Channel] = []
    bit = 0
    order = list(enumerate(fields, start=1))
    for sub, f in order if little else reversed(order):
        aligned = bit % 8 == 0 and f.bits in (8, 16, 32)
        factor, offset = 1.0, 0.0
        if f.min is not None and f.max is not None:
            steps = (1 << f.bits) - (1 if span == "full" else 0)
            per_unit = steps / (f.max - f.min)  # raw counts per engineering unit
            if outputs:  # raw = factor * value + offset
                factor, offset = per_unit, -f.min * per_unit
            else:  # value = factor * raw + offset
                factor, offset = 1.0 / per_unit, f.min
        chans.append(
            field_channel(
                obj, sub, f.name, f.type, f.bits, aligned, factor, offset, f.unit, f.scaled, f.safe_value
            )
        )
        bit += f.bits
    return tuple(chans)


def field_channel(
    obj: int,
    sub: int,
    name: str,
    kind: str,
    bits: int,
    aligned: bool,
    factor: float,
    offset: float,
    unit: str | None,
    scaled: bool,
    safe_value: float | None,
    description: str = "",
) -> Channel:
    """The image channel of a frame field: ``kind`` uint / int / float32 (``aligned``: a whole-byte
    number in the row, else a bit field), ``factor``/``offset`` as the PDO model's."""
    name_of = {"float32": "float", "int": f"int{bits}"}.get(kind, f"uint{bits}")
    dt = datatypes.lookup(name_of if aligned else f"bit{bits}")
    assert dt is not None
    return Channel(
        index=obj,
        sub_index=sub,
        type=dt,
        name=name,
        unit=unit,
        factor=factor,
        offset=offset,
        scaled=scaled,
        description=description,
        safe_value=safe_value,
    )


def encode_frame(fields: tuple[RawCanField, ...], span: str, values: Mapping[str, float]) -> bytes:
    """One frame from engineering values with Python integers (outside the cycle: safe stops, tests);
    a missing field is 0, out-of-range values saturate. The cycle uses the process image instead."""
    x = 0
    for f in fields:
        v = float(values.get(f.name, 0.0))
        mask = (1 << f.bits) - 1
        if f.min is not None and f.max is not None:
            steps = mask + (1 if span == "power_of_two" else 0)
            raw = round((v - f.min) * steps / (f.max - f.min))
        else:
            raw = int(v)
        x = (x << f.bits) | min(mask, max(0, raw))
    return x.to_bytes(sum(f.bits for f in fields) // 8, "big")
