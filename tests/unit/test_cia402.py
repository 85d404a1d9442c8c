"""CiA 402 master side: statusword decoding, the table, and the vectorised controller against emulated drives."""

from __future__ import annotations

import itertools
from pathlib import Path

import numpy as np
import numpy.typing as npt
import pytest

from fieldbus.core.cia402 import (
    COMMAND_BY_NIBBLE,
    CONTROLLER_CW,
    CONTROLWORD,
    STATUSWORD_LUT,
    STATUSWORD_PATTERNS,
    TRANSITIONS,
    UNKNOWN_STATE,
    Cia402Controller,
    Goal,
    Mode,
    SafeStop,
    State402,
    Trigger,
    command_of,
    decode_state,
    decode_states,
    mermaid_diagram,
    next_command,
    transition_table_markdown,
)
from fieldbus.platform.allocs import net_blocks
from sim_slaves.drive402 import Cia402Drive, DictObjectStore, DriveParams, default_objects

S = State402
N = 64

# -------------------------------------------------------------- statusword decoding

# hand-written statuswords, as real drives send them (bit 4 voltage enabled, bit 9 remote, ...)
HAND_WORDS: list[tuple[int, State402 | None]] = [
    (0x0000, S.NOT_READY_TO_SWITCH_ON),
    (0x0010, S.NOT_READY_TO_SWITCH_ON),  # voltage present, self test running
    (0x0040, S.SWITCH_ON_DISABLED),
    (0x0250, S.SWITCH_ON_DISABLED),  # typical: remote + voltage enabled
    (0x0270, S.SWITCH_ON_DISABLED),  # bit 5 is don't-care here
    (0x0021, S.READY_TO_SWITCH_ON),
    (0x0231, S.READY_TO_SWITCH_ON),
    (0x0023, S.SWITCHED_ON),
    (0x0233, S.SWITCHED_ON),
    (0x0027, S.OPERATION_ENABLED),
    (0x0237, S.OPERATION_ENABLED),
    (0x1637, S.OPERATION_ENABLED),  # + target reached + follows target (CSP)
    (0x3637, S.OPERATION_ENABLED),  # + following error bit 13
    (0x00B7, S.OPERATION_ENABLED),  # + warning bit 7
    (0x0007, S.QUICK_STOP_ACTIVE),
    (0x0217, S.QUICK_STOP_ACTIVE),
    (0x000F, S.FAULT_REACTION_ACTIVE),
    (0x021F, S.FAULT_REACTION_ACTIVE),
    (0x003F, S.FAULT_REACTION_ACTIVE),
    (0x0008, S.FAULT),
    (0x0218, S.FAULT),
    (0x0238, S.FAULT),
    (0x0041, None),  # x1xx 0001: no state has "switch on disabled" with "ready"
    (0x0029, None),  # x01x 1001
    (0x0067, None),  # x11x 0111
    (0x0001, None),  # x00x 0001
]


@pytest.mark.parametrize(
    ("word", "state"), HAND_WORDS, ids=lambda v: f"{v:#06x}" if isinstance(v, int) else str(v)
)
def test_decode_hand_written_statuswords(word: int, state: State402 | None) -> None:
    assert decode_state(word) is state
    out = np.zeros(1, dtype=np.int8)
    decode_states(np.array([word], dtype=np.uint16), out)
    assert out[0] == (UNKNOWN_STATE if state is None else state)


def test_every_state_has_a_pattern_and_vectorised_decode_matches_the_masks() -> None:
    assert {p.state for p in STATUSWORD_PATTERNS} == set(State402)
    words = np.arange(65536, dtype=np.uint16)
    out = np.empty(65536, dtype=np.int8)
    decode_states(words, out, np.empty(65536, dtype=np.intp))
    expected = np.full(65536, UNKNOWN_STATE, dtype=np.int8)
    for p in STATUSWORD_PATTERNS:
        expected[(words & p.mask) == p.value] = p.state
    np.testing.assert_array_equal(out, expected)
    np.testing.assert_array_equal(out, STATUSWORD_LUT)
    for s in State402:
        assert (out == s).sum() > 0


