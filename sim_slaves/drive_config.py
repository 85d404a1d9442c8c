"""An emulated CiA 402 drive that follows its drive map: :class:`~sim_slaves.drive402.DriveParams` from
the map's scaling, its start-up SDOs and a network file's ``emulator:`` options.

A map that scales its channels to joint units says what drive it describes:

- **position** (0x6064 input, or 0x607A output): counts per radian of the
  driven shaft, so counts per shaft revolution = encoder increments per motor
  revolution (0x608F) x gear ratio (0x6091, motor revolutions per shaft
  revolution). The gear comes from ``gear_ratio`` (emulator option), else the
  map's start-up write of 0x6091, else from the encoder resolution
  (``position_encoder_resolution`` or a start-up write of 0x608F: gear =
  counts per shaft revolution / increments per motor revolution), else 1.
  Position units are then counts per shaft revolution / gear per motor
  revolution.
- **velocity** (0x606C, or 0x60FF): velocity units per rad/s of the shaft;
  with the position's counts per rad, velocity units per count/s (1 when the
  velocity is counts/s, 30 for the 0.001 rpm of a 0x60A9-configured drive...).
- **torque** (0x6077, or 0x6071) in N·m: N·m of the driven shaft per ‰, so the
  motor's rated torque (0x6076) = 1000 x that / gear. A torque in % of rated
  says nothing about N·m and leaves the default (1 N·m).

Units: an input's ``factor`` is units per raw count, an output's raw counts
per unit (``fieldbus.core.pdo.model.Channel``); angles in rad, deg or rev,
speeds in rad/s, deg/s, rpm or rev/s, torques in N·m or mN·m; a scaled
channel without a unit is taken as SI (rad, rad/s, N·m: ethercat_driver_ros2's
convention). Channels in counts, increments, % or unscaled say nothing, and
neither do an input and an output that scale one quantity differently (more
than 0.1 % apart: not one drive).

Count-based defaults the map does not set (following-error window 0x6065,
position window 0x6067, velocity window 0x606D, quick-stop deceleration
0x6085) keep the physical size they have on the default 17-bit drive: they
scale with the position units per motor revolution (and the velocity unit).
So a 2^20-count, 50:1 drive's following-error window is 80,000 counts, the
same 0.48 rad at the motor as 10,000 counts of the 17-bit default.

Emulator options (``sim_slaves.emulator_options``; SI unless named) override
what the map implies: ``position_encoder_resolution`` (0x608F, increments per
motor revolution), ``gear_ratio`` (0x6091), ``motor_rated_torque_nm``
(0x6076), ``max_torque_permille`` (0x6072), ``max_motor_speed_rpm``
(0x6080), ``software_position_limit`` ([min, max] counts, 0x607D),
``quick_stop_deceleration`` (0x6085, acceleration units),
``quick_stop_option`` (0x605A), ``following_error_window`` (0x6065, counts),
``inertia_kg_m2`` (rotor + load at the motor shaft). Other keys are
``DriveParams`` fields and pass through.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import fields
from fractions import Fraction
from typing import Any

from fieldbus.core.pdo.model import Channel, Direction, DriveMap
from sim_slaves.drive402 import GEAR_DENOMINATOR, TWO_PI, DriveParams

BASE = DriveParams()
BASE_COUNTS_PER_REV = BASE.counts_per_rev  # the default drive the count-based defaults belong to
AGREE = 1e-3  # an input's and an output's scaling of one quantity agree within this (relative)

_ANGLE = {"rad": 1.0, "deg": math.pi / 180.0, "degree": math.pi / 180.0, "degrees": math.pi / 180.0,
          "°": math.pi / 180.0, "rev": TWO_PI, "revolution": TWO_PI, "revolutions": TWO_PI, "turn": TWO_PI,
          "turns": TWO_PI}  # fmt: skip
_SPEED = {"rad/s": 1.0, "deg/s": math.pi / 180.0, "°/s": math.pi / 180.0, "rpm": TWO_PI / 60.0,
          "rev/min": TWO_PI / 60.0, "rev/s": TWO_PI, "rps": TWO_PI, "turn/s": TWO_PI}  # fmt: skip
_TORQUE = {"nm": 1.0, "mnm": 1e-3}  # after dropping "·", "*", ".", " " and lower-casing

#: emulator options that are not DriveParams fields (see the module docstring; the others are)
UNIT_OPTIONS = frozenset(
    {
        "position_encoder_resolution",
        "gear_ratio",
        "motor_rated_torque_nm",
        "software_position_limit",
        "quick_stop_deceleration",
        "following_error_window",
    }
)
_FIELDS = frozenset(f.name for f in fields(DriveParams))


def _si(channel: Channel, table: Mapping[str, float], *, torque: bool = False) -> float | None:
    """SI units per one of the channel's units (rad, rad/s or N·m), None if its unit is not of that kind."""
    if channel.unit is None:
        return 1.0 if channel.factor != 1.0 else None
    unit = channel.unit.strip().lower()
    if torque:
        for mark in ("·", "*", ".", " ", "⋅"):
            unit = unit.replace(mark, "")
    return table.get(unit)


