"""The controller's steady-cycle fast path writes what the full table step writes, cycle by cycle.

Two controllers see the same inputs: one with the fast path (the default), one with it off
(``fast_path = False``: every cycle runs the whole table step, as before the fast path). A
randomized drive model (the transitions of :data:`TRANSITIONS`, taken late or not at all, faults,
automatic exits, statuswords no state matches, extra statusword bits, mode displays that lag)
closes the loop on the fast one; random events hit both alike: goals and mode requests changed
(through the methods and in place), ``hold_reset``, a safe stop, a budget reset, the caller
rewriting controlword and mode bits, and the DDS server's way of holding a stopped group (it
decodes into ``ctrl.state`` and does not step). Every cycle compares every word written and every
per-axis result. The oracle is our own full path, which tests/unit/test_cia402.py judges against
emulated drives; nothing outside this project says what the words should be.

Then the cost, counted rather than timed: the C calls (numpy) one steady step makes.
"""

from __future__ import annotations

import random
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt
import pytest

from fieldbus.core import cia402
from fieldbus.core.cia402 import (
    CONTROLLER_PULSE,
    CONTROLLER_REACHED,
    FAULT_RESET_BIT,
    STATUSWORD_LUT,
    STATUSWORD_STATE_BITS,
    UNKNOWN_STATE,
    Cia402Controller,
    Goal,
    Mode,
    State402,
    Trigger,
    command_of,
    decode_states,
    transition,
)

S = State402
UNKNOWN_WORDS = [int(w) for w in np.flatnonzero(STATUSWORD_LUT == UNKNOWN_STATE)[:64]]
EXTRA_BITS = (0x0000, 0x0010, 0x0200, 0x0210, 0x0400, 0x1600, 0x3600, 0x0080)

RESULTS = (
    "state",
    "reached",
    "stuck",
    "transitions",
    "cycles",
    "since_progress",
    "mode_ok",
    "fault_resets",
    "gave_up",
    "seeded",
    "_prev_state",
    "_last_sm",
    "_phase",
    "_held",
    "_switching",
    "_window_start",
    "_window_count",
)


class _Direction:
    """One direction of an image: named (N,) arrays."""

    def __init__(self, **arrays: npt.NDArray[Any]) -> None:
        self._arrays = arrays

    @property
    def names(self) -> tuple[str, ...]:
        return tuple(self._arrays)

    def __getitem__(self, name: str) -> npt.NDArray[Any]:
        return self._arrays[name]


class _Image:
    def __init__(self, n: int) -> None:
        self.outputs = _Direction(
            controlword=np.zeros(n, np.uint16),
            modes_of_operation=np.zeros(n, np.int8),
            target_position=np.zeros(n),
            target_velocity=np.zeros(n),
        )
        self.inputs = _Direction(
            statusword=np.zeros(n, np.uint16),
            modes_of_operation_display=np.zeros(n, np.int8),
            position_actual_value=np.zeros(n),
        )


