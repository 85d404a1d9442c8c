"""The trajectory generator of the emulated drive's profile modes (CiA 402-2 PP, mode 1; PV, mode 3).

Pure functions of one cycle, in SI units at the motor shaft (rad, rad/s,
rad/s²); the drive converts from its objects: 0x6081 profile velocity,
0x6083 profile acceleration, 0x6084 profile deceleration (velocity and
acceleration units). A trapezoidal profile: accelerate at ``accel`` up to
``v_max``, cruise, decelerate at ``decel`` so as to stop on the target.
A move starts from the generator's present position and velocity, so a
set-point changed in motion ("change set immediately") joins smoothly, and a
move that starts against the present velocity first brakes at ``decel``.
"""

from __future__ import annotations

import math


def stopping_distance(v: float, decel: float) -> float:
    """Signed distance [rad] a ramp at ``decel`` [rad/s²] needs to stop from ``v`` [rad/s]."""
    return v * abs(v) / (2.0 * decel)


def position_step(
    p: float, v: float, target: float, v_max: float, accel: float, decel: float, dt: float
) -> tuple[float, float, bool]:
    """One cycle of ``dt`` [s] of a point-to-point move toward ``target`` [rad].

    ``p`` [rad], ``v`` [rad/s]: the generator's state; ``v_max`` > 0 [rad/s],
    ``accel``/``decel`` > 0 [rad/s²]. Returns the new position, velocity and
    whether the move is done (``p == target``, ``v == 0``). The speed is held
    within what can still stop on the target (``sqrt(2 decel |e|)``); the last
    cycle lands on the target. Never a speed change of more than ``accel`` or
    ``decel`` x ``dt`` per cycle: a target too close to stop on from the present
    speed is passed, braking at ``decel``, and approached again from the far side.
    """
    e = target - p
    if e == 0.0 and v == 0.0:
        return p, 0.0, True
    s = 1.0 if e > 0.0 else -1.0 if e < 0.0 else -math.copysign(1.0, v)
    if v * s < 0.0:  # moving away from the target: brake first
        v_new = v + s * decel * dt
        if v_new * s > -1e-9 * decel * dt:  # through zero (or a rounding residue of it): stop
            v_new = 0.0
        return p + 0.5 * (v + v_new) * dt, v_new, False
    speed = abs(v)
    cruise = max(v_max, speed - decel * dt) if speed > v_max else min(v_max, speed + accel * dt)
    # the fastest speed at the end of this cycle from which a ramp at decel still stops on the target
    # (trapezoidal integration: this cycle covers (speed + new) dt / 2, the ramp new² / 2 decel)
    reach = abs(e)
    ddt = decel * dt
    slow = speed <= ddt * (1.0 + 1e-6)  # can stop within this cycle at decel
    left = reach - 0.5 * speed * dt
    if left <= 0.0:
        if slow:
            return target, 0.0, True
        speed_new = speed - ddt  # too fast to stop on the target: brake at decel, pass it, come back
    else:
        brake = ddt * (math.sqrt(0.25 + 2.0 * left / (ddt * dt)) - 0.5)
        # never slower than braking at decel allows (closer than that: pass the target and come back)
        speed_new = max(0.0, speed - ddt, min(cruise, brake))
    step = 0.5 * (speed + speed_new) * dt
    if slow and reach - step <= 1e-12 * max(1.0, reach):
        return target, 0.0, True
    return p + s * step, s * speed_new, False


def velocity_step(v: float, target: float, accel: float, decel: float, dt: float) -> float:
    """One cycle of ``dt`` [s] of the velocity ramp toward ``target`` [rad/s] (PV; PP's halt with 0).

    Speeding up (``|target| > |v|``, same direction or from rest) ramps at ``accel``
    [rad/s²], slowing down at ``decel``; a reversal brakes to zero at ``decel``, then speeds up at ``accel``.
    """
    dv = target - v
    if dv == 0.0:
        return v
    speeding_up = v * target >= 0.0 and abs(target) > abs(v)
    rate = (accel if speeding_up else decel) * dt
    if abs(dv) <= rate * (1.0 + 1e-9):  # the last step lands on the target (not a rounding short of it)
        return target
    v_new = v + math.copysign(rate, dv)
    if not speeding_up and (v_new * v < 0.0 or abs(v_new) < 1e-9 * rate):
        return 0.0  # a reversal stops at zero first; from there it speeds up at accel
    return v_new
