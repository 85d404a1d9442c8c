"""The AMR base of examples/amr_base.yaml on the in-process emulator, in virtual time: a 2 m square
by cmd_vel, the odometry against the emulated drives' own shaft positions, the timeout ramp, faults."""

from __future__ import annotations

import itertools
import math
from pathlib import Path

import numpy as np
import pytest

import fieldbus
from fieldbus.testing import emulate
from fieldbus.wheeled_base import WheeledBase

NETWORK = Path(__file__).resolve().parents[2] / "examples" / "amr_base.yaml"
COUNTS_PER_RAD = 4096 * 20 / (2 * math.pi)  # seed 001: encoder 4096 counts/rev, reduction 20


class Truth:
    """The base's pose from the emulated drives' shaft positions, integrated here in 1 ms steps
    (midpoint heading): independent of fieldbus's odometry."""

    def __init__(self, positions: list[float]) -> None:
        self.last = [p / COUNTS_PER_RAD for p in positions]
        self.x = self.y = self.heading = 0.0
        self.travel = 0.0

    def update(self, positions: list[float]) -> None:
        now = [p / COUNTS_PER_RAD for p in positions]
        dl, dr = ((n - o) * 0.08 for n, o in zip(now, self.last, strict=True))
        self.last = now
        ds, dth = (dl + dr) / 2, (dr - dl) / 0.45
        mid = self.heading + dth / 2
        self.x += ds * math.cos(mid)
        self.y += ds * math.sin(mid)
        self.heading += dth
        self.travel += abs(ds)


def _enable(emu: object, base: WheeledBase) -> tuple[fieldbus.Cia402Controller, object]:
    op = emu.op  # type: ignore[attr-defined]
    wheels = op["wheels"]
    ctrl = fieldbus.Cia402Controller(wheels.n_axes, mode=fieldbus.Mode.CSV)
    ctrl.set_goal(fieldbus.Goal.ENABLE)
    return ctrl, wheels


def _run(emu, base, ctrl, wheels, truth, cycles, cmd=None):  # type: ignore[no-untyped-def]
    op, dt = emu.op, emu.cycle_time_us / 1e6
    steps = []
    for _ in range(cycles):
        res = op.exchange()
        now = emu.clock.now_ns() / 1e9
        ctrl.step_image(wheels)
        if cmd is not None:
            base.command(cmd[0], cmd[1], now)
        steps.append(base.step(res, now, dt, enabled=bool(ctrl.reached.all())))
        truth.update(emu.drive_positions("wheels"))
        emu.clock.sleep(dt)
    return steps


def test_a_two_metre_square_by_cmd_vel_and_the_odometry_against_the_drives_own_positions() -> None:
    with emulate(NETWORK) as emu:
        base = WheeledBase(emu.op)
        assert base.params.wheel_separation == 0.45
        ctrl, wheels = _enable(emu, base)
        truth = Truth(emu.drive_positions("wheels"))
        _run(emu, base, ctrl, wheels, truth, 300)  # enable; no command: the wheels hold still
        assert ctrl.reached.all()
        assert truth.travel < 1e-6 and abs(base.odometry.x) < 1e-6
        for _side in range(4):
            _run(emu, base, ctrl, wheels, truth, 2000, cmd=(1.0, 0.0))  # 2 m at 1 m/s (ramps: 1 s)
            _run(emu, base, ctrl, wheels, truth, 700, cmd=(0.0, 0.0))
            turn = 0
            while abs(math.remainder(base.odometry.heading - (_side + 1) * math.pi / 2, math.tau)) > 0.002:
                _run(emu, base, ctrl, wheels, truth, 1, cmd=(0.0, 1.0))
                turn += 1
                assert turn < 5_000
            _run(emu, base, ctrl, wheels, truth, 400, cmd=(0.0, 0.0))
        odo = base.odometry
        error = math.hypot(odo.x - truth.x, odo.y - truth.y)
        assert truth.travel > 7.0
        assert error <= 0.005 * truth.travel, (odo.x, odo.y, truth.x, truth.y, truth.travel)
        assert abs(math.remainder(odo.heading - truth.heading, math.tau)) < 0.01


