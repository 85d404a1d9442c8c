"""Damiao DM-J motors on raw CAN: the family's protocol as data (a drive map's ``rawcan.damiao``) and its codec.

Pure: no I/O. The facts the maps declare (cited in ``docs/can-actuators.md``):

- commands go to the motor's CAN id (ESC_ID, register 8) plus a mode offset: MIT at +0x000 (the MIT
  frame of :mod:`fieldbus.core.rawcan`), position-velocity at +0x100 (two float32: position rad,
  speed limit rad/s), velocity at +0x200 (one float32, rad/s), position-force at +0x300 (float32
  position, uint16 speed limit x 100, uint16 current per-unit x 10000); numbers little-endian;
- replies come on the master id (MST_ID, register 7), byte 0 = error code << 4 | id;
- registers on CAN id 0x7FF: ``[id lo, id hi, op, register, 4 value bytes little-endian]`` with op
  0x33 read, 0x55 write, 0xAA save to flash, 0xCC refresh (ask for a status reply); the motor answers
  a read or a write with the same layout on its master id;
- CTRL_MODE (register 10) selects the mode whose frames the motor obeys; TIMEOUT (register 9, in
  units of 50 us) disables the motor when commands stop; PMAX/VMAX/TMAX (21-23) are the ranges the
  MIT frame is scaled over and must equal the map's.
"""

from __future__ import annotations

import struct
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

from fieldbus.core.command_guard import finite
from fieldbus.core.yamlsrc import PathT

DAMIAO_KEYS = ("mode", "timeout_ms", "clear", "modes", "registers", "error_field", "errors", "ok_codes")
MODE_KEYS = ("name", "ctrl_mode", "id_offset", "fields")
MODE_FIELD_KEYS = ("from", "type", "scale", "per_unit")
REGISTER_KEYS = (
    "can_id", "read", "write", "save", "refresh", "master_id", "timeout", "ctrl_mode", "pmax", "vmax", "tmax"
)  # fmt: skip
ERROR_KEYS = ("code", "name")
MODE_TYPES = {"float32": ("<f", 4), "uint16": ("<H", 2), "int16": ("<h", 2)}  # int16: ODrive's feed-forwards
CLEAR_ERROR = bytes([0xFF] * 7 + [0xFB])
# the limit registers and the MIT command field whose range each must equal
LIMIT_FIELDS = (("PMAX", "pmax", "position"), ("VMAX", "vmax", "velocity"), ("TMAX", "tmax", "torque"))


@dataclass(frozen=True)
class ModeField:
    """One number of a mode frame, taken from a command channel: ``raw = value * scale``
    (``per_unit``: ``value / max_of_that_channel * scale``); uint16 fields saturate at 0..65535."""

    source: str
    type: str  # float32 | uint16 | int16 (signed, saturates at -32768..32767)
    scale: float = 1.0
    per_unit: bool = False


@dataclass(frozen=True)
class Mode:
    """A control mode: CTRL_MODE value, CAN id offset, frame fields (none: the MIT command frame)."""

    name: str
    ctrl_mode: int
    id_offset: int
    fields: tuple[ModeField, ...] = ()

    @property
    def mit(self) -> bool:
        return not self.fields


@dataclass(frozen=True)
class Registers:
    """Register access: CAN id, op codes and the register numbers the bring-up uses."""

    can_id: int = 0x7FF
    read: int = 0x33
    write: int = 0x55
    save: int = 0xAA
    refresh: int = 0xCC
    master_id: int = 7
    timeout: int = 9
    ctrl_mode: int = 10
    pmax: int = 21
    vmax: int = 22
    tmax: int = 23


@dataclass(frozen=True)
class DamiaoProtocol:
    """A Damiao map's family section: modes, registers, the CAN timeout and the error codes by name."""

    modes: tuple[Mode, ...]
    mode: str  # the mode written to CTRL_MODE at bring-up
    registers: Registers
    timeout_ms: float  # CAN timeout written to TIMEOUT at bring-up (0: none)
    error_field: str  # reply field holding the error code
    errors: tuple[tuple[int, str], ...]
    ok_codes: frozenset[int]  # codes that are states (disabled, enabled), not faults
    clear: bytes = CLEAR_ERROR
    limits: tuple[tuple[str, int, float], ...] = ()  # (register name, number, value from the MIT ranges)

    def mode_named(self, name: str) -> Mode:
        for m in self.modes:
            if m.name == name:
                return m
        raise KeyError(name)

    def error_name(self, code: int) -> str:
        return dict(self.errors).get(code, f"unknown error 0x{code:X}")

    @property
    def timeout_units(self) -> int:
        """TIMEOUT register value: the CAN timeout in units of 50 us."""
        return round(self.timeout_ms * 20)


