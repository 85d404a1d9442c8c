"""The vectorised drive bank: same behaviour as the scalar drive, one drive faults alone.

What a step costs (nearly flat in the number of drives) is measured side by side in
benchmarks/drive_step.py: on a loaded machine a unit test of it measured the load.
"""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import numpy.typing as npt
import pytest

from fieldbus.core.cia402 import State402
from sim_slaves.drive402 import Cia402Drive, DictObjectStore, DriveParams, Obj, default_objects
from sim_slaves.drive_bank import DriveBank

DT = 1e-3
S = State402
GEARED = DriveParams(
    counts_per_rev=1 << 20,
    gear_ratio=50.0,
    velocity_units_per_count_s=0.5,
    rated_torque_nm=0.5,
    max_motor_speed_rpm=10.0,
    software_position_limit=(-15_000, 15_000),
    following_error_window_counts=500_000,  # the max speed makes it lag: no following-error fault
)

MIXED = (
    (DriveParams(), 8),
    (DriveParams(), 9),
    (DriveParams(), 10),
    (DriveParams(command_delay_cycles=3, current_loop_bandwidth_hz=400.0, coulomb_friction_nm=0.05), 8),
    (DriveParams(thermal=True, thermal_capacitance_j_per_k=0.05, fault_temperature_c=60.0), 8),
    (DriveParams(quick_stop_option=6, inertia_kg_m2=5e-4, friction_nm_s_per_rad=0.0), 8),
    # geared, 2^20 counts per motor revolution, velocity units of 2 counts/s, 0.5 N·m rated, held within
    # software position limits (the sine's 20,000 counts reach past them) and a max speed (CSP: 1.5 rad/s
    # wanted, 10 rpm allowed)
    (GEARED, 8),
    # the same in CSV: 50,000 units = 0.6 rad/s wanted, 5 rpm allowed
    (replace(GEARED, max_motor_speed_rpm=5.0), 9),
)


def _commands(k: int, i: int) -> tuple[int, int, int, int]:
    """Controlword, target position [counts], velocity [counts/s], torque [‰] of drive ``i`` at step ``k``."""
    cw = (0x00, 0x06, 0x07, 0x0F)[min(k, 3)]
    if i == 5 and 400 <= k < 700:
        cw = 0x02  # quick stop, then (option 6) stay until the master disables voltage
    if i == 5 and 700 <= k < 703:
        cw = (0x00, 0x06, 0x07)[k - 700]
    if i == 2 and 650 <= k < 660:
        cw = 0x80 if k == 655 else 0x00  # fault reset edge, then the way back up
    if i == 2 and 660 <= k < 663:
        cw = (0x06, 0x07, 0x0F)[k - 660]
    t = k * DT
    position = round(20_000 * math.sin(2 * math.pi * 2 * t))
    return cw, position, round(50_000 * math.cos(2 * math.pi * t)), round(400 * math.sin(9 * t))


def _steps(k: int, n: int, per_drive: bool) -> npt.NDArray[np.float64]:
    """The step of each drive at step ``k`` [s]: one for all, or stretches of drives with other substep counts."""
    dt = np.full(n, DT)
    if per_drive:
        if k % 3 == 0:
            dt[2:4] = 0.5e-3  # 2 substeps at 4 kHz, beside the others' 4
        if k % 5 == 0:
            dt[5] = 0.75e-3
    return dt