def test_the_base_ramps_to_rest_after_the_timeout_and_resumes_only_on_a_new_command() -> None:
    with emulate(NETWORK) as emu:
        base = WheeledBase(emu.op)
        ctrl, wheels = _enable(emu, base)
        truth = Truth(emu.drive_positions("wheels"))
        _run(emu, base, ctrl, wheels, truth, 300)
        _run(emu, base, ctrl, wheels, truth, 1200, cmd=(1.0, 0.0))
        assert base.last is not None and base.last.linear == pytest.approx(1.0)
        steps = _run(emu, base, ctrl, wheels, truth, 1300)  # the client went quiet
        timeout = round(base.params.cmd_vel_timeout * 1000)
        assert not steps[timeout - 2].timed_out and steps[timeout + 1].timed_out
        ramp = [s.linear for s in steps[timeout:]]
        assert all(a - b <= 1.5e-3 + 1e-12 for a, b in itertools.pairwise(ramp))  # 1.5 m/s^2
        rest = next(i for i, v in enumerate(ramp) if v == 0.0)
        assert rest <= math.ceil(1.0 / 1.5 * 1000) + 1
        # at rest: the wheels' own speeds are zero; nothing moves until a command comes
        before = list(truth.last)
        _run(emu, base, ctrl, wheels, truth, 500)
        assert np.allclose(truth.last, before, atol=1e-4)
        assert np.allclose(wheels.outputs["target_velocity"], 0.0)


def test_a_refused_command_is_not_a_command_and_a_safe_stop_drops_it() -> None:
    with emulate(NETWORK) as emu:
        base = WheeledBase(emu.op)
        ctrl, wheels = _enable(emu, base)
        truth = Truth(emu.drive_positions("wheels"))
        _run(emu, base, ctrl, wheels, truth, 300)
        assert base.command(math.nan, 0.0, emu.clock.now_ns() / 1e9) == "nan"
        assert base.command(math.inf, 0.0, emu.clock.now_ns() / 1e9) == "inf"
        _run(emu, base, ctrl, wheels, truth, 100)
        assert truth.travel < 1e-6
        _run(emu, base, ctrl, wheels, truth, 500, cmd=(0.5, 0.0))
        emu.lose_cycles("wheels", 30)  # the bus latches its safe stop
        steps = _run(emu, base, ctrl, wheels, truth, 40, cmd=(0.5, 0.0))
        assert emu.op.result.safe_stop
        assert steps[-1].linear == 0.0 and np.allclose(wheels.outputs["target_velocity"], 0.0)


def test_the_seed_can_drive_wraps_its_counters_and_the_odometry_counts_every_turn() -> None:
    """examples/amr_seed_can.yaml: seed 001's own CAN drive (int16 encoder counts wrap every 0.8 wheel
    turn); 3 m straight at 1 m/s: the odometry against the emulated motors' own (never wrapped) angles."""
    can_net = NETWORK.parent / "amr_seed_can.yaml"
    with emulate(can_net) as emu:
        op = emu.op
        base = WheeledBase(op)
        assert all(w.wrap == pytest.approx(65536 / COUNTS_PER_RAD) for w in base.wheels)
        dt = emu.cycle_time_us / 1e6
        start = list(emu.drive_positions("base"))
        wrapped = 0
        last = None
        for k in range(450):  # 4.5 s at 10 ms: 1 s ramp, 3 s at 1 m/s, ramp down
            res = op.exchange()
            now = emu.clock.now_ns() / 1e9
            if k < 350:
                base.command(1.0, 0.0, now)
            base.step(res, now, dt)
            pos = float(op["base"].inputs["position"][0])
            wrapped += last is not None and abs(pos - last) > 1.0
            last = pos
            emu.clock.sleep(dt)
        truth = [(p - s) * 0.08 for p, s in zip(emu.drive_positions("base"), start, strict=True)]
        assert wrapped >= 5  # the image's angle wrapped again and again
        assert truth[0] > 3.0 and truth[1] > 3.0
        assert base.odometry.x == pytest.approx(sum(truth) / 2, rel=0.005)
        assert abs(base.odometry.y) < 0.01
