"""CiA 402 (IEC 61800-7-201) drive state machine as tables, and a vectorised master controller.

One module, one table. :data:`TRANSITIONS` (transitions 0-16 with their
numbers) is the only statement of the state machine; the master side
(:class:`Cia402Controller`, through the planner tables built from it at import)
and the emulated drive (``sim_slaves.drive402``) both read it.

Directions, from the master's side: the **controlword** (0x6040) is a master
*output* written to the drive (RxPDO in the drive's terms); the **statusword**
(0x6041) and **modes_of_operation_display** (0x6061) are master *inputs* read
from the drive (TxPDO). **modes_of_operation** (0x6060) is an output.

Pure: no clock, no I/O. Time is counted in cycles (calls of
:meth:`Cia402Controller.step`). The per-cycle path allocates nothing that
outlives the call: every array is preallocated and ufuncs write with ``out=``
(a steady cycle compares byte copies of a few arrays: short-lived ``bytes``,
which the garbage collector does not track).
"""

from __future__ import annotations

from collections import deque
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from enum import IntEnum
from types import MappingProxyType
from typing import Any, Protocol

import numpy as np
import numpy.typing as npt

from fieldbus.core.acyclic_modes import AcyclicModes
from fieldbus.core.pdo.model import DriveMap
from fieldbus.errors import ChannelNameError

# --------------------------------------------------------------------------- states


class State402(IntEnum):
    """The eight states of the CiA 402 power drive system (PDS) state machine."""

    NOT_READY_TO_SWITCH_ON = 0
    SWITCH_ON_DISABLED = 1
    READY_TO_SWITCH_ON = 2
    SWITCHED_ON = 3
    OPERATION_ENABLED = 4
    QUICK_STOP_ACTIVE = 5
    FAULT_REACTION_ACTIVE = 6
    FAULT = 7


UNKNOWN_STATE = -1
"""Code :func:`decode_states` writes for a statusword that matches no state pattern."""


@dataclass(frozen=True)
class StatusPattern:
    """``statusword & mask == value`` identifies ``state`` (statusword = master input)."""

    state: State402
    mask: int
    value: int


# IEC 61800-7-201 / CiA 402 statusword coding (bits 0-3 ready/switched on/op enabled/fault,
# bit 5 quick stop (active low), bit 6 switch on disabled):
STATUSWORD_PATTERNS: tuple[StatusPattern, ...] = (
    StatusPattern(State402.NOT_READY_TO_SWITCH_ON, 0x004F, 0x0000),  # xxxx xxxx x0xx 0000
    StatusPattern(State402.SWITCH_ON_DISABLED, 0x004F, 0x0040),  # xxxx xxxx x1xx 0000
    StatusPattern(State402.READY_TO_SWITCH_ON, 0x006F, 0x0021),  # xxxx xxxx x01x 0001
    StatusPattern(State402.SWITCHED_ON, 0x006F, 0x0023),  # xxxx xxxx x01x 0011
    StatusPattern(State402.OPERATION_ENABLED, 0x006F, 0x0027),  # xxxx xxxx x01x 0111
    StatusPattern(State402.QUICK_STOP_ACTIVE, 0x006F, 0x0007),  # xxxx xxxx x00x 0111
    StatusPattern(State402.FAULT_REACTION_ACTIVE, 0x004F, 0x000F),  # xxxx xxxx x0xx 1111
    StatusPattern(State402.FAULT, 0x004F, 0x0008),  # xxxx xxxx x0xx 1000
)

STATUSWORD_STATE_BITS: Mapping[State402, int] = MappingProxyType(
    {p.state: p.value for p in STATUSWORD_PATTERNS}
)
"""Canonical state bits a drive reports in its statusword for each state."""


class StatusBit(IntEnum):
    """Statusword (0x6041, master input) bit masks other than the state bits."""

    VOLTAGE_ENABLED = 1 << 4
    QUICK_STOP = 1 << 5  # active low: 0 = quick stop active
    WARNING = 1 << 7
    REMOTE = 1 << 9  # controlword is processed (drive under fieldbus control)
    TARGET_REACHED = 1 << 10
    INTERNAL_LIMIT_ACTIVE = 1 << 11
    FOLLOWS_TARGET = 1 << 12  # CSP/CSV/CST: drive follows the cyclic target value
    FOLLOWING_ERROR = 1 << 13  # CSP: following error window exceeded


def _build_statusword_lut() -> npt.NDArray[np.int8]:
    lut = np.full(65536, UNKNOWN_STATE, dtype=np.int8)
    words = np.arange(65536, dtype=np.uint32)
    for p in STATUSWORD_PATTERNS:
        hit = (words & p.mask) == p.value
        if np.any(lut[hit] != UNKNOWN_STATE):
            raise AssertionError(f"statusword patterns overlap at {p.state.name}")
        lut[hit] = p.state
    lut.flags.writeable = False
    return lut


STATUSWORD_LUT: npt.NDArray[np.int8] = _build_statusword_lut()
"""65536-entry table: statusword (uint16) -> :class:`State402` code, or :data:`UNKNOWN_STATE`."""


def decode_state(statusword: int) -> State402 | None:
    """State of one statusword (master input), or ``None`` when it matches no pattern."""
    code = int(STATUSWORD_LUT[statusword & 0xFFFF])
    return None if code == UNKNOWN_STATE else State402(code)


def decode_states(
    statusword: npt.NDArray[Any], out: npt.NDArray[np.int8], scratch: npt.NDArray[np.intp] | None = None
) -> None:
    """Decode statuswords (uint16 master inputs, one per axis) into ``out`` (int8 state codes).

    Unknown bit patterns give :data:`UNKNOWN_STATE`. ``scratch`` (an ``intp`` array
    of the same length) makes the call allocation-free; without it numpy casts
    the indices into a temporary.
    """
    if scratch is None:
        np.take(STATUSWORD_LUT, statusword, out=out, mode="clip")
    else:
        np.copyto(scratch, statusword, casting="unsafe")
        np.take(STATUSWORD_LUT, scratch, out=out, mode="clip")


# --------------------------------------------------------------------------- controlword


class Trigger(IntEnum):
    """What moves the state machine: a controlword command (0-5) or a drive-internal event (6-8)."""

    DISABLE_VOLTAGE = 0
    QUICK_STOP = 1
    SHUTDOWN = 2
    SWITCH_ON = 3
    DISABLE_OPERATION = 3  # alias: same controlword bits as SWITCH_ON (0x07)
    ENABLE_OPERATION = 4
    FAULT_RESET = 5  # rising edge of controlword bit 7
    POWER_ON = 6  # drive-internal: power applied
    AUTO = 7  # drive-internal: self-test done / fault reaction done / quick stop done
    FAULT = 8  # drive-internal: a fault occurred


MASTER_COMMANDS: frozenset[Trigger] = frozenset(
    {
        Trigger.DISABLE_VOLTAGE,
        Trigger.QUICK_STOP,
        Trigger.SHUTDOWN,
        Trigger.SWITCH_ON,
        Trigger.ENABLE_OPERATION,
        Trigger.FAULT_RESET,
    }
)

