"""``emu.slow_sdo``: a drive whose SDO server answers late shows why ``hold_reset`` matters.

CANopen nodes on the kit's lockstep bus, virtual time. The demo map has no 0x603F in its PDOs: on a
drive fault the master reads it by SDO. With the SDO server slowed by 5 cycles, a controller that
resets the fault at once lets the drive clear 0x603F before the read is served (the fault comes with
code 0); one that passes ``hold_reset=op.fault_code_pending(group)`` gets the code. Judged by the
emulated drive's own fault code; master and emulator are both this project's code.
"""

from __future__ import annotations

import json
from pathlib import Path

import pytest

import fieldbus
from fieldbus.commands.demo import DEMO_MAP
from fieldbus.testing import EmulationError, FaultNotSupported, emulate

pytest.importorskip("can")
pytest.importorskip("canopen")

CODE = 0x7121  # motor blocked


def _net(tmp_path: Path) -> Path:
    f = tmp_path / "net.yaml"
    f.write_text(
        "cycle_time_us: 2000\nreceive_timeout_us: 1500\nbuses:\n"
        f"  - {{name: arm, type: canopen, interface: can0,\n"
        f"     slaves: [{{name: 'j{{i}}', map: {json.dumps(str(DEMO_MAP))}, node_id: 1, count: 2}}]}}\n"
    )
    return f


def _codes(tmp_path: Path, *, slow: int, hold: bool) -> tuple[list[int | None], int]:
    """The codes of the drive faults the master reported, and the controller's fault resets of j1."""
    with emulate(_net(tmp_path)) as emu:
        op, img = emu.op, emu.op["arm"]
        ctrl = fieldbus.Cia402Controller(2, mode=fieldbus.Mode.CSP)
        ctrl.set_goal(fieldbus.Goal.ENABLE)
        faults: list[fieldbus.DriveFault] = []

        def step(_k: int) -> None:
            res = op.exchange()
            faults.extend(e for e in res.events if isinstance(e, fieldbus.DriveFault))
            ctrl.step(
                img.inputs["statusword"],
                img.outputs["controlword"],
                hold_reset=op.fault_code_pending("arm") if hold else None,
            )
            img.outputs["target_position"][:] = img.inputs["position_actual_value"]

        emu.run(step, 300)
        assert ctrl.all_reached
        if slow:
            emu.slow_sdo("arm", "j1", slow)
        emu.drive_fault("arm", "j1", CODE)
        emu.run(step, 300)
        assert ctrl.all_reached  # reset and enabled again either way
        return [f.code for f in faults if f.slave == "j1" and f.code is not None], int(ctrl.fault_resets[1])


def test_without_a_slow_sdo_server_the_code_comes_even_without_the_hold(tmp_path: Path) -> None:
    codes, _ = _codes(tmp_path, slow=0, hold=False)
    assert codes == [CODE]


def test_a_slow_sdo_server_makes_the_reset_race_the_read_and_the_hold_wins_it(tmp_path: Path) -> None:
    lost, _ = _codes(tmp_path, slow=5, hold=False)
    assert lost == [0], lost  # the drive cleared 0x603F on the reset before the read was served
    held, resets = _codes(tmp_path, slow=5, hold=True)
    assert held == [CODE] and resets == 1


def test_slow_sdo_is_refused_where_it_has_no_meaning(tmp_path: Path) -> None:
    f = tmp_path / "ecat.yaml"
    f.write_text(
        "cycle_time_us: 1000\nbuses:\n"
        "  - {name: arm, type: ethercat, interface: sim, slaves: [{name: j, map: 'shipped:generic_cia402'}]}\n"
    )
    with emulate(f) as emu:
        with pytest.raises(FaultNotSupported, match="slow_sdo"):
            emu.slow_sdo("arm", "j", 3)
        with pytest.raises((fieldbus.FieldbusError, EmulationError), match="cycles must be >= 0"):
            emu.slow_sdo("arm", "j", -1)