@pytest.mark.parametrize("per_drive", [False, True], ids=["one-dt", "dt-per-drive"])
def test_a_bank_stepped_together_matches_scalar_drives_step_for_step(per_drive: bool) -> None:
    """Mixed modes, quick stop, an injected fault and its reset, delay, current lag, friction, heat.

    dt-per-drive: stretches of the bank step with other substep counts in the same call (as after a
    power cycle), each stretch together.
    """
    params = [p for p, _ in MIXED]
    scalar = [Cia402Drive(p) for p in params]
    bank = DriveBank(params)
    s_ods = [DictObjectStore(default_objects(p)) for p in params]
    b_ods = [DictObjectStore(default_objects(p)) for p in params]
    for od_pair, (_, mode) in zip(zip(s_ods, b_ods, strict=True), MIXED, strict=True):
        for od in od_pair:
            od.values[(Obj.MODES_OF_OPERATION, 0)] = mode
    bank.drives[4].load_torque_nm = scalar[4].load_torque_nm = 0.8
    states_seen: set[State402] = set()
    limits_hit = [False, False]
    for k in range(900):
        if k == 600:
            scalar[2].inject_fault(0x5000)
            bank.drives[2].inject_fault(0x5000)
        dts = _steps(k, len(params), per_drive)
        for i in range(len(params)):
            cw, tp, tv, tt = _commands(k, i)
            for od in (s_ods[i], b_ods[i]):
                od.values[(Obj.CONTROLWORD, 0)] = cw
                od.values[(Obj.TARGET_POSITION, 0)] = tp
                od.values[(Obj.TARGET_VELOCITY, 0)] = tv
                od.values[(Obj.TARGET_TORQUE, 0)] = tt
            scalar[i].step(s_ods[i], float(dts[i]))
            bank.load_inputs(i, b_ods[i])
        bank.step(0, len(params), dts if per_drive else DT)
        for i, d in enumerate(scalar):
            bank.store_outputs(i, b_ods[i])
            b = bank.drives[i]
            assert b.state is d.state, (k, i)
            assert b.error_code == d.error_code, (k, i)
            assert b.position_rad == pytest.approx(d.position_rad, abs=1e-9), (k, i)
            assert b.temperature_c == pytest.approx(d.temperature_c, abs=1e-9), (k, i)
            for obj in (Obj.STATUSWORD, Obj.TORQUE_ACTUAL, Obj.MODES_DISPLAY):
                assert b_ods[i].values[(obj, 0)] == s_ods[i].values[(obj, 0)], (k, i, obj)
            for obj in (Obj.POSITION_ACTUAL, Obj.VELOCITY_ACTUAL, Obj.FOLLOWING_ERROR_ACTUAL):
                assert abs(int(b_ods[i].values[(obj, 0)]) - int(s_ods[i].values[(obj, 0)])) <= 1, (k, i, obj)
            states_seen.add(d.state)
        limits_hit[0] |= (
            abs(scalar[6].position_rad) * scalar[6].counts_per_rad > 14_990
        )  # at a position limit
        limits_hit[1] |= abs(scalar[7].velocity_rad_s) > 0.99 * 5.0 * 2 * math.pi / 60  # at the max speed
    # the scenario went through the interesting states (else it proves little)
    assert {S.OPERATION_ENABLED, S.QUICK_STOP_ACTIVE, S.FAULT, S.SWITCHED_ON} <= states_seen
    assert scalar[4].state is S.FAULT and scalar[4].error_code == 0x4310  # overheated
    assert scalar[2].state is S.OPERATION_ENABLED  # reset and enabled again
    assert limits_hit == [True, True]  # the geared drives met their limits, and never passed them:
    assert abs(scalar[6].position_rad) * scalar[6].counts_per_rad < 15_100
    assert max(abs(d.velocity_rad_s) for d in scalar[6:]) < 1.1 * 10.0 * 2 * math.pi / 60


def test_a_geared_limited_bank_on_the_plain_csp_path_matches_scalar_drives() -> None:
    """The lean CSP path (every drive enabled in CSP) with velocity units, a max speed and position limits."""
    params = [GEARED, replace(GEARED, max_motor_speed_rpm=0.0, software_position_limit=(-40_000, 12_000))]
    scalar: list[Cia402Drive] = [Cia402Drive(p) for p in params]
    s_ods = [DictObjectStore(default_objects(p)) for p in params]
    bank = DriveBank(params)
    for bd, p in zip(bank.drives, params, strict=True):
        bd.bind(DictObjectStore(default_objects(p)))
    bank.mode_request[:] = 8
    peak_position, peak_speed = 0, 0.0
    for k in range(1500):
        cw = (0x00, 0x06, 0x07, 0x0F)[min(k, 3)]
        tp = round(30_000 * math.sin(2 * math.pi * 2 * k * DT))
        for drive, od in zip(scalar, s_ods, strict=True):
            od.values[(Obj.CONTROLWORD, 0)] = cw
            od.values[(Obj.TARGET_POSITION, 0)] = tp
            drive.step(od, DT)
        bank.controlword[:] = cw
        bank.target_position[:] = tp
        bank.step(0, 2, DT)
        for i, sd in enumerate(scalar):
            assert bank.drives[i].position_rad == pytest.approx(sd.position_rad, abs=1e-9), (k, i)
            assert bank.statusword[i] == s_ods[i].values[(Obj.STATUSWORD, 0)], (k, i)
            assert abs(bank.velocity_counts[i] - s_ods[i].values[(Obj.VELOCITY_ACTUAL, 0)]) <= 1, (k, i)
        peak_position = max(peak_position, int(bank.position_counts[1]))
        peak_speed = max(peak_speed, abs(float(bank.vel[0])))
    assert bank._uniform[(0, 2)] == "csp"  # the lean path ran
    assert 11_900 < peak_position < 13_000  # held at the upper limit, a small overshoot (the sine: 30,000)
    limit = 10.0 * 2 * math.pi / 60  # 10 rpm [rad/s]; the sine wants 2.3 rad/s
    assert (
        0.99 * limit < peak_speed < 1.25 * limit
    )  # the velocity loop overshoots its clipped demand a little
    assert all(sd.state is S.OPERATION_ENABLED for sd in scalar)


def _enabled_bank(n: int, params: DriveParams | None = None) -> DriveBank:
    bank = DriveBank([params or DriveParams()] * n)
    for d in bank.drives:
        d.bind(DictObjectStore())
    bank.mode_request[:] = 8
    for cw in (0x00, 0x06, 0x07, 0x0F):
        bank.controlword[:] = cw
        bank.step(0, n, DT)
    assert (bank.state == S.OPERATION_ENABLED).all()
    return bank