def test_controlword_commands() -> None:
    assert command_of(0x06) is Trigger.SHUTDOWN
    assert command_of(0x07) is Trigger.SWITCH_ON
    assert Trigger.DISABLE_OPERATION.value == Trigger.SWITCH_ON.value  # same bits, 0x07
    assert command_of(0x0F) is Trigger.ENABLE_OPERATION
    assert command_of(0x00) is Trigger.DISABLE_VOLTAGE
    assert command_of(0x02) is Trigger.QUICK_STOP
    assert command_of(0x0E) is Trigger.SHUTDOWN  # bit 3 is don't-care for shutdown
    assert command_of(0x01) is Trigger.DISABLE_VOLTAGE
    assert command_of(0x017F) is Trigger.ENABLE_OPERATION  # halt / mode bits do not change the command
    for cmd, word in CONTROLWORD.items():
        if cmd is not Trigger.FAULT_RESET:
            assert command_of(word) is cmd
    assert len(COMMAND_BY_NIBBLE) == 16


def test_table_has_transitions_0_to_16_and_the_diagram_is_drawn_from_it() -> None:
    assert sorted({t.number for t in TRANSITIONS}) == list(range(17))
    diagram = mermaid_diagram()
    for t in TRANSITIONS:
        src = "[*]" if t.source is None else t.source.name
        assert f"{src} --> {t.target.name}: {t.number}: " in diagram


def test_planner_paths() -> None:
    assert next_command(S.SWITCH_ON_DISABLED, S.OPERATION_ENABLED) is Trigger.SHUTDOWN
    assert next_command(S.READY_TO_SWITCH_ON, S.OPERATION_ENABLED) is Trigger.SWITCH_ON
    assert next_command(S.SWITCHED_ON, S.OPERATION_ENABLED) is Trigger.ENABLE_OPERATION
    assert next_command(S.FAULT, S.OPERATION_ENABLED) is Trigger.FAULT_RESET
    # never through the guarded transition 16: quick stop active goes back via switch on disabled
    assert next_command(S.QUICK_STOP_ACTIVE, S.OPERATION_ENABLED) is Trigger.DISABLE_VOLTAGE
    assert next_command(S.OPERATION_ENABLED, S.SWITCH_ON_DISABLED) is Trigger.DISABLE_VOLTAGE
    assert next_command(S.FAULT, S.SWITCH_ON_DISABLED, allow_fault_reset=False) is None
    assert CONTROLLER_CW[S.OPERATION_ENABLED, Goal.ENABLE] == 0x0F


# -------------------------------------------------------------- a chain of emulated drives


class Chain:
    """``n`` emulated drives behind a vectorised process image (master inputs / outputs as arrays)."""

    def __init__(self, n: int = N, params: DriveParams | list[DriveParams] | None = None) -> None:
        plist = params if isinstance(params, list) else [params or DriveParams()] * n
        self.drives = [Cia402Drive(p) for p in plist]
        self.ods = [DictObjectStore(default_objects(p)) for p in plist]
        self.controlword: npt.NDArray[np.uint16] = np.zeros(n, dtype=np.uint16)  # master outputs
        self.modes_out: npt.NDArray[np.int8] = np.full(n, 8, dtype=np.int8)
        self.statusword: npt.NDArray[np.uint16] = np.zeros(n, dtype=np.uint16)  # master inputs
        self.modes_display: npt.NDArray[np.int8] = np.zeros(n, dtype=np.int8)
        self.history: list[npt.NDArray[np.int8]] = []
        self.cw_history: list[npt.NDArray[np.uint16]] = []

    def cycle(self) -> None:
        """Outputs to every drive, one drive step (1 ms), inputs back."""
        self.cw_history.append(self.controlword.copy())
        for i, (d, od) in enumerate(zip(self.drives, self.ods, strict=True)):
            v = od.values
            v[(0x6040, 0)] = int(self.controlword[i])
            v[(0x6060, 0)] = int(self.modes_out[i])
            d.step(od, 1e-3)
            self.statusword[i] = v[(0x6041, 0)]
            self.modes_display[i] = v[(0x6061, 0)]
        self.history.append(np.array([d.state for d in self.drives], dtype=np.int8))

    def run(self, ctl: Cia402Controller, cycles: int, *, modes: bool = False) -> int:
        """Cycle until every axis reached its goal; returns the cycles used (or ``cycles``)."""
        for k in range(cycles):
            if modes:
                ctl.step(self.statusword, self.controlword, self.modes_display, self.modes_out)
            else:
                ctl.step(self.statusword, self.controlword)
            if ctl.all_reached:
                return k
            self.cycle()
        return cycles

    def reset_history(self) -> None:
        self.history = [np.array([d.state for d in self.drives], dtype=np.int8)]
        self.cw_history = []

    def axis_path(self, i: int) -> list[State402]:
        path: list[State402] = []
        for row in self.history:
            s = State402(int(row[i]))
            if not path or path[-1] is not s:
                path.append(s)
        return path


