"""The testing kit's faults on multi-axis slaves: ``emu.drive_fault(..., axis=k)`` (issue 25 item 4).

Our own code on both sides (the in-process EtherCAT emulator and our master); the EtherCAT
multi-axis emulator itself is checked against pysoem in test_multiaxis.py.
"""

from __future__ import annotations

from pathlib import Path

import pytest

import fieldbus
from fieldbus.core.cia402 import State402
from fieldbus.core.drivefault import DriveFault
from fieldbus.errors import FieldbusError
from fieldbus.testing import emulate

MAPS = Path(__file__).resolve().parents[2] / "pdo_maps"
TWO_AXIS = MAPS / "generic_cia402_2axis.yaml"
SENSOR = 0x7300


def _network(tmp_path: Path) -> Path:
    net = tmp_path / "arm.yaml"
    net.write_text(
        f"""
name: arm
cycle_time_us: 1000
buses:
  - name: arm
    type: ethercat
    interface: eth0
    slaves:
      - {{name: shoulder, map: {TWO_AXIS}}}
      - {{name: elbow, map: {TWO_AXIS}}}
"""
    )
    return net


@pytest.mark.parametrize("ethercat", ["sim", pytest.param("veth", marks=pytest.mark.veth)])
def test_drive_fault_axis_2_faults_that_axis_and_the_event_names_its_row(
    tmp_path: Path, ethercat: str, request: pytest.FixtureRequest
) -> None:
    """Over veth the master is the real pysoem and the fault goes through the runner's command."""
    if ethercat == "veth":
        request.getfixturevalue("veth_possible")  # pysoem there, the machine makes a veth pair
    timeout = {"receive_timeout_us": 20000} if ethercat == "veth" else {}
    _fault_axis_2(tmp_path, ethercat, timeout)


def _fault_axis_2(tmp_path: Path, ethercat: str, timeout: dict[str, int]) -> None:
    with emulate(_network(tmp_path), ethercat=ethercat, **timeout) as emu:
        op = emu.op
        arm = op["arm"]
        ctrl = fieldbus.Cia402Controller(arm.n_axes, mode=fieldbus.Mode.CSP)
        ctrl.set_goal(fieldbus.Goal.ENABLE)
        faults: list[DriveFault] = []

        def step(_k: int) -> None:
            res = op.exchange()
            faults.extend(e for e in res.events if isinstance(e, DriveFault) and e.code is not None)
            if res.fresh:
                ctrl.step_image(arm)

        emu.run(step, cycles=300)
        assert emu.drive_states("arm") == [State402.OPERATION_ENABLED] * 4
        emu.drive_fault("arm", "elbow", SENSOR, axis=2)
        emu.run(step, cycles=20)
        # the elbow's axis 2 is row 3 of the group; no other axis faulted
        assert [(f.slave, f.axis, f.slave_axis, f.code) for f in faults] == [("elbow", 3, 1, SENSOR)]
        assert op.result.drive_faults["arm"].tolist() == [0, 0, 0, 1]  # fault edges per row
        assert "elbow axis 2 (arm[3])" in str(faults[0])
        with pytest.raises(FieldbusError, match=r"axes 1\.\.2, got axis=3"):
            emu.drive_fault("arm", "elbow", SENSOR, axis=3)
