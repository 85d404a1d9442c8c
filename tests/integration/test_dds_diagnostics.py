"""The served bus's diagnostics (``fieldbus monitor --dds`` shows them): drive faults by name, per axis.

In process on the sim emulator (``fieldbus.testing.emulate``, a virtual clock):
the server's cycle is stepped by the test, the fault injected in the emulated
drive, and the DiagnosticArray the server would publish is read back.
"""

from __future__ import annotations

import json
from pathlib import Path

import pytest

pytest.importorskip("cyclonedds")

import fieldbus
from fieldbus.dds.participant import Participant
from fieldbus.dds.server import BusServer, ServeOptions
from fieldbus.testing import emulate

DEMO_JOINT = Path(fieldbus.__file__).resolve().parent / "data" / "demo_joint.yaml"


def _values(server: BusServer, hardware_id: str) -> dict[str, str]:
    (status,) = [s for s in server.diagnostics().status if s.hardware_id == hardware_id]
    return {kv.key: kv.value for kv in status.values}


def test_a_drive_fault_is_in_the_diagnostics_by_axis_code_and_name(tmp_path: Path) -> None:
    net = tmp_path / "robot.yaml"
    net.write_text(
        "name: robot\ncycle_time_us: 1000\nreceive_timeout_us: 500\nbuses:\n  - name: bus\n    type: ethercat\n"
        f"    interface: sim\n    slaves: [{{name: 'j{{i}}', map: {json.dumps(str(DEMO_JOINT))}, count: 3}}]\n"
    )
    with emulate(net, bring_up=False) as emu:
        server = BusServer(emu.network, Participant(231, "lo"), ServeOptions("robot"))
        server.attach(emu.bring_up())
        group = next(iter(server.groups))
        ctrl = server.groups[group].ctrl
        assert ctrl is not None
        ctrl.set_goal(fieldbus.Goal.ENABLE)
        emu.run(server.step, 300)
        assert not any(k.endswith("/drive_error") for k in _values(server, group))
        emu.drive_fault("bus", "j1", 0x7300)
        emu.run(server.step, 50)
        values = _values(server, group)
    assert [k for k in values if k.endswith("/drive_error")] == ["j1/drive_error"]
    assert values["j1/drive_error"].startswith("0x7300 sensor") and values["j1/drive_error"].endswith(
        "1 fault(s)"
    )
    # the fault stays named after the server's CiA 402 state machine has reset it and re-enabled
    assert values["j1/drive_state"] == "OPERATION_ENABLED"
