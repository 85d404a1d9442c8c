"""Bumpless enable and mode switches through ``Cia402Controller.step_image`` on the sim backend.

The drives are the in-process EtherCAT emulator (``backend="sim"``) on a
virtual clock advanced 1 ms per cycle, so every figure is in cycles. The
user's loop writes nothing while the library seeds the targets; the checks
read the commanded and actual positions of every cycle.
"""

from __future__ import annotations

import json
from collections.abc import Callable
from pathlib import Path

import numpy as np
import numpy.typing as npt

import fieldbus
from fieldbus import Cia402Controller, Goal, Mode, State402
from fieldbus.core.pdo.image import ProcessImage
from fieldbus.platform.allocs import net_blocks
from fieldbus.testing import VirtualClock

DEMO_MAP = Path(fieldbus.__file__).resolve().parent / "data" / "demo_joint.yaml"  # CSP/CST, rad and N·m
DT_S = 1e-3
SPEED = 2.0  # rad/s of the user's moves
STEP = SPEED * DT_S  # one cycle of motion [rad]


def _net_file(tmp_path: Path, axes: int) -> Path:
    f = tmp_path / "net.yaml"
    m = json.dumps(str(DEMO_MAP))
    f.write_text(
        "cycle_time_us: 1000\nreceive_timeout_us: 5000\nsafe_stop_after: 10\nbuses:\n"
        f"  - {{name: arm, type: ethercat, interface: sim0, slaves: [{{name: 'j{{i}}', map: {m}, count: {axes}}}]}}\n"
    )
    return f


class Log:
    """Per cycle: commanded target_position (what the next exchange sends), actual position, mode, state."""

    def __init__(self) -> None:
        self.cmd: list[npt.NDArray[np.float64]] = []
        self.act: list[npt.NDArray[np.float64]] = []
        self.mode: list[npt.NDArray[np.int8]] = []
        self.state: list[npt.NDArray[np.int8]] = []

    def arrays(self) -> tuple[npt.NDArray[np.float64], ...]:
        return tuple(np.array(x, dtype=np.float64) for x in (self.cmd, self.act, self.mode, self.state))


def _run(
    op: fieldbus.Operational,
    clock: VirtualClock,
    ctrl: Cia402Controller,
    img: ProcessImage,
    cycles: int,
    log: Log,
    user: Callable[[], None] = lambda: None,
) -> None:
    for _ in range(cycles):
        clock.advance(1_000_000)
        res = op.exchange()
        assert res.fresh
        ctrl.step_image(img)
        user()
        log.cmd.append(img.outputs["target_position"].copy())
        log.act.append(img.inputs["position_actual_value"].copy())
        log.mode.append(img.inputs["modes_of_operation_display"].copy())
        log.state.append(ctrl.state.copy())


def _moving(img: ProcessImage) -> Callable[[], None]:
    """The user's CSP move from whatever target is in the image: from the joint's present speed up to
    ``SPEED`` (20 rad/s², a smooth trajectory), never more than one cycle of motion per cycle."""
    speed: list[float] = []

    def user() -> None:
        if not speed:
            speed.append(float(np.min(img.inputs["velocity_actual_value"])))
        speed[0] = min(SPEED, speed[0] + 20.0 * DT_S)
        img.outputs["target_position"][:] += speed[0] * DT_S

    return user


def test_enable_from_a_nonzero_position_and_csp_cst_csp_while_moving_never_jump(tmp_path: Path) -> None:
    clock = VirtualClock()
    net = fieldbus.open_network(_net_file(tmp_path, 2), backend="sim", clock=clock)
    try:
        op = net.bring_up()
        img = op["arm"]
        ctrl = Cia402Controller(2, mode=Mode.CSP)
        log = Log()
        # 1. enable where the joints are (0), move them away, disable: they coast on, off target
        ctrl.set_goal(Goal.ENABLE)
        _run(op, clock, ctrl, img, 20, log)
        assert ctrl.all_reached
        _run(op, clock, ctrl, img, 300, log, _moving(img))
        ctrl.set_goal(Goal.DISABLE)
        _run(op, clock, ctrl, img, 400, log)
        pos = img.inputs["position_actual_value"].copy()
        assert np.all(pos > 0.7), pos  # non-zero, and well past the last target (0.6 rad)
        mark = len(log.cmd)
        # 2. enable again from there; the user writes nothing yet
        ctrl.set_goal(Goal.ENABLE)
        _run(op, clock, ctrl, img, 20, log)
        assert ctrl.all_reached
        # 3. move in CSP, switch to CST while moving (torque seeded 0: it coasts), back to CSP while moving
        _run(op, clock, ctrl, img, 200, log, _moving(img))
        ctrl.request_mode(Mode.CST)
        _run(op, clock, ctrl, img, 100, log)
        assert np.all(img.inputs["modes_of_operation_display"] == Mode.CST)
        assert np.all(img.inputs["velocity_actual_value"] > 0.3 * SPEED)  # still moving
        ctrl.request_mode(Mode.CSP)
        _run(op, clock, ctrl, img, 3, log)  # the user has not written yet
        assert np.all(img.inputs["modes_of_operation_display"] == Mode.CSP) and ctrl.all_reached
        _run(op, clock, ctrl, img, 200, log, _moving(img))
    finally:
        net.close()

    cmd, act, mode, state = (a[mark:] for a in log.arrays())
    enabled = state == State402.OPERATION_ENABLED
    in_csp = enabled & (mode == Mode.CSP)
    assert in_csp[:, 0].sum() > 380 and (enabled & (mode == Mode.CST))[:, 0].sum() > 90
    # where CSP begins (the enable, the switch back): the command starts at most one cycle of motion
    # from the actual position; then it moves at most one cycle of motion per cycle
    starts = in_csp & ~np.vstack([np.zeros((1, 2), dtype=bool), in_csp[:-1]])
    assert starts.sum() == 4  # two axes, each enabled once and switched back once
    gap = np.abs(cmd - act)[starts]
    assert gap.max() <= STEP * 1.05, gap
    both = in_csp[1:] & in_csp[:-1]
    assert float(np.abs(np.diff(cmd, axis=0))[both].max()) <= STEP * 1.05
    # the actual position never moves more than one cycle of motion in a cycle (no jerk)
    assert float(np.abs(np.diff(act, axis=0)).max()) <= STEP * 1.05


def test_step_image_allocates_nothing_per_cycle() -> None:
    drive = fieldbus.load_drive_map(DEMO_MAP)
    img = ProcessImage(fieldbus.layout(drive), n_axes=12)
    ctrl = Cia402Controller(12)
    ctrl.set_goal(Goal.ENABLE)
    sw = img.inputs["statusword"]
    words = np.array([[0x1637] * 12, [0x0218] * 6 + [0x0231] * 6], dtype=np.uint16)
    k = [0]

    def one_cycle() -> None:
        np.copyto(sw, words[k[0] & 1])
        k[0] += 1
        ctrl.step_image(img)

    ctrl.step_image(img)  # binds the image's channels
    ctrl.request_mode(Mode.CST, axes=slice(0, 6))
    assert net_blocks(one_cycle, cycles=10_000) <= 0