def test_one_drive_faults_while_the_others_keep_running() -> None:
    n = 12
    bank = _enabled_bank(n)
    bank.drives[5].load_torque_nm = 50.0  # far beyond the 3 N·m peak: the joint is dragged away
    faulted_at = None
    for k in range(1, 1500):
        bank.target_position[:] = round(30_000 * math.sin(2 * math.pi * k * DT))
        bank.step(0, n, DT)
        if faulted_at is None and bank.drives[5].state is S.FAULT:
            faulted_at = k
    assert faulted_at is not None and faulted_at < 100
    assert bank.drives[5].error_code == 0x8611  # following error
    others = [i for i in range(n) if i != 5]
    assert all(bank.drives[i].state is S.OPERATION_ENABLED for i in others)
    assert np.abs(bank.following_error[others]).max() < 100  # still tracking the sine
    assert (bank.statusword[others] & 0x6F == 0x27).all()  # statusword: OPERATION ENABLED
    assert bank.statusword[5] & 0x4F == 0x08  # statusword: FAULT
    assert (bank.error_code[others] == 0).all()


def test_a_steady_run_still_hears_a_new_controlword_and_a_mode_request() -> None:
    """A run whose state machines have had nothing to do for a while (the few-calls check of
    DriveBank._state_machines) still takes a quick stop and a mode change in the cycle they come."""
    bank = _enabled_bank(3)
    for _ in range(20):
        bank.step(0, 3, DT)
    assert (0, 3) in bank._calm  # the steady check is the one at work
    bank.controlword[1] = 0x02  # quick stop
    bank.step(0, 3, DT)
    assert [d.state for d in bank.drives] == [S.OPERATION_ENABLED, S.QUICK_STOP_ACTIVE, S.OPERATION_ENABLED]
    for _ in range(20):
        bank.step(0, 3, DT)
    assert (0, 3) in bank._calm
    bank.mode_request[2] = 9  # CSV
    bank.step(0, 3, DT)
    assert bank.mode_display.tolist() == [8, 8, 9]
    assert bank.drives[0].state is S.OPERATION_ENABLED  # (drive 1, option 2: stopped, now disabled)


def test_a_drive_alone_is_a_bank_of_one_and_moves_exactly_as_in_a_bank() -> None:
    """One model: a drive built alone steps through its own bank of one, bit for bit as a drive of a bank.

    Each drive of the mixed scenario alone, against a bank of three copies of it commanded alike (so
    the bank takes the same path: the lean CSP one, or the general one). Before, the drive alone had
    physics of its own, equal to the bank's to ~1e-11 rad only.
    """
    for i, (p, mode) in enumerate(MIXED):
        alone = Cia402Drive(p)
        assert alone.bank.drives == [alone] and alone.slot == 0
        bank = DriveBank([p] * 3)
        a_od = DictObjectStore(default_objects(p))
        b_ods = [DictObjectStore(default_objects(p)) for _ in range(3)]
        for od in (a_od, *b_ods):
            od.values[(Obj.MODES_OF_OPERATION, 0)] = mode
        alone.load_torque_nm = 0.8 if i == 4 else 0.0
        bank.load[:] = alone.load_torque_nm
        states = set()
        for k in range(450):
            if k == 420:  # (the quick-stopper is in QUICK STOP ACTIVE since step 400)
                alone.inject_fault(0x5000)
                for d in bank.drives:
                    d.inject_fault(0x5000)
            cw, tp, tv, tt = _commands(k, i)
            for j, od in enumerate((a_od, *b_ods)):
                od.values.update({(0x6040, 0): cw, (0x607A, 0): tp, (0x60FF, 0): tv, (0x6071, 0): tt})
                if j:
                    bank.load_inputs(j - 1, od)
            alone.step(a_od, DT)
            bank.step(0, 3, DT)
            bank.store_outputs(1, b_ods[1])
            b = bank.drives[1]
            assert (alone.state, alone.position_rad, alone.velocity_rad_s, alone.temperature_c) == (
                b.state,
                b.position_rad,
                b.velocity_rad_s,
                b.temperature_c,
            ), (k, i)
            assert a_od.values == b_ods[1].values, (k, i)
            states.add(alone.state)
        assert S.FAULT in states, i  # each went through the injected fault (and the quick-stopper: QSA)


def test_the_bank_reaches_no_private_attribute_of_a_drive() -> None:
    """drive_bank uses the drive's public interface: no ``x._name`` but on ``self``, no private imports
    (but its own optional C substeps, ``sim_slaves._motion``)."""
    import ast
    import inspect

    from sim_slaves import drive_bank

    tree = ast.parse(inspect.getsource(drive_bank))
    reached = [
        f"line {node.lineno}: {ast.unparse(node)}"
        for node in ast.walk(tree)
        if isinstance(node, ast.Attribute)
        and node.attr.startswith("_")
        and not node.attr.startswith("__")
        and not (isinstance(node.value, ast.Name) and node.value.id == "self")
    ]
    imported = [
        f"line {node.lineno}: {alias.name}"
        for node in ast.walk(tree)
        if isinstance(node, ast.ImportFrom)
        for alias in node.names
        if alias.name.startswith("_") and not (node.module == "sim_slaves" and alias.name == "_motion")
    ]
    assert reached == [] and imported == []
