"""A differential-drive (wheeled) base: command limits, wheel kinematics and odometry, one step per cycle.

The parameters carry the names and meanings of ros2_controllers' ``diff_drive_controller`` (its
``diff_drive_controller_parameter.yaml``), so a base's ROS 2 parameters copy over; docs/amr.md lists
the few that mean something else here. Pure: time is a parameter (seconds), nothing here does I/O.

Directions follow REP 103: +x forward, angular +z counter-clockwise seen from above, the odometry
frame fixed, the base frame moving. A wheel's positive velocity (rad/s) drives its side forward:
a mirrored wheel whose drive counts the other way gets its map's scaling negated, as
ros2_controllers expects of the hardware.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass, field
from enum import IntFlag


class Limited(IntFlag):
    """Which limit changed a commanded speed in a step (0 when none did)."""

    NONE = 0
    VELOCITY = 1
    ACCELERATION = 2
    JERK = 4


@dataclass(frozen=True)
class SpeedLimits:
    """Limits of one speed (``linear.x`` in m/s or ``angular.z`` in rad/s), ros2_controllers' meanings.

    NaN turns a limit off. Signs as ros2_controllers writes them: ``max_acceleration`` >= 0 (speeding
    up forward), ``max_deceleration`` <= 0 (slowing down while moving forward),
    ``max_acceleration_reverse`` <= 0 (speeding up backward), ``max_deceleration_reverse`` >= 0
    (slowing down while moving backward). An unset ``min_velocity`` is ``-max_velocity``, an unset
    ``min_jerk`` is ``-max_jerk``; unset deceleration and reverse limits mirror ``max_acceleration``.
    """

    max_velocity: float = math.nan
    min_velocity: float = math.nan
    max_acceleration: float = math.nan
    max_deceleration: float = math.nan
    max_acceleration_reverse: float = math.nan
    max_deceleration_reverse: float = math.nan
    max_jerk: float = math.nan
    min_jerk: float = math.nan

    def resolved(self) -> SpeedLimits:
        """The limits with every unset value derived as the class docstring says."""
        acc = self.max_acceleration
        dec = self.max_deceleration if not math.isnan(self.max_deceleration) else -acc
        acc_rev = self.max_acceleration_reverse if not math.isnan(self.max_acceleration_reverse) else -acc
        dec_rev = self.max_deceleration_reverse if not math.isnan(self.max_deceleration_reverse) else -dec
        return SpeedLimits(
            max_velocity=self.max_velocity,
            min_velocity=self.min_velocity if not math.isnan(self.min_velocity) else -self.max_velocity,
            max_acceleration=acc,
            max_deceleration=dec,
            max_acceleration_reverse=acc_rev,
            max_deceleration_reverse=dec_rev,
            max_jerk=self.max_jerk,
            min_jerk=self.min_jerk if not math.isnan(self.min_jerk) else -self.max_jerk,
        )


def _clip(x: float, lo: float, hi: float) -> float:
    """``x`` within ``[lo, hi]``; a NaN bound is no bound."""
    if not math.isnan(hi) and x > hi:
        return hi
    if not math.isnan(lo) and x < lo:
        return lo
    return x


def limit_speed(v: float, v0: float, v1: float, dt: float, lim: SpeedLimits) -> tuple[float, Limited]:
    """``v`` (the wanted speed) limited in value, rate and jerk, given the last two sent ``v0``, ``v1``.

    ``lim`` must be :meth:`SpeedLimits.resolved`. The rate limit is the acceleration or deceleration
    of the direction the speed is in: away from zero is acceleration, toward zero deceleration; a
    step across zero is bounded by the deceleration of the side it leaves.
    """
    flags = Limited.NONE
    out = _clip(v, lim.min_velocity, lim.max_velocity)
    if out != v:
        flags |= Limited.VELOCITY
    if dt <= 0.0:
        return out, flags
    dv = out - v0
    if not math.isnan(lim.max_jerk):
        dv0 = v0 - v1
        ddv = _clip(dv - dv0, lim.min_jerk * dt * dt, lim.max_jerk * dt * dt)
        if ddv != dv - dv0:
            dv = dv0 + ddv
            flags |= Limited.JERK
    if v0 > 0.0 or (v0 == 0.0 and dv > 0.0):  # moving (or starting) forward
        lo, hi = lim.max_deceleration * dt, lim.max_acceleration * dt
    else:  # moving (or starting) backward
        lo, hi = lim.max_acceleration_reverse * dt, lim.max_deceleration_reverse * dt
    bounded = _clip(dv, lo, hi)
    if bounded != dv:
        flags |= Limited.ACCELERATION
        dv = bounded
    limited = v0 + dv
    if (limited - out) * (out - v0) > 0.0:  # the jerk bound must not overshoot the wanted speed
        limited = out
    return limited, flags


@dataclass(frozen=True)
class DiffDriveParams:
    """A wheeled base as ros2_controllers' diff_drive_controller describes it (SI units, seconds)."""

    left_wheel_names: tuple[str, ...]
    right_wheel_names: tuple[str, ...]
    wheel_separation: float  # m, between the wheels' contact lines
    wheel_radius: float  # m
    wheel_separation_multiplier: float = 1.0
    left_wheel_radius_multiplier: float = 1.0
    right_wheel_radius_multiplier: float = 1.0
    odom_frame_id: str = "odom"
    base_frame_id: str = "base_link"
    tf_frame_prefix_enable: bool = True
    tf_frame_prefix: str = ""
    pose_covariance_diagonal: tuple[float, ...] = (0.0,) * 6
    twist_covariance_diagonal: tuple[float, ...] = (0.0,) * 6
    open_loop: bool = False  # odometry from the commanded speeds instead of the wheels
    position_feedback: bool = True  # odometry from wheel positions (else from wheel velocities)
    enable_odom_tf: bool = True
    cmd_vel_timeout: float = 0.5  # s without a command, then the base ramps to a stop
    publish_rate: float = 50.0  # Hz of odometry and tf
    velocity_rolling_window_size: int = 10  # cycles averaged for the odometry's twist
    linear: SpeedLimits = field(default_factory=SpeedLimits)  # linear.x, m/s
    angular: SpeedLimits = field(default_factory=SpeedLimits)  # angular.z, rad/s

    @property
    def wheel_names(self) -> tuple[str, ...]:
        """Every wheel joint, left then right: the order of :attr:`BaseStep.wheel_velocity`."""
        return self.left_wheel_names + self.right_wheel_names

    def frame(self, name: str, prefix: str = "") -> str:
        """A frame id as published: ``tf_frame_prefix`` (else ``prefix``, the namespace) + ``/`` + name."""
        if not self.tf_frame_prefix_enable:
            return name
        pre = (self.tf_frame_prefix or prefix).strip("/")
        return f"{pre}/{name}" if pre else name


