"""Multi-axis CiA 402 slaves (issue 25 item 4): one EtherCAT slave, two drives at +0x800.

The sim tests use our own code on both sides (the in-process ESC emulator and our master);
the veth test runs the real pysoem master against the emulator in a child process.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

import fieldbus
from fieldbus.core.cia402 import State402
from fieldbus.core.drivefault import DriveFault
from fieldbus.recording.load import load
from fieldbus.testing import emulate

MAPS = Path(__file__).resolve().parents[2] / "pdo_maps"
TWO_AXIS = MAPS / "generic_cia402_2axis.yaml"
TARGETS = np.array([1000.0, -2000.0, 3000.0, 500.0])  # counts, one per axis (row)


def _network(tmp_path: Path, map_path: Path, interface: str = "eth0") -> Path:
    net = tmp_path / "arm.yaml"
    net.write_text(
        f"""
name: arm
cycle_time_us: 1000
buses:
  - name: arm
    type: ethercat
    interface: {interface}
    slaves:
      - {{name: shoulder, map: {map_path}}}
      - {{name: elbow, map: {map_path}}}
"""
    )
    return net


def _enable_and_track(emu: fieldbus.testing.Emulation, cycles: int) -> None:
    """Enable every axis, then send each its own target from fresh cycle 300 on; ``cycles`` fresh cycles.

    Over veth the emulator runs on the wall clock: a loaded machine that stalls longer than the slaves'
    100 ms SyncManager watchdog takes them out of OP, the master misses cycles and latches the safe
    stop (the drives fault, 0x8100). That stop is checked (missed cycles came first; never on virtual
    time) and cleared on a fresh cycle as an operator would, at most twice; the ``cycles`` fresh
    cycles then count again from the clear.
    """
    op = emu.op
    arm = op["arm"]
    ctrl = fieldbus.Cia402Controller(arm.n_axes, mode=fieldbus.Mode.CSP)
    ctrl.set_goal(fieldbus.Goal.ENABLE)
    fresh, missed, clears = [0], [0], [0]
    callers = [op.result.safe_stop]  # a stop latched before (the caller's, being cleared): not ours

    def step(_k: int) -> bool:
        res = op.exchange()
        if not res.fresh:
            missed[0] += 1
            return False
        callers[0] = callers[0] and res.safe_stop
        if res.safe_stop and not callers[0] and clears[0] < 2:
            assert not emu.virtual and missed[0] > 0, "a safe stop without a missed cycle"
            if op.clear_safe_stop():
                clears[0] += 1
                fresh[0] = 0
        ctrl.step_image(arm)
        if fresh[0] >= 300:
            arm.outputs["target_position"][:] = TARGETS
        fresh[0] += 1
        return fresh[0] >= cycles

    emu.run(step, cycles=4 * cycles)
    assert fresh[0] >= cycles, (fresh, missed, clears)


def _check_both_axes_track(emu: fieldbus.testing.Emulation) -> None:
    arm = emu.op["arm"]
    assert arm.n_axes == 4  # two slaves x two axes
    assert emu.drive_states("arm") == [State402.OPERATION_ENABLED] * 4  # the emulator's own view, per axis
    assert list(arm.inputs["statusword"] & 0x6F) == [0x27] * 4  # the master's view: OPERATION ENABLED
    np.testing.assert_allclose(arm.inputs["position_actual_value"], TARGETS, atol=20)


def test_a_two_axis_slave_runs_both_axes_on_the_sim_backend(tmp_path: Path) -> None:
    with emulate(_network(tmp_path, TWO_AXIS)) as emu:
        assert emu.drive_states("arm") == [State402.SWITCH_ON_DISABLED] * 4
        rec = emu.op.record(tmp_path / "arm.mcap")
        _enable_and_track(emu, 1500)
        rec.close()
        _check_both_axes_track(emu)
        # the trace and the recording name each axis's row
        assert emu.trace.group_fresh("arm").shape[1] == 4 and emu.trace.group_fresh("arm")[-1].all()
    enabled = [
        e["slave"] for e in load(tmp_path / "arm.mcap").events
        if e["kind"] == "cia402_state" and e["new"] == "OPERATION_ENABLED"
    ]  # fmt: skip
    assert sorted(enabled) == ["elbow.axis1", "elbow.axis2", "shoulder.axis1", "shoulder.axis2"]


@pytest.mark.veth
def test_a_two_axis_slave_runs_both_axes_over_veth_with_pysoem(
    tmp_path: Path, request: pytest.FixtureRequest
) -> None:
    request.getfixturevalue("veth_possible")
    with emulate(_network(tmp_path, TWO_AXIS), ethercat="veth", receive_timeout_us=20000) as emu:
        # SOEM mapped what the maps imply: 2 x 13 output and 2 x 15 input bytes per slave
        backend = emu.network.backend("arm")
        assert [(a.out_size, a.in_size) for a in backend.areas] == [(26, 30)] * 2
        _enable_and_track(emu, 1500)
        _check_both_axes_track(emu)


@pytest.mark.parametrize(
    ("code_by", "ethercat"),
    [
        ("pdo", "sim"),
        ("sdo", "sim"),
        pytest.param("sdo", "veth", marks=pytest.mark.veth),
    ],
)
def test_sdos_to_axis_2_objects_reach_axis_2(
    tmp_path: Path, code_by: str, ethercat: str, request: pytest.FixtureRequest
) -> None:
    """0x6841 reads axis 2's statusword; 0x6865 sets axis 2's following error window, not axis 1's.

    ``code_by`` "sdo": a map without 0x603F in its PDOs; the fault's code is read from 0x683F, and
    the map asks for the diagnosis history (0x10F3), whose message names axis 2. Over veth the master
    is the real pysoem.
    """
    map_path = TWO_AXIS
    if code_by == "sdo":
        map_path = tmp_path / "two_axis_no_code.yaml"
        text = TWO_AXIS.read_text()
        line = next(x for x in text.splitlines() if "0x603F" in x and "index:" in x)
        map_path.write_text(text.replace(line + "\n", "") + "ethercat: {diagnosis_history: true}\n")
    if ethercat == "veth":
        request.getfixturevalue("veth_possible")  # pysoem there, the machine makes a veth pair
    _axis_2_fault(tmp_path, map_path, code_by, ethercat)


def _axis_2_fault(tmp_path: Path, map_path: Path, code_by: str, ethercat: str) -> None:
    timeout = {"receive_timeout_us": 20000} if ethercat == "veth" else {}
    with emulate(_network(tmp_path, map_path), bring_up=False, ethercat=ethercat, **timeout) as emu:
        pre = emu.network.pre_op()
        pre.sdo_write("arm", "shoulder", 0x6865, 0, (5).to_bytes(4, "little"))  # 5 counts: axis 2 only
        assert int.from_bytes(pre.sdo_read("arm", "shoulder", 0x6065, 0), "little") == 10_000  # axis 1 kept
        op = pre.safe_op().op()
        arm = op["arm"]
        ctrl = fieldbus.Cia402Controller(arm.n_axes, mode=fieldbus.Mode.CSP)
        ctrl.set_goal(fieldbus.Goal.ENABLE)
        faults: list[DriveFault] = []

        def step(k: int) -> None:
            res = op.exchange()
            faults.extend(e for e in res.events if isinstance(e, DriveFault) and e.code is not None)
            if res.fresh:
                if int(arm.inputs["statusword"][1]) & 0x08:  # no fault reset: the code read must find it
                    ctrl.set_goal(fieldbus.Goal.DISABLE)
                ctrl.step_image(arm)
                if k >= 300:
                    arm.outputs["target_position"][:] = arm.inputs["position_actual_value"] + 2000

        emu.run(step, cycles=400)
        # the shoulder's axis 2 (row 1) faults on its following error, no other axis does
        assert [(f.slave, f.axis, f.slave_axis, f.code) for f in faults] == [("shoulder", 1, 1, 0x8611)]
        if code_by == "sdo":  # the history's newest message: following error, of axis 2
            newest = faults[0].history[0] if faults[0].history else None
            assert newest is not None and (newest.name, newest.params) == ("following error", (0x8611, 2))
        ctrl.set_goal(fieldbus.Goal.DISABLE)  # leave the fault standing

        def disable(_k: int) -> None:
            if op.exchange().fresh:
                ctrl.step_image(arm)

        emu.run(disable, cycles=50)
        assert emu.drive_states("arm")[1] == State402.FAULT
        statusword = op.submit_sdo_read("arm", "shoulder", 0x6841, 0)
        emu.run(lambda _k: op.exchange() and statusword.done(), cycles=50)
        assert int.from_bytes(statusword.result(), "little") == int(arm.inputs["statusword"][1])
        assert [bool(int(w) & 0x08) for w in arm.inputs["statusword"]] == [False, True, False, False]


def test_both_axes_of_a_two_axis_slave_home_from_the_maps_homing_section(tmp_path: Path) -> None:
    """The homing: section is written to each axis (0x6098 and 0x6898, ...); each axis homes by itself."""
    homed = tmp_path / "two_axis_homed.yaml"
    offset = 1234  # counts: what the position reads at the home point
    homed.write_text(TWO_AXIS.read_text() + f"homing: {{method: 37, offset: {offset}, timeout_ms: 2000}}\n")
    with emulate(_network(tmp_path, homed)) as emu:
        op = emu.op
        arm = op["arm"]
        ctrl = fieldbus.Cia402Controller(arm.n_axes, mode=fieldbus.Mode.CSP)
        homing = fieldbus.Homing.from_maps(ctrl, [s.map for s in op.groups["arm"].slaves], op.cycle_time_us)
        ctrl.set_goal(fieldbus.Goal.ENABLE)
        homing.start(order=[[0, 2], [1, 3]])  # every slave's axis 1, then its axis 2

        def home(_k: int) -> bool:
            if op.exchange().fresh:
                ctrl.step_image(arm)
                homing.step(arm.inputs["statusword"], arm.outputs["controlword"])
            return homing.done

        emu.run(home, cycles=5000)
        assert homing.done and list(homing.phase) == [4] * 4  # HomingPhase.DONE on every axis
        assert list(arm.inputs["position_actual_value"]) == [offset] * 4


def test_a_power_cycled_two_axis_slave_is_configured_again_and_both_axes_run(tmp_path: Path) -> None:
    """The recovery maps both axes' PDOs again and writes both axes' start-up SDOs (0x6060, 0x6860)."""
    with emulate(_network(tmp_path, TWO_AXIS)) as emu:
        _enable_and_track(emu, 1000)
        emu.power_cycle("arm", "elbow")  # the elbow's OD goes back to defaults: mapping and mode lost
        op, bus = emu.op, emu.op.result.buses[0]
        before = bus.recoveries
        emu.run(lambda _k: op.exchange() and bus.recoveries > before and not bus.recovering, cycles=3000)
        assert (
            bus.recoveries > before and op.result.safe_stop
        )  # back in OP; the safe stop holds until cleared
        op.clear_safe_stop()  # opens after release_after fresh cycles
        _enable_and_track(emu, 2000)
        assert not op.result.safe_stop
        _check_both_axes_track(emu)
        modes = [emu.op.submit_sdo_read("arm", "elbow", index, 0) for index in (0x6060, 0x6860)]
        emu.run(lambda _k: emu.op.exchange() and all(f.done() for f in modes), cycles=50)
        assert [f.result() for f in modes] == [b"\x08", b"\x08"]  # CSP on both axes, written again
