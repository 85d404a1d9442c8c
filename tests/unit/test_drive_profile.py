"""Profile position (PP, mode 1) and profile velocity (PV, mode 3) in the emulated drive.

The trajectory generator (``sim_slaves.profile402``) is checked against the closed-form trapezoid;
the scalar drive (``drive402``) and the vectorised bank (``drive_bank``) run the same PP/PV scenarios
and must agree step for step, and end where CiA 402-2 says (absolute, relative, change immediately,
queued set-point, halt, PV ramps). Our own emulator on both sides: the independent masters are
canopen's BaseNode402 (tests/integration/test_profile_canopen_oracle.py) and pysoem over veth.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import pytest

from fieldbus.core.cia402 import State402
from sim_slaves.drive402 import Cia402Drive, DictObjectStore, DriveParams, Obj, default_objects
from sim_slaves.drive_bank import DriveBank
from sim_slaves.profile402 import position_step, velocity_step

DT = 1e-3
V_PROFILE = 100_000  # 0x6081 [counts/s]
ACCEL = 500_000  # 0x6083 [counts/s²]
DECEL = 250_000  # 0x6084 [counts/s²]
NEW, IMMEDIATE, RELATIVE, HALT = 0x10, 0x20, 0x40, 0x100
REACHED, ACK = 0x400, 0x1000


def _trapezoid_steps(distance: float, v_max: float, accel: float, decel: float) -> float:
    """Closed-form duration [s] of a rest-to-rest trapezoid (or triangle) over ``distance``."""
    ramps = v_max * v_max / (2 * accel) + v_max * v_max / (2 * decel)
    if ramps <= distance:
        return v_max / accel + v_max / decel + (distance - ramps) / v_max
    peak = (2 * distance * accel * decel / (accel + decel)) ** 0.5
    return peak / accel + peak / decel


def _run_generator(p: float, v: float, target: float, v_max: float, a: float, d: float) -> list[float]:
    vs = [v]
    for _ in range(100_000):
        p, v, done = position_step(p, v, target, v_max, a, d, DT)
        vs.append(v)
        if done:
            assert p == target and v == 0.0
            return vs
    raise AssertionError("the move never ended")


@pytest.mark.parametrize(
    ("distance", "v_max", "accel", "decel"),
    [(10.0, 5.0, 20.0, 10.0), (-3.0, 8.0, 5.0, 40.0), (0.05, 5.0, 20.0, 10.0), (1e-4, 1.0, 1.0, 1.0)],
)
def test_the_generator_moves_rest_to_rest_in_the_trapezoid_time_within_its_limits(
    distance: float, v_max: float, accel: float, decel: float
) -> None:
    vs = np.array(_run_generator(0.0, 0.0, distance, v_max, accel, decel))
    cycles = len(vs) - 1
    expected = _trapezoid_steps(abs(distance), v_max, accel, decel) / DT
    assert abs(cycles - expected) <= 2, (cycles, expected)
    assert np.abs(vs).max() <= v_max * (1 + 1e-9)
    dv = np.diff(vs) * np.sign(distance) / DT
    assert dv.max() <= accel * (1 + 1e-6) and dv.min() >= -decel * (1 + 1e-6)


def test_a_target_changed_in_motion_joins_smoothly_and_a_reverse_brakes_at_the_deceleration() -> None:
    # 5 rad/s toward +10 rad, then the target moves behind: brake at decel through zero, then back
    p, v = 2.0, 5.0
    vs = [v]
    for _ in range(20_000):
        p, v, done = position_step(p, v, -1.0, 5.0, 20.0, 10.0, DT)
        vs.append(v)
        if done:
            break
    assert p == -1.0 and v == 0.0
    v_arr = np.array(vs)
    dv = np.diff(v_arr) / DT
    braking = v_arr[:-1] > 0.0  # still moving away: the ramp at decel (10), not accel (20)
    assert abs(int(braking.sum()) - 500) <= 1 and np.allclose(dv[braking], -10.0)  # 5 rad/s at 10 rad/s²
    assert np.abs(dv).max() <= 20.0 * (1 + 1e-6)


def test_from_any_motion_the_generator_lands_on_target_never_changing_speed_faster_than_its_ramps() -> None:
    """Seeded random starts (position, velocity up to twice the limit, near and far targets) and one
    made to fail: 5 rad/s half a cycle's travel short of the target (a snap to rest was a 5 rad/s step)."""
    rng = np.random.default_rng(25)
    cases = [(0.0, 5.0, 0.001, 5.0, 10.0, 10.0)]
    for _ in range(400):
        v_max, accel, decel = (
            10 ** rng.uniform(-0.5, 1.5),
            10 ** rng.uniform(0.5, 3),
            10 ** rng.uniform(0.5, 3),
        )
        p = rng.uniform(-10, 10)
        reach = float(rng.choice([0.0, 1e-9, 1e-3, 0.1, 3.0])) * rng.uniform(-1, 1)
        cases.append((p, rng.uniform(-2, 2) * v_max, p + reach, v_max, accel, decel))
    for p, v, target, v_max, accel, decel in cases:
        top = max(abs(v), v_max) * (1 + 1e-9)
        for _ in range(200_000):
            p_new, v_new, done = position_step(p, v, target, v_max, accel, decel, DT)
            if v * v_new >= 0.0 and abs(v_new) > abs(v):
                assert abs(v_new) - abs(v) <= accel * DT * (1 + 1e-6), (p, v, target)
            else:
                assert abs(v_new - v) <= decel * DT * (1 + 1e-6), (p, v, target, v_new)
            assert abs(v_new) <= top
            p, v = p_new, v_new
            if done:
                break
        assert done and p == target and v == 0.0


