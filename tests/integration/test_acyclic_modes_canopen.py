"""Mode objects by SDO on the CANopen emulator: a map without 0x6060/0x6061 in its PDOs homes and switches.

Same scenario as ``test_acyclic_modes.py`` (homing method 37, then CSP -> CSV -> CSP) over our CANopen
backend on python-can's virtual bus. The mode request goes out as SDO downloads of 0x6060 on the cycle's
acyclic channel; judged by the emulator's object dictionary (0x6060 as written, 0x6061 as the drive
shows it), which our SDO client wrote (the emulator's SDO server is ours too). python-can's virtual bus
runs on threads, so the emulator's time is wall-clock here: the check is on states and objects.
"""

from __future__ import annotations

import itertools
import json
import time
from pathlib import Path
from typing import Any

import pytest
import yaml

import fieldbus
from fieldbus import Cia402Controller, Goal, Homing, Mode
from fieldbus.core.acyclic_modes import AcyclicModes
from fieldbus.core.cia402 import HomingPhase

can = pytest.importorskip("can")

from sim_slaves.canopen import CanopenSimulator  # noqa: E402

pytestmark = pytest.mark.timeout(120)
DEMO_MAP = Path(fieldbus.__file__).resolve().parent / "data" / "demo_joint.yaml"
CYCLE_S = 0.005
_channels = itertools.count()


def _map(tmp_path: Path) -> Path:
    doc = yaml.safe_load(DEMO_MAP.read_text())
    for section in ("rpdo", "tpdo"):
        for pdo in doc[section]:
            pdo["channels"] = [c for c in pdo["channels"] if c["index"] not in (0x6060, 0x6061)]
    doc["homing"] = {"method": 37, "offset": 0, "timeout_ms": 3000}
    f = tmp_path / "joint_no_modes.yaml"
    f.write_text(yaml.safe_dump(doc, sort_keys=False))
    return f


def test_canopen_homes_and_switches_modes_by_sdo(tmp_path: Path) -> None:
    map_file = _map(tmp_path)
    drive = fieldbus.load_drive_map(map_file)
    channel = f"fb-acyclic-modes-{next(_channels)}-{time.monotonic_ns()}"
    net_file = tmp_path / "net.yaml"
    net_file.write_text(
        "cycle_time_us: 5000\nreceive_timeout_us: 50000\nbuses:\n"
        f"  - {{name: bus, type: canopen, interface: {channel}, can_interface: virtual,\n"
        f"     slaves: [{{name: j, map: {json.dumps(str(map_file))}, node_id: 5}}]}}\n"
    )
    with (
        can.Bus(interface="virtual", channel=channel) as bus,
        CanopenSimulator(bus, [(drive, 5)], dt_s=CYCLE_S) as sim,
        fieldbus.open_network(net_file) as net,
    ):
        op = net.bring_up()
        img = op["bus"]
        assert "modes_of_operation" not in img.outputs.names
        od = sim.node(5).od
        ctrl = Cia402Controller(1, mode=Mode.CSP)
        ctrl.set_goal(Goal.ENABLE)
        modes = AcyclicModes.for_group(op, "bus")
        homing = Homing.from_maps(ctrl, [drive], op.cycle_time_us)
        seen_hm = False

        def run_until(done: Any, limit: int = 3000) -> None:
            for _ in range(limit):
                if not op.exchange().fresh:
                    continue
                ctrl.step_image(img, modes=modes)
                if done():
                    return
            raise AssertionError(f"not done: {ctrl.state}, display {modes.display}")

        run_until(lambda: ctrl.all_reached)
        assert od.get_value(0x6061, 0) == Mode.CSP
        homing.start()

        def homed() -> bool:
            nonlocal seen_hm
            homing.step(img.inputs["statusword"], img.outputs["controlword"])
            seen_hm = seen_hm or od.get_value(0x6061, 0) == Mode.HOMING
            return homing.done and ctrl.all_reached

        run_until(homed)
        assert homing.phase[0] == HomingPhase.DONE and seen_hm
        assert od.get_value(0x6060, 0) == od.get_value(0x6061, 0) == Mode.CSP
        for mode in (Mode.CSV, Mode.CSP):
            ctrl.request_mode(mode)
            run_until(lambda m=mode: ctrl.all_reached and int(modes.display[0]) == m)
            assert od.get_value(0x6060, 0) == od.get_value(0x6061, 0) == mode  # the drive's own objects
        assert list(modes.writes) == [5]  # CSP, HM, CSP, CSV, CSP: one download each
    assert not sim.errors
