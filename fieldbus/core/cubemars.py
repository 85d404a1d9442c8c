"""CubeMars AK actuators on raw CAN: the family's protocol as data (a drive map's ``rawcan.cubemars``) and its codec.

Pure: no I/O. Two protocols, one per map (the firmware's mode is chosen in CubeMars' own tool, not over
CAN), the facts cited in ``docs/can-actuators.md`` (CubeMars "AK Series Module Driver User Manual",
sections "Servo mode" and "MIT mode"; neurobionics/TMotorCANControl ``servo_can.py``):

- ``protocol: servo``: commands on 29-bit ids ``packet << 8 | motor id``; packets 0 duty, 1 current,
  2 current brake, 3 speed (electrical rpm), 4 position, 5 set origin, 6 position-speed loop; numbers
  big-endian two's complement (``int32``/``int16``/``uint8``) at the map's scales (raw per engineering
  unit: duty x 100000, current A x 1000, position deg x 10000, ...). The motor reports a status frame on
  ``status_packet << 8 | motor id`` (0x29): int16 position x 0.1 deg, int16 speed x 10 erpm, int16
  current x 0.01 A, int8 temperature (°C), uint8 error code. The packet a cycle sends is chosen by the
  image's ``mode_field`` (so the safe stop can pick "current 0").
- ``protocol: mit``: the MIT frame of :mod:`fieldbus.core.rawcan` on the motor's 11-bit id; replies of
  8 bytes (id, p16, v12, i12, temperature as °C + 40, error code) or, on older firmware, of
  ``short_reply`` (6) bytes: the first six. The position counter wraps at ±PMAX: :class:`Unwrapper`
  turns the wrapped reply into a multi-turn position (the map's ``unwrap.into`` reply field).
"""

from __future__ import annotations

import math
import struct
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

from fieldbus.core.command_guard import finite
from fieldbus.core.yamlsrc import PathT

CUBEMARS_KEYS = (
    "protocol", "mode", "modes", "mode_field", "status_packet", "origin_packet", "status", "error_field",
    "errors", "unwrap", "short_reply",
)  # fmt: skip
MODE_KEYS = ("name", "packet", "fields")
FIELD_KEYS = ("from", "type", "scale")
STATUS_KEYS = ("to", "type", "scale")
UNWRAP_KEYS = ("from", "into")
ERROR_KEYS = ("code", "name")
TYPES = {"int32": (">i", 4), "int16": (">h", 2), "int8": (">b", 1), "uint8": (">B", 1)}


@dataclass(frozen=True)
class ServoField:
    """One big-endian number of a frame: ``raw = round(value * scale)`` (status: ``value = raw * scale``)."""

    channel: str  # the image channel it comes from (command) or goes to (status)
    type: str  # int32 | int16 | int8 | uint8; saturates at the type's range
    scale: float = 1.0


@dataclass(frozen=True)
class ServoMode:
    """A servo-mode packet: its number (the id's high bits) and its data fields."""

    name: str
    packet: int
    fields: tuple[ServoField, ...]


@dataclass(frozen=True)
class CubemarsProtocol:
    """A CubeMars map's family section (``protocol`` servo or mit)."""

    protocol: str  # "servo" | "mit"
    error_field: str
    errors: tuple[tuple[int, str], ...]
    modes: tuple[ServoMode, ...] = ()
    mode: str = ""  # servo: the mode written to the image's mode_field at bring-up
    mode_field: str = ""  # servo: the command channel holding the packet number to send
    status_packet: int = 0x29
    origin_packet: int = 5
    status: tuple[ServoField, ...] = ()
    unwrap: tuple[str, str] | None = None  # mit: (wrapped reply field, multi-turn reply field)
    short_reply: int | None = None  # mit: a reply length older firmware sends (the first bytes of the frame)
    reply_bytes: int = 8  # mit: the reply frame's length (the reply fields but the unwrapped one)

    def mode_named(self, name: str) -> ServoMode:
        for m in self.modes:
            if m.name == name:
                return m
        raise KeyError(name)

    def mode_of_packet(self, packet: int) -> ServoMode | None:
        for m in self.modes:
            if m.packet == packet:
                return m
        return None

    def error_name(self, code: int) -> str:
        return dict(self.errors).get(code, f"unknown error {code}")


def servo_id(packet: int, node: int) -> int:
    """The 29-bit id of servo packet ``packet`` for motor ``node``."""
    return (packet & 0x1FFFFF) << 8 | (node & 0xFF)


