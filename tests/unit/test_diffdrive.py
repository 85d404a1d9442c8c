"""The wheeled base's core: limits, kinematics and exact odometry, in steps of virtual time."""

from __future__ import annotations

import itertools
import math
import textwrap

import pytest

from fieldbus.core.diffdrive import (
    DiffDrive,
    DiffDriveParams,
    Limited,
    Odometry,
    SpeedLimits,
    limit_speed,
    quaternion_z,
)
from fieldbus.core.network import network_from_text
from fieldbus.errors import PdoMapError

SEED = dict(wheel_separation=0.45, wheel_radius=0.08)  # seed 001's AMR


def _base(**kw: object) -> DiffDriveParams:
    args: dict[str, object] = dict(left_wheel_names=("l",), right_wheel_names=("r",), **SEED)
    args.update(kw)
    return DiffDriveParams(**args)  # type: ignore[arg-type]


def test_wheel_speeds_are_the_differential_model() -> None:
    base = DiffDrive(_base())
    base.command(1.0, 0.0, 0.0)
    step = base.step(0.0, 0.01)
    assert step.wheel_velocity == pytest.approx((1.0 / 0.08, 1.0 / 0.08))
    base.command(0.0, 2.0, 0.01)
    step = base.step(0.01, 0.01)
    # right forward, left backward: v = w * b / 2 / r
    assert step.wheel_velocity == pytest.approx((-2.0 * 0.225 / 0.08, 2.0 * 0.225 / 0.08))


def test_multipliers_and_several_wheels_per_side() -> None:
    base = DiffDrive(
        _base(
            left_wheel_names=("fl", "rl"),
            right_wheel_names=("fr", "rr"),
            left_wheel_radius_multiplier=2.0,
            wheel_separation_multiplier=2.0,
        )
    )
    base.command(0.4, 1.0, 0.0)
    v = base.step(0.0, 0.01).wheel_velocity
    assert len(v) == 4 and v[0] == v[1] and v[2] == v[3]
    assert v[0] == pytest.approx((0.4 - 1.0 * 0.45) / (0.08 * 2.0))
    assert v[2] == pytest.approx((0.4 + 1.0 * 0.45) / 0.08)


def test_odometry_follows_the_arc_exactly_even_in_coarse_steps() -> None:
    """Quarter of a circle of radius 1 m in 4 steps: exact integration lands on (1, 1, pi/2); Euler
    integration of the same steps would be off by centimetres."""
    p = _base(wheel_separation=0.5, wheel_radius=0.1)
    odo = Odometry(p)
    radius, turn = 1.0, math.pi / 2
    left_arc = (radius - 0.25) * turn  # m each side travels
    right_arc = (radius + 0.25) * turn
    odo.update_from_positions(0.0, 0.0, 0.1)
    for k in range(1, 5):
        odo.update_from_positions(left_arc * k / 4 / 0.1, right_arc * k / 4 / 0.1, 0.1)
    assert odo.x == pytest.approx(1.0, abs=1e-12)
    assert odo.y == pytest.approx(1.0, abs=1e-12)
    assert odo.heading == pytest.approx(math.pi / 2, abs=1e-12)
    # what a first-order (Euler) step of the same motion gives: far off
    euler_x = sum(radius * turn / 4 * math.cos(turn / 4 * k) for k in range(1, 5))
    assert abs(euler_x - 1.0) > 0.05


def test_odometry_of_a_square_closes_and_never_turns_nan() -> None:
    p = _base()
    odo = Odometry(p)
    left = right = 0.0
    r, half = 0.08, 0.225
    odo.update_from_positions(left, right, 0.01)
    for _side in range(4):
        for _ in range(200):  # 2 m straight in 200 steps
            left += 0.01 / r
            right += 0.01 / r
            odo.update_from_positions(left, right, 0.01)
        for _ in range(100):  # turn pi/2 on the spot in 100 steps
            d = (math.pi / 2 / 100) * half / r
            left -= d
            right += d
            odo.update_from_positions(left, right, 0.01)
        odo.update_from_positions(math.nan, right, 0.01)  # a stale wheel: skipped
        odo.update_from_positions(left, math.inf, 0.01)
    assert math.isfinite(odo.x) and math.isfinite(odo.y)
    assert odo.x == pytest.approx(0.0, abs=1e-9) and odo.y == pytest.approx(0.0, abs=1e-9)
    assert abs(math.remainder(odo.heading, math.tau)) < 1e-9