class Odometry:
    """The base's pose in the odometry frame (m, rad), integrated exactly along each step's arc.

    From wheel positions (rad, unwrapped: many turns count on): each step's travel per side is the
    change of its mean wheel angle times its radius; the base moves on the circle those two travels
    describe (a straight line when they are equal). A step with a non-finite position is skipped,
    so the pose never turns NaN.
    """

    def __init__(self, params: DiffDriveParams) -> None:
        self.p = params
        self.x = 0.0
        self.y = 0.0
        self.heading = 0.0
        self.linear = 0.0  # m/s, rolling mean
        self.angular = 0.0  # rad/s, rolling mean
        self._last: tuple[float, float] | None = None
        window = max(1, params.velocity_rolling_window_size)
        self._lin: deque[float] = deque(maxlen=window)
        self._ang: deque[float] = deque(maxlen=window)

    @property
    def separation(self) -> float:
        return self.p.wheel_separation * self.p.wheel_separation_multiplier

    def reset(self, x: float = 0.0, y: float = 0.0, heading: float = 0.0) -> None:
        """Set the pose (``set_odometry``); speeds and the wheels' reference start over."""
        self.x, self.y, self.heading = float(x), float(y), float(heading)
        self.linear = self.angular = 0.0
        self._last = None
        self._lin.clear()
        self._ang.clear()

    def update_from_positions(self, left_rad: float, right_rad: float, dt: float) -> bool:
        """One step from the sides' mean wheel angles (rad); False when skipped (non-finite, first)."""
        if not (math.isfinite(left_rad) and math.isfinite(right_rad)):
            return False
        left = left_rad * self.p.wheel_radius * self.p.left_wheel_radius_multiplier
        right = right_rad * self.p.wheel_radius * self.p.right_wheel_radius_multiplier
        if self._last is None:
            self._last = (left, right)
            return False
        dl, dr = left - self._last[0], right - self._last[1]
        self._last = (left, right)
        self._integrate((dl + dr) / 2.0, (dr - dl) / self.separation, dt)
        return True

    def update_from_velocities(self, left_rad_s: float, right_rad_s: float, dt: float) -> bool:
        """One step from the sides' mean wheel speeds (rad/s) over ``dt`` seconds."""
        if not (math.isfinite(left_rad_s) and math.isfinite(right_rad_s)) or dt <= 0.0:
            return False
        dl = left_rad_s * dt * self.p.wheel_radius * self.p.left_wheel_radius_multiplier
        dr = right_rad_s * dt * self.p.wheel_radius * self.p.right_wheel_radius_multiplier
        self._integrate((dl + dr) / 2.0, (dr - dl) / self.separation, dt)
        return True

    def update_open_loop(self, linear: float, angular: float, dt: float) -> bool:
        """One step from the commanded speeds (m/s, rad/s): ``open_loop`` odometry."""
        if not (math.isfinite(linear) and math.isfinite(angular)) or dt <= 0.0:
            return False
        self._integrate(linear * dt, angular * dt, dt)
        return True

    def _integrate(self, ds: float, dtheta: float, dt: float) -> None:
        """Move ``ds`` metres along an arc that turns ``dtheta`` radians (exact, not Euler)."""
        h0 = self.heading
        if abs(dtheta) < 1e-9:  # straight: the chord's direction is the mid heading
            mid = h0 + dtheta / 2.0
            self.x += ds * math.cos(mid)
            self.y += ds * math.sin(mid)
        else:
            r = ds / dtheta
            self.x += r * (math.sin(h0 + dtheta) - math.sin(h0))
            self.y -= r * (math.cos(h0 + dtheta) - math.cos(h0))
        self.heading = math.remainder(h0 + dtheta, math.tau)
        if dt > 0.0:
            self._lin.append(ds / dt)
            self._ang.append(dtheta / dt)
            self.linear = sum(self._lin) / len(self._lin)
            self.angular = sum(self._ang) / len(self._ang)


