"""The ``base:`` section of a network file: a wheeled base in diff_drive_controller's parameters.

The section is the ``ros__parameters`` block of a ros2_controllers ``diff_drive_controller`` as it
stands (or that block itself, under ``ros__parameters``): nested (``linear: {x: {max_velocity: 1}}``)
or dotted (``linear.x.max_velocity: 1``) keys. ``type`` and the parameters that have no meaning
here (``publish_limited_velocity``, ``use_stamped_vel``, ``wheels_per_side``) are accepted and
ignored; the deprecated ``has_*_limits: false`` turns that group of limits off, as it does there.
Every wheel must be a joint of the network (a slave's name, or ``<slave>.axis<k>``).
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping
from typing import Any

from fieldbus.core.diffdrive import DiffDriveParams, SpeedLimits
from fieldbus.core.yamlread import Reader
from fieldbus.core.yamlsrc import PathT

_NUMBERS = (
    "wheel_separation", "wheel_radius", "wheel_separation_multiplier", "left_wheel_radius_multiplier",
    "right_wheel_radius_multiplier", "cmd_vel_timeout", "publish_rate",
)  # fmt: skip
_BOOLS = ("tf_frame_prefix_enable", "open_loop", "position_feedback", "enable_odom_tf")
_STRINGS = ("odom_frame_id", "base_frame_id", "tf_frame_prefix")
_IGNORED = ("type", "publish_limited_velocity", "use_stamped_vel", "wheels_per_side")
_KEYS = (
    "left_wheel_names", "right_wheel_names", *_NUMBERS, *_BOOLS, *_STRINGS, *_IGNORED,
    "pose_covariance_diagonal", "twist_covariance_diagonal", "velocity_rolling_window_size",
    "linear", "angular",
)  # fmt: skip
_LIMITS = tuple(SpeedLimits.__dataclass_fields__)
_LIMIT_KEYS = (
    *_LIMITS,
    "min_acceleration",
    "has_velocity_limits",
    "has_acceleration_limits",
    "has_jerk_limits",
)


def parse_base(r: Reader, raw: Any, path: PathT, joints: Iterable[str]) -> DiffDriveParams:
    """The ``base:`` section at ``path``; ``joints`` are the network's joint names (rows)."""
    flat = _nested(r, raw, path)
    if set(flat) == {"ros__parameters"}:
        path = (*path, "ros__parameters")
        flat = _nested(r, flat["ros__parameters"], path)
    m = r.mapping(
        flat,
        path,
        _KEYS,
        required=("left_wheel_names", "right_wheel_names", "wheel_separation", "wheel_radius"),
    )
    known = set(joints)
    sides: dict[str, tuple[str, ...]] = {}
    for side in ("left_wheel_names", "right_wheel_names"):
        names = r.sequence(m[side], (*path, side))
        if not names:
            raise r.err((*path, side), "a base needs at least one wheel on each side")
        for i, n in enumerate(names):
            name = r.string(n, (*path, side, i))
            if name not in known:
                raise r.err((*path, side, i), f"'{name}' is not a joint of this network")
        sides[side] = tuple(names)
    both = sides["left_wheel_names"] + sides["right_wheel_names"]
    if len(set(both)) != len(both):
        raise r.err(path, "a wheel is named twice in left_wheel_names / right_wheel_names")
    kw: dict[str, Any] = {}
    for key in _NUMBERS:
        if key in m:
            kw[key] = _positive(r, m[key], (*path, key), allow_zero=key == "cmd_vel_timeout")
    for key in (
        "wheel_separation_multiplier",
        "left_wheel_radius_multiplier",
        "right_wheel_radius_multiplier",
    ):
        if key in m:  # a multiplier may be negative (a mirrored wheel), never 0
            kw[key] = r.number(m[key], (*path, key))
            if kw[key] == 0.0:
                raise r.err((*path, key), "a multiplier of 0 makes the base unsteerable")
    for key in _BOOLS:
        if key in m:
            kw[key] = r.boolean(m[key], (*path, key))
    for key in _STRINGS:
        if key in m:
            kw[key] = r.string(m[key], (*path, key))
    for key in ("odom_frame_id", "base_frame_id"):
        if key in kw and not kw[key]:
            raise r.err((*path, key), "a frame id cannot be empty")
    for key in ("pose_covariance_diagonal", "twist_covariance_diagonal"):
        if key in m:
            values = r.sequence(m[key], (*path, key))
            if len(values) != 6:
                raise r.err((*path, key), f"expected 6 numbers (x y z roll pitch yaw), got {len(values)}")
            kw[key] = tuple(r.number(v, (*path, key, i)) for i, v in enumerate(values))
    if "velocity_rolling_window_size" in m:
        kw["velocity_rolling_window_size"] = r.integer(
            m["velocity_rolling_window_size"], (*path, "velocity_rolling_window_size"), 1, 10_000
        )
    kw["linear"] = _limits(r, m.get("linear"), (*path, "linear"), "x")
    kw["angular"] = _limits(r, m.get("angular"), (*path, "angular"), "z")
    return DiffDriveParams(
        left_wheel_names=sides["left_wheel_names"], right_wheel_names=sides["right_wheel_names"], **kw
    )


