"""``fieldbus.ProfileMove`` alone, against statuswords written by the test (one function, not a bus).

The end-to-end proofs are on emulated drives: tests/integration/test_profile_sim.py (sim backend,
virtual time), test_profile_veth.py (pysoem), and canopen's BaseNode402 on the emulator. Here the
corner cases a drive seldom shows: a stale bit 12 from the cyclic modes, a stale bit 10 from the
previous PV target, the time-out, the other controlword bits, a missing channel.
"""

from __future__ import annotations

import numpy as np
import pytest

from fieldbus import Cia402Controller, Goal, Mode, ProfileMove, ProfilePhase
from fieldbus.errors import ChannelNameError

OE = 0x0027  # statusword: OPERATION ENABLED
ACK, REACHED = 0x1000, 0x0400


class Axes:
    """Two axes' arrays as a cycle sees them; the statusword is what the test says the drives answer."""

    def __init__(self, mode: Mode) -> None:
        self.ctrl = Cia402Controller(2, mode=mode)
        self.ctrl.set_goal(Goal.ENABLE)
        self.moves = ProfileMove(self.ctrl, timeout_cycles=[50, 1000])
        self.sw = np.full(2, OE, dtype=np.uint16)
        self.cw = np.zeros(2, dtype=np.uint16)
        self.tp = np.zeros(2)
        self.tv = np.zeros(2)

    def cycle(self, n: int = 1) -> None:
        for _ in range(n):
            self.ctrl.step(self.sw, self.cw)
            self.moves.step(self.sw, self.cw, self.tp, self.tv)


def test_pp_waits_out_a_stale_bit_12_then_runs_the_handshake_keeping_the_other_bits() -> None:
    ax = Axes(Mode.CSP)
    ax.sw[:] = OE | ACK  # CSP's bit 12 "follows target": not an acknowledge of anything
    ax.cycle(3)
    ax.moves.move_to([1.0, 2.0], relative=True, immediate=True)
    ax.cycle(5)
    assert list(ax.moves.phase) == [ProfilePhase.ARMED] * 2
    assert list(ax.tp) == [1.0, 2.0] and list(ax.cw & 0x10) == [0, 0]  # no edge while bit 12 is up
    assert list(ax.cw & 0x6F) == [0x6F, 0x6F]  # bits 5, 6 of the set-point; bits 0-3 the controller's
    ax.sw[:] = OE  # the drive in PP, bit 12 low
    ax.cycle()
    assert list(ax.moves.phase) == [ProfilePhase.SENT] * 2 and list(ax.cw & 0x10) == [0x10, 0x10]
    ax.sw[:] = OE | ACK  # acknowledged
    ax.cycle()
    assert list(ax.moves.phase) == [ProfilePhase.MOVING] * 2 and list(ax.cw & 0x10) == [0, 0]
    ax.sw[:] = OE | ACK | REACHED  # bit 10 with bit 12 still up: not this move's
    ax.cycle()
    assert list(ax.moves.phase) == [ProfilePhase.MOVING] * 2 and not ax.moves.done
    ax.sw[:] = OE | REACHED
    ax.cycle()
    assert list(ax.moves.phase) == [ProfilePhase.DONE] * 2 and ax.moves.done
    assert list(ax.cw & 0x0F) == [0x0F, 0x0F]


def test_pv_believes_bit_10_only_once_the_drive_had_time_to_answer_the_new_target() -> None:
    ax = Axes(Mode.PROFILE_VELOCITY)
    ax.sw[:] = OE | REACHED  # at the previous target speed
    ax.cycle(3)
    ax.moves.run_at([1.5, -1.5])
    ax.cycle(2)  # WAIT -> MOVING at once (enabled), then cycles whose bit 10 may still be the old target's
    assert list(ax.moves.phase) == [ProfilePhase.MOVING] * 2 and list(ax.tv) == [1.5, -1.5]
    ax.cycle()
    assert list(ax.moves.phase) == [ProfilePhase.DONE] * 2
    ax.cycle(5)
    assert list(ax.tv) == [1.5, -1.5]  # still written: the axes keep the speed


def test_each_axis_times_out_on_its_own_and_drops_bit_4() -> None:
    ax = Axes(Mode.CSP)
    ax.cycle(3)
    ax.moves.move_to([0.1, 0.2])
    ax.cycle(51)  # never acknowledged
    assert list(ax.moves.phase) == [ProfilePhase.TIMED_OUT, ProfilePhase.SENT]
    assert list(ax.cw & 0x10) == [0, 0x10]
    ax.moves.halt(axes=1)
    ax.cycle()
    assert list(ax.cw & 0x100) == [0, 0x100]


def test_an_axis_switched_to_another_mode_is_released_and_its_target_left_to_the_user() -> None:
    ax = Axes(Mode.CSP)
    ax.cycle(3)
    ax.moves.move_to(0.5, relative=True)  # the target output holds the offset, not a position
    ax.cycle(2)
    ax.sw[:] = OE | ACK
    ax.cycle()
    ax.moves.halt(axes=0)
    ax.sw[:] = OE | REACHED
    ax.cycle()
    assert list(ax.moves.phase) == [ProfilePhase.DONE] * 2
    ax.ctrl.request_mode(Mode.CSP, axes=0)  # back to the user's own targets on axis 0
    ax.tp[:] = 7.0  # the user's CSP target (or the controller's seed)
    ax.cycle()
    assert list(ax.moves.phase) == [ProfilePhase.IDLE, ProfilePhase.DONE]
    assert ax.tp[0] == 7.0 and int(ax.cw[0]) & 0x170 == 0  # neither the offset nor bits 4-6, 8
    assert int(ax.cw[1]) & 0x40 == 0x40  # axis 1 still the move's (bit 6 relative)


class _Direction:
    def __init__(self, **arrays: np.ndarray) -> None:
        self._arrays = arrays

    @property
    def names(self) -> tuple[str, ...]:
        return tuple(self._arrays)

    def __getitem__(self, name: str) -> np.ndarray:
        return self._arrays[name]


class _Image:
    def __init__(self, outputs: _Direction, inputs: _Direction) -> None:
        self.outputs, self.inputs = outputs, inputs


def test_pv_on_an_image_without_target_velocity_names_the_missing_channel() -> None:
    ctrl = Cia402Controller(1, mode=Mode.PROFILE_VELOCITY)
    moves = ProfileMove(ctrl)
    img = _Image(
        _Direction(controlword=np.zeros(1, np.uint16), target_position=np.zeros(1)),
        _Direction(statusword=np.full(1, OE, np.uint16)),
    )
    moves.step_image(img)  # nothing asked yet: fine
    moves.run_at(1.0)
    with pytest.raises(ChannelNameError, match="PV needs a target_velocity channel"):
        moves.step_image(img)
