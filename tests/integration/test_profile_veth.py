"""One PP move over veth with the real pysoem master: ``fieldbus.ProfileMove`` against the EtherCAT
emulator in its child process, on the wire (needs root and pysoem; skipped with the machine's reason).

The map's ``motion_profile:`` section is written at bring-up by pysoem's SDO download; the
set-point handshake is read back from the trace, cycle by cycle, and the joint ends on its target.
Paced on the wall clock (the emulator runs in real time); the checks are in cycles and counts.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

import fieldbus
from fieldbus import Cia402Controller, Goal, Mode, ProfileMove, ProfilePhase
from fieldbus.testing import emulate

pytestmark = pytest.mark.timeout(180)
DEMO_MAP = Path(fieldbus.__file__).resolve().parent / "data" / "demo_joint.yaml"
COUNTS_PER_RAD = 20860.7568
NEW, ACK, REACHED = 0x10, 0x1000, 0x400


def _net(tmp_path: Path) -> Path:
    joint = tmp_path / "joint.yaml"
    joint.write_text(
        DEMO_MAP.read_text()
        + "motion_profile: {velocity: 100000, acceleration: 500000, deceleration: 500000, timeout_ms: 8000}\n"
    )
    net = tmp_path / "arm.yaml"
    net.write_text(
        "name: arm\ncycle_time_us: 1000\nreceive_timeout_us: 5000\nsafe_stop_after: 50\nbuses:\n"
        f"  - {{name: arm, type: ethercat, interface: eth0, slaves: [{{name: j, map: {json.dumps(str(joint))}}}]}}\n"
    )
    return net


def test_a_pp_move_over_veth_with_pysoem_ends_on_target_after_the_handshake(
    tmp_path: Path, request: pytest.FixtureRequest
) -> None:
    request.getfixturevalue("veth_possible")
    with emulate(_net(tmp_path), ethercat="veth", receive_timeout_us=20000) as emu:
        op = emu.op
        (group,) = op.groups
        img = op[group]
        ctrl = Cia402Controller(1, mode=Mode.CSP)
        ctrl.set_goal(Goal.ENABLE)
        moves = ProfileMove.from_maps(ctrl, [s.map for s in op.groups[group].slaves], op.cycle_time_us)

        def step(k: int) -> bool:
            if op.exchange().fresh:
                ctrl.step_image(img)
                moves.step_image(img)
            return ctrl.all_reached and moves.done

        emu.run(step, cycles=3000)  # enable in CSP (ends early once enabled)
        assert ctrl.all_reached
        target = float(img.inputs["position_actual_value"][0]) + 1.5  # rad: 31,291 counts
        since = emu.trace.mark()
        moves.move_to(target)
        emu.run(step, cycles=8000)  # ends early once the move is done
        fresh = emu.trace.fresh[since:]
        cw = emu.trace.outputs(group)["controlword"][since:, 0]
        sw = emu.trace.inputs(group)["statusword"][since:, 0]
        pos = emu.trace.inputs(group)["position_actual_value"][since:, 0]
    assert moves.phase[0] == ProfilePhase.DONE
    sent = int(np.flatnonzero(cw & NEW)[0])
    acked = sent + int(np.flatnonzero(sw[sent:] & ACK)[0])
    dropped = sent + int(np.flatnonzero(cw[sent:] & NEW == 0)[0])
    reached = dropped + int(np.flatnonzero(sw[dropped:] & REACHED)[0])
    assert sent <= acked < dropped < reached, (sent, acked, dropped, reached)
    assert not (sw[acked:reached] & REACHED).any()
    # the way there: from the start toward the target, never past it (the drive's own trapezoid; its
    # duration in cycles depends on the machine's pacing here, see test_profile_sim.py for that)
    window = 100 / COUNTS_PER_RAD  # the drive's position window 0x6067 [rad]
    way = pos[acked:reached]
    assert (np.diff(way) >= -window).all() and way.max() <= target + window
    end = float(img.inputs["position_actual_value"][0])
    assert abs(end - target) * COUNTS_PER_RAD <= 100, end - target  # the drive's position window
    assert fresh.mean() > 0.9, fresh.mean()