def test_enable_64_axes_from_switch_on_disabled() -> None:
    chain = Chain()
    chain.cycle()  # power on: NOT READY -> SWITCH ON DISABLED
    ctl = Cia402Controller(N)
    ctl.step(chain.statusword, chain.controlword)
    assert (ctl.state == S.SWITCH_ON_DISABLED).all()
    ctl.set_goal(Goal.ENABLE)
    used = chain.run(ctl, 50)
    assert ctl.all_reached, ctl.state
    assert used == 3, "one table step per cycle: shutdown, switch on, enable operation"
    assert all(d.state is S.OPERATION_ENABLED for d in chain.drives)
    for i in range(N):
        assert chain.axis_path(i) == [
            S.SWITCH_ON_DISABLED,
            S.READY_TO_SWITCH_ON,
            S.SWITCHED_ON,
            S.OPERATION_ENABLED,
        ]
    np.testing.assert_array_equal(ctl.transitions, 3)
    assert not ctl.any_stuck
    assert [int(c[0]) for c in chain.cw_history[-3:]] == [0x06, 0x07, 0x0F]


def test_enable_from_fault_with_a_reset_pulse_mixed_axes() -> None:
    chain = Chain()
    chain.cycle()
    faulted = np.arange(N) % 2 == 0
    for i in range(N):
        if faulted[i]:
            chain.drives[i].inject_fault(0x2310)
    chain.cycle()
    chain.cycle()
    ctl = Cia402Controller(N)
    ctl.step(chain.statusword, chain.controlword)
    assert (ctl.state[faulted] == S.FAULT).all() and (ctl.state[~faulted] == S.SWITCH_ON_DISABLED).all()
    ctl.set_goal(Goal.ENABLE)
    chain.reset_history()
    chain.run(ctl, 50)
    assert ctl.all_reached
    for i in range(N):
        path = chain.axis_path(i)
        tail = [S.SWITCH_ON_DISABLED, S.READY_TO_SWITCH_ON, S.SWITCHED_ON, S.OPERATION_ENABLED]
        assert path == ([S.FAULT, *tail] if faulted[i] else tail), (i, path)
    # the faulted axes saw bit 7 rise (0x80), then the sequence with bit 7 low
    words = [int(c[0]) for c in chain.cw_history]
    assert words[:4] == [0x80, 0x06, 0x07, 0x0F]
    assert all(int(chain.ods[i].values[(0x603F, 0)]) == 0 for i in range(N))


def test_enable_against_slow_drives() -> None:
    params = [DriveParams(transition_cycles=1 + i % 4, mode_switch_cycles=1 + i % 3) for i in range(N)]
    chain = Chain(params=params)
    ctl = Cia402Controller(N, timeout_cycles=10)
    ctl.set_goal(Goal.ENABLE)
    used = chain.run(ctl, 100, modes=True)
    assert ctl.all_reached and used > 3
    assert not ctl.any_stuck
    assert all(d.state is S.OPERATION_ENABLED for d in chain.drives)