def test_the_velocity_ramp_speeds_up_at_accel_and_slows_or_reverses_at_decel() -> None:
    v, n = 0.0, 0
    while v != 3.0:
        v, n = velocity_step(v, 3.0, 10.0, 30.0, DT), n + 1
    assert n == 300
    while v != -3.0:
        v, n = velocity_step(v, -3.0, 10.0, 30.0, DT), n + 1
    assert n == 300 + 100 + 300  # brake to 0 at 30 rad/s², then speed up at 10 rad/s²


# -- the drive and the bank ------------------------------------------------------------------------


Scenario = Callable[[int], tuple[int, int, int]]  # step -> (controlword, 0x607A, 0x60FF)
ENABLE = (0x06, 0x06, 0x06, 0x07, 0x07, 0x0F)


def _enable(k: int) -> int:
    return ENABLE[k] if k < len(ENABLE) else 0x0F


def _absolute(k: int) -> tuple[int, int, int]:
    return _enable(k) | (NEW if 10 <= k < 20 else 0), 200_000, 0


def _relative(k: int) -> tuple[int, int, int]:
    edge = 10 <= k < 15 or 1800 <= k < 1805
    return _enable(k) | (NEW | RELATIVE if edge else 0), 50_000, 0


def _immediate(k: int) -> tuple[int, int, int]:
    if k < 300:
        return _enable(k) | (NEW if 10 <= k < 15 else 0), 300_000, 0
    return 0x0F | (NEW | IMMEDIATE if 300 <= k < 305 else 0), -50_000, 0


def _queued(k: int) -> tuple[int, int, int]:
    if k < 100:
        return _enable(k) | (NEW if 10 <= k < 15 else 0), 100_000, 0
    if k < 120:  # queued behind the first move
        return 0x0F | (NEW if k < 105 else 0), 150_000, 0
    return 0x0F | (NEW if 120 <= k < 125 else 0), 400_000, 0  # queue full: refused


def _halted(k: int) -> tuple[int, int, int]:
    return _enable(k) | (NEW if 10 <= k < 15 else 0) | (HALT if 400 <= k < 1400 else 0), 150_000, 0


def _velocity(k: int) -> tuple[int, int, int]:
    v = 100_000 if k < 1500 else -50_000
    return _enable(k) | (HALT if k >= 2500 else 0), 0, v


SCENARIOS: tuple[tuple[str, int, Scenario], ...] = (
    ("absolute", 1, _absolute),
    ("relative", 1, _relative),
    ("immediate", 1, _immediate),
    ("queued", 1, _queued),
    ("halted", 1, _halted),
    ("velocity", 3, _velocity),
)
CYCLES = 3600


def _od(p: DriveParams, mode: int) -> DictObjectStore:
    od = DictObjectStore(default_objects(p))
    od.values[(Obj.MODES_OF_OPERATION, 0)] = mode
    od.values[(0x6081, 0)] = V_PROFILE
    od.values[(0x6083, 0)] = ACCEL
    od.values[(0x6084, 0)] = DECEL
    return od