def test_acceleration_limits_ramp_in_the_counted_number_of_steps() -> None:
    lim = SpeedLimits(max_velocity=1.5, max_acceleration=0.5, max_deceleration=-2.0).resolved()
    v, v1, n = 0.0, 0.0, 0
    while v < 1.0:
        nv, flags = limit_speed(1.0, v, v1, 0.01, lim)
        v1, v, n = v, nv, n + 1
        assert nv - v1 <= 0.5 * 0.01 + 1e-12
    assert n == 200 and flags == Limited.NONE  # the last step reaches 1.0 without limiting
    n = 0
    while v > 0.0:
        nv, _ = limit_speed(0.0, v, v1, 0.01, lim)
        v1, v, n = v, nv, n + 1
    assert n == 50  # 1 m/s at 2 m/s^2
    # over the velocity limit: clamped and said
    assert limit_speed(9.0, 1.5, 1.5, 0.01, lim) == (1.5, Limited.VELOCITY)
    # reverse mirrors forward when unset
    assert lim.max_acceleration_reverse == -0.5 and lim.max_deceleration_reverse == 2.0
    assert lim.min_velocity == -1.5


def test_reverse_limits_are_their_own() -> None:
    lim = SpeedLimits(
        max_acceleration=1.0,
        max_deceleration=-1.0,
        max_acceleration_reverse=-0.25,
        max_deceleration_reverse=4.0,
    ).resolved()
    v, flags = limit_speed(-1.0, 0.0, 0.0, 0.1, lim)
    assert v == pytest.approx(-0.025) and flags == Limited.ACCELERATION
    v, flags = limit_speed(0.0, -1.0, -1.0, 0.1, lim)
    assert v == pytest.approx(-0.6) and flags == Limited.ACCELERATION


def test_jerk_limit_bounds_the_change_of_acceleration() -> None:
    lim = SpeedLimits(max_acceleration=10.0, max_jerk=100.0).resolved()
    v, flags = limit_speed(1.0, 0.0, 0.0, 0.01, lim)
    assert v == pytest.approx(0.01) and Limited.JERK in flags  # da <= 100 * 0.01 -> dv <= 1e-2
    v2, _ = limit_speed(1.0, v, 0.0, 0.01, lim)
    assert v2 - v == pytest.approx(0.02)


def test_a_timeout_ramps_to_zero_within_the_deceleration_then_holds() -> None:
    p = _base(
        cmd_vel_timeout=0.5, linear=SpeedLimits(max_velocity=1.5, max_acceleration=1.0, max_deceleration=-1.0)
    )
    base = DiffDrive(p)
    t, dt = 0.0, 0.01
    base.command(1.0, 0.0, t)
    for _ in range(100):  # 1 s: up to speed (0.5 s timeout renewed every 0.25 s)
        if round(t / dt) % 25 == 0:
            base.command(1.0, 0.0, t)
        base.step(t, dt)
        t += dt
    assert base.step(t, dt).linear == pytest.approx(1.0)
    last_cmd = t
    t += dt
    steps = []
    while t < last_cmd + 3.0:
        steps.append(base.step(t, dt))
        t += dt
    timed = [s for s in steps if s.timed_out]
    assert timed and all(s.asked_linear == 0.0 for s in timed)
    assert all(a.linear - b.linear <= 1.0 * dt + 1e-12 for a, b in itertools.pairwise(steps))
    stopped = next(i for i, s in enumerate(steps) if s.linear == 0.0)
    assert stopped <= round((0.5 + 1.0) / dt) + 2  # the timeout, then 1 s of ramp
    assert all(s.linear == 0.0 for s in steps[stopped:])


def test_non_finite_commands_are_refused_and_do_not_keep_the_base_alive() -> None:
    base = DiffDrive(_base(cmd_vel_timeout=0.1))
    assert base.command(0.2, 0.0, 0.0) is None
    assert base.command(math.nan, 0.0, 0.05) == "nan"
    assert base.command(0.0, math.inf, 0.09) == "inf"
    assert base.step(0.05, 0.01).asked_linear == 0.2
    assert base.step(0.2, 0.01).timed_out  # the refused ones did not renew the command
    base.command(0.3, 0.0, 0.3)
    base.hold()
    assert base.step(0.31, 0.01).asked_linear == 0.0


