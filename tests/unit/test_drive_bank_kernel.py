"""The C substeps of the plain CSP path (sim_slaves._motion) against numpy's: the same bits, step after step.

Two banks built alike take the same commands; one steps with the C kernel,
the other with ``drive_bank.motion_kernel`` set to None (the numpy reference).
Every state and output array must hold the same bits after every step (float
arrays compared as their bit patterns, so a different rounding anywhere, a
fused multiply-add or another order of operations, fails). Both sides are our
own code: the oracle for the model itself is test_drive_bank.py (the bank
against drives alone); here the reference is the numpy path.
"""

from __future__ import annotations

import math
from dataclasses import replace
from typing import Any

import numpy as np
import numpy.typing as npt
import pytest

from fieldbus.core.cia402 import State402
from sim_slaves import drive_bank
from sim_slaves.drive402 import DictObjectStore, DriveParams, default_objects
from sim_slaves.drive_bank import DriveBank

DT = 1e-3
WIDE = 50_000_000  # following-error window [counts]: no fault takes a drive off the CSP path

STATE = ("pos", "vel", "integ", "prev_target", "prev_vff", "tau", "tau_eff", "shaft", "limit", "fe_time")
OUTPUTS = ("statusword", "position_counts", "velocity_counts", "torque_permille", "following_error", "noise")


def _random_params(rng: np.random.Generator, case: str, rate_hz: float) -> DriveParams:
    """One drive of ``case``: its mechanics and gains drawn, and the case's limit or imperfection."""
    p = DriveParams(
        control_rate_hz=rate_hz,
        counts_per_rev=int(rng.choice([4096, 1 << 17, 1 << 20])),
        inertia_kg_m2=float(rng.uniform(2e-5, 1e-3)),
        friction_nm_s_per_rad=float(rng.choice([0.0, rng.uniform(1e-4, 5e-3)])),
        velocity_bandwidth_hz=float(rng.uniform(40.0, 300.0)),
        position_gain_per_s=float(rng.uniform(50.0, 400.0)),
        velocity_feedforward=float(rng.uniform(0.0, 1.0)),
        torque_feedforward=float(rng.uniform(0.0, 1.0)),
        following_error_window_counts=WIDE,
        command_delay_cycles=int(rng.integers(0, 3)),
    )
    return _case(p, case, rng)


def _case(p: DriveParams, case: str, rng: np.random.Generator) -> DriveParams:
    if case == "noise":
        return replace(p, encoder_counts_per_rev=int(rng.choice([1000, 1 << 14])), encoder_noise_counts=2.5)
    if case == "speed":
        return replace(p, max_motor_speed_rpm=float(rng.uniform(5.0, 30.0)))
    if case == "position":  # within 0.1-0.8 rad each side: the targets reach 1 rad
        lo, hi = rng.uniform(0.1, 0.8, 2) * p.counts_per_rev / (2 * math.pi)
        return replace(p, software_position_limit=(-int(lo), int(hi)))
    if case == "torque":
        return replace(p, max_torque_permille=int(rng.integers(5, 60)))
    if case == "following":  # a narrow window, a timeout beyond the run: over it now and then, no fault
        return replace(
            p, following_error_window_counts=int(rng.integers(50, 400)), following_error_timeout_ms=60_000
        )
    if case == "mixed":
        return _case(p, str(rng.choice(["plain", "noise", "speed", "position", "torque", "following"])), rng)
    return p


def _bank(params: list[DriveParams]) -> DriveBank:
    bank = DriveBank(params, seed=5)
    for d, p in zip(bank.drives, params, strict=True):
        d.bind(DictObjectStore(default_objects(p)))
    bank.mode_request[:] = 8  # CSP
    return bank


def _bits(x: npt.NDArray[Any]) -> npt.NDArray[Any]:
    """An array's bit patterns (floats as int64; the others as they are)."""
    return x.view(np.int64) if x.dtype == np.float64 else x


def _assert_same(c: DriveBank, ref: DriveBank, k: int) -> None:
    for name in STATE + OUTPUTS:
        x, y = getattr(c, name), getattr(ref, name)
        assert np.array_equal(_bits(x), _bits(y)), (k, name, x, y)
    assert np.array_equal(c.state, ref.state), k