def parse_damiao(r: Any, raw: Any, path: PathT, command: Any, reply: Any) -> DamiaoProtocol:
    """Validate ``rawcan.damiao`` (``command``/``reply``: the parsed MIT frame fields)."""
    m: Mapping[Any, Any] = r.mapping(raw, path, DAMIAO_KEYS, required=("modes", "error_field", "errors"))
    by_name = {f.name: f for f in command}
    modes: list[Mode] = []
    for i, item in enumerate(r.sequence(m["modes"], (*path, "modes"))):
        mp: PathT = (*path, "modes", i)
        mm = r.mapping(item, mp, MODE_KEYS, required=("name", "ctrl_mode", "id_offset"))
        fields: list[ModeField] = []
        size = 0
        for j, fraw in enumerate(r.sequence(mm.get("fields"), (*mp, "fields"))):
            fp: PathT = (*mp, "fields", j)
            fm = r.mapping(fraw, fp, MODE_FIELD_KEYS, required=("from", "type"))
            src = r.string(fm["from"], (*fp, "from"))
            if src not in by_name:
                raise r.err((*fp, "from"), f"'{src}' is not a command field ({', '.join(by_name)})")
            per_unit = r.boolean(fm.get("per_unit", False), (*fp, "per_unit"))
            if per_unit and by_name[src].max is None:
                raise r.err((*fp, "per_unit"), f"per_unit needs a range (max) on command field '{src}'")
            kind = r.choice(fm["type"], (*fp, "type"), MODE_TYPES)
            size += MODE_TYPES[kind][1]
            scale = r.number(fm.get("scale", 1.0), (*fp, "scale"))
            fields.append(ModeField(src, kind, scale, per_unit))
        if size > 8:
            raise r.err((*mp, "fields"), f"the fields take {size} bytes; a classic CAN frame has 8")
        modes.append(
            Mode(
                r.name(mm["name"], (*mp, "name")),
                r.integer(mm["ctrl_mode"], (*mp, "ctrl_mode"), 0, 0xFFFFFFFF),
                r.integer(mm["id_offset"], (*mp, "id_offset"), 0, 0x7FF),
                tuple(fields),
            )
        )
    if not modes or not any(md.mit for md in modes):
        raise r.err((*path, "modes"), "name the modes, the MIT one (no fields: the command frame) among them")
    names = [md.name for md in modes]
    if len(set(names)) != len(names):
        raise r.err((*path, "modes"), "duplicate mode name")
    mode = r.choice(m.get("mode", names[0]), (*path, "mode"), names)
    regs = _registers(r, m.get("registers", {}), (*path, "registers"))
    error_field = r.string(m["error_field"], (*path, "error_field"))
    if not any(f.name == error_field and not f.scaled for f in reply):
        raise r.err((*path, "error_field"), f"'{error_field}' is not an unscaled reply field")
    errors: list[tuple[int, str]] = []
    for i, item in enumerate(r.sequence(m["errors"], (*path, "errors"))):
        ep: PathT = (*path, "errors", i)
        em = r.mapping(item, ep, ERROR_KEYS, required=ERROR_KEYS)
        errors.append((r.integer(em["code"], (*ep, "code"), 0, 255), r.string(em["name"], (*ep, "name"))))
    ok = frozenset(
        r.integer(v, (*path, "ok_codes", i), 0, 255)
        for i, v in enumerate(r.sequence(m.get("ok_codes", [0, 1]), (*path, "ok_codes")))
    )
    limits: list[tuple[str, int, float]] = []
    for reg_name, key, field_name in LIMIT_FIELDS:
        f = by_name.get(field_name)
        if f is None or f.min is None or f.max is None or f.min != -f.max:
            raise r.err(path, f"{reg_name} is the range of a command field '{field_name}' from -max to max")
        limits.append((reg_name, getattr(regs, key), f.max))
    timeout = r.number(m.get("timeout_ms", 0.0), (*path, "timeout_ms"))
    if not 0.0 <= timeout * 20 <= 0xFFFFFFFF:
        raise r.err((*path, "timeout_ms"), f"{timeout:g} ms does not fit TIMEOUT (0..2**32-1 units of 50 us)")
    clear = CLEAR_ERROR
    if "clear" in m:
        items = r.sequence(m["clear"], (*path, "clear"))
        if len(items) != 8:
            raise r.err((*path, "clear"), f"the clear-error frame has 8 bytes, not {len(items)}")
        clear = bytes(r.integer(v, (*path, "clear", i), 0, 255) for i, v in enumerate(items))
    return DamiaoProtocol(
        tuple(modes), mode, regs, timeout, error_field, tuple(errors), ok, clear, tuple(limits)
    )


