"""Emulated drives follow their maps: a 2^20-count, 50:1 joint tracks a sine and stops at its 0x6085.

Through the public API only (``fieldbus.open_network`` on the ``sim`` backend,
``Cia402Controller``), on a stepped clock: every exchange is 1 ms of the
emulator's time, so the run is the same on a busy machine. The map
(``tests/data/geared_joint_2p20_50.yaml``) scales position to rad of the joint
(2^20 x 50 / 2 pi counts per rad); before the emulated drive read the map it
was a 17-bit ungeared drive whatever the scaling, and this sine made it
trip its following-error fault. What is checked against our own code only:
the emulator and the master are both this project's (no independent oracle
for drive physics); the object values are read back by SDO through the
emulated ESC's mailbox.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

import fieldbus

GEARED = Path(__file__).resolve().parents[1] / "data" / "geared_joint_2p20_50.yaml"
COUNTS_PER_RAD = 2**20 * 50 / (2 * math.pi)  # the map's scaling: counts per rad of the joint
AMPLITUDE = 0.3  # rad
FREQ = 1.0  # Hz
SECONDS = 5.0
AXES = 3
FAULT_BIT = 0x0008  # statusword bit 3


def _network(tmp_path: Path, emulator: str = "") -> Path:
    path = tmp_path / "net.yaml"
    extra = f", emulator: {emulator}" if emulator else ""
    path.write_text(
        "cycle_time_us: 1000\nbuses:\n"
        f"  - {{name: arm, type: ethercat, interface: sim, slaves: "
        f"[{{name: 'j{{i}}', map: '{GEARED}', count: {AXES}{extra}}}]}}\n"
    )
    return path


def _stepped_clock(period_ns: int = 1_000_000) -> object:
    """The emulator's clock: every frame is one cycle (``period_ns``) later than the one before."""
    now = [0]

    def clock() -> int:
        now[0] += period_ns
        return now[0]

    return clock


def _u32(data: bytes) -> int:
    return int.from_bytes(data, "little")


def _track(op: fieldbus.Operational, seconds: float) -> tuple[float, int, np.ndarray]:
    """Enable every axis, then follow ``p0 + A sin(2 pi f t)``: (max tracking error [rad], cycles with
    a fault bit, the start positions). The error is the actual position minus the target of the
    cycle before (the newest the drive can have acted on)."""
    arm = op["arm"]
    out, inp = arm.outputs, arm.inputs
    ctrl = fieldbus.Cia402Controller(AXES)
    ctrl.set_goal(fieldbus.Goal.ENABLE)
    for _ in range(200):
        op.exchange()
        ctrl.step(inp["statusword"], out["controlword"])
        out["target_position"][:] = inp["position_actual_value"]
        if ctrl.all_reached:
            break
    assert ctrl.all_reached, ctrl.state
    p0 = inp["position_actual_value"].copy()
    worst, faulted = 0.0, 0
    prev = out["target_position"].copy()
    for k in range(1, round(seconds * 1000) + 1):
        op.exchange()
        faulted += bool((inp["statusword"] & FAULT_BIT).any())
        worst = max(worst, float(np.abs(inp["position_actual_value"] - prev).max()))
        prev = out["target_position"].copy()
        out["target_position"][:] = p0 + AMPLITUDE * math.sin(2 * math.pi * FREQ * k * 1e-3)
    return worst, faulted, p0


CASES = [
    ("", 2**20 * 50, (1, 1)),  # the map alone: 52,428,800 counts per revolution, ungeared
    ("{gear_ratio: 50}", 2**20, (50, 1)),
    ("{position_encoder_resolution: 1048576}", 2**20, (50, 1)),  # the gear inferred from the scaling
]
IDS = ["map-alone", "gear-50", "encoder-2p20"]


@pytest.mark.parametrize("emulator", [c[0] for c in CASES], ids=IDS)
def test_a_2p20_count_50_to_1_joint_tracks_a_sine_without_a_fault(tmp_path: Path, emulator: str) -> None:
    net = fieldbus.open_network(_network(tmp_path, emulator), backend="sim", clock=_stepped_clock())
    with net:
        worst, faulted, _ = _track(net.bring_up(), SECONDS)
        assert faulted == 0
        assert worst < 0.01, worst  # rad of the joint; the sine moves up to 1.9 mrad per cycle


@pytest.mark.parametrize(("emulator", "increments", "gear"), CASES, ids=IDS)
def test_the_emulated_drive_s_objects_carry_what_the_map_implies(
    tmp_path: Path, emulator: str, increments: int, gear: tuple[int, int]
) -> None:
    """0x608F encoder increments per motor revolution, 0x6091 gear, 0x6076 rated torque (the map's
    0.05 N·m per unit at the joint / gear), read by SDO through the emulated ESC's mailbox."""
    with fieldbus.open_network(_network(tmp_path, emulator), backend="sim", clock=_stepped_clock()) as net:
        pre = net.pre_op()
        assert _u32(pre.sdo_read("arm", "j0", 0x608F, 1)) == increments
        assert _u32(pre.sdo_read("arm", "j0", 0x608F, 2)) == 1
        assert (
            _u32(pre.sdo_read("arm", "j0", 0x6091, 1)),
            _u32(pre.sdo_read("arm", "j0", 0x6091, 2)),
        ) == gear
        assert _u32(pre.sdo_read("arm", "j0", 0x6076, 0)) == round(50_000 * gear[1] / gear[0])  # mN·m


def test_a_quick_stop_ramps_down_at_the_deceleration_of_0x6085(tmp_path: Path) -> None:
    """Quick stop at the sine's peak speed (1.9 rad/s): the joint's velocity_actual_value falls by
    0x6085 (counts/s² at the motor, through the map's factor: 5 rad/s² at the joint) every second."""
    decel = 5.0  # rad/s² at the joint
    counts = round(decel * COUNTS_PER_RAD)
    net = fieldbus.open_network(
        _network(tmp_path, f"{{gear_ratio: 50, quick_stop_deceleration: {counts}}}"),
        backend="sim",
        clock=_stepped_clock(),
    )
    with net:
        op = net.bring_up()
        arm = op["arm"]
        out, inp = arm.outputs, arm.inputs
        _track(op, 2.0)  # ends at the sine's peak speed, moving forward
        speeds = [float(inp["velocity_actual_value"][0])]
        assert speeds[0] > 1.8
        out["controlword"][:] = 0x0002  # quick stop (CiA 402 command: bits 1 set, 2 clear)
        for _ in range(600):
            op.exchange()
            speeds.append(float(inp["velocity_actual_value"][0]))
        v = np.array(speeds)
        ramp = v[(v < 0.9 * v[0]) & (v > 0.1 * v[0])]  # the middle of the ramp, away from its ends
        slope = -np.diff(ramp) * 1000.0  # rad/s²
        assert len(ramp) > 100
        assert np.median(slope) == pytest.approx(decel, rel=0.02)
        assert abs(v[-1]) < 0.01  # at rest
        assert (inp["statusword"] & 0x4F == 0x40).all()  # option 2: then SWITCH ON DISABLED