def _per_raw(
    drive: DriveMap, index: int, out_index: int, table: Mapping[str, float], torque: bool = False
) -> float | None:
    """SI units per raw unit of the scaled channels ``index`` (input) and ``out_index`` (output).

    None when neither is scaled in units of that kind, or when both are and
    disagree by more than :data:`AGREE` (the map does not describe one drive).
    """
    found = []
    for direction, obj in ((Direction.INPUTS, index), (Direction.OUTPUTS, out_index)):
        ch = drive.find(direction, obj)
        if ch is None or ch.factor == 0.0:
            continue
        si = _si(ch, table, torque=torque)
        if si is not None:
            found.append((abs(ch.factor) if direction is Direction.INPUTS else 1.0 / abs(ch.factor)) * si)
    if not found or (len(found) == 2 and abs(found[0] - found[1]) > AGREE * max(found)):
        return None
    return found[0]


def _startup(drive: DriveMap, index: int, sub: int) -> float | None:
    """The value the map's start-up SDOs write into ``index:sub``, if any (the last write)."""
    value = None
    for w in drive.sdo:
        if w.index == index and w.sub_index == sub:
            value = w.value
    return value


def _ratio(drive: DriveMap, index: int) -> float | None:
    """Sub 1 / sub 2 of a record the map writes at start-up (0x608F, 0x6091), if it writes sub 1."""
    first = _startup(drive, index, 1)
    if first is None:
        return None
    second = _startup(drive, index, 2)
    return float(first) / float(second) if second else float(first)


def drive_params(drive: DriveMap, options: Mapping[str, Any] | None = None) -> DriveParams:
    """The emulated drive of ``drive`` with ``options`` (see the module docstring).

    Raises ``ValueError`` for a combination no drive can have (as
    :class:`~sim_slaves.drive402.DriveParams` does).
    """
    opts = dict(options or {})
    unknown = set(opts) - UNIT_OPTIONS - _FIELDS
    if unknown:
        raise ValueError(f"unknown drive options: {', '.join(sorted(unknown))}")
    rad_per_count = _per_raw(drive, 0x6064, 0x607A, _ANGLE)
    shaft_counts = TWO_PI / rad_per_count if rad_per_count else None  # counts per shaft revolution
    resolution = opts.get("position_encoder_resolution") or _ratio(drive, 0x608F)
    gear = opts.get("gear_ratio") or _ratio(drive, 0x6091)
    if gear is None:
        # inferred: the nearest simple ratio (a map's factor is rounded: 2^20 x 50 counts come back as 49.9999996)
        gear = (
            float(Fraction(shaft_counts / resolution).limit_denominator(GEAR_DENOMINATOR))
            if shaft_counts and resolution
            else 1.0
        )
    gear = float(gear)
    if shaft_counts:
        counts_per_rev = max(1, round(shaft_counts / gear))
    elif resolution:
        counts_per_rev = max(1, round(resolution))
    else:
        counts_per_rev = BASE.counts_per_rev
    kw: dict[str, Any] = {k: v for k, v in opts.items() if k in _FIELDS}
    kw["counts_per_rev"] = counts_per_rev
    kw["gear_ratio"] = gear
    if resolution and round(resolution) != counts_per_rev and not opts.get("encoder_counts_per_rev"):
        kw["encoder_counts_per_rev"] = round(resolution)
    velocity_units = 1.0
    rad_s_per_unit = _per_raw(drive, 0x606C, 0x60FF, _SPEED)
    if rad_s_per_unit and rad_per_count:
        velocity_units = rad_per_count / rad_s_per_unit  # velocity units per count/s
    kw["velocity_units_per_count_s"] = velocity_units
    nm_per_permille = _per_raw(drive, 0x6077, 0x6071, _TORQUE, torque=True)
    if "motor_rated_torque_nm" in opts:
        kw["rated_torque_nm"] = float(opts["motor_rated_torque_nm"])
    elif nm_per_permille:
        kw["rated_torque_nm"] = nm_per_permille * 1000.0 / gear
    scale = counts_per_rev / BASE_COUNTS_PER_REV  # count-based defaults keep their physical size
    if "following_error_window" in opts:
        kw["following_error_window_counts"] = int(opts["following_error_window"])
    kw.setdefault("following_error_window_counts", round(BASE.following_error_window_counts * scale))
    kw.setdefault("position_window_counts", max(1, round(BASE.position_window_counts * scale)))
    kw.setdefault(
        "velocity_window_counts_s", max(1, round(BASE.velocity_window_counts_s * scale * velocity_units))
    )
    if "quick_stop_deceleration" in opts:
        kw["quick_stop_decel_counts_s2"] = int(opts["quick_stop_deceleration"])
    kw.setdefault(
        "quick_stop_decel_counts_s2", round(BASE.quick_stop_decel_counts_s2 * scale * velocity_units)
    )
    if "software_position_limit" in opts:
        lo, hi = opts["software_position_limit"]
        kw["software_position_limit"] = (int(lo), int(hi))
    return DriveParams(**kw)