class _Counted:
    """A kernel whose calls are counted: substep calls, and output calls that C settled / left to numpy."""

    def __init__(self, kernel: drive_bank.MotionKernel) -> None:
        self.kernel = kernel
        self.substeps = 0
        self.settled = 0
        self.declined = 0

    def csp(self, *args: Any) -> bool:
        self.substeps += 1
        return self.kernel.csp(*args)

    def csp_outputs(self, *args: Any) -> bool:
        done = self.kernel.csp_outputs(*args)
        self.settled += done
        self.declined += not done
        return done


def _step_both(
    c: DriveBank,
    ref: DriveBank,
    kernel: drive_bank.MotionKernel,
    monkeypatch: pytest.MonkeyPatch,
    cw: int,
    targets: npt.NDArray[np.int64],
) -> None:
    for bank, k in ((c, kernel), (ref, None)):
        monkeypatch.setattr(drive_bank, "motion_kernel", k)
        bank.controlword[:] = cw
        bank.target_position[:] = targets
        bank.step(0, bank.n, DT)


def _targets(rng: np.random.Generator, n: int, k: int, cpr: npt.NDArray[np.float64]) -> npt.NDArray[np.int64]:
    """A sine of about 1 rad at 1.5 Hz, a random walk on it, and now and then a jump (torque limit)."""
    wave = np.sin(2 * math.pi * 1.5 * k * DT + np.arange(n))
    jump = (rng.random(n) < 0.01) * rng.uniform(-0.5, 0.5, n)
    return np.round((wave + jump + rng.normal(0.0, 0.002, n)) * cpr / (2 * math.pi)).astype(np.int64)


def test_the_kernel_is_built() -> None:
    """CI builds the extension (pip install -e '.[all]'): its absence is a failure, not a quiet numpy path."""
    assert drive_bank.motion_kernel is not None, (
        "sim_slaves._motion is not built (python setup.py build_ext --inplace)"
    )


@pytest.mark.parametrize("n", [1, 3, 17])
@pytest.mark.parametrize(
    "case", ["plain", "noise", "speed", "position", "torque", "following", "mixed", "alike"]
)
def test_the_c_substeps_give_the_numpy_paths_bits(n: int, case: str, monkeypatch: pytest.MonkeyPatch) -> None:
    """Random banks in CSP at 1 kHz, 600 steps: every array bit for bit as the numpy path's.

    ``alike``: every drive the default one (4 substeps; the coefficients are numbers); the others draw
    each drive's mechanics and gains (arrays) and the bank's control rate (3 or 5 substeps); ``mixed``
    draws the case per drive too.
    """
    kernel = drive_bank.motion_kernel
    assert kernel is not None, "sim_slaves._motion is not built"
    counted = _Counted(kernel)
    rng = np.random.default_rng([n, len(case)])
    if case == "alike":
        params = [replace(DriveParams(), following_error_window_counts=WIDE, max_torque_permille=400)] * n
    else:
        rate_hz = float(rng.choice([3000.0, 5000.0]))  # 3 or 5 substeps: k / steps rounds
        params = [_random_params(rng, case, rate_hz) for _ in range(n)]
    c, ref = _bank(params), _bank(params)
    cpr = np.array([p.counts_per_rev for p in params], dtype=np.float64)
    for cw in (0x00, 0x06, 0x07, 0x0F):
        _step_both(c, ref, counted, monkeypatch, cw, np.zeros(n, dtype=np.int64))
    assert (c.state == State402.OPERATION_ENABLED).all()
    before = counted.substeps
    limited = held = timed = 0
    peak_speed = np.zeros(n)
    for k in range(600):
        _step_both(c, ref, counted, monkeypatch, 0x0F, _targets(rng, n, k, cpr))
        _assert_same(c, ref, k)
        limited += int(c.limit.any())
        held += int(((c.target_position < c.pmin) | (c.target_position > c.pmax)).any())
        peak_speed = np.maximum(peak_speed, np.abs(c.vel))
        timed += int(c.fe_time.any())
    assert counted.substeps - before == 600  # the C kernel stepped every cycle (the plain CSP path)
    if case == "following":  # numpy's turn while beyond the window (the timer), C's the rest
        assert counted.declined > 0 and counted.settled > 0 and timed > 0
    elif case != "mixed":
        assert counted.declined == 0 and counted.settled == counted.substeps
    assert c._uniform[(0, n)] == "csp"
    if case == "torque":
        assert limited > 0  # the torque limit was hit
    if case == "position":
        assert held > 0  # targets beyond the software limits were held
    if case == "speed":  # the sine wants up to 9 rad/s, the limits allow 0.5-3: the clip was at work
        assert (peak_speed > 0.9 * c.vmax).all()


