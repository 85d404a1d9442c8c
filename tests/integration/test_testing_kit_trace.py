"""The kit's trace as a new user reads it: rows, cycle indices, events and the assertions users wrote.

On the in-process EtherCAT emulator, virtual time: every run gives the same cycles on any machine.
Checked against our own code only (the emulator and the master are both this project's).
"""

from __future__ import annotations

from pathlib import Path

import pytest

import fieldbus
from fieldbus.testing import (
    EmulationAssertion,
    assert_drive_states,
    assert_event,
    assert_no_event,
    assert_no_target_jump,
    assert_safe_stop_latched,
    emulate,
)

QUICK_STOP_CW = 0x0002  # controlword "quick stop" (bit 2 low, bit 1 high): the CiA 402 safe output
OE = fieldbus.State402.OPERATION_ENABLED


def _net(tmp_path: Path) -> Path:
    f = tmp_path / "arm.yaml"
    f.write_text(
        "cycle_time_us: 1000\nreceive_timeout_us: 500\nsafe_stop_after: 5\nbuses:\n"
        "  - {name: arm, type: ethercat, interface: enp3s0,\n"
        "     slaves: [{name: 'j{i}', map: 'shipped:generic_cia402', count: 2}]}\n"
    )
    return f


class Follower:
    """Enables both axes and holds each where it is (plus ``offset`` counts); records the k it is given."""

    def __init__(self, op: fieldbus.Operational) -> None:
        self.op = op
        self.arm = op["arm"]
        self.ctrl = fieldbus.Cia402Controller(2, mode=fieldbus.Mode.CSP)
        self.ctrl.set_goal(fieldbus.Goal.ENABLE)
        self.ks: list[int] = []
        self.offset = 0.0

    def step(self, k: int) -> None:
        self.ks.append(k)
        assert k == self.op.result.cycle  # before the exchange: the trace row it fills
        res = self.op.exchange()
        if res.fresh and not res.safe_stop:
            self.ctrl.step(self.arm.inputs["statusword"], self.arm.outputs["controlword"])
            self.arm.outputs["target_position"][:] = self.arm.inputs["position_actual_value"] + self.offset


def test_run_gives_the_cycle_index_across_calls_and_it_is_the_trace_row(tmp_path: Path) -> None:
    with emulate(_net(tmp_path)) as emu:
        f = Follower(emu.op)
        emu.run(f.step, 100)
        emu.run(f.step, 50)
        assert f.ks == list(range(150))  # not 0..99 then 0..49
        assert len(emu.trace) == emu.op.result.cycle == 150
        # row k of the outputs is what cycle k sent: the controlword written after cycle k-1's exchange
        cw = emu.trace.outputs("arm")["controlword"]
        assert cw[0].tolist() == [0, 0] and cw[-1].tolist() == [0x000F, 0x000F]
        assert emu.cia402_states("arm") == [OE, OE]


def test_outputs_row_of_the_latch_is_the_controllers_and_the_safe_outputs_follow(tmp_path: Path) -> None:
    with emulate(_net(tmp_path)) as emu:
        f = Follower(emu.op)
        emu.run(f.step, 300)
        since = emu.trace.mark()
        emu.lose_cycles("arm", 8)
        emu.run(f.step, 20)
        at = assert_safe_stop_latched(emu.trace, within=8, since=since)
        cw = emu.trace.outputs("arm")["controlword"]
        assert cw[at].tolist() == [0x000F, 0x000F]  # the frame of the latch cycle left before the verdict
        assert (cw[at + 1 :] & 0x0006 == QUICK_STOP_CW).all()  # the safe outputs from the next frame on
        e = assert_event(emu.trace, "safe_stop", since=since)
        assert e.cycle == at and e.event.bus == "arm"  # type: ignore[attr-defined]


def test_the_trace_keeps_drive_faults_and_recoveries_as_events(tmp_path: Path) -> None:
    with emulate(_net(tmp_path)) as emu:
        f = Follower(emu.op)
        emu.run(f.step, 300)
        assert_no_event(emu.trace)
        since = emu.trace.mark()
        emu.drive_fault("arm", "j1", "sensor error")
        emu.run(f.step, 20)
        fault = assert_event(emu.trace, "drive_fault", since=since, within=5, slave="j1")
        assert fault.event.axis == 1  # type: ignore[attr-defined]  # its row in the group
        # the map has no 0x603F in its PDOs: the code, read by SDO, comes in a second event
        coded = assert_event(emu.trace, "drive_fault", since=since, within=20, slave="j1", code=0x7300)
        assert coded.cycle > fault.cycle
        with pytest.raises(EmulationAssertion, match="no 'drive_fault' event with slave='j0'"):
            assert_event(emu.trace, "drive_fault", since=since, slave="j0")
        with pytest.raises(EmulationAssertion, match="2 'drive_fault' events in cycles"):
            assert_no_event(emu.trace, "drive_fault", since=since)
        before = emu.trace.mark()
        emu.power_cycle("arm", "j0")
        emu.run(f.step, 3000)
        rec = assert_event(emu.trace, "recovered", since=before)
        assert rec.event.bus == "arm" and rec.cycle > before  # type: ignore[attr-defined]
        assert [e.kind for e in emu.trace.events_of(since=since)].count("drive_fault") >= 1


def test_no_target_jump_while_enabled_and_every_drive_in_its_states(tmp_path: Path) -> None:
    with emulate(_net(tmp_path)) as emu:
        f = Follower(emu.op)
        emu.run(f.step, 300)
        trace = emu.trace
        checked = assert_no_target_jump(trace, "arm", 0.01)
        assert checked > 2 * 200  # both axes enabled for most of the run
        assert assert_drive_states(emu.op, OE) == 2
        assert assert_drive_states(trace, [OE], since=trace.mark() - 50) == 100
        since = trace.mark()
        f.offset = 0.5  # a jump of 0.5 (the map's position unit) while enabled
        emu.run(f.step, 3)
        with pytest.raises(EmulationAssertion, match=r"axis 0: target_position jumped by 0.5 in cycle"):
            assert_no_target_jump(trace, "arm", 0.01, since=since)
        assert_no_target_jump(trace, "arm", [0.6, 0.6], since=since)  # a bound per axis
        with pytest.raises(
            EmulationAssertion, match=r"not in OPERATION_ENABLED: arm\[0\] SWITCH_ON_DISABLED"
        ):
            emu.power_cycle("arm", "j0")
            emu.run(f.step, 2000)
            assert_drive_states(emu.op, OE)
        assert_drive_states(emu.op, [OE, fieldbus.State402.SWITCH_ON_DISABLED])