class _Drives:
    """Drives that follow the controlword through the transition table, late and unreliably."""

    def __init__(self, n: int, rng: random.Random) -> None:
        self.rng = rng
        self.state = [S.SWITCH_ON_DISABLED] * n
        self.extra = [0x0200] * n
        self.bit7 = [False] * n
        self.unknown = [0] * n  # cycles left of a statusword no state matches
        self.display = [int(Mode.CSP)] * n
        self.position = [0.0] * n

    def step(self, cw: npt.NDArray[Any], modes: npt.NDArray[Any], sw: npt.NDArray[Any], md: Any) -> None:
        r = self.rng
        for i, s in enumerate(self.state):
            word = int(cw[i])
            edge = bool(word & FAULT_RESET_BIT) and not self.bit7[i]
            self.bit7[i] = bool(word & FAULT_RESET_BIT)
            if s not in (S.FAULT_REACTION_ACTIVE, S.FAULT) and r.random() < 0.004:
                s = S.FAULT_REACTION_ACTIVE
            elif s in (S.NOT_READY_TO_SWITCH_ON, S.FAULT_REACTION_ACTIVE) and r.random() < 0.5:
                s = transition(s, Trigger.AUTO).target  # type: ignore[union-attr]
            elif s is S.FAULT:
                if edge and r.random() < 0.7:  # some faults outlive a reset
                    s = S.SWITCH_ON_DISABLED
            elif s is S.QUICK_STOP_ACTIVE and r.random() < 0.2:
                s = S.SWITCH_ON_DISABLED  # quick stop done
            else:
                t = transition(s, command_of(word))
                if t is not None and not t.condition and r.random() < 0.8:
                    s = t.target
            if r.random() < 0.002:
                s = S.NOT_READY_TO_SWITCH_ON  # power cycle
            self.state[i] = s
            if r.random() < 0.01:
                self.extra[i] = r.choice(EXTRA_BITS)
            if r.random() < 0.003:
                self.unknown[i] = r.randint(1, 4)
            self.unknown[i] = max(0, self.unknown[i] - 1)
            sw[i] = r.choice(UNKNOWN_WORDS) if self.unknown[i] else STATUSWORD_STATE_BITS[s] | self.extra[i]
            if md is not None and r.random() < 0.4:
                self.display[i] = int(modes[i])
            if s is S.OPERATION_ENABLED:
                self.position[i] += 0.001
        if md is not None:
            md[:] = self.display


def _same(fast: Cia402Controller, full: Cia402Controller, k: int) -> None:
    assert fast._cycle == full._cycle, k
    for name in RESULTS:
        a, b = getattr(fast, name), getattr(full, name)
        assert np.array_equal(a, b), f"cycle {k}: {name} {a} (fast) != {b} (full)"