def _nested(r: Reader, raw: Any, path: PathT) -> dict[str, Any]:
    """``raw`` with dotted keys (``linear.x.max_velocity``) folded into nested mappings."""
    if not isinstance(raw, Mapping):
        raise r.err(path, "expected a mapping")
    out: dict[str, Any] = {}
    for key, value in raw.items():
        if not isinstance(key, str) or "." not in key:
            out[key] = value
            continue
        head, _, rest = key.partition(".")
        sub = out.setdefault(head, {})
        if not isinstance(sub, dict):
            raise r.err((*path, key), f"'{head}' is given twice", key=True)
        sub[rest] = value
    for key, value in list(out.items()):
        if isinstance(value, dict) and any(isinstance(k, str) and "." in k for k in value):
            out[key] = _nested(r, value, (*path, key))
    return out


def _positive(r: Reader, raw: Any, path: PathT, *, allow_zero: bool = False) -> float:
    v = r.number(raw, path)
    if v < 0.0 or (v == 0.0 and not allow_zero):
        raise r.err(path, f"expected a number {'>=' if allow_zero else '>'} 0, got {v:g}")
    return v


def _limits(r: Reader, raw: Any, path: PathT, axis: str) -> SpeedLimits:
    """``linear: {x: {...}}`` / ``angular: {z: {...}}``; ``.NAN`` (or nothing) turns a limit off."""
    if raw is None:
        return SpeedLimits()
    group = r.mapping(_nested(r, raw, path), path, (axis,))
    if axis not in group:
        return SpeedLimits()
    path = (*path, axis)
    m = r.mapping(_nested(r, group[axis], path), path, _LIMIT_KEYS)
    values = {k: r.number(m[k], (*path, k), allow_nan=True) for k in _LIMITS if k in m}
    if "min_acceleration" in m:  # the older signed form: dv >= min_acceleration * dt in either direction
        lo = r.number(m["min_acceleration"], (*path, "min_acceleration"), allow_nan=True)
        values.setdefault("max_deceleration", lo)
        values.setdefault("max_acceleration_reverse", lo)
        values.setdefault("max_deceleration_reverse", values.get("max_acceleration", math.nan))
    for flag, keys in (
        ("has_velocity_limits", ("max_velocity", "min_velocity")),
        ("has_acceleration_limits", ("max_acceleration", "max_deceleration", "max_acceleration_reverse", "max_deceleration_reverse")),
        ("has_jerk_limits", ("max_jerk", "min_jerk")),
    ):  # fmt: skip
        if flag in m and not r.boolean(m[flag], (*path, flag)):
            for k in keys:
                values[k] = math.nan
    for k, sign in (
        ("max_velocity", 1), ("max_acceleration", 1), ("max_deceleration_reverse", 1), ("max_jerk", 1),
        ("min_velocity", -1), ("max_deceleration", -1), ("max_acceleration_reverse", -1), ("min_jerk", -1),
    ):  # fmt: skip
        v = values.get(k, math.nan)
        if not math.isnan(v) and v * sign < 0.0:
            want = ">= 0" if sign > 0 else "<= 0 (ros2_controllers' sign)"
            raise r.err((*path, k), f"expected a number {want}, got {v:g}")
    return SpeedLimits(**values)