CONTROLWORD: Mapping[Trigger, int] = MappingProxyType(
    {
        Trigger.SHUTDOWN: 0x0006,
        Trigger.SWITCH_ON: 0x0007,  # also "disable operation"
        Trigger.ENABLE_OPERATION: 0x000F,
        Trigger.DISABLE_VOLTAGE: 0x0000,
        Trigger.QUICK_STOP: 0x0002,
        Trigger.FAULT_RESET: 0x0080,  # acts on the 0 -> 1 edge of bit 7
    }
)
"""Controlword (0x6040, master output) bits 0-3 and 7 for each command."""

CONTROLWORD_STATE_BITS = 0x008F
"""Controlword bits owned by the state machine (0-3, 7); bits 4-6, 8 (halt) and up are mode-specific."""

FAULT_RESET_BIT = 0x0080


@dataclass(frozen=True)
class CommandPattern:
    """``controlword & mask == value`` is ``command`` (bit 7 is read only for its rising edge)."""

    command: Trigger
    mask: int
    value: int


# IEC 61800-7-201 command coding of bits 0-3 (bit 7 = 0 in the standard; a drive here
# ignores a held bit 7 and reacts only to its rising edge, as FAULT_RESET).
COMMAND_PATTERNS: tuple[CommandPattern, ...] = (
    CommandPattern(Trigger.DISABLE_VOLTAGE, 0x0002, 0x0000),  # xxxx xx0x
    CommandPattern(Trigger.QUICK_STOP, 0x0006, 0x0002),  # xxxx x01x
    CommandPattern(Trigger.SHUTDOWN, 0x0007, 0x0006),  # xxxx x110
    CommandPattern(Trigger.SWITCH_ON, 0x000F, 0x0007),  # xxxx 0111 (= disable operation)
    CommandPattern(Trigger.ENABLE_OPERATION, 0x000F, 0x000F),  # xxxx 1111
)


def _build_nibble_commands() -> tuple[Trigger, ...]:
    out: list[Trigger] = []
    for nibble in range(16):
        hits = [p.command for p in COMMAND_PATTERNS if nibble & p.mask == p.value]
        if len(hits) != 1:
            raise AssertionError(f"controlword nibble {nibble:#x} decodes to {hits}")
        out.append(hits[0])
    return tuple(out)


COMMAND_BY_NIBBLE: tuple[Trigger, ...] = _build_nibble_commands()
"""Controlword bits 0-3 (0..15) -> the command they encode."""


def command_of(controlword: int) -> Trigger:
    """The command in a controlword (master output); fault reset is an edge, see :data:`FAULT_RESET_BIT`."""
    return COMMAND_BY_NIBBLE[controlword & 0x000F]


# --------------------------------------------------------------------------- transitions


@dataclass(frozen=True)
class Transition:
    """One arrow of the CiA 402 state diagram.

    ``source`` is ``None`` only for transition 0 (power on). ``condition`` names a
    drive-side guard; the controller never plans through a guarded transition.
    """

    number: int
    source: State402 | None
    trigger: Trigger
    target: State402
    condition: str = ""

    @property
    def trigger_name(self) -> str:
        """The trigger's name as the standard calls it here (transition 5 is "disable operation")."""
        return "DISABLE_OPERATION" if self.number == 5 else self.trigger.name


_S = State402
_T = Trigger

TRANSITIONS: tuple[Transition, ...] = (
    Transition(0, None, _T.POWER_ON, _S.NOT_READY_TO_SWITCH_ON),
    Transition(1, _S.NOT_READY_TO_SWITCH_ON, _T.AUTO, _S.SWITCH_ON_DISABLED),
    Transition(2, _S.SWITCH_ON_DISABLED, _T.SHUTDOWN, _S.READY_TO_SWITCH_ON),
    Transition(3, _S.READY_TO_SWITCH_ON, _T.SWITCH_ON, _S.SWITCHED_ON),
    # "switch on + enable operation" (0x0F) performs 3, then 4 on a following cycle
    Transition(3, _S.READY_TO_SWITCH_ON, _T.ENABLE_OPERATION, _S.SWITCHED_ON),
    Transition(4, _S.SWITCHED_ON, _T.ENABLE_OPERATION, _S.OPERATION_ENABLED),
    Transition(5, _S.OPERATION_ENABLED, _T.DISABLE_OPERATION, _S.SWITCHED_ON),
    Transition(6, _S.SWITCHED_ON, _T.SHUTDOWN, _S.READY_TO_SWITCH_ON),
    Transition(7, _S.READY_TO_SWITCH_ON, _T.DISABLE_VOLTAGE, _S.SWITCH_ON_DISABLED),
    Transition(7, _S.READY_TO_SWITCH_ON, _T.QUICK_STOP, _S.SWITCH_ON_DISABLED),
    Transition(8, _S.OPERATION_ENABLED, _T.SHUTDOWN, _S.READY_TO_SWITCH_ON),
    Transition(9, _S.OPERATION_ENABLED, _T.DISABLE_VOLTAGE, _S.SWITCH_ON_DISABLED),
    Transition(10, _S.SWITCHED_ON, _T.DISABLE_VOLTAGE, _S.SWITCH_ON_DISABLED),
    Transition(10, _S.SWITCHED_ON, _T.QUICK_STOP, _S.SWITCH_ON_DISABLED),
    Transition(11, _S.OPERATION_ENABLED, _T.QUICK_STOP, _S.QUICK_STOP_ACTIVE),
    Transition(12, _S.QUICK_STOP_ACTIVE, _T.DISABLE_VOLTAGE, _S.SWITCH_ON_DISABLED),
    Transition(12, _S.QUICK_STOP_ACTIVE, _T.AUTO, _S.SWITCH_ON_DISABLED, "quick stop done, option code 0-4"),
    *(
        Transition(13, s, _T.FAULT, _S.FAULT_REACTION_ACTIVE)
        for s in State402
        if s not in (_S.FAULT_REACTION_ACTIVE, _S.FAULT)
    ),
    Transition(14, _S.FAULT_REACTION_ACTIVE, _T.AUTO, _S.FAULT),
    Transition(15, _S.FAULT, _T.FAULT_RESET, _S.SWITCH_ON_DISABLED),
    Transition(
        16, _S.QUICK_STOP_ACTIVE, _T.ENABLE_OPERATION, _S.OPERATION_ENABLED, "quick stop option code 5-8"
    ),
)
"""The CiA 402 state machine: every transition 0-16, one row per (source, trigger)."""


def _index_transitions() -> Mapping[tuple[State402, Trigger], Transition]:
    index: dict[tuple[State402, Trigger], Transition] = {}
    for t in TRANSITIONS:
        if t.source is None:
            continue
        key = (t.source, t.trigger)
        if key in index:
            raise AssertionError(f"two transitions for {key}")
        index[key] = t
    return MappingProxyType(index)


TRANSITION_INDEX: Mapping[tuple[State402, Trigger], Transition] = _index_transitions()
"""``(source, trigger) -> Transition`` (transition 0 has no source and is not indexed)."""


def transition(state: State402, trigger: Trigger) -> Transition | None:
    """The transition ``trigger`` causes in ``state``, or ``None`` (the trigger is ignored there)."""
    return TRANSITION_INDEX.get((state, trigger))