def test_safe_stop_leaves_operation_enabled_within_one_drive_cycle() -> None:
    for word, expected in (
        (SafeStop.QUICK_STOP, S.QUICK_STOP_ACTIVE),
        (SafeStop.DISABLE_VOLTAGE, S.SWITCH_ON_DISABLED),
    ):
        chain = Chain()
        ctl = Cia402Controller(N, safe_stop_word=word)
        ctl.set_goal(Goal.ENABLE)
        chain.run(ctl, 20)
        assert ctl.all_reached
        chain.controlword |= 0x0100  # the halt bit belongs to the caller: kept
        ctl.safe_stop(chain.controlword)
        assert ((chain.controlword & 0x8F) == word).all()
        chain.cycle()
        assert all(d.state is expected for d in chain.drives), word
        ctl.step(chain.statusword, chain.controlword)
        assert not (ctl.state == S.OPERATION_ENABLED).any()
        assert ctl.all_reached  # the safe stop is the goal now
        assert ((chain.controlword & 0x0100) != 0).all()
        for _ in range(5):  # it stays stopped
            chain.cycle()
            ctl.step(chain.statusword, chain.controlword)
        assert not (ctl.state == S.OPERATION_ENABLED).any()


def test_quick_stop_goal_on_some_axes() -> None:
    chain = Chain()
    ctl = Cia402Controller(N)
    ctl.set_goal(Goal.ENABLE)
    chain.run(ctl, 20)
    ctl.set_goal(Goal.QUICK_STOP, np.s_[:8])
    ctl.step(chain.statusword, chain.controlword)
    chain.cycle()
    ctl.step(chain.statusword, chain.controlword)
    assert (ctl.state[:8] == S.QUICK_STOP_ACTIVE).all()
    assert (ctl.state[8:] == S.OPERATION_ENABLED).all()
    ctl.set_goal(Goal.ENABLE, np.s_[:8])  # back: via switch on disabled (transition 12), never 16
    chain.run(ctl, 20)
    assert ctl.all_reached
    assert {chain.drives[0].last_transition} == {4}