def parse_cubemars(r: Any, raw: Any, path: PathT, command: Any, reply: Any) -> CubemarsProtocol:
    """Validate ``rawcan.cubemars`` (``command``/``reply``: the parsed image fields)."""
    m: Mapping[Any, Any] = r.mapping(raw, path, CUBEMARS_KEYS, required=("protocol", "error_field", "errors"))
    protocol = r.choice(m["protocol"], (*path, "protocol"), ("servo", "mit"))
    replies = {f.name: f for f in reply}
    error_field = r.string(m["error_field"], (*path, "error_field"))
    if error_field not in replies or replies[error_field].scaled:
        raise r.err((*path, "error_field"), f"'{error_field}' is not an unscaled reply field")
    errors: list[tuple[int, str]] = []
    for i, item in enumerate(r.sequence(m["errors"], (*path, "errors"))):
        ep: PathT = (*path, "errors", i)
        em = r.mapping(item, ep, ERROR_KEYS, required=ERROR_KEYS)
        errors.append((r.integer(em["code"], (*ep, "code"), 0, 255), r.string(em["name"], (*ep, "name"))))
    if protocol == "mit":
        return _parse_mit(r, m, path, error_field, tuple(errors), reply)
    return _parse_servo(r, m, path, error_field, tuple(errors), command, reply)