def _registers(r: Any, raw: Any, path: PathT) -> Registers:
    m = r.mapping(raw, path, REGISTER_KEYS)
    return Registers(
        **{k: r.integer(v, (*path, k), 0, 0x7FF if k == "can_id" else 255) for k, v in m.items()}
    )


# -- codec -----------------------------------------------------------------------------------------------
def register_frame(node: int, op: int, register: int, value: bytes = bytes(4)) -> bytes:
    """The data of a register request for motor ``node`` (sent on ``Registers.can_id``)."""
    return bytes([node & 0xFF, (node >> 8) & 0xFF, op, register]) + value


def register_reply(node: int, data: bytes, ops: tuple[int, ...]) -> tuple[int, int, bytes] | None:
    """``(op, register, value bytes)`` when ``data`` is motor ``node``'s answer with one of ``ops``; else None."""
    if len(data) != 8 or data[0] != node & 0xFF or data[1] != (node >> 8) & 0xFF or data[2] not in ops:
        return None
    return data[2], data[3], bytes(data[4:8])


def pack_register(value: float, is_float: bool) -> bytes:
    """A register value as its 4 little-endian bytes (float32 or uint32)."""
    return struct.pack("<f", value) if is_float else struct.pack("<I", int(value))


def unpack_register(data: bytes, is_float: bool) -> float:
    return float(struct.unpack("<f" if is_float else "<I", data)[0])


def float32(value: float) -> float:
    """``value`` rounded to float32, as a register holds it."""
    return float(struct.unpack("<f", struct.pack("<f", value))[0])


def encode_fields(
    fields: tuple[ModeField, ...], values: Mapping[str, float], maxima: Mapping[str, float], size: int = 8
) -> bytes:
    """Little-endian numbers taken from engineering values, zero-padded to ``size`` bytes.

    A NaN or infinite value is refused (:class:`~fieldbus.core.output_rules.UnsafeOutputError`), never
    packed: the cycle's output rules keep them out of the image before a family codec reads it.
    """
    out = bytearray(size)
    at = 0
    for f in fields:
        x = finite(f.source, float(values.get(f.source, 0.0)))  # the output rules ran: never NaN on the wire
        if f.per_unit:
            x = abs(x) / maxima[f.source]
        x *= f.scale
        fmt, size = MODE_TYPES[f.type]
        if f.type == "uint16":
            x = min(65535.0, max(0.0, round(abs(x))))
            struct.pack_into(fmt, out, at, int(x))
        elif f.type == "int16":
            struct.pack_into(fmt, out, at, int(min(32767.0, max(-32768.0, round(x)))))
        else:
            struct.pack_into(fmt, out, at, x)
        at += size
    return bytes(out)


def decode_mode(mode: Mode, data: bytes, maxima: Mapping[str, float]) -> dict[str, float]:
    """The engineering values a mode frame carries, keyed by their command channel."""
    return decode_fields(mode.fields, data, maxima)


def decode_fields(
    fields: tuple[ModeField, ...], data: bytes, maxima: Mapping[str, float]
) -> dict[str, float]:
    """The engineering values little-endian ``fields`` carry in ``data``, keyed by their command channel."""
    out: dict[str, float] = {}
    at = 0
    for f in fields:
        fmt, size = MODE_TYPES[f.type]
        x = float(struct.unpack_from(fmt, data, at)[0]) / f.scale
        if f.per_unit:
            x *= maxima[f.source]
        out[f.source] = x
        at += size
    return out