def test_mode_switch_waits_for_the_display() -> None:
    params = [DriveParams(mode_switch_cycles=5)] * N
    chain = Chain(params=params)
    ctl = Cia402Controller(N, mode=Mode.CSP)
    ctl.request_mode(Mode.CSV, np.s_[: N // 2])
    ctl.set_goal(Goal.ENABLE)
    ever_enabled_in_wrong_mode = False
    for _ in range(40):
        ctl.step(chain.statusword, chain.controlword, chain.modes_display, chain.modes_out)
        enabled = ctl.state == S.OPERATION_ENABLED
        ever_enabled_in_wrong_mode |= bool((enabled & (chain.modes_display != ctl.mode_request)).any())
        if ctl.all_reached:
            break
        chain.cycle()
    assert ctl.all_reached
    assert not ever_enabled_in_wrong_mode
    assert (chain.modes_out[: N // 2] == 9).all() and (chain.modes_out[N // 2 :] == 8).all()
    assert all(d.mode_display == (9 if i < N // 2 else 8) for i, d in enumerate(chain.drives))
    # switch the running axes to CST while enabled: reached only once the display follows
    ctl.request_mode(Mode.CST, np.s_[:4])
    ctl.step(chain.statusword, chain.controlword, chain.modes_display, chain.modes_out)
    assert not ctl.reached[:4].any() and ctl.reached[4:].all()
    cycles = chain.run(ctl, 20, modes=True)
    assert ctl.all_reached and cycles == 5
    assert (chain.modes_display[:4] == 10).all()


def test_stuck_axis_is_detected() -> None:
    chain = Chain()
    chain.cycle()
    chain.drives[5].inject_fault(0x7500, persistent=True)  # cannot be reset
    ctl = Cia402Controller(N, timeout_cycles=20)
    ctl.set_goal(Goal.ENABLE)
    chain.run(ctl, 100)
    assert not ctl.all_reached
    assert ctl.stuck[5] and ctl.stuck.sum() == 1
    assert ctl.state[5] == S.FAULT
    assert ctl.cycles[5] >= 20 and not ctl.reached[5]
    # the reset pulse came max_fault_resets times, then the axis gave up and stays in FAULT (S7)
    bits = [0] + [int(c[5]) & 0x80 for c in chain.cw_history]
    rising = sum(1 for a, b in itertools.pairwise(bits) if b and not a)
    assert rising == ctl.max_fault_resets == ctl.fault_resets[5] == 3
    assert ctl.gave_up[5] and ctl.gave_up.sum() == 1
    assert not any(int(c[5]) & 0x80 for c in chain.cw_history[-50:])
    chain.drives[5].clear_fault_cause()
    chain.run(ctl, 20)
    assert not ctl.reached[5] and ctl.state[5] == S.FAULT  # a give-up is lifted only on purpose
    ctl.reset_fault_budget(5)
    chain.run(ctl, 20)
    assert ctl.all_reached and not ctl.any_stuck


def test_a_silent_drive_is_stuck_too() -> None:
    ctl = Cia402Controller(4, timeout_cycles=5)
    ctl.set_goal(Goal.ENABLE)
    sw = np.full(4, 0x0250, dtype=np.uint16)  # frozen in switch on disabled
    cw = np.zeros(4, dtype=np.uint16)
    ctl.step(sw, cw)  # first sight of the axis (unknown -> SWITCH ON DISABLED) counts as progress
    for _ in range(5):
        ctl.step(sw, cw)
        assert not ctl.any_stuck
    ctl.step(sw, cw)  # the 6th cycle without a state change: more than timeout_cycles
    assert ctl.stuck.all() and (cw == 0x06).all()
    np.testing.assert_array_equal(ctl.since_progress, 6)


def test_fault_reset_pulse_width_is_configurable() -> None:
    ctl = Cia402Controller(1, fault_reset_cycles=3)
    ctl.set_goal(Goal.FAULT_RESET)
    sw = np.array([0x0218], dtype=np.uint16)
    cw = np.zeros(1, dtype=np.uint16)
    bits = []
    for _ in range(9):
        ctl.step(sw, cw)
        bits.append(int(cw[0]) >> 7 & 1)
    assert bits == [1, 1, 1, 0, 0, 0, 1, 1, 1]
    sw[0] = 0x0250
    ctl.step(sw, cw)
    assert cw[0] == 0x00 and ctl.reached[0]


def test_non_state_machine_bits_are_kept_and_unknown_words_hold() -> None:
    ctl = Cia402Controller(2)
    ctl.set_goal(Goal.ENABLE)
    cw = np.array([0x0170, 0x0000], dtype=np.uint16)  # halt + mode-specific bits 4-6 on axis 0
    sw = np.array([0x0233, 0x0233], dtype=np.uint16)  # switched on
    ctl.step(sw, cw)
    assert list(cw) == [0x017F, 0x000F]
    sw[:] = 0x0041  # garbage: matches no state
    ctl.step(sw, cw)
    assert list(cw) == [0x017F, 0x000F]
    assert (ctl.state == -1).all()


def test_disable_goal_does_not_reset_a_fault() -> None:
    ctl = Cia402Controller(1)
    sw = np.array([0x0218], dtype=np.uint16)
    cw = np.zeros(1, dtype=np.uint16)
    for _ in range(5):
        ctl.step(sw, cw)
        assert cw[0] == 0
    assert ctl.reached[0]


def test_zero_allocations_per_cycle() -> None:
    chain = Chain()
    ctl = Cia402Controller(N)
    ctl.set_goal(Goal.ENABLE)
    chain.run(ctl, 20, modes=True)
    sw, cw, md, mo = chain.statusword, chain.controlword, chain.modes_display, chain.modes_out
    # vary the inputs so every branch runs: half the axes toggle between FAULT and OPERATION ENABLED
    words = np.array([[0x1637] * N, [0x0218] * (N // 2) + [0x1637] * (N // 2)], dtype=np.uint16)
    k = [0]

    def one_cycle() -> None:
        np.copyto(sw, words[k[0] & 1])
        k[0] += 1
        ctl.step(sw, cw, md, mo)

    assert net_blocks(one_cycle, cycles=10_000) <= 0

    def no_modes() -> None:
        ctl.step(sw, cw)

    assert net_blocks(no_modes, cycles=10_000) <= 0


def test_bad_arguments() -> None:
    with pytest.raises(ValueError, match="n_axes"):
        Cia402Controller(0)
    with pytest.raises(ValueError, match="timeout_cycles"):
        Cia402Controller(2, timeout_cycles=0)


def test_docs_page_is_drawn_from_the_table() -> None:
    """The page's table and diagram are the generated ones; its code runs in tests/unit/test_docs.py."""
    text = (Path(__file__).resolve().parents[2] / "docs" / "cia402.md").read_text()
    assert transition_table_markdown() in text
    assert f"```mermaid\n{mermaid_diagram()}\n```" in text