def _parse_mit(
    r: Any,
    m: Mapping[Any, Any],
    path: PathT,
    error_field: str,
    errors: tuple[tuple[int, str], ...],
    reply: Any,
) -> CubemarsProtocol:
    """``protocol: mit``: the unwrapped position (``unwrap``), the short reply of older firmware."""
    replies = {f.name: f for f in reply}
    for key in ("modes", "mode", "mode_field", "status", "status_packet", "origin_packet"):
        if key in m:
            raise r.err((*path, key), f"'{key}' is for protocol servo", key=True)
    unwrap = None
    if "unwrap" in m:
        um = r.mapping(m["unwrap"], (*path, "unwrap"), UNWRAP_KEYS, required=UNWRAP_KEYS)
        src, into = (
            r.string(um["from"], (*path, "unwrap", "from")),
            r.string(um["into"], (*path, "unwrap", "into")),
        )
        f = replies.get(src)
        if f is None or f.min is None or f.max is None:
            raise r.err((*path, "unwrap", "from"), f"'{src}' is not a scaled reply field (min..max)")
        if into not in replies or replies[into].type != "float32" or reply[-1].name != into:
            raise r.err((*path, "unwrap", "into"), f"'{into}' is not the last reply field, float32")
        unwrap = (src, into)
    wire = [f for f in reply if unwrap is None or f.name != unwrap[1]]
    bits = sum(f.bits for f in wire)
    if any(f.type != "uint" for f in wire) or bits > 64:
        raise r.err(
            (*path, "unwrap"),
            f"the MIT reply on the wire is {bits} bits of unsigned fields; a classic frame has at most 64 "
            "(only the unwrap.into field is not on the wire)",
        )
    short = None
    if "short_reply" in m:
        short = r.integer(m["short_reply"], (*path, "short_reply"), 1, bits // 8)
    return CubemarsProtocol(
        "mit", error_field, errors, unwrap=unwrap, short_reply=short, reply_bytes=bits // 8
    )


def _parse_servo(
    r: Any,
    m: Mapping[Any, Any],
    path: PathT,
    error_field: str,
    errors: tuple[tuple[int, str], ...],
    command: Any,
    reply: Any,
) -> CubemarsProtocol:
    """``protocol: servo``: the packets (``modes``), the image's mode field, the status frame."""
    commands = {f.name: f for f in command}
    replies = {f.name: f for f in reply}
    for key in ("unwrap", "short_reply"):
        if key in m:
            raise r.err((*path, key), f"'{key}' is for protocol mit", key=True)
    modes: list[ServoMode] = []
    for i, item in enumerate(r.sequence(m.get("modes"), (*path, "modes"))):
        mp: PathT = (*path, "modes", i)
        mm = r.mapping(item, mp, MODE_KEYS, required=("name", "packet"))
        fields = _fields(r, mm.get("fields", []), (*mp, "fields"), "from", commands)
        modes.append(
            ServoMode(
                r.name(mm["name"], (*mp, "name")), r.integer(mm["packet"], (*mp, "packet"), 0, 255), fields
            )
        )
    if not modes:
        raise r.err((*path, "modes"), "name the servo packets the map uses")
    names = [md.name for md in modes]
    if len(set(names)) != len(names) or len({md.packet for md in modes}) != len(modes):
        raise r.err((*path, "modes"), "duplicate mode name or packet")
    mode = r.choice(m.get("mode", names[0]), (*path, "mode"), names)
    mode_field = r.string(m.get("mode_field", "mode"), (*path, "mode_field"))
    if mode_field not in commands or commands[mode_field].type != "uint" or commands[mode_field].scaled:
        raise r.err((*path, "mode_field"), f"'{mode_field}' is not an unscaled uint command field")
    status = _fields(r, m.get("status"), (*path, "status"), "to", replies)
    if error_field not in {f.channel for f in status}:
        raise r.err((*path, "status"), f"the status frame carries no '{error_field}'")
    return CubemarsProtocol(
        "servo",
        error_field,
        errors,
        tuple(modes),
        mode,
        mode_field,
        r.integer(m.get("status_packet", 0x29), (*path, "status_packet"), 0, 0x1FFFFF),
        r.integer(m.get("origin_packet", 5), (*path, "origin_packet"), 0, 0x1FFFFF),
        status,
    )


def _fields(r: Any, raw: Any, path: PathT, key: str, channels: Mapping[str, Any]) -> tuple[ServoField, ...]:
    out: list[ServoField] = []
    size = 0
    for j, fraw in enumerate(r.sequence(raw, path)):
        fp: PathT = (*path, j)
        fm = r.mapping(fraw, fp, (key, "type", "scale"), required=(key, "type"))
        name = r.string(fm[key], (*fp, key))
        if name not in channels:
            raise r.err((*fp, key), f"'{name}' is not a field of the image ({', '.join(channels)})")
        kind = r.choice(fm["type"], (*fp, "type"), TYPES)
        scale = r.number(fm.get("scale", 1.0), (*fp, "scale"))
        if scale == 0.0:
            raise r.err((*fp, "scale"), "scale must not be 0")
        size += TYPES[kind][1]
        out.append(ServoField(name, kind, scale))
    if size > 8:
        raise r.err(path, f"the fields take {size} bytes; a classic CAN frame has 8")
    return tuple(out)


# -- codec -----------------------------------------------------------------------------------------------
def _limits(kind: str) -> tuple[int, int]:
    bits = TYPES[kind][1] * 8
    return (0, (1 << bits) - 1) if kind.startswith("u") else (-(1 << (bits - 1)), (1 << (bits - 1)) - 1)


def encode_servo(fields: tuple[ServoField, ...], values: Mapping[str, float]) -> bytes:
    """The data of a servo packet from engineering values: ``round(value * scale)``, saturated to its type.

    A NaN or infinite value is refused (:class:`~fieldbus.core.output_rules.UnsafeOutputError`): the
    cycle's output rules replace those before any codec runs, so one here is a path that bypassed them.
    """
    return _pack(fields, values, status=False)


def encode_status(fields: tuple[ServoField, ...], values: Mapping[str, float]) -> bytes:
    """A status frame from engineering values: ``round(value / scale)``, saturated (emulators, tests)."""
    return _pack(fields, values, status=True)


def _pack(fields: tuple[ServoField, ...], values: Mapping[str, float], *, status: bool) -> bytes:
    out = bytearray()
    for f in fields:
        v = float(values.get(f.channel, 0.0))
        if (
            not status
        ):  # a command: only a value that passed the output rules is packed, never NaN as INT32_MAX
            finite(f.channel, v)
        x = v / f.scale if status else v * f.scale
        lo, hi = _limits(f.type)
        raw = int(min(hi, max(lo, round(x)))) if math.isfinite(x) else (lo if x < 0 else hi)
        out += struct.pack(TYPES[f.type][0], raw)
    return bytes(out)


def decode_servo(fields: tuple[ServoField, ...], data: bytes) -> dict[str, float]:
    """Engineering values a big-endian frame carries, keyed by image channel (``raw * scale``)."""
    out: dict[str, float] = {}
    at = 0
    for f in fields:
        fmt, size = TYPES[f.type]
        out[f.channel] = struct.unpack_from(fmt, data, at)[0] * f.scale
        at += size
    return out


def decode_command(fields: tuple[ServoField, ...], data: bytes) -> dict[str, float]:
    """Engineering values of a servo packet's data (``raw / scale``), keyed by image channel."""
    out: dict[str, float] = {}
    at = 0
    for f in fields:
        fmt, size = TYPES[f.type]
        out[f.channel] = struct.unpack_from(fmt, data, at)[0] / f.scale
        at += size
    return out


class Unwrapper:
    """Multi-turn position from a counter that wraps at ``lo``/``hi`` (MIT mode: ±PMAX).

    A step of more than half the span between two replies is taken as a wrap: the motor must move less
    than ``(hi - lo) / 2`` between replies (25 rad / 2 at 1 kHz: 12,500 rad/s, far beyond any AK motor).
    """

    def __init__(self, lo: float, hi: float) -> None:
        self.span = hi - lo
        self.turns = 0
        self.last: float | None = None

    def __call__(self, wrapped: float) -> float:
        if self.last is not None:
            step = wrapped - self.last
            if step > self.span / 2:
                self.turns -= 1
            elif step < -self.span / 2:
                self.turns += 1
        self.last = wrapped
        return wrapped + self.turns * self.span

    def reset(self) -> None:
        """Forget the history (after a set-zero: the counter restarts at 0)."""
        self.turns, self.last = 0, None
