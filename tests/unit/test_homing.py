"""fieldbus.core.cia402.Homing against emulated drives (our own emulator: the canopen oracle is not done)."""

from __future__ import annotations

import numpy as np

from fieldbus.core.cia402 import Cia402Controller, Goal, Homing, HomingPhase, Mode
from sim_slaves.drive402 import Cia402Drive, DictObjectStore, DriveParams, Obj, default_objects


def _drive(method: int, speed: int) -> tuple[Cia402Drive, DictObjectStore]:
    p = DriveParams(negative_switch_rad=-0.5)
    od = DictObjectStore(default_objects(p))
    od.values.update({(0x6098, 0): method, (0x607C, 0): 0, (0x6099, 1): speed, (0x6099, 2): speed})
    return Cia402Drive(p), od


def test_axes_home_in_order_then_return_to_their_mode_with_errors_and_timeouts_per_axis() -> None:
    setup = [(35, 0), (17, 100_000), (1, 0), (17, 0)]  # here; switch; unsupported; never reaches the switch
    drives = [_drive(m, v) for m, v in setup]
    n = len(drives)
    ctrl = Cia402Controller(n, mode=Mode.CSP)
    ctrl.set_goal(Goal.ENABLE)
    homing = Homing(ctrl, timeout_cycles=500)
    sw = np.zeros(n, dtype=np.uint16)
    md = np.zeros(n, dtype=np.int8)
    cw = np.zeros(n, dtype=np.uint16)
    mo = np.zeros(n, dtype=np.int8)
    homing.start(order=[[1], [0, 2, 3]])  # axis 1 first (a hip before its knee), then the others
    started_second = None
    for k in range(2000):
        for i, (d, od) in enumerate(drives):
            od.values[(Obj.CONTROLWORD, 0)] = int(cw[i])
            od.values[(Obj.MODES_OF_OPERATION, 0)] = int(mo[i])
            d.step(od, 1e-3)
            sw[i] = od.values[(Obj.STATUSWORD, 0)]
            md[i] = od.values[(Obj.MODES_DISPLAY, 0)]
        ctrl.step(sw, cw, md, mo)
        homing.step(sw, cw)
        if started_second is None and homing.phase[0] != HomingPhase.IDLE:
            started_second = k
            assert homing.phase[1] == HomingPhase.DONE  # the second stage waits for the first
        if homing.done and ctrl.all_reached:
            break
    assert homing.done
    assert list(homing.phase) == [
        HomingPhase.DONE,
        HomingPhase.DONE,
        HomingPhase.FAILED,
        HomingPhase.TIMED_OUT,
    ]
    assert list(md) == [Mode.CSP] * n and ctrl.all_reached  # every axis back in CSP, enabled
    assert started_second is not None and started_second > 50  # the switch search took time
    assert abs(drives[1][0].position_rad) < 0.05  # home offset 0 at the switch; it stopped just past it
    assert homing.cycles[3] == 501


def test_a_second_homing_does_not_believe_the_bits_left_from_the_first() -> None:
    """Bits 10/12 of a finished homing are still set when the next edge goes out: not a new 'attained'."""
    from fieldbus.core.cia402 import SETTLE_CYCLES, Cia402Controller, Goal, Homing, HomingPhase

    ctrl = Cia402Controller(1)
    ctrl.set_goal(Goal.ENABLE)
    homing = Homing(ctrl)
    homing.start()
    stale = np.array([0x0237 | 0x1400], dtype=np.uint16)  # OPERATION ENABLED, attained + target reached
    cw = np.zeros(1, dtype=np.uint16)
    phases = []
    for _ in range(1 + SETTLE_CYCLES):  # armed, then the edge and SETTLE_CYCLES - 1 more
        ctrl.step(stale, cw)
        homing.step(stale, cw)
        phases.append(int(homing.phase[0]))
    assert phases[-1] == HomingPhase.RUNNING, phases  # the edge is out; the old bits are not believed
    busy = np.array([0x0237], dtype=np.uint16)  # the drive answered the edge: homing in progress
    ctrl.step(busy, cw)
    homing.step(busy, cw)
    assert homing.phase[0] == HomingPhase.RUNNING
    ctrl.step(stale, cw)
    homing.step(stale, cw)
    assert homing.phase[0] == HomingPhase.DONE


def test_a_drive_that_leaves_operation_enabled_while_homing_has_failed_at_once() -> None:
    """A fault (here a bus dropout's 0x8100) mid-search interrupts the drive's homing: after the fault
    reset the drive waits for a new bit-4 edge, so the axis is FAILED when the fault is seen, not
    RUNNING until its timeout (30 s by default; a loaded machine's veth test waited that long)."""
    ctrl = Cia402Controller(2, mode=Mode.CSP)
    ctrl.set_goal(Goal.ENABLE)
    homing = Homing(ctrl)
    homing.start()
    enabled = np.array([0x0237, 0x0237], dtype=np.uint16)  # OPERATION ENABLED, searching
    mode6 = np.array([Mode.HOMING, Mode.HOMING], dtype=np.int8)
    cw = np.zeros(2, dtype=np.uint16)
    mo = np.zeros(2, dtype=np.int8)
    for _ in range(10):
        ctrl.step(enabled, cw, mode6, mo)
        homing.step(enabled, cw)
    assert list(homing.phase) == [HomingPhase.RUNNING] * 2 and (cw & 0x10).all()
    faulted = np.array([0x0237, 0x0218], dtype=np.uint16)  # axis 1 in FAULT
    ctrl.step(faulted, cw, mode6, mo)
    homing.step(faulted, cw)
    assert list(homing.phase) == [HomingPhase.RUNNING, HomingPhase.FAILED]
    assert cw[1] & 0x10 == 0 and cw[0] & 0x10  # bit 4 dropped on the failed axis only


def test_a_dropout_that_takes_the_start_edge_fails_the_homing_instead_of_waiting_for_ever() -> None:
    """Over a bus, the frame carrying the bit-4 edge can be lost to a dropout (the slave's watchdog):
    the emulated drive faults 0x8100 without having started, and after the fault reset it is OPERATION
    ENABLED in mode 6 with bit 4 already high: no edge, no homing. The axis must not stay RUNNING."""
    drive, od = _drive(17, 100_000)
    ctrl = Cia402Controller(1, mode=Mode.CSP)
    ctrl.set_goal(Goal.ENABLE)
    homing = Homing(ctrl, timeout_cycles=20_000)
    sw, cw = np.zeros(1, dtype=np.uint16), np.zeros(1, dtype=np.uint16)
    md, mo = np.zeros(1, dtype=np.int8), np.zeros(1, dtype=np.int8)
    homing.start()
    lost = None
    for k in range(2000):
        if lost is None and homing.phase[0] == HomingPhase.RUNNING:
            lost = k  # this cycle's outputs never reach the drive, which faults
            drive.connection_lost()
        else:
            od.values[(Obj.CONTROLWORD, 0)] = int(cw[0])
            od.values[(Obj.MODES_OF_OPERATION, 0)] = int(mo[0])
        drive.step(od, 1e-3)
        sw[0] = od.values[(Obj.STATUSWORD, 0)]
        md[0] = od.values[(Obj.MODES_DISPLAY, 0)]
        ctrl.step(sw, cw, md, mo)
        homing.step(sw, cw)
    assert lost is not None
    assert homing.phase[0] == HomingPhase.FAILED and homing.done  # (was RUNNING until the timeout)
    assert ctrl.all_reached and md[0] == Mode.CSP  # enabled again, back in its previous mode