def test_profile_modes_in_the_drive_and_the_bank_agree_step_for_step_and_end_on_target() -> None:
    p = DriveParams()
    n = len(SCENARIOS)
    scalar = [Cia402Drive(p) for _ in SCENARIOS]
    bank = DriveBank([p] * n)
    s_ods = [_od(p, mode) for _, mode, _ in SCENARIOS]
    b_ods = [_od(p, mode) for _, mode, _ in SCENARIOS]
    sw_log = np.zeros((CYCLES, n), dtype=np.int64)
    pos_log = np.zeros((CYCLES, n), dtype=np.int64)
    vel_log = np.zeros((CYCLES, n), dtype=np.int64)
    for k in range(CYCLES):
        for i, (_, _, scenario) in enumerate(SCENARIOS):
            cw, tp, tv = scenario(k)
            for od in (s_ods[i], b_ods[i]):
                od.values[(Obj.CONTROLWORD, 0)] = cw
                od.values[(Obj.TARGET_POSITION, 0)] = tp
                od.values[(Obj.TARGET_VELOCITY, 0)] = tv
            scalar[i].step(s_ods[i], DT)
            bank.load_inputs(i, b_ods[i])
        bank.step(0, n, DT)
        for i, (name, _, _) in enumerate(SCENARIOS):
            bank.store_outputs(i, b_ods[i])
            sw = int(s_ods[i].values[(Obj.STATUSWORD, 0)])
            assert int(b_ods[i].values[(Obj.STATUSWORD, 0)]) == sw, (k, name)
            assert bank.drives[i].position_rad == pytest.approx(scalar[i].position_rad, abs=1e-9), (k, name)
            sw_log[k, i] = sw
            pos_log[k, i] = int(s_ods[i].values[(Obj.POSITION_ACTUAL, 0)])
            vel_log[k, i] = int(s_ods[i].values[(Obj.VELOCITY_ACTUAL, 0)])
    for d in scalar:
        assert d.state is State402.OPERATION_ENABLED and d.error_code == 0
    col = {name: i for i, (name, _, _) in enumerate(SCENARIOS)}
    window = DriveParams().position_window_counts

    # absolute: acknowledged on the edge's cycle, until the cycle bit 4 drops; reached at the end only
    sw = sw_log[:, col["absolute"]]
    assert not sw[9] & ACK and sw[10] & ACK and sw[19] & ACK and not sw[20] & ACK
    assert sw[9] & REACHED  # at rest before the set-point: the (empty) move is done
    assert not (sw[10:2000] & REACHED).any()
    speeds = np.abs(np.diff(pos_log[:, col["absolute"]])) / DT
    assert speeds.max() <= V_PROFILE * 1.02  # the cascade follows the generator, capped at 0x6081
    # the move takes about the trapezoid's time (2.3 s) plus the loop's settling, then stays reached
    reached_at = int(np.flatnonzero(sw[10:] & REACHED)[0]) + 10
    expected = 10 + _trapezoid_steps(200_000, V_PROFILE, ACCEL, DECEL) / DT
    assert expected - 2 <= reached_at <= expected + 60, (reached_at, expected)
    assert (sw[reached_at:] & REACHED).all()

    ends = {
        "absolute": 200_000,
        "relative": 100_000,
        "immediate": -50_000,
        "queued": 150_000,
        "halted": 150_000,
    }
    for name, end in ends.items():
        assert abs(pos_log[-1, col[name]] - end) <= window, (name, pos_log[-1, col[name]])
        assert sw_log[-1, col[name]] & REACHED, name
    # queued: the second set-point is acknowledged while the first move runs (queue full: bit 12 stays
    # up), the third is refused, the second runs after the first
    sw = sw_log[:, col["queued"]]
    assert sw[100] & ACK and (sw[105:1000] & ACK).all()
    assert abs(pos_log[:, col["queued"]].max() - 150_000) <= window
    # halted: stands still (bit 10) during the halt short of the target, resumes when it drops
    sw, pos = sw_log[:, col["halted"]], pos_log[:, col["halted"]]
    assert sw[1390] & REACHED and abs(pos[1390] - pos[1300]) <= 2 and pos[1390] < 140_000
    # velocity: ramps to 100,000 then -50,000 counts/s (bit 10 at speed), halts (bit 12: speed 0)
    sw, vel = sw_log[:, col["velocity"]], vel_log[:, col["velocity"]]
    assert abs(vel[1400] - 100_000) <= 1000 and sw[1400] & REACHED and not sw[1400] & ACK
    ramp_up = int(np.flatnonzero(sw[6:] & REACHED)[0]) + 6
    assert 6 + 200 - 10 <= ramp_up <= 6 + 200 + 20, ramp_up  # 100,000 / 500,000 s
    assert not sw[1600] & REACHED  # decelerating through zero at 0x6084
    assert abs(vel[2400] + 50_000) <= 1000 and sw[2400] & REACHED
    assert abs(vel[-1]) <= 1000 and sw[-1] & ACK and sw[-1] & REACHED