def _run(seed: int, how: str, n: int = 3, cycles: int = 2500) -> int:
    """One randomized run; returns the cycles the fast controller took its fast path."""
    rng = random.Random(seed)
    kw: dict[str, Any] = dict(timeout_cycles=rng.choice((5, 40)), fault_reset_cycles=rng.choice((1, 2)))
    kw.update(max_fault_resets=2, fault_reset_window_cycles=300, max_reset_hold_cycles=6)
    fast, full = Cia402Controller(n, **kw), Cia402Controller(n, **kw)
    full.fast_path = False
    imgs = (_Image(n), _Image(n))
    drives = _Drives(n, rng)
    for c in (fast, full):
        c.set_goal(Goal.ENABLE)
    hold = np.zeros(n, dtype=bool)
    scratch = np.zeros(n, dtype=np.intp)
    stopped = direct = 0
    fast_cycles = 0
    use_modes = how != "no modes"
    for k in range(cycles):
        # the inputs, the same for both (the drives answer the fast controller's last words)
        fo, fi = imgs[0].outputs, imgs[0].inputs
        drives.step(
            fo["controlword"],
            fo["modes_of_operation"],
            fi["statusword"],
            fi["modes_of_operation_display"] if use_modes else None,
        )
        for name in ("statusword", "modes_of_operation_display", "position_actual_value"):
            imgs[1].inputs[name][:] = fi[name]
        fi["position_actual_value"][:] = drives.position
        imgs[1].inputs["position_actual_value"][:] = drives.position
        # events, applied to both alike
        e = rng.random()
        axes: Any = rng.choice((slice(None), rng.randrange(n)))
        goal = rng.choice(list(Goal)) if k % 3 else Goal.ENABLE
        timeout, mode = rng.choice((-1, 3, 40)), rng.choice((Mode.CSP, Mode.CSV))
        code = rng.choice([*State402, UNKNOWN_STATE])
        for c, img in zip((fast, full), imgs, strict=True):
            out = img.outputs
            if e < 0.012:
                c.set_goal(goal, axes)
            elif e < 0.016:
                c.request_mode(Mode.CSV if c.mode_request[0] == Mode.CSP else Mode.CSP, axes)
            elif e < 0.018:
                c.reset_fault_budget(axes)
            elif e < 0.019:
                c.safe_stop(out["controlword"])
            elif e < 0.022:
                c.goal[axes] = goal  # in place, no restart
            elif e < 0.024:
                c.set_goal(Goal(int(c.goal[0])))  # the same goal again: counters restart
            elif e < 0.026:
                c.timeout_cycles = timeout  # -1: stuck at once, even at the goal
            elif e < 0.028:
                c.mode_request[axes] = mode  # in place, no restart
            elif e < 0.031:
                c.state[axes] = code  # someone wrote the state array (the server decodes into it)
        r2 = rng.random()
        for img in imgs:
            out = img.outputs
            if r2 < 0.03:
                out["controlword"][axes] ^= 0x0110  # the caller's bits 4 and 8
            elif r2 < 0.04:
                out["controlword"][axes] = 0xFFFF  # someone else wrote all of it (a safe-stop writer)
            elif r2 < 0.05:
                out["modes_of_operation"][axes] = 3
            elif r2 < 0.06:
                out["target_position"][axes] += 1.0  # the user's command
        if rng.random() < 0.05:
            hold[:] = [rng.random() < 0.5 for _ in range(n)]
        if direct == 0 and rng.random() < 0.01:  # a stretch of steps beside step_image
            direct = rng.randint(1, 40)
        if stopped == 0 and rng.random() < 0.005:
            stopped = rng.randint(1, 30)
        # the cycle
        for c, img in zip((fast, full), imgs, strict=True):
            out, inp = img.outputs, img.inputs
            if stopped:  # the DDS server's stopped group: the state is decoded, the controller not stepped
                decode_states(inp["statusword"], c.state, scratch)
            elif how == "image" and not direct:
                c.step_image(img, hold)
            elif how in ("modes", "image"):  # "image": now and then a step beside step_image
                c.step(
                    inp["statusword"],
                    out["controlword"],
                    inp["modes_of_operation_display"],
                    out["modes_of_operation"],
                    hold,
                )
            else:
                c.step(inp["statusword"], out["controlword"], hold_reset=hold)
        if not stopped:
            fast_cycles += fast._fast
        stopped, direct = max(0, stopped - 1), max(0, direct - 1)
        _same(fast, full, k)
        for name in ("controlword", "modes_of_operation", "target_position", "target_velocity"):
            a, b = imgs[0].outputs[name], imgs[1].outputs[name]
            assert np.array_equal(a, b), f"cycle {k}: {name} {a} (fast) != {b} (full)"
    return fast_cycles


@pytest.mark.parametrize("how", ["image", "modes", "no modes"])
@pytest.mark.parametrize("seed", range(6))
def test_the_fast_path_writes_what_the_full_step_writes_cycle_by_cycle(how: str, seed: int) -> None:
    fast = _run(seed, how)
    assert fast > 500  # the run took the fast path often (steady stretches), not only the full step


def test_a_reached_cell_never_pulses() -> None:
    """The fast path leans on it: every axis at its goal means no fault reset is under way."""
    assert not (CONTROLLER_REACHED & CONTROLLER_PULSE).any()


# -------------------------------------------------------------- what a steady step costs


class _CountingNumpy:
    """numpy for the controller's module, counting the calls of its functions and ufuncs (the cost of
    a cycle on a few axes: about a microsecond each, whatever they compute)."""

    def __init__(self) -> None:
        self.calls = 0

    def __getattr__(self, name: str) -> Any:
        attr = getattr(np, name)
        if not callable(attr) or isinstance(attr, type):
            return attr

        def counted(*a: Any, **k: Any) -> Any:
            self.calls += 1
            return attr(*a, **k)

        return counted