def test_nan_in_the_state_spreads_the_same_way(monkeypatch: pytest.MonkeyPatch) -> None:
    """A NaN target, torque limit, speed limit or load (a poisoned array): numpy's NaN rules in C too."""
    kernel = drive_bank.motion_kernel
    assert kernel is not None, "sim_slaves._motion is not built"
    params = [replace(DriveParams(), following_error_window_counts=WIDE, max_motor_speed_rpm=300.0)] * 5
    c, ref = _bank(params), _bank(params)
    for cw in (0x00, 0x06, 0x07, 0x0F):
        _step_both(c, ref, kernel, monkeypatch, cw, np.zeros(5, dtype=np.int64))
    rng = np.random.default_rng(3)
    with np.errstate(invalid="ignore"):  # NaN counts cast to int64: the same on both sides
        for k in range(200):
            if k == 50:
                for bank in (c, ref):
                    bank.prev_target[0] = math.nan  # the feed-forward and the reference of drive 0
                    bank.tmax[1] = math.nan
                    bank.vmax[2] = math.nan
                    bank.load[3] = math.nan
            _step_both(c, ref, kernel, monkeypatch, 0x0F, _targets(rng, 5, k, np.full(5, float(1 << 17))))
            for name in STATE:
                x, y = getattr(c, name), getattr(ref, name)
                assert np.array_equal(x, y, equal_nan=x.dtype == np.float64), (k, name, x, y)
                if x.dtype == np.float64:  # and the bits of the numbers (signs of zeros included)
                    ok = ~np.isnan(x)
                    assert np.array_equal(_bits(x)[ok], _bits(y)[ok]), (k, name)
    assert np.isnan(c.pos[:4]).all() and np.isfinite(c.pos[4])  # it spread in drives 0-3 alone
    assert c.limit[:4].all()  # NaN != NaN: numpy counts the drive as torque-limited, so does C


def _near_half(rng: np.random.Generator, per_unit: npt.NDArray[np.float64]) -> npt.NDArray[np.float64]:
    """Values that ``per_unit`` turns into whole numbers and a half, give or take a few units in the last
    place: where floor(x + 0.5) tells one rounding order from another."""
    n = len(per_unit)
    half = (rng.integers(-30_000, 30_000, n) + 0.5) / per_unit
    return np.asarray(half * (1.0 + rng.integers(-4, 5, n) * 2.0**-52), dtype=np.float64)