@dataclass(frozen=True)
class BaseStep:
    """What one step of the base decided: wheel targets (rad/s, left wheels then right) and why."""

    wheel_velocity: tuple[float, ...]
    linear: float  # m/s sent this step, after the limits
    angular: float  # rad/s sent this step, after the limits
    asked_linear: float  # m/s the command (or the timeout's 0) asked
    asked_angular: float
    linear_limited: Limited
    angular_limited: Limited
    timed_out: bool  # no command within cmd_vel_timeout: ramping to (or holding) zero


class DiffDrive:
    """One wheeled base: take ``cmd_vel`` commands, step once per cycle, keep odometry.

    A command is refused (and changes nothing, not even its age) when a value is NaN or infinite.
    After ``cmd_vel_timeout`` seconds without a command the asked speeds are 0 and the limits ramp
    the base down, then hold it. :meth:`hold` drops the command (a stop, a disable, a lost claim):
    the next step asks zero from the speeds the base is actually sent, never a jump.
    """

    def __init__(self, params: DiffDriveParams) -> None:
        self.p = params
        self.odometry = Odometry(params)
        self._lin_lim = params.linear.resolved()
        self._ang_lim = params.angular.resolved()
        self._cmd: tuple[float, float] | None = None
        self._cmd_at = -math.inf
        self._lin = [0.0, 0.0]  # the last two sent linear speeds, newest first
        self._ang = [0.0, 0.0]

    def command(self, linear_x: float, angular_z: float, now_s: float) -> str | None:
        """Take a ``cmd_vel`` (m/s, rad/s) received at ``now_s``; the refusal's reason, or None."""
        for v in (linear_x, angular_z):
            if math.isnan(v):
                return "nan"
            if math.isinf(v):
                return "inf"
        self._cmd = (float(linear_x), float(angular_z))
        self._cmd_at = now_s
        return None

    def hold(self) -> None:
        """Forget the command: the base ramps to zero from where it is, and waits for a new one."""
        self._cmd = None
        self._cmd_at = -math.inf

    def reset_speeds(self) -> None:
        """The drives are stopped (disabled, faulted): the limiter starts again from rest."""
        self._lin = [0.0, 0.0]
        self._ang = [0.0, 0.0]

    def step(
        self,
        now_s: float,
        dt_s: float,
        wheel_position: tuple[float, ...] | None = None,
        wheel_velocity: tuple[float, ...] | None = None,
    ) -> BaseStep:
        """One cycle: the limited command as wheel speeds, and the odometry from the wheels' feedback.

        ``wheel_position`` (rad) / ``wheel_velocity`` (rad/s) are per wheel in :attr:`DiffDriveParams.
        wheel_names` order; None (or a stale NaN) leaves the odometry where it is this step.
        """
        timed_out = self._cmd is None or now_s - self._cmd_at > self.p.cmd_vel_timeout
        asked_lin, asked_ang = (0.0, 0.0) if timed_out or self._cmd is None else self._cmd
        lin, lf = limit_speed(asked_lin, self._lin[0], self._lin[1], dt_s, self._lin_lim)
        ang, af = limit_speed(asked_ang, self._ang[0], self._ang[1], dt_s, self._ang_lim)
        self._lin = [lin, self._lin[0]]
        self._ang = [ang, self._ang[0]]
        half = ang * self.p.wheel_separation * self.p.wheel_separation_multiplier / 2.0
        left = (lin - half) / (self.p.wheel_radius * self.p.left_wheel_radius_multiplier)
        right = (lin + half) / (self.p.wheel_radius * self.p.right_wheel_radius_multiplier)
        nl, nr = len(self.p.left_wheel_names), len(self.p.right_wheel_names)
        self._odometry(dt_s, lin, ang, nl, wheel_position, wheel_velocity)
        return BaseStep(
            wheel_velocity=(left,) * nl + (right,) * nr,
            linear=lin,
            angular=ang,
            asked_linear=asked_lin,
            asked_angular=asked_ang,
            linear_limited=lf,
            angular_limited=af,
            timed_out=timed_out,
        )

    def _odometry(
        self,
        dt: float,
        lin: float,
        ang: float,
        nl: int,
        pos: tuple[float, ...] | None,
        vel: tuple[float, ...] | None,
    ) -> None:
        odo = self.odometry
        if self.p.open_loop:
            odo.update_open_loop(lin, ang, dt)
        elif self.p.position_feedback and pos is not None:
            odo.update_from_positions(_mean(pos[:nl]), _mean(pos[nl:]), dt)
        elif not self.p.position_feedback and vel is not None:
            odo.update_from_velocities(_mean(vel[:nl]), _mean(vel[nl:]), dt)


def _mean(values: tuple[float, ...]) -> float:
    return sum(values) / len(values) if values else math.nan


def quaternion_z(yaw: float) -> tuple[float, float, float, float]:
    """The rotation ``yaw`` rad about +z as a quaternion ``(x, y, z, w)`` (ROS order)."""
    return (0.0, 0.0, math.sin(yaw / 2.0), math.cos(yaw / 2.0))