@pytest.fixture
def numpy_calls(monkeypatch: pytest.MonkeyPatch) -> _CountingNumpy:
    counting = _CountingNumpy()
    monkeypatch.setattr(cia402, "np", counting)
    return counting


def _per_call(counting: _CountingNumpy, fn: Any, cycles: int) -> float:
    """numpy calls the controller makes per call of ``fn``, over ``cycles`` calls."""
    counting.calls = 0
    for _ in range(cycles):
        fn()
    return counting.calls / cycles


@pytest.mark.parametrize("n", [3, 12])
def test_a_steady_step_makes_a_handful_of_numpy_calls(n: int, numpy_calls: _CountingNumpy) -> None:
    ctrl = Cia402Controller(n)
    ctrl.set_goal(Goal.ENABLE)
    sw = np.full(n, STATUSWORD_STATE_BITS[S.OPERATION_ENABLED] | 0x1600, dtype=np.uint16)
    cw, md, mo = np.zeros(n, np.uint16), np.full(n, int(Mode.CSP), np.int8), np.zeros(n, np.int8)
    for _ in range(3):
        ctrl.step(sw, cw, md, mo)
    assert ctrl.all_reached
    assert _per_call(numpy_calls, lambda: ctrl.step(sw, cw, md, mo), 50) == 0  # before: 40
    cw |= 0x0100  # the caller's halt bit: the state-machine bits are written again, the halt kept
    assert _per_call(numpy_calls, lambda: ctrl.step(sw, cw, md, mo), 1) == 2
    assert int(cw[0]) == 0x010F
    ctrl.fast_path = False
    assert _per_call(numpy_calls, lambda: ctrl.step(sw, cw, md, mo), 50) >= 20  # the full step, for scale
    assert int(cw[0]) & 0x8F == 0x0F


@pytest.fixture
def sim_op(tmp_path: Path) -> Iterator[Any]:
    pytest.importorskip("pysoem")
    from fieldbus.commands.demo import DEMO_MAP
    from fieldbus.network import open_network
    from fieldbus.testing import VirtualClock

    f = tmp_path / "net.yaml"
    f.write_text(
        "cycle_time_us: 1000\nreceive_timeout_us: 1000\nbuses:\n"
        f"  - {{name: bus, type: ethercat, interface: none0, slaves: [{{name: 'j{{i}}', map: '{DEMO_MAP}', "
        "count: 3}]}\n"
    )
    with open_network(f, backend="sim", clock=VirtualClock()) as network:
        yield network.bring_up()


def test_steady_cycles_on_a_sim_network_skip_the_table_step(sim_op: Any, numpy_calls: _CountingNumpy) -> None:
    """Three demo joints enabled on the sim backend: once they hold OPERATION ENABLED, a cycle's
    step_image makes no numpy call and the targets stay the caller's."""
    op = sim_op
    img = op["bus"]
    ctrl = Cia402Controller(3)
    ctrl.set_goal(Goal.ENABLE)
    for _ in range(100):
        ctrl.step_image(img)
        op.exchange()
    assert ctrl.all_reached and (ctrl.state == S.OPERATION_ENABLED).all()
    target = img.outputs["target_position"]
    moved = target + 0.01

    def cycle() -> None:
        ctrl.step_image(img)
        target[:] = moved  # the caller's command, written after step_image as a loop does
        assert op.exchange().fresh

    steps = [0]
    real = ctrl._fault_reset_pulse

    def counted(*a: Any) -> None:
        steps[0] += 1
        real(*a)

    ctrl._fault_reset_pulse = counted  # type: ignore[method-assign]
    for _ in range(50):
        cycle()
    assert steps[0] == 0  # before: the full table step every cycle (50)
    assert not ctrl.seeded.any() and np.array_equal(target, moved)
    assert _per_call(numpy_calls, cycle, 20) == 0  # before: 49
    assert int(img.outputs["controlword"][0]) & 0x8F == 0x0F
