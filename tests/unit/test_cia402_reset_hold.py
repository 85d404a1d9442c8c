"""Cia402Controller holds a fault reset while the axis's error-code read is pending (bounded, not counted)."""

from __future__ import annotations

import numpy as np

from fieldbus.core.cia402 import FAULT_RESET_BIT, Cia402Controller, Goal, Mode

FAULT_SW = 0x0008  # statusword of FAULT


def _bit7(cw: np.ndarray) -> list[bool]:
    return [bool(int(w) & FAULT_RESET_BIT) for w in cw]


def test_the_reset_waits_for_the_code_read_then_pulses_once() -> None:
    ctrl = Cia402Controller(2, mode=Mode.CSP)
    ctrl.set_goal(Goal.ENABLE)
    sw = np.full(2, FAULT_SW, dtype=np.uint16)
    cw = np.zeros(2, dtype=np.uint16)
    hold = np.array([True, False])
    seen: list[list[bool]] = []
    for _ in range(5):  # axis 0's read pending for 5 cycles; axis 1 has nothing to wait for
        ctrl.step(sw, cw, hold_reset=hold)
        seen.append(_bit7(cw))
    assert [s[0] for s in seen] == [False] * 5
    assert [s[1] for s in seen] == [True, False, True, False, True]
    assert ctrl.fault_resets[0] == 0  # a held reset is not spent from the budget
    hold[0] = False
    ctrl.step(sw, cw, hold_reset=hold)
    assert _bit7(cw)[0] and ctrl.fault_resets[0] == 1  # released: the pulse starts at once


def test_the_hold_is_bounded_per_fault() -> None:
    ctrl = Cia402Controller(1, mode=Mode.CSP, max_reset_hold_cycles=3)
    ctrl.set_goal(Goal.ENABLE)
    sw = np.full(1, FAULT_SW, dtype=np.uint16)
    cw = np.zeros(1, dtype=np.uint16)
    hold = np.ones(1, dtype=bool)  # a read that never completes
    bits = []
    for _ in range(5):
        ctrl.step(sw, cw, hold_reset=hold)
        bits.append(_bit7(cw)[0])
    assert bits == [False, False, False, True, False]
    # out of fault and into it again: the next fault may wait again
    ctrl.step(np.full(1, 0x0040, dtype=np.uint16), cw, hold_reset=hold)  # SWITCH ON DISABLED
    ctrl.step(sw, cw, hold_reset=hold)
    assert not _bit7(cw)[0]