def next_command(state: State402, goal: State402, *, allow_fault_reset: bool = True) -> Trigger | None:
    """First master command on a shortest path from ``state`` to ``goal`` through :data:`TRANSITIONS`.

    Only unguarded transitions triggered by master commands are used; ``None``
    when ``state == goal`` or no such path exists (e.g. from states that only
    leave automatically). Ties are broken by :class:`Trigger` order.
    """
    if state == goal:
        return None
    edges: dict[State402, list[Transition]] = {s: [] for s in State402}
    for t in TRANSITIONS:
        if t.source is None or t.condition or t.trigger not in MASTER_COMMANDS:
            continue
        if t.trigger is Trigger.FAULT_RESET and not allow_fault_reset:
            continue
        edges[t.source].append(t)
    for lst in edges.values():
        lst.sort(key=lambda t: (int(t.trigger), t.number))
    first: dict[State402, Trigger] = {}
    seen = {state}
    queue: deque[State402] = deque([state])
    while queue:
        s = queue.popleft()
        for t in edges[s]:
            if t.target in seen:
                continue
            seen.add(t.target)
            first[t.target] = first.get(s, t.trigger)
            if t.target == goal:
                return first[t.target]
            queue.append(t.target)
    return None


def mermaid_diagram() -> str:
    """The state diagram as a mermaid ``stateDiagram-v2``, drawn from :data:`TRANSITIONS`."""
    lines = ["stateDiagram-v2"]
    for t in TRANSITIONS:
        src = "[*]" if t.source is None else t.source.name
        label = f"{t.number}: {t.trigger_name}"
        if t.trigger in CONTROLWORD:
            label += f" ({CONTROLWORD[t.trigger]:#06x})"
        if t.condition:
            label += f" [{t.condition}]"
        lines.append(f"    {src} --> {t.target.name}: {label}")
    return "\n".join(lines)


def transition_table_markdown() -> str:
    """:data:`TRANSITIONS` as a markdown table (for docs/cia402.md)."""
    rows = [
        "| # | from | trigger | controlword (bits 0-3, 7) | to | condition |",
        "|---|------|---------|---------------------------|----|-----------|",
    ]
    for t in TRANSITIONS:
        if t.trigger is Trigger.FAULT_RESET:
            word = f"`{FAULT_RESET_BIT:#06x}` rising edge"
        elif t.trigger in CONTROLWORD:
            word = f"`{CONTROLWORD[t.trigger]:#06x}`"
        else:
            word = "internal fault" if t.trigger is Trigger.FAULT else "automatic"
        src = "power on" if t.source is None else t.source.name
        rows.append(f"| {t.number} | {src} | {t.trigger_name} | {word} | {t.target.name} | {t.condition} |")
    return "\n".join(rows)


# --------------------------------------------------------------------------- modes


class Mode(IntEnum):
    """modes_of_operation (0x6060, master output) / display (0x6061, master input) values."""

    NO_MODE = 0
    PROFILE_POSITION = 1
    PROFILE_VELOCITY = 3
    PROFILE_TORQUE = 4
    HOMING = 6
    INTERPOLATED_POSITION = 7
    CSP = 8  # cyclic synchronous position
    CSV = 9  # cyclic synchronous velocity
    CST = 10  # cyclic synchronous torque


# --------------------------------------------------------------------------- controller


class Goal(IntEnum):
    """What the master wants of an axis; :class:`Cia402Controller` walks the table toward it."""

    DISABLE = 0  # SWITCH_ON_DISABLED by disable voltage; a fault is left latched
    ENABLE = 1  # OPERATION_ENABLED in the requested mode (resets a fault on the way)
    QUICK_STOP = 2  # quick stop command; reached in QUICK_STOP_ACTIVE, SWITCH_ON_DISABLED or FAULT
    FAULT_RESET = 3  # reset a fault, then rest in SWITCH_ON_DISABLED


class SafeStop(IntEnum):
    """Controlword command of a safe stop (master output): the network's safe stop and close use it."""

    QUICK_STOP = 0x0002
    DISABLE_VOLTAGE = 0x0000


_KEEP_BITS = np.uint16(0xFFFF & ~CONTROLWORD_STATE_BITS)
_SAFE_WORDS = {w: np.uint16(w) for w in SafeStop}


def write_command_word(controlword_out: npt.NDArray[np.uint16], word: SafeStop) -> None:
    """Write a safe-stop command into the state-machine bits (0-3, 7) of every controlword, in place.

    The other bits (mode specific, halt, manufacturer) are kept. This is the one
    implementation of the safe stop's controlword: the network writes it every
    cycle while a safe stop is latched, and :meth:`Cia402Controller.safe_stop` uses it.
    """
    np.bitwise_and(controlword_out, _KEEP_BITS, out=controlword_out)
    np.bitwise_or(controlword_out, _SAFE_WORDS[word], out=controlword_out)


_HOLD = 0xFFFF  # table marker: keep the last state-machine bits (unknown statusword)
_N_ROWS = len(State402) + 1  # last row: UNKNOWN_STATE (index -1 wraps onto it)
_N_GOALS = len(Goal)

_GOAL_TARGET: Mapping[Goal, State402] = MappingProxyType(
    {
        Goal.DISABLE: State402.SWITCH_ON_DISABLED,
        Goal.ENABLE: State402.OPERATION_ENABLED,
        Goal.FAULT_RESET: State402.SWITCH_ON_DISABLED,
    }
)
_QUICK_STOP_REACHED = (State402.QUICK_STOP_ACTIVE, State402.SWITCH_ON_DISABLED, State402.FAULT)


def _build_controller_tables() -> tuple[npt.NDArray[np.uint16], npt.NDArray[np.bool_], npt.NDArray[np.bool_]]:
    """Per (state row, goal): the state-machine controlword bits, whether the goal is reached,
    and whether the cell is a fault-reset pulse. Derived from :data:`TRANSITIONS` by :func:`next_command`.
    """
    cw = np.zeros((_N_ROWS, _N_GOALS), dtype=np.uint16)
    reached = np.zeros((_N_ROWS, _N_GOALS), dtype=bool)
    pulse = np.zeros((_N_ROWS, _N_GOALS), dtype=bool)
    for goal in Goal:
        for s in State402:
            if goal is Goal.QUICK_STOP:
                cw[s, goal] = CONTROLWORD[Trigger.QUICK_STOP]
                reached[s, goal] = s in _QUICK_STOP_REACHED
                continue
            target = _GOAL_TARGET[goal]
            reset_allowed = goal is not Goal.DISABLE
            cmd = next_command(s, target, allow_fault_reset=reset_allowed)
            if s == target:  # hold the goal: the command that leads into it
                cmd = Trigger.ENABLE_OPERATION if goal is Goal.ENABLE else Trigger.DISABLE_VOLTAGE
                reached[s, goal] = True
            elif goal is Goal.DISABLE and s is State402.FAULT:
                reached[s, goal] = True  # power is off; the fault stays latched
            if cmd is Trigger.FAULT_RESET:
                pulse[s, goal] = True
                cw[s, goal] = 0  # bit 7 is added by the pulse generator
            elif cmd is None:  # only automatic exits (NOT_READY, FAULT_REACTION): wait neutrally
                cw[s, goal] = CONTROLWORD[Trigger.DISABLE_VOLTAGE]
            else:
                cw[s, goal] = CONTROLWORD[cmd]
    cw[_N_ROWS - 1, :] = _HOLD
    for a in (cw, reached, pulse):
        a.flags.writeable = False
    return cw, reached, pulse