CHANGE_ON_SETPOINT = 0x200  # controlword bit 9


def _pp_run(scenario: Scenario, option: int = 0, cycles: int = 2500) -> tuple[np.ndarray, np.ndarray]:
    """A PP scenario on the scalar drive and the bank side by side (they must agree); positions and
    statuswords per cycle. ``option``: 0x60F2."""
    p = DriveParams()
    drive, bank = Cia402Drive(p), DriveBank([p])
    s_od, b_od = _od(p, 1), _od(p, 1)
    for od in (s_od, b_od):
        od.values[(0x60F2, 0)] = option
    pos, sws = np.zeros(cycles, dtype=np.int64), np.zeros(cycles, dtype=np.int64)
    for k in range(cycles):
        cw, tp, _ = scenario(k)
        for od in (s_od, b_od):
            od.values[(Obj.CONTROLWORD, 0)] = cw
            od.values[(Obj.TARGET_POSITION, 0)] = tp
        drive.step(s_od, DT)
        bank.load_inputs(0, b_od)
        bank.step(0, 1, DT)
        bank.store_outputs(0, b_od)
        assert b_od.values[(Obj.STATUSWORD, 0)] == s_od.values[(Obj.STATUSWORD, 0)], k
        pos[k] = int(s_od.values[(Obj.POSITION_ACTUAL, 0)])
        sws[k] = int(s_od.values[(Obj.STATUSWORD, 0)])
    return pos, sws


def _two_setpoints(bit9: int) -> Scenario:
    def scenario(k: int) -> tuple[int, int, int]:
        if k < 100:
            return _enable(k) | (NEW if 10 <= k < 15 else 0), 100_000, 0
        return 0x0F | (NEW | bit9 if 100 <= k < 105 else 0), 200_000, 0

    return scenario


def test_change_on_setpoint_passes_the_first_target_at_speed_instead_of_stopping_on_it() -> None:
    queued, _ = _pp_run(_two_setpoints(0), cycles=3500)
    flying, sw = _pp_run(_two_setpoints(CHANGE_ON_SETPOINT), cycles=3500)
    window = DriveParams().position_window_counts

    def speed_at(pos: np.ndarray, where: int) -> float:
        k = int(np.flatnonzero(pos >= where)[0])
        return float(pos[k + 1] - pos[k - 1]) / (2 * DT)

    assert speed_at(queued, 100_000) < 0.1 * V_PROFILE  # bit 9 low: rest on the first target
    assert speed_at(flying, 100_000) > 0.9 * V_PROFILE  # bit 9: through it at the profile velocity
    assert abs(flying[-1] - 200_000) <= window and abs(queued[-1] - 200_000) <= window and sw[-1] & REACHED
    assert int(np.flatnonzero(flying >= 200_000 - window)[0]) < int(
        np.flatnonzero(queued >= 200_000 - window)[0]
    )


@pytest.mark.parametrize("option", [0, 2])
def test_positioning_option_code_says_what_a_relative_target_is_relative_to(option: int) -> None:
    """0x60F2 bits 0-1: 0 the preceding target, 2 the actual position. The first relative move of
    50,000 is halted at ~30,000 (bit 8) and released at once with a second relative 50,000."""

    def scenario(k: int) -> tuple[int, int, int]:
        edge = 10 <= k < 15 or 700 <= k < 705
        halt = HALT if 200 <= k < 700 else 0
        return _enable(k) | (NEW | RELATIVE | IMMEDIATE if edge else 0) | halt, 50_000, 0

    pos, sw = _pp_run(scenario, option, cycles=3000)
    halted_at = int(pos[699])
    assert 20_000 < halted_at < 45_000
    want = 100_000 if option == 0 else halted_at + 50_000
    assert abs(pos[-1] - want) <= DriveParams().position_window_counts, (pos[-1], want)
    assert sw[-1] & REACHED