@pytest.mark.parametrize("encoder", ["ideal", "coarse"])
def test_the_outputs_round_at_half_counts_as_numpy_does(
    encoder: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Positions, speeds, torques and targets a hair from half a count: counts, following error, speed
    and torque actual values as the numpy path gives them (another order of operations rounds some of
    them the other way)."""
    kernel = drive_bank.motion_kernel
    assert kernel is not None, "sim_slaves._motion is not built"
    counted = _Counted(kernel)
    rng = np.random.default_rng(17)
    n = 64
    params = [
        replace(
            DriveParams(),
            counts_per_rev=int(rng.choice([4096, 1 << 17, 1 << 20])),
            rated_torque_nm=float(rng.uniform(0.1, 3.0)),
            velocity_units_per_count_s=float(rng.choice([1.0, 0.1, 0.37])),
            encoder_counts_per_rev=int(rng.choice([1000, 1 << 14])) if encoder == "coarse" else 0,
            following_error_window_counts=WIDE,
        )
        for _ in range(n)
    ]
    c, ref = _bank(params), _bank(params)
    for cw in (0x00, 0x06, 0x07, 0x0F):
        _step_both(c, ref, counted, monkeypatch, cw, np.zeros(n, dtype=np.int64))
    assert c.ideal_encoder is (encoder == "ideal")
    run = slice(0, n)
    before = counted.settled
    for k in range(64):
        pos = _near_half(rng, c.cpr if c.ideal_encoder else c.epr)
        vel, tau = _near_half(rng, c.vpr), _near_half(rng, 1000.0 / c.rated)
        target = _near_half(rng, c.cpr)
        for bank, kern in ((c, counted), (ref, None)):
            monkeypatch.setattr(drive_bank, "motion_kernel", kern)
            bank.pos[:], bank.vel[:], bank.tau[:] = pos, vel, tau
            bank._csp_outputs(run, DT, target, False)
        _assert_same(c, ref, k)
    assert counted.settled - before == 64 and counted.declined == 0


@pytest.mark.parametrize("powered", [True, False], ids=["holding", "coasting"])
def test_a_rotor_at_rest_settles_to_zero_not_to_subnormals_on_both_paths(
    powered: bool, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Held still (CSP, a constant target) or coasting unpowered, a rotor's speed and integrator decay
    geometrically: within 4 s they would be subnormal (below 2.2e-308), where x86 arithmetic is some
    100 times slower. They become 0 instead, in C as in numpy, bit for bit, and stay there."""
    kernel = drive_bank.motion_kernel
    assert kernel is not None, "sim_slaves._motion is not built"
    friction = DriveParams().friction_nm_s_per_rad if powered else 0.05  # coasting: stops within 0.1 s
    params = [replace(DriveParams(), following_error_window_counts=WIDE, friction_nm_s_per_rad=friction)] * 3
    c, ref = _bank(params), _bank(params)
    enable = (0x00, 0x06, 0x07, 0x0F) if powered else (0x00,)
    for cw in enable:
        _step_both(c, ref, kernel, monkeypatch, cw, np.zeros(3, dtype=np.int64))
    if not powered:
        c.vel[:] = ref.vel[:] = [3.0, -2.0, 0.5]  # spinning when the power went
    target = np.array([1000, -700, 5], dtype=np.int64)
    tiny = np.finfo(np.float64).tiny
    for k in range(6000):
        _step_both(c, ref, kernel, monkeypatch, 0x0F if powered else 0x00, target)
        _assert_same(c, ref, k)
        for x in (c.vel, c.integ):
            assert not ((x != 0.0) & (np.abs(x) < tiny)).any(), (k, x)
    assert (c.vel == 0.0).all()  # settled exactly
    assert (c.state == (State402.OPERATION_ENABLED if powered else State402.SWITCH_ON_DISABLED)).all()


def test_the_kernel_s_bank_refuses_drives_outside_it_and_no_substep() -> None:
    """Both cycles of the C bank check their drive range and substeps the same way, naming the call."""
    bank = _bank([DriveParams(control_rate_hz=1000.0)] * 3)
    kernel = bank._held_by_kernel()
    assert kernel is not None, "sim_slaves._motion is not built (python setup.py build_ext --inplace)"
    for a, b, steps in ((0, 4, 1), (2, 1, 1), (-1, 2, 1), (0, 3, 0)):
        with pytest.raises(
            ValueError, match=rf"idle_cycle: need 0 <= a <= b <= 3 .* a={a} b={b} steps={steps}"
        ):
            kernel.idle_cycle(a, b, steps, 0.0, 0.0, 0.0, 0.0, 0, 0, 0)
        with pytest.raises(
            ValueError, match=rf"csp_cycle: need 0 <= a <= b <= 3 .* a={a} b={b} steps={steps}"
        ):
            kernel.csp_cycle(a, b, 0.001, steps, 0.0, 0.0, 0.0, 0.0, 0.0, False, 0, 0, 0)