CONTROLLER_CW, CONTROLLER_REACHED, CONTROLLER_PULSE = _build_controller_tables()
"""Controller tables, shape ``(len(State402) + 1, len(Goal))``; the last row is UNKNOWN_STATE."""

_CW_FLAT = CONTROLLER_CW.reshape(-1)
_REACHED_FLAT = CONTROLLER_REACHED.reshape(-1)
_PULSE_FLAT = CONTROLLER_PULSE.reshape(-1)


class DirectionLike(Protocol):
    """One direction of a process image: named (N,) channel views."""

    @property
    def names(self) -> tuple[str, ...]: ...

    def __getitem__(self, name: str) -> npt.NDArray[Any]: ...


class ProcessImageLike(Protocol):
    """What :meth:`Cia402Controller.step_image` needs of a group's image (a :class:`ProcessImage`)."""

    @property
    def outputs(self) -> DirectionLike: ...

    @property
    def inputs(self) -> DirectionLike: ...


_SEEDED: tuple[tuple[str, str | None], ...] = (
    ("target_position", "position_actual_value"),  # CSP, PP, IP: where the axis is
    ("target_velocity", None),  # CSV, PV: 0, stand still (never the actual velocity: that keeps it going)
    ("target_torque", None),  # CST, PT: 0, no jump whatever the load
)
"""Every target (master output) a transition overwrites, and the actual value (master input) it may take."""


class _ImageBinding:
    """The channel views of one image :meth:`Cia402Controller.step_image` uses, looked up once."""

    def __init__(self, img: ProcessImageLike, n_axes: int) -> None:
        out, inp = img.outputs, img.inputs
        self.img = img
        for d, name in ((inp, "statusword"), (out, "controlword")):
            if name not in d.names:
                raise ChannelNameError(f"step_image needs a {name} channel (channels: {', '.join(d.names)})")
        self.statusword = inp["statusword"]
        self.controlword = out["controlword"]
        if self.statusword.shape != (n_axes,):
            raise ValueError(f"the image has {self.statusword.shape[0]} axes, the controller {n_axes}")
        has_modes = "modes_of_operation" in out.names
        self.modes_out = out["modes_of_operation"] if has_modes else None
        has_display = "modes_of_operation_display" in inp.names
        self.modes_display = inp["modes_of_operation_display"] if has_display else None
        self.zero = np.zeros((), dtype=np.float64)
        # (target, the actual value it is seeded from; None: 0)
        self.seeds: list[tuple[npt.NDArray[Any], npt.NDArray[Any] | None]] = []
        for target, actual in _SEEDED:
            if target not in out.names or (actual is not None and actual not in inp.names):
                continue  # no target; or a position with nothing to hold it at: left to the user
            self.seeds.append((out[target], None if actual is None else inp[actual]))


