"""The ETG.1020 diagnosis history (0x10F3) reaches the user with a drive fault (issue 25 item 5, EtherCAT).

A fault injected by name through fieldbus.testing; the emulated drive writes a history message; the
network reads it acyclically and reports the fault again with the history decoded. Over veth the
master is the real pysoem (its SDO uploads, our decoding); on the sim backend both sides are ours.
"""

from __future__ import annotations

from pathlib import Path

import pytest

import fieldbus
from fieldbus.core.drivefault import DriveFault
from fieldbus.network import BusEvent
from fieldbus.testing import emulate

MAPS = Path(__file__).resolve().parents[2] / "pdo_maps"


def _with_history(src: Path, dst: Path, keep: bool = True) -> Path:
    """``src`` with ``ethercat: {diagnosis_history: true}`` (or not), 0x603F left out of its PDOs."""
    lines = [x for x in src.read_text().splitlines() if not ("0x603F" in x and "index:" in x)]
    dst.write_text("\n".join(lines) + ("\nethercat: {diagnosis_history: true}\n" if keep else "\n"))
    return dst


def _network(tmp_path: Path, maps: list[Path]) -> Path:
    slaves = "\n".join(f"      - {{name: j{i}, map: {m}}}" for i, m in enumerate(maps))
    net = tmp_path / "robot.yaml"
    net.write_text(
        f"name: robot\ncycle_time_us: 1000\nbuses:\n  - name: robot\n    type: ethercat\n"
        f"    interface: eth0\n    slaves:\n{slaves}\n"
    )
    return net


def _fault_and_collect(emu: fieldbus.testing.Emulation, slave: str, name: str) -> list[object]:
    op = emu.op
    img = op["robot"]
    ctrl = fieldbus.Cia402Controller(img.n_axes, mode=fieldbus.Mode.CSP)
    ctrl.set_goal(fieldbus.Goal.ENABLE)
    events: list[object] = []

    def step(k: int) -> None:
        if k == 200:
            emu.drive_fault("robot", slave, name)
        if k == 201:
            ctrl.set_goal(fieldbus.Goal.DISABLE)  # leave the fault standing
        res = op.exchange()
        events.extend(res.events)
        if res.fresh:
            ctrl.step_image(img)

    emu.run(step, cycles=600)
    return events


def _check(events: list[object], slave: str, code: int, name: str, slave_axis: int = 0) -> None:
    faults = [e for e in events if isinstance(e, DriveFault) and e.slave == slave]
    assert [f.code for f in faults] == [None, code]  # the edge, then the fault with its code and history
    last = faults[-1]
    assert last.history is not None and len(last.history) == 1
    (msg,) = last.history
    assert (msg.emcy_code, msg.name, msg.severity) == (code, name, "error")
    assert msg.params == (code, slave_axis + 1)  # the error code and the axis (1-based)
    assert name in str(last)
    assert not [e for e in events if isinstance(e, BusEvent) and e.kind == "acyclic_error"]


def test_the_history_comes_with_the_fault_on_the_sim_backend(tmp_path: Path) -> None:
    one = _with_history(MAPS / "generic_cia402.yaml", tmp_path / "one.yaml")
    with emulate(_network(tmp_path, [one, one])) as emu:
        events = _fault_and_collect(emu, "j1", "sensor error")
    _check(events, "j1", 0x7300, "sensor error")


def test_a_two_axis_slave_keeps_a_history_too(tmp_path: Path) -> None:
    two = _with_history(MAPS / "generic_cia402_2axis.yaml", tmp_path / "two.yaml")
    with emulate(_network(tmp_path, [two])) as emu:
        events = _fault_and_collect(emu, "j0", "following error")
    _check(events, "j0", 0x8611, "following error", slave_axis=0)


def test_without_the_map_flag_the_history_is_not_read(tmp_path: Path) -> None:
    plain = _with_history(MAPS / "generic_cia402.yaml", tmp_path / "plain.yaml", keep=False)
    with emulate(_network(tmp_path, [plain])) as emu:
        events = _fault_and_collect(emu, "j0", "sensor error")
    faults = [e for e in events if isinstance(e, DriveFault)]
    assert [(f.code, f.history) for f in faults] == [(None, None), (0x7300, None)]


@pytest.mark.veth
def test_the_history_comes_with_the_fault_over_veth_with_pysoem(
    tmp_path: Path, request: pytest.FixtureRequest
) -> None:
    one = _with_history(MAPS / "generic_cia402.yaml", tmp_path / "one.yaml")
    request.getfixturevalue("veth_possible")
    with emulate(_network(tmp_path, [one, one]), ethercat="veth", receive_timeout_us=20000) as emu:
        events = _fault_and_collect(emu, "j1", "sensor error")
    _check(events, "j1", 0x7300, "sensor error")