def test_quaternion() -> None:
    x, y, z, w = quaternion_z(math.pi / 2)
    assert (x, y) == (0.0, 0.0) and z == pytest.approx(math.sqrt(0.5)) and w == pytest.approx(math.sqrt(0.5))


NET = """
buses:
  - name: wheels
    type: sim
    slaves:
      - {{name: left_wheel, map: generic_cia402.yaml}}
      - {{name: right_wheel, map: generic_cia402.yaml}}
base:
{base}
"""


def _net(base: str, tmp_path: object) -> object:
    import shutil
    from pathlib import Path

    import fieldbus

    folder = Path(str(tmp_path))
    shutil.copy(Path(fieldbus.PDO_MAPS) / "generic_cia402.yaml", folder / "generic_cia402.yaml")
    text = NET.format(base=textwrap.indent(textwrap.dedent(base), "  "))
    return network_from_text(text, file=str(folder / "net.yaml"), base=folder)


def test_a_ros2_controllers_parameter_block_loads_as_it_is(tmp_path: object) -> None:
    net = _net(
        """
        ros__parameters:
          type: diff_drive_controller/DiffDriveController
          left_wheel_names: ["left_wheel"]
          right_wheel_names: ["right_wheel"]
          wheel_separation: 0.45
          wheel_radius: 0.08
          publish_rate: 50.0
          base_frame_id: base_footprint
          cmd_vel_timeout: 0.5
          pose_covariance_diagonal: [0.001, 0.001, 0.001, 0.001, 0.001, 0.01]
          linear.x.max_velocity: 1.5
          linear.x.max_acceleration: 1.0
          angular:
            z:
              max_velocity: 2.5
              has_jerk_limits: false
              max_jerk: .NAN
        """,
        tmp_path,
    )
    base = net.base  # type: ignore[attr-defined]
    assert base.wheel_names == ("left_wheel", "right_wheel")
    assert base.linear.max_velocity == 1.5 and base.linear.max_acceleration == 1.0
    assert base.angular.max_velocity == 2.5 and math.isnan(base.angular.max_jerk)
    assert base.base_frame_id == "base_footprint" and base.pose_covariance_diagonal[5] == 0.01


@pytest.mark.parametrize(
    ("body", "where", "what"),
    [
        ("left_wheel_names: [lw]\nright_wheel_names: [right_wheel]\nwheel_separation: 0.4\nwheel_radius: 0.1",
         "base.left_wheel_names[0]", "'lw' is not a joint"),
        ("left_wheel_names: [left_wheel]\nright_wheel_names: [right_wheel]\nwheel_separation: 0\nwheel_radius: 0.1",
         "base.wheel_separation", "> 0"),
        ("left_wheel_names: [left_wheel]\nright_wheel_names: [right_wheel]\nwheel_separation: 0.4\n"
         "wheel_radius: 0.1\nlinear: {x: {max_deceleration: 2.0}}", "base.linear.x.max_deceleration", "<= 0"),
        ("left_wheel_names: [left_wheel]\nright_wheel_names: [right_wheel]\nwheel_separation: 0.4\n"
         "wheel_radius: 0.1\npose_covariance_diagonal: [1, 2]", "base.pose_covariance_diagonal", "expected 6"),
        ("left_wheel_names: [left_wheel]\nright_wheel_names: [right_wheel]\nwheel_separation: 0.4\n"
         "wheel_radius: 0.1\nwheel_seperation: 1", "base.wheel_seperation", "did you mean wheel_separation"),
    ],
)  # fmt: skip
def test_a_bad_base_is_a_located_error(body: str, where: str, what: str, tmp_path: object) -> None:
    with pytest.raises(PdoMapError) as exc:
        _net(body, tmp_path)
    text = str(exc.value)
    assert "net.yaml:" in text and where in text and what in text


def test_validate_summarises_the_base_of_the_shipped_example() -> None:
    from pathlib import Path

    from fieldbus.commands.validate import check

    example = Path(__file__).resolve().parents[2] / "examples" / "amr_base.yaml"
    summary = check(str(example))
    assert summary["base"]["wheel_separation"] == 0.45 and summary["base"]["max_linear"] == 1.5
    assert summary["base"]["left_wheel_names"] == ["left_wheel"]