class Cia402Controller:
    """Non-blocking CiA 402 master logic for ``n_axes`` drives, one table step per cycle.

    Each cycle :meth:`step` reads the statusword array (master inputs), writes
    the state-machine bits (0-3, 7) of the controlword array (master outputs)
    in place and leaves every other controlword bit as the caller set it
    (bits 4-6 mode-specific, bit 8 halt, ...). Per-axis goals live in
    :attr:`goal` (set them with :meth:`set_goal`).

    Per-axis results, updated every cycle (read-only views for the caller):
    :attr:`state` (int8 :class:`State402` codes, -1 unknown), :attr:`reached`,
    :attr:`transitions` (state changes seen since the goal was set),
    :attr:`cycles` (cycles spent not at the goal since it was set),
    :attr:`stuck` (no state change for more than ``timeout_cycles`` while
    the goal is not reached), :attr:`mode_ok` (display matches request).

    A fault reset is a pulse on bit 7: ``fault_reset_cycles`` cycles high
    (the rising edge), as many low, repeated while the drive stays in FAULT.
    Automatic resets are bounded (invariant S7 of ``docs/safety.md``): at most
    ``max_fault_resets`` per axis within ``fault_reset_window_cycles``; beyond
    that the axis stays in FAULT, :attr:`gave_up` says so, and only
    :meth:`reset_fault_budget` lets it try again. :attr:`fault_resets` counts
    the resets sent per axis.
    """

    def __init__(
        self,
        n_axes: int,
        *,
        timeout_cycles: int = 1000,
        safe_stop_word: SafeStop = SafeStop.QUICK_STOP,
        fault_reset_cycles: int = 1,
        mode: Mode = Mode.CSP,
        max_fault_resets: int = 3,
        fault_reset_window_cycles: int = 10_000,
        max_reset_hold_cycles: int = 200,
    ) -> None:
        if n_axes < 1:
            raise ValueError(f"n_axes must be >= 1, got {n_axes}")
        if timeout_cycles < 1:
            raise ValueError(f"timeout_cycles must be >= 1, got {timeout_cycles}")
        if fault_reset_cycles < 1:
            raise ValueError(f"fault_reset_cycles must be >= 1, got {fault_reset_cycles}")
        if max_fault_resets < 0 or fault_reset_window_cycles < 1:
            raise ValueError(
                f"max_fault_resets must be >= 0 and fault_reset_window_cycles >= 1, got "
                f"{max_fault_resets} and {fault_reset_window_cycles}"
            )
        self.max_fault_resets = max_fault_resets
        self.fault_reset_window_cycles = fault_reset_window_cycles
        # cycles a fault reset may wait for the axis's error-code read (``hold_reset`` of :meth:`step`)
        self.max_reset_hold_cycles = max_reset_hold_cycles
        self.n_axes = n_axes
        self.timeout_cycles = timeout_cycles
        self.safe_stop_word = SafeStop(safe_stop_word)
        self.fault_reset_cycles = fault_reset_cycles
        n = n_axes
        self.goal: npt.NDArray[np.int8] = np.full(n, Goal.DISABLE, dtype=np.int8)
        self.state: npt.NDArray[np.int8] = np.full(n, UNKNOWN_STATE, dtype=np.int8)
        self.reached: npt.NDArray[np.bool_] = np.zeros(n, dtype=bool)
        self.stuck: npt.NDArray[np.bool_] = np.zeros(n, dtype=bool)
        self.transitions: npt.NDArray[np.int32] = np.zeros(n, dtype=np.int32)
        self.cycles: npt.NDArray[np.int32] = np.zeros(n, dtype=np.int32)
        self.since_progress: npt.NDArray[np.int32] = np.zeros(n, dtype=np.int32)
        self.mode_request: npt.NDArray[np.int8] = np.full(n, int(mode), dtype=np.int8)
        self.mode_ok: npt.NDArray[np.bool_] = np.ones(n, dtype=bool)
        self.fault_resets: npt.NDArray[np.int64] = np.zeros(n, dtype=np.int64)  # resets sent per axis, ever
        self.gave_up: npt.NDArray[np.bool_] = np.zeros(n, dtype=bool)  # too many resets: left in FAULT
        self._window_start = np.zeros(n, dtype=np.int64)
        self._window_count = np.zeros(n, dtype=np.int64)
        self._cycle = 0
        # scratch, preallocated once
        self._prev_state = np.full(n, UNKNOWN_STATE, dtype=np.int8)
        self._idx = np.zeros(n, dtype=np.intp)
        self._sm = np.zeros(n, dtype=np.uint16)
        self._last_sm = np.zeros(n, dtype=np.uint16)
        self._phase = np.zeros(n, dtype=np.int32)
        self._held = np.zeros(n, dtype=np.int32)  # cycles the pending reset of this fault was held
        self._holding = np.zeros(n, dtype=bool)
        self._tmp_i32 = np.zeros(n, dtype=np.int32)
        self._changed = np.zeros(n, dtype=bool)
        self._b1 = np.zeros(n, dtype=bool)
        self._b2 = np.zeros(n, dtype=bool)
        self._pulse = np.zeros(n, dtype=bool)
        self._goal_enable = np.zeros(n, dtype=bool)
        self._goal_not_enable = np.ones(n, dtype=bool)
        self._keep_mask = np.uint16(0xFFFF & ~CONTROLWORD_STATE_BITS)
        self._hold = np.uint16(_HOLD)
        self._bit7 = np.uint16(FAULT_RESET_BIT)
        self._switch_on = np.uint16(CONTROLWORD[Trigger.SWITCH_ON])
        self._zero_i32 = np.int32(0)
        # the targets of every transition (step_image)
        self._binding: _ImageBinding | None = None
        self.seeded: npt.NDArray[np.bool_] = np.zeros(n, dtype=bool)  # step_image seeded the targets now
        self._left = np.zeros(n, dtype=bool)
        self._old_state = np.full(n, UNKNOWN_STATE, dtype=np.int8)
        self._switching = np.zeros(n, dtype=bool)  # mode switch requested, display not yet following
        self._enabled_code = np.int8(State402.OPERATION_ENABLED)
        self._init_fast_paths()

    def _init_fast_paths(self) -> None:
        """The fast paths' bookkeeping: nothing known yet, the next step runs in full."""
        # the steady cycle (:meth:`step`'s fast path): what the last full step read, when it was a fixed point
        self._steady: tuple[Any, ...] | None = None
        self._words_of: npt.NDArray[Any] | None = None  # the statusword array of the steady cycle
        self._words = b""  # its bytes when last seen steady: the state array holds their decode
        self._cw_written = b""  # the controlword's bytes as the last step left them
        self._modes_written = b""  # modes_of_operation's bytes as the last step left them
        self._fast = False  # the last step took the fast path
        self._pulse_idle = True  # no pulse last cycle: held and phase are all 0
        self._image_quiet = False  # the last full step_image seeded nothing and no mode switch was pending

    # -- goals (not in the cycle's hot path, but allocation-free too) --

    def set_goal(self, goal: Goal, axes: Any = slice(None)) -> None:
        """Set the goal of ``axes`` (an index, slice, or mask; default all) and restart their counters."""
        self.goal[axes] = Goal(goal)
        self._restart(axes)

    def request_mode(self, mode: Mode | int, axes: Any = slice(None)) -> None:
        """Ask ``axes`` to switch to ``mode`` (written to modes_of_operation each :meth:`step`)."""
        np.not_equal(self.mode_request, np.int8(int(mode)), out=self._b1)
        self._b2.fill(False)
        self._b2[axes] = True
        np.logical_and(self._b1, self._b2, out=self._b1)
        np.logical_or(self._switching, self._b1, out=self._switching)
        self.mode_request[axes] = int(mode)
        self._restart(axes)

    def _restart(self, axes: Any) -> None:
        self._steady = None
        self.transitions[axes] = 0
        self.cycles[axes] = 0
        self.since_progress[axes] = 0
        self.stuck[axes] = False
        self.reached[axes] = False
        np.equal(self.goal, Goal.ENABLE, out=self._goal_enable)
        np.logical_not(self._goal_enable, out=self._goal_not_enable)

    # -- the cycle --

    #: False: every :meth:`step` runs the whole table step, each part of it, as before the fast paths
    #: (tests and benchmarks compare both)
    fast_path = True

    def step(
        self,
        statusword: npt.NDArray[Any],
        controlword_out: npt.NDArray[Any],
        modes_display: npt.NDArray[Any] | None = None,
        modes_out: npt.NDArray[Any] | None = None,
        hold_reset: npt.NDArray[np.bool_] | None = None,
    ) -> None:
        """One cycle: statusword (uint16, master inputs) -> controlword (uint16, master outputs, in place).

        With ``modes_display`` (0x6061, master input) and ``modes_out`` (0x6060,
        master output) the requested modes are written and an ENABLE goal waits
        in SWITCHED_ON until the display matches (and is reached only then).
        ``hold_reset`` (bool per axis, e.g. ``Operational.fault_code_pending(group)``):
        an axis whose fault's error code is still being read acyclically gets no
        fault reset yet (a reset clears 0x603F in the drive), for at most
        :attr:`max_reset_hold_cycles` cycles per fault; a held reset is not counted.

        A steady cycle is cheap (:attr:`fast_path`): when the last full step left
        every axis at its goal with no state change, and this one decodes the same
        states from the statuswords and reads the same goals, mode requests and
        displays through the same arrays, the full step would change nothing but
        the cycle count and write what it wrote then. Then only the outputs the
        caller changed since are written again (same words), nothing else runs;
        the same statuswords as then are not even decoded again.
        The result arrays (:attr:`reached`, :attr:`cycles`, ...) are read only for
        the caller; the goal and the mode request change through their methods or
        in place, both seen.
        """
        state = self.state
        # the statuswords of the steady cycle again: the state array holds their decode (checked below)
        words = statusword.tobytes()
        same_words = self._steady is not None and statusword is self._words_of and words == self._words
        if not same_words:
            decode_states(statusword, state, self._idx)
        if self._steady_again(controlword_out, modes_display, modes_out):
            if not same_words:  # other bits changed (target reached ...): these are the words now
                self._words_of, self._words = statusword, words
            self._repeat_steady(controlword_out, modes_out)
            return
        if same_words:  # but someone wrote the state array (the DDS server decodes into it while stopped)
            decode_states(statusword, state, self._idx)
        self._table_step(controlword_out, modes_display, modes_out, hold_reset)
        # every axis at its goal and none changed state (so no pulse, and progress counts stand still):
        # the next step with the same states, goals and modes is this one again
        if (
            self.fast_path
            and np.count_nonzero(self.reached) == self.n_axes
            and not np.count_nonzero(self._changed)
        ):
            self._steady = (
                controlword_out,
                modes_display,
                modes_out,
                state.tobytes(),
                self.goal.tobytes(),
                self.mode_request.tobytes(),
                None if modes_display is None else modes_display.tobytes(),
                self.timeout_cycles,
            )
            self._words_of, self._words = statusword, words
            self._cw_written = controlword_out.tobytes()
            self._modes_written = b"" if modes_out is None else modes_out.tobytes()
        else:
            self._steady = None

    def _steady_again(
        self,
        controlword_out: npt.NDArray[Any],
        modes_display: npt.NDArray[Any] | None,
        modes_out: npt.NDArray[Any] | None,
    ) -> bool:
        """The last full step was steady and this one has its states, goals, modes and arrays."""
        key = self._steady
        return (
            key is not None
            and self.fast_path
            and controlword_out is key[0]
            and modes_display is key[1]
            and modes_out is key[2]
            and self.state.tobytes() == key[3]
            and self.goal.tobytes() == key[4]
            and self.mode_request.tobytes() == key[5]
            and (modes_display is None or modes_display.tobytes() == key[6])
            and self.timeout_cycles == key[7]
        )

    def _repeat_steady(self, controlword_out: npt.NDArray[Any], modes_out: npt.NDArray[Any] | None) -> None:
        """The full step's fixed point: no pulse, no progress to count; the words written again only
        where the caller changed them since (master outputs, the same values as then)."""
        self._cycle += 1
        self._fast = True
        if modes_out is not None and modes_out.tobytes() != self._modes_written:
            np.copyto(modes_out, self.mode_request, casting="unsafe")
            self._modes_written = modes_out.tobytes()
        if controlword_out.tobytes() != self._cw_written:  # the caller wrote it: (cw & keep) | sm again
            np.bitwise_and(controlword_out, self._keep_mask, out=controlword_out)
            np.bitwise_or(controlword_out, self._sm, out=controlword_out)
            self._cw_written = controlword_out.tobytes()

    def _table_step(
        self,
        controlword_out: npt.NDArray[Any],
        modes_display: npt.NDArray[Any] | None,
        modes_out: npt.NDArray[Any] | None,
        hold_reset: npt.NDArray[np.bool_] | None,
    ) -> None:
        """The full step on the decoded :attr:`state`: table, modes, fault reset, controlword, progress."""
        self._fast = False
        self._image_quiet = False
        state, idx, sm = self.state, self._idx, self._sm
        np.not_equal(state, self._prev_state, out=self._changed)
        np.add(self.transitions, self._changed, out=self.transitions)
        np.copyto(self._prev_state, state)

        # table lookup: flat index state * n_goals + goal; UNKNOWN (-1) wraps onto the last row
        np.multiply(state, _N_GOALS, out=idx)
        np.add(idx, self.goal, out=idx)
        np.take(_CW_FLAT, idx, out=sm, mode="wrap")
        np.take(_REACHED_FLAT, idx, out=self.reached, mode="wrap")
        np.take(_PULSE_FLAT, idx, out=self._pulse, mode="wrap")
        np.equal(sm, self._hold, out=self._b1)
        np.copyto(sm, self._last_sm, where=self._b1)

        # modes: write the request; with a display, gate the enable on a match
        if modes_out is not None:
            np.copyto(modes_out, self.mode_request, casting="unsafe")
        if modes_display is None:
            self.mode_ok.fill(True)
        else:
            self._gate_enable_on_mode(modes_display)
        self._fault_reset_pulse(hold_reset)

        # write bits 0-3, 7; keep the caller's other bits
        np.bitwise_and(controlword_out, self._keep_mask, out=controlword_out)
        np.bitwise_or(controlword_out, sm, out=controlword_out)
        np.copyto(self._last_sm, sm)

        # progress bookkeeping
        np.logical_not(self.reached, out=self._b2)
        np.add(self.cycles, self._b2, out=self.cycles)
        np.add(self.since_progress, self._b2, out=self.since_progress)
        np.logical_or(self._changed, self.reached, out=self._b1)
        np.copyto(self.since_progress, self._zero_i32, where=self._b1)
        np.greater(self.since_progress, self.timeout_cycles, out=self.stuck)
        self._cycle += 1

    def _gate_enable_on_mode(self, modes_display: npt.NDArray[Any]) -> None:
        """Modes: compare the display with the request; an ENABLE goal waits in SWITCHED_ON for a match."""
        sm = self._sm
        np.equal(modes_display, self.mode_request, out=self.mode_ok)
        if np.count_nonzero(self.mode_ok) == self.n_axes and self.fast_path:  # every display follows
            return
        np.equal(self.state, np.int8(State402.SWITCHED_ON), out=self._b1)
        np.logical_and(self._b1, self._goal_enable, out=self._b1)
        np.logical_not(self.mode_ok, out=self._b2)
        np.logical_and(self._b1, self._b2, out=self._b1)
        np.copyto(sm, self._switch_on, where=self._b1)
        np.logical_or(self.mode_ok, self._goal_not_enable, out=self._b2)
        np.logical_and(self.reached, self._b2, out=self.reached)

    def _fault_reset_pulse(self, hold_reset: npt.NDArray[np.bool_] | None) -> None:
        """Fault-reset pulse: N cycles with bit 7 high (rising edge), N low, repeat; bounded per axis."""
        pulsing = np.count_nonzero(self._pulse)
        if not pulsing and self._pulse_idle and self.fast_path:  # no reset now or last cycle: all stay 0
            return
        sm, phase = self._sm, self._phase
        np.greater(self._pulse, self.gave_up, out=self._pulse)  # an axis that gave up gets no pulse
        np.multiply(self._held, self._pulse, out=self._held)  # out of fault: the next fault may wait again
        if hold_reset is not None:  # its 0x603F read is pending: no reset yet (bounded per fault)
            np.less(self._held, self.max_reset_hold_cycles, out=self._holding)
            np.logical_and(self._holding, hold_reset, out=self._holding)
            np.logical_and(self._holding, self._pulse, out=self._holding)
            np.add(self._held, self._holding, out=self._held)
            np.greater(self._pulse, self._holding, out=self._pulse)  # the pulse starts when released
        np.multiply(phase, self._pulse, out=phase)
        np.remainder(phase, 2 * self.fault_reset_cycles, out=self._tmp_i32)
        np.equal(self._tmp_i32, 0, out=self._b2)
        np.logical_and(self._b2, self._pulse, out=self._b2)  # a reset begins now
        if self._b2.any():
            self._count_resets(self._b2)
        np.less(self._tmp_i32, self.fault_reset_cycles, out=self._b1)
        np.logical_and(self._b1, self._pulse, out=self._b1)
        np.bitwise_or(sm, self._bit7, out=sm, where=self._b1)
        np.add(phase, self._pulse, out=phase)
        self._pulse_idle = not pulsing  # no pulse now: held and phase were set to 0

    def _count_resets(self, starting: npt.NDArray[np.bool_]) -> None:
        """Axes whose reset pulse begins this cycle: count it, or give up past the budget (rare path)."""
        for i in np.flatnonzero(starting):
            if self._cycle - self._window_start[i] >= self.fault_reset_window_cycles:
                self._window_start[i] = self._cycle
                self._window_count[i] = 0
            if self._window_count[i] >= self.max_fault_resets:
                self.gave_up[i] = True
                self._pulse[i] = False
                continue
            self._window_count[i] += 1
            self.fault_resets[i] += 1

    def reset_fault_budget(self, axes: Any = slice(None)) -> None:
        """Let ``axes`` that gave up (:attr:`gave_up`) reset their faults again, with a fresh budget."""
        self.gave_up[axes] = False
        self._window_count[axes] = 0
        self._window_start[axes] = self._cycle

    def safe_stop(self, controlword_out: npt.NDArray[Any]) -> None:
        """Write the safe-stop command into every controlword (master outputs) now, and make it the goal.

        Quick stop (0x02) or disable voltage (0x00), per ``safe_stop_word``; bits
        outside 0-3 and 7 are kept (:func:`write_command_word`, the same code the
        network's safe stop runs). Call it when ``CycleResult.safe_stop`` turns
        True, so that this controller's goal agrees with what the network sends;
        later :meth:`step` calls keep the axes stopped.
        """
        self.goal.fill(Goal.QUICK_STOP if self.safe_stop_word is SafeStop.QUICK_STOP else Goal.DISABLE)
        self._restart(slice(None))
        write_command_word(controlword_out, self.safe_stop_word)
        self._last_sm.fill(self.safe_stop_word)

    # -- the whole image: the targets of every transition --

    def step_image(
        self,
        img: ProcessImageLike,
        hold_reset: npt.NDArray[np.bool_] | None = None,
        modes: AcyclicModes | None = None,
    ) -> None:
        """One cycle on a group's process image: :meth:`step` plus the targets of every transition.

        Reads the statusword and, where the map has them, modes_of_operation_display
        and the actual values (master inputs); writes the controlword and
        modes_of_operation (master outputs) as :meth:`step` does. Then, per axis,
        **no transition starts motion** (invariant S11 of ``docs/safety.md``): in
        every cycle of a transition - the axis not OPERATION ENABLED (disabled, a
        safe stop, a fault and its reset, a power cycle and its recovery), the
        cycle it is first seen enabled again, every cycle of a mode switch (from
        :meth:`request_mode` until the display shows the new mode) - **every**
        target in the image is overwritten with its seed, whatever the requested
        mode: target_position <- position_actual_value (CSP, PP), target_velocity
        <- 0 (CSV, PV), target_torque <- 0 (CST; the axis coasts). A position
        seed is bumpless; a velocity seed of 0 brakes an axis that was moving
        (never the actual velocity: that would keep it going after an enable).
        :attr:`seeded` says which axes were seeded this cycle.

        So a command older than the transition is gone from the image: only a
        value written *after* this call, in the transition's last seeded cycle
        or later, reaches the drive. A loop that keeps its own command (a
        trajectory) must restart it from the image's target while
        :attr:`seeded` is set: the library cannot tell an old value written
        again from a new one. Channels are found by their CiA 402 names; a
        target_position without position_actual_value is left alone. Values are
        copied in the image's units: the target and the actual value must share
        a unit (both counts, or both rad...), as the map loader checks for the
        shipped maps. Allocation-free after the first call on an image.
        ``hold_reset``: as in :meth:`step`. ``modes``: for an image without
        modes_of_operation / its display (0x6060/0x6061 not in the PDOs), an
        :class:`~fieldbus.core.acyclic_modes.AcyclicModes` of the same group that
        carries them by SDO; it is stepped here, once per call, never waiting,
        and told of every recovery (the bus brought a slave back, an axis left
        OPERATION ENABLED) so that it reads the display again before the next enable.
        """
        b = self._binding
        if b is None or b.img is not img:
            b = self._binding = _ImageBinding(img, self.n_axes)
        display, out = b.modes_display, b.modes_out
        acyclic = modes is not None and out is None and display is None  # the mode objects go by SDO
        if acyclic:
            assert modes is not None
            display, out = modes.display, modes.request
            modes.forget_recovered()  # before the controller compares it: after a recovery it is unknown
            np.copyto(self._old_state, self.state)
        self.step(b.statusword, b.controlword, display, out, hold_reset)
        if acyclic:
            assert modes is not None
            left = self._left  # axes that left OPERATION ENABLED: the next enable is a re-enable
            np.equal(self._old_state, self._enabled_code, out=left)
            np.not_equal(self.state, self._enabled_code, out=self._b1)
            np.logical_and(left, self._b1, out=left)
            if left.any():
                modes.forget(left)
            modes.step()
        if self._fast and self._image_quiet:  # the same enabled states as then: nothing to seed, no switch
            return
        seed = self.seeded
        np.not_equal(self.state, self._enabled_code, out=seed)
        np.logical_or(seed, self._changed, out=seed)  # the cycle it is first seen enabled
        np.logical_or(seed, self._switching, out=seed)
        if display is not None:
            np.logical_and(self._switching, self._goal_not_enable, out=self._b1)  # nothing to wait for
            np.logical_or(self._b1, self.mode_ok, out=self._b1)
        else:
            self._b1.fill(True)
        np.greater(self._switching, self._b1, out=self._switching)  # done once the display follows
        for target, actual in b.seeds:
            np.copyto(target, b.zero if actual is None else actual, where=seed, casting="unsafe")
        self._image_quiet = not np.count_nonzero(seed) and not np.count_nonzero(self._switching)

    @property
    def all_reached(self) -> bool:
        """Every axis is at its goal."""
        return bool(self.reached.all())

    @property
    def any_stuck(self) -> bool:
        """Some axis made no progress for more than ``timeout_cycles`` cycles."""
        return bool(self.stuck.any())


