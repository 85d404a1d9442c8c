"""Tests of the example arm controller against emulated drives, with fieldbus.testing only.

The joints are geared drives (arm_joint.yaml: a 2^20-count motor encoder behind a 50:1 gear), and
the emulated drives take their resolution and gear from that map.

Every test runs on the in-process EtherCAT emulator and on CANopen (virtual
time: as fast as the CPU allows, the same cycles on any machine) and over a
veth pair with the real pysoem master (wall time; skipped where the machine
refuses a veth pair).
"""

from __future__ import annotations

from pathlib import Path

import pytest
from arm_controller import ArmController

from fieldbus.testing import (
    Emulation,
    assert_all_enabled,
    assert_inputs_held,
    assert_no_miss,
    assert_safe_stop_latched,
)

HERE = Path(__file__).parent
SENSOR_FAULT = 0x7300  # CiA 402 error code: sensor


def follow(emu: Emulation, controller: ArmController, cycles: int = 1500) -> None:
    """Step the controller until the arm follows its sine again (all joints enabled), ``cycles`` at most.

    On virtual time (sim, canopen) nothing stalls: that is one run. Over veth the emulated drives
    run in a child process on the wall clock, and each has a 100 ms SyncManager watchdog: a machine
    busy enough to deschedule this process longer than that takes a drive out of OP. The master then
    sees the missed cycles and latches the safe stop, as it must; the arm stops. That stop is checked
    here, not ignored, and then resumed as an operator would (at most twice).
    """

    def until_following(k: int) -> bool:  # returning True ends emu.run early
        controller.step(k)
        return controller.following

    for _ in range(3):
        if controller.stopped:
            controller.resume()
        since = emu.trace.mark()
        emu.run(until_following, cycles=cycles)
        if controller.following:
            return
        assert not emu.virtual, "the joints did not all enable"
        assert_stalled(emu, controller, since)
    pytest.fail("the joints did not all enable: stopped by a stall three times")


def assert_stalled(emu: Emulation, controller: ArmController, since: int) -> None:
    """The arm stopped since cycle ``since`` the way a stall stops it: missed cycles, then the latch."""
    assert not emu.trace.fresh[since:].all(), "stopped, yet every cycle was fresh"
    assert emu.trace.safe_stop[-1] and controller.stopped


@pytest.fixture(params=["sim", "veth", "canopen"])
def arm(request: pytest.FixtureRequest, fieldbus_emulation) -> tuple[Emulation, ArmController]:
    """The arm's network file as it is, on emulated drives; the controller enabled and following."""
    if request.param == "veth":  # a user-space emulator on a shared machine: a few ms of slack
        emu = fieldbus_emulation(HERE / "arm.yaml", ethercat="veth", receive_timeout_us=20000)
    elif request.param == "canopen":  # the same arm on CANopen, emulated in lockstep on virtual time
        emu = fieldbus_emulation(HERE / "arm_canopen.yaml")
    else:
        emu = fieldbus_emulation(HERE / "arm.yaml")
    controller = ArmController(emu.op)
    follow(emu, controller)
    return emu, controller


def test_tracks_the_sine(arm: tuple[Emulation, ArmController]) -> None:
    emu, controller = arm
    for _ in range(3):
        since = emu.trace.mark()
        emu.run(controller.step, cycles=2000)
        if emu.virtual or not controller.stopped:
            break
        # over veth a busy machine can stall the emulator longer than safe_stop_after cycles:
        # the arm stops (as it must); check that stop, resume, and track again
        assert_stalled(emu, controller, since)
        follow(emu, controller)
    assert_all_enabled(emu.op)
    if emu.virtual:  # over veth a late reply is possible on a loaded machine: not the controller's doing
        assert_no_miss(emu.trace, since=since)
    assert controller.max_error_rad < 0.01
    assert not controller.stopped


def test_a_burst_of_lost_frames_latches_the_safe_stop(arm: tuple[Emulation, ArmController]) -> None:
    emu, controller = arm
    since = emu.trace.mark()
    emu.lose_cycles("arm", 12)
    emu.run(controller.step, cycles=100)
    assert_safe_stop_latched(emu.trace, within=10, since=since)
    assert_inputs_held(emu.trace, "arm", since=since, until=since + 12)
    assert controller.stopped
    # the drives themselves left OPERATION ENABLED (quick stop), not just the controller
    assert all(s is not None and s.name != "OPERATION_ENABLED" for s in emu.drive_states("arm"))
    controller.resume()
    follow(emu, controller)
    assert controller.following and not controller.stopped
    assert_all_enabled(emu.op)


def test_a_drive_fault_reaches_the_controller_with_its_code(arm: tuple[Emulation, ArmController]) -> None:
    emu, controller = arm
    emu.drive_fault("arm", "elbow", SENSOR_FAULT)
    emu.run(controller.step, cycles=100)
    assert controller.fault_codes == {1: SENSOR_FAULT}
    follow(emu, controller)  # the controller resets the fault and enables again
    assert controller.following
    assert_all_enabled(emu.op)


def test_a_power_cycled_drive_stops_the_arm_comes_back_and_is_enabled_again(
    arm: tuple[Emulation, ArmController],
) -> None:
    emu, controller = arm
    status = emu.op.result.bus("arm")
    before = status.recoveries
    since = emu.trace.mark()
    emu.power_cycle("arm", "wrist")
    emu.run(controller.step, cycles=1000)
    # the wrist is gone for more than safe_stop_after cycles: the arm stops...
    assert_safe_stop_latched(emu.trace, within=10, since=since)
    assert controller.stopped
    # ...and the master brings the slave back to OP by itself
    assert status.recoveries > before and not status.recovering
    controller.resume()  # what an operator does once the cause is known
    follow(emu, controller)
    assert controller.following
    assert_all_enabled(emu.op)
