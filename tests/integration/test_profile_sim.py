"""The library's profile modes end to end on the sim backend: ``fieldbus.ProfileMove`` over the
in-process EtherCAT emulator, on a virtual clock (1 ms per cycle), every figure in cycles.

PP: each axis's set-point handshake is read back from the trace of every cycle (controlword bit 4
sent, statusword bit 12 seen, bit 4 dropped, bit 10 seen, in that order), the move lasts the
trapezoid the map's ``motion_profile:`` section sets (0x6081/0x6083/0x6084 written at bring-up),
and each axis ends on its target. PV: the axes ramp to their velocities and stop again. Our own
emulator answers (the independent masters are canopen's BaseNode402 and pysoem over veth).
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import numpy.typing as npt

import fieldbus
from fieldbus import Cia402Controller, Goal, Mode, ProfileMove, ProfilePhase
from fieldbus.testing import emulate

DEMO_MAP = Path(fieldbus.__file__).resolve().parent / "data" / "demo_joint.yaml"
COUNTS_PER_RAD = 20860.7568
V, ACC, DEC = 100_000, 500_000, 250_000  # 0x6081 [counts/s], 0x6083/0x6084 [counts/s²]
WINDOW_RAD = 100 / COUNTS_PER_RAD  # the emulated drive's position window 0x6067 (100 counts)
NEW, ACK, REACHED = 0x10, 0x1000, 0x400


def _files(tmp_path: Path) -> Path:
    text = DEMO_MAP.read_text().replace(
        "      - {index: 0x6060, sub_index: 0, type: int8, default: 8}\n",
        "      - {index: 0x6060, sub_index: 0, type: int8, default: 8}\n"
        "      - {index: 0x60FF, sub_index: 0, type: int32, factor: 20860.7568, unit: rad/s}\n",
    )
    joint = tmp_path / "joint.yaml"
    joint.write_text(
        text
        + f"motion_profile: {{velocity: {V}, acceleration: {ACC}, deceleration: {DEC}, timeout_ms: 5000}}\n"
    )
    net = tmp_path / "arm.yaml"
    net.write_text(
        "name: arm\ncycle_time_us: 1000\nreceive_timeout_us: 5000\nsafe_stop_after: 10\nbuses:\n"
        f"  - {{name: arm, type: ethercat, interface: sim0, slaves: [{{name: 'j{{i}}', map: {json.dumps(str(joint))}, count: 2}}]}}\n"
    )
    return net


def _trapezoid_cycles(distance_counts: float) -> float:
    ramps = V * V / (2 * ACC) + V * V / (2 * DEC)
    assert ramps <= distance_counts
    return (V / ACC + V / DEC + (distance_counts - ramps) / V) * 1000


def _first(mask: npt.NDArray[np.bool_]) -> int:
    hits = np.flatnonzero(mask)
    assert hits.size, "never"
    return int(hits[0])


def test_profile_move_runs_the_pp_handshake_and_pv_ramps_on_the_sim_backend(tmp_path: Path) -> None:
    with emulate(_files(tmp_path)) as emu:
        op = emu.op
        (group,) = op.groups
        img = op[group]
        ctrl = Cia402Controller(img.n_axes, mode=Mode.CSP)
        ctrl.set_goal(Goal.ENABLE)
        moves = ProfileMove.from_maps(ctrl, [s.map for s in op.groups[group].slaves], op.cycle_time_us)
        assert list(moves.timeout_cycles) == [5000, 5000]

        def step(k: int) -> bool:
            if op.exchange().fresh:
                ctrl.step_image(img)
                moves.step_image(img)
            return moves.done  # True ends emu.run early

        emu.run(lambda k: step(k) and False, cycles=50)  # enabled in CSP, holding
        assert ctrl.all_reached
        start = img.inputs["position_actual_value"].copy()
        since = emu.trace.mark()
        targets = start + np.array([3.0, -2.0])  # rad: 62,582 and 41,721 counts
        moves.move_to(targets)
        emu.run(step, cycles=6000)
        assert moves.done and list(moves.phase) == [ProfilePhase.DONE] * 2
        cw = emu.trace.outputs(group)["controlword"][since:]
        sw = emu.trace.inputs(group)["statusword"][since:]
        mode = emu.trace.inputs(group)["modes_of_operation_display"][since:]
        for axis in range(2):
            c, s = cw[:, axis], sw[:, axis]
            in_pp = _first(mode[:, axis] == 1)
            sent = _first(c & NEW != 0)
            acked = sent + _first(s[sent:] & ACK != 0)  # (bit 12 before PP is CSP's "follows target")
            dropped = sent + _first(c[sent:] & NEW == 0)
            cleared = acked + _first(s[acked:] & ACK == 0)
            reached = cleared + _first(s[cleared:] & REACHED != 0)
            # the handshake, cycle by cycle: PP displayed, bit 4 up, bit 12 answers, bit 4 down in the
            # cycle after bit 12 is seen, bit 12 down, then (after the move) bit 10
            assert in_pp < sent <= acked < dropped == acked + 1 < cleared + 1 <= reached, (
                axis, in_pp, sent, acked, dropped, cleared, reached,
            )  # fmt: skip
            assert not (s[acked:reached] & REACHED).any()
            distance = abs(targets[axis] - start[axis]) * COUNTS_PER_RAD
            expected = _trapezoid_cycles(distance)
            assert expected - 3 <= reached - acked <= expected + 60, (axis, reached - acked, expected)
        end = img.inputs["position_actual_value"]
        assert np.abs(end - targets).max() <= WINDOW_RAD, end - targets
        peak = np.abs(np.diff(emu.trace.inputs(group)["position_actual_value"][since:], axis=0)).max(axis=0)
        assert (peak * 1000 * COUNTS_PER_RAD <= V * 1.02).all(), peak  # at most 0x6081 per cycle

        # a relative move of the hip, then PV: both axes ramp to their speeds, then back to rest
        moves.move_to(0.5, axes=0, relative=True)
        emu.run(step, cycles=3000)
        assert moves.phase[0] == ProfilePhase.DONE
        assert abs(img.inputs["position_actual_value"][0] - (targets[0] + 0.5)) <= WINDOW_RAD
        moves.run_at([2.0, -1.0])  # rad/s
        emu.run(step, cycles=1000)
        assert list(moves.phase) == [ProfilePhase.DONE] * 2
        assert list(img.inputs["modes_of_operation_display"]) == [3, 3]
        assert np.abs(img.inputs["velocity_actual_value"] - [2.0, -1.0]).max() < 0.05
        moves.run_at(0.0)
        emu.run(lambda k: step(k) and False, cycles=1000)
        assert np.abs(img.inputs["velocity_actual_value"]).max() < 0.05
        assert (img.inputs["statusword"] & (ACK | REACHED) == ACK | REACHED).all()  # speed 0, reached
        assert not op.result.safe_stop