# --------------------------------------------------------------------------- homing


class HomingPhase(IntEnum):
    """Where each axis is in :class:`Homing` (per-axis codes in :attr:`Homing.phase`)."""

    IDLE = 0  # not asked to home (or never)
    WAIT = 1  # HOMING requested; waiting for OPERATION ENABLED in mode 6
    ARMED = 2  # bit 4 low for one cycle, so the next cycle is a rising edge
    RUNNING = 3  # bit 4 high; watching statusword bits 10/12/13
    DONE = 4  # homing attained (bits 12 and 10); back in the previous mode
    FAILED = 5  # homing error (bit 13); back in the previous mode
    TIMED_OUT = 6  # no result within timeout_cycles; bit 4 dropped (interrupts it), previous mode


HOMING_START_BIT = 0x0010  # controlword bit 4 in homing mode (master output): rising edge starts
HOMING_ATTAINED = 0x1000  # statusword bit 12 in homing mode (master input)
HOMING_ERROR = 0x2000  # statusword bit 13 in homing mode (master input)


SETTLE_CYCLES = 2  # cycles after the bit-4 edge before a homing's statusword bits are believed


class Homing:
    """Non-blocking, per-axis homing on top of a :class:`Cia402Controller`, one step per cycle.

    :meth:`start` switches the axes to HOMING (mode 6); each :meth:`step`, called
    right after the controller's step with the same arrays, gives each axis's
    controlword bit 4 a rising edge once the axis is OPERATION ENABLED in mode 6,
    then follows statusword bits 12 (attained, with 10) and 13 (error); an axis
    that leaves OPERATION ENABLED in mode 6 while homing has failed too. When an
    axis is done, failed or took more than ``timeout_cycles`` cycles, bit 4 drops
    and the axis goes back to the mode it had before :meth:`start`. The homing
    parameters (0x6098 method, 0x607C offset, 0x6099 speeds, 0x609A acceleration)
    are configuration, written at bring-up from the drive map's ``homing:``
    section. Axes home together or, with ``order``, in declared stages.
    ``timeout_cycles`` is one number for every axis or one per axis; :meth:`from_maps`
    takes each axis's from its map's ``homing.timeout_ms``.
    """

    def __init__(self, ctrl: Cia402Controller, *, timeout_cycles: int | Sequence[int] = 30_000) -> None:
        n = ctrl.n_axes
        limit = np.broadcast_to(np.asarray(timeout_cycles, dtype=np.int64), (n,)).astype(np.int32)
        if (limit < 1).any():
            raise ValueError(f"timeout_cycles must be >= 1, got {timeout_cycles}")
        self.ctrl = ctrl
        self.timeout_cycles = limit  # per axis [cycles]
        self.phase: npt.NDArray[np.int8] = np.zeros(n, dtype=np.int8)
        self.cycles: npt.NDArray[np.int32] = np.zeros(n, dtype=np.int32)  # cycles since start
        self._running = np.zeros(n, dtype=np.int32)  # cycles since the bit-4 edge went out
        self._prev_mode = np.full(n, int(Mode.CSP), dtype=np.int8)
        self._stages: list[npt.NDArray[np.bool_]] = []
        self._m = np.zeros(n, dtype=bool)
        self._m2 = np.zeros(n, dtype=bool)
        self._sw = np.zeros(n, dtype=np.uint16)
        self._bit4 = np.uint16(HOMING_START_BIT)
        self._not_bit4 = np.uint16(0xFFFF & ~HOMING_START_BIT)

    @classmethod
    def from_maps(cls, ctrl: Cia402Controller, maps: Sequence[DriveMap], cycle_time_us: int) -> Homing:
        """Homing for axes described by ``maps`` (one per axis, e.g. ``[s.map for s in op.groups[g].slaves]``),
        each timed out after its ``homing.timeout_ms`` (30 s without a section) at ``cycle_time_us``.
        A multi-axis slave's map may stand for all its axes (one map per slave)."""
        if len(maps) != ctrl.n_axes and sum(m.axes for m in maps) == ctrl.n_axes:
            maps = [m for m in maps for _ in range(m.axes)]
        if len(maps) != ctrl.n_axes:
            raise ValueError(f"{len(maps)} drive maps for {ctrl.n_axes} axes")
        if cycle_time_us < 1:
            raise ValueError(f"cycle_time_us must be >= 1, got {cycle_time_us}")
        ms = [m.homing.timeout_ms if m.homing is not None else 30_000 for m in maps]
        return cls(ctrl, timeout_cycles=[max(1, -(-t * 1000 // cycle_time_us)) for t in ms])

    def start(self, axes: Any = slice(None), *, order: list[Any] | None = None) -> None:
        """Home ``axes`` (index, slice or mask), all at once; or the stages of ``order`` one after another
        (a list of axis selections: a leg's hips before its knees). Allocates: call it outside the cycle."""
        stages = [axes] if order is None else list(order)
        self._stages = []
        for st in stages:
            m = np.zeros(self.ctrl.n_axes, dtype=bool)
            m[st] = True
            self._stages.append(m)
        self._begin(self._stages.pop(0))

    def _begin(self, m: npt.NDArray[np.bool_]) -> None:
        self._prev_mode[m] = self.ctrl.mode_request[m]
        self.phase[m] = HomingPhase.WAIT
        self.cycles[m] = 0
        self._running[m] = 0
        self.ctrl.request_mode(Mode.HOMING, m)

    def step(self, statusword: npt.NDArray[Any], controlword_out: npt.NDArray[Any]) -> None:
        """One cycle, after :meth:`Cia402Controller.step`: bit 4 of the controlwords (master outputs)
        from the statuswords (master inputs)."""
        ph, m, m2 = self.phase, self._m, self._m2
        np.copyto(self._sw, statusword, casting="unsafe")
        # ARMED -> RUNNING (bit 4 goes high now, after a cycle low: a rising edge)
        np.equal(ph, HomingPhase.ARMED, out=m2)
        np.copyto(ph, np.int8(HomingPhase.RUNNING), where=m2)
        # WAIT -> ARMED once enabled in mode 6 (the controller's goal reached)
        np.equal(ph, HomingPhase.WAIT, out=m)
        np.logical_and(m, self.ctrl.reached, out=m)
        np.copyto(ph, np.int8(HomingPhase.ARMED), where=m)
        active = (ph >= HomingPhase.WAIT) & (ph <= HomingPhase.RUNNING)
        np.add(self.cycles, active, out=self.cycles)
        running = ph == HomingPhase.RUNNING
        np.add(self._running, running, out=self._running)
        np.bitwise_and(controlword_out, self._not_bit4, out=controlword_out)
        np.bitwise_or(controlword_out, self._bit4, out=controlword_out, where=running)
        # the statusword is judged only once it can answer the edge: the edge goes out this cycle, the
        # drive sees it, its answer comes back (bits 10/12/13 of an earlier homing are stale until then)
        judged = running & (self._running > SETTLE_CYCLES)
        attained = judged & ((self._sw & (HOMING_ATTAINED | StatusBit.TARGET_REACHED)) == 0x1400)
        # a drive that left OPERATION ENABLED in mode 6 (a fault, a bus dropout, a quick stop) has
        # interrupted its homing (CiA 402: it runs only there); after a fault reset it waits for a new
        # bit-4 edge, so waiting for bits 12/13 would only end at the timeout
        failed = (judged & ((self._sw & HOMING_ERROR) != 0)) | (running & ~self.ctrl.reached)
        late = active & (self.cycles > self.timeout_cycles)
        if attained.any() or failed.any() or late.any():  # rare path: an axis finishes
            self._finish(attained, failed & ~attained, late & ~attained & ~failed, controlword_out)

    def _finish(
        self,
        attained: npt.NDArray[np.bool_],
        failed: npt.NDArray[np.bool_],
        late: npt.NDArray[np.bool_],
        controlword_out: npt.NDArray[Any],
    ) -> None:
        for mask, phase in (
            (attained, HomingPhase.DONE),
            (failed, HomingPhase.FAILED),
            (late, HomingPhase.TIMED_OUT),
        ):
            if not mask.any():
                continue
            self.phase[mask] = phase
            controlword_out[mask] &= self._not_bit4
            for i in np.flatnonzero(mask):
                self.ctrl.request_mode(int(self._prev_mode[i]), int(i))
        busy = (self.phase >= HomingPhase.WAIT) & (self.phase <= HomingPhase.RUNNING)
        if self._stages and not busy.any():
            self._begin(self._stages.pop(0))

    @property
    def done(self) -> bool:
        """No axis is homing any more (each is IDLE, DONE, FAILED or TIMED_OUT)."""
        return (
            not bool(((self.phase >= HomingPhase.WAIT) & (self.phase <= HomingPhase.RUNNING)).any())
            and not self._stages
        )
