"""``emulate(..., can="udp")``: every CAN bus of a network served by one emulator process on ``fieldbus_udp``,
each bus with its own family's emulator (the family from the map: ``can_process --kind auto``).

The wall clock and two processes: nothing here bounds time; the receive timeout is generous and the
safe stop and the Damiao motors' CAN timeout are kept out of the way so that a loaded machine only
costs cycles, not the motion.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("can")

import fieldbus
from fieldbus.testing import FaultNotSupported, emulate

pytestmark = pytest.mark.timeout(300)
TARGET_TURN = 0.05


def _children() -> list[str]:
    """The command lines of this process's children (Linux /proc)."""
    pids: list[str] = []
    for task in os.listdir(f"/proc/{os.getpid()}/task"):
        try:
            pids += Path(f"/proc/{os.getpid()}/task/{task}/children").read_text().split()
        except OSError:
            continue
    out = []
    for pid in pids:
        try:
            out.append(Path(f"/proc/{pid}/cmdline").read_bytes().replace(b"\0", b" ").decode())
        except OSError:
            continue
    return out


def _network(tmp_path: Path) -> Path:
    odrive = fieldbus.PDO_MAPS / "odrive_s1.yaml"
    # the Damiao's own CAN timeout (the map's 50 ms) kept out of the way too, as the safe stop is: over two
    # wall-clock processes a loaded machine can leave a motor without a command longer than that, and it
    # then stops itself (error 0xD) and stays off; that reaction is tested on virtual time (test_damiao)
    text = (fieldbus.PDO_MAPS / "damiao_dm_j4310.yaml").read_text()
    assert text.count("timeout_ms: 50 ") == 1
    damiao = tmp_path / "damiao_dm_j4310.yaml"
    damiao.write_text(text.replace("timeout_ms: 50 ", "timeout_ms: 5000 "))
    f = tmp_path / "robot.yaml"
    f.write_text(
        "cycle_time_us: 1000\nreceive_timeout_us: 20000\nsafe_stop_after: 100000\nbuses:\n"
        f"  - {{name: front, type: rawcan, interface: can0, slaves: [{{name: 'f{{i}}', map: '{odrive}', "
        "node_id: 1, count: 2}]}\n"
        f"  - {{name: rear, type: rawcan, interface: can1, slaves: [{{name: 'r{{i}}', map: '{odrive}', "
        "node_id: 1, count: 2}]}\n"
        f"  - {{name: arm, type: rawcan, interface: can2, slaves: [{{name: 'a{{i}}', map: '{damiao}', "
        "node_id: 1, count: 2}]}\n"
    )
    return f


@pytest.mark.skipif(not Path(f"/proc/{os.getpid()}/task").is_dir(), reason="needs Linux /proc")
def test_two_odrive_buses_and_a_damiao_bus_run_from_one_emulator_process(tmp_path: Path) -> None:
    before = [c for c in _children() if "sim_slaves.can_process" in c]
    with emulate(_network(tmp_path), can="udp") as emu:
        assert not emu.virtual
        ours = [c for c in _children() if "sim_slaves.can_process" in c and c not in before]
        assert len(ours) == 1, ours  # one process for the three buses
        assert ours[0].count("--channel") == 3 and ours[0].count("--kind auto") == 3
        op = emu.op
        for bus in ("front", "rear"):
            op[bus].outputs["position"][:] = TARGET_TURN
        op["arm"].outputs["kp"][:], op["arm"].outputs["kd"][:] = 20.0, 1.0
        op["arm"].outputs["position"][:] = 0.3
        emu.cycles(400)
        fresh = emu.trace.arrays()["fresh"]
        assert fresh.sum() > 0
        for bus in ("front", "rear"):
            assert list(op[bus].inputs["axis_state"]) == [8, 8]  # closed loop, from the heartbeats
            assert np.all(np.abs(op[bus].inputs["position"] - TARGET_TURN) < 0.01), op[bus].inputs["position"]
        assert np.all(np.abs(op["arm"].inputs["position"] - 0.3) < 0.03), op["arm"].inputs["position"]
        with pytest.raises(FaultNotSupported, match="child process"):
            emu.drive_fault("front", "f0", 0x2000)
    assert not [c for c in _children() if "sim_slaves.can_process" in c and c not in before]
