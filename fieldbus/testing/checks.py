"""Assertions a controller's tests need often, on a :class:`~fieldbus.testing.Trace` or the live network.

Each raises :class:`EmulationAssertion` (an ``AssertionError``: pytest shows
its message) that says what was expected and what the cycles showed; each
returns what it found, for further checks. Windows are cycle indices of the
trace: ``since`` inclusive, ``until`` exclusive (default: the last cycle run).
"""

from __future__ import annotations

from collections.abc import Iterable
from typing import TYPE_CHECKING, Any

import numpy as np
import numpy.typing as npt

from fieldbus.core.cia402 import State402, decode_state, decode_states
from fieldbus.testing.trace import Trace, TraceEvent

if TYPE_CHECKING:
    from fieldbus.network import Operational


class EmulationAssertion(AssertionError):
    """A check of the testing kit failed (the message says which cycles and what they showed)."""


def _window(trace: Trace, since: int, until: int | None) -> tuple[int, int]:
    end = len(trace) if until is None else min(until, len(trace))
    if since < 0 or since > end:
        raise EmulationAssertion(f"window [{since}, {end}) is outside the {len(trace)} cycles run")
    return since, end


def _cycles(idx: Any, limit: int = 10) -> str:
    items = [int(i) for i in idx[:limit]]
    more = f" and {len(idx) - limit} more" if len(idx) > limit else ""
    return ", ".join(map(str, items)) + more


def assert_safe_stop_latched(trace: Trace, *, within: int, since: int, until: int | None = None) -> int:
    """The safe stop latched within ``within`` cycles from cycle ``since`` and stayed latched until ``until``.

    Returns the cycle at which it latched. A stop already latched before ``since`` fails:
    it would say nothing about the fault injected there.
    """
    since, end = _window(trace, since, until)
    stop = trace.safe_stop
    if since > 0 and stop[since - 1]:
        raise EmulationAssertion(f"the safe stop was latched already before cycle {since}")
    hit = np.flatnonzero(stop[since:end])
    if not hit.size or hit[0] >= within:
        ran = end - since
        raise EmulationAssertion(
            f"no safe stop within {within} cycles of cycle {since} ({ran} cycles run; "
            f"fresh in {int(trace.fresh[since:end].sum())} of them)"
        )
    at = since + int(hit[0])
    released = np.flatnonzero(~stop[at:end])
    if released.size:
        raise EmulationAssertion(
            f"the safe stop latched at cycle {at} but was released at cycle {at + int(released[0])}"
        )
    return at


def assert_no_safe_stop(trace: Trace, *, since: int = 0, until: int | None = None) -> None:
    """No cycle of the window ended with the safe stop latched."""
    since, end = _window(trace, since, until)
    hit = np.flatnonzero(trace.safe_stop[since:end])
    if hit.size:
        raise EmulationAssertion(f"safe stop latched in cycles {_cycles(hit + since)}")


def assert_no_miss(trace: Trace, *, since: int = 0, until: int | None = None) -> None:
    """Every cycle of the window was fresh on every bus (no lost, late or short reply)."""
    since, end = _window(trace, since, until)
    missed = np.flatnonzero(~trace.fresh[since:end]) + since
    if missed.size:
        first = int(missed[0])
        verdicts = ", ".join(f"{b}: {int(trace.verdict(b)[first])}" for b in trace.bus_names)
        raise EmulationAssertion(
            f"{missed.size} of {end - since} cycles missed: {_cycles(missed)} "
            f"(cycle {first} verdicts {verdicts}; 0 OK, 1 SHORT, 2 TIMEOUT)"
        )


def assert_inputs_held(trace: Trace, group: str, *, since: int = 0, until: int | None = None) -> int:
    """In every cycle of the window where an axis of ``group`` was not fresh, its inputs equal the
    cycle before's (stale inputs never change). Returns how many stale axis-cycles were checked;
    none at all fails (the window saw no miss, so it proves nothing)."""
    since, end = _window(trace, max(since, 1), until)
    inputs = trace.inputs(group)
    fresh = trace.group_fresh(group)
    stale = np.argwhere(~fresh[since:end])
    if not stale.size:
        raise EmulationAssertion(
            f"group '{group}': no stale input in cycles [{since}, {end}): nothing was held"
        )
    for k, axis in stale:
        c = since + int(k)
        if inputs[c, axis].tobytes() != inputs[c - 1, axis].tobytes():
            changed = [n for n in inputs.dtype.names or () if inputs[c, axis][n] != inputs[c - 1, axis][n]]
            raise EmulationAssertion(
                f"group '{group}' axis {int(axis)}: stale in cycle {c} but its inputs changed ({', '.join(changed)})"
            )
    return len(stale)


def assert_all_enabled(op: Operational, group: str | None = None) -> None:
    """Every CiA 402 axis (of ``group``, or of every group with a statusword) reads OPERATION ENABLED now."""
    groups = [group] if group is not None else [g for g in op if "statusword" in op[g].inputs.names]
    if not groups:
        raise EmulationAssertion("no axis group has a statusword (not CiA 402 drives)")
    bad = []
    for g in groups:
        image = op[g]
        if "statusword" not in image.inputs.names:
            raise EmulationAssertion(f"group '{g}' has no statusword input")
        for axis, word in enumerate(image.inputs["statusword"]):
            state = decode_state(int(word))
            if state is not State402.OPERATION_ENABLED:
                bad.append(f"{g}[{axis}] {state.name if state else 'UNKNOWN'} (0x{int(word):04X})")
    if bad:
        raise EmulationAssertion("not OPERATION ENABLED: " + ", ".join(bad))


def assert_event(
    trace: Trace,
    kind: str,
    *,
    since: int = 0,
    until: int | None = None,
    within: int | None = None,
    **fields: Any,
) -> TraceEvent:
    """An event of kind ``kind`` (``drive_fault``, ``safe_stop``, ``recovered``, ...; see
    :func:`~fieldbus.testing.trace.event_kind`) in cycles [``since``, ``until``), within ``within``
    cycles of ``since`` if given, whose attributes equal ``fields`` (``slave="j1"``, ``code=0x7300``).
    Returns the first such event."""
    since, end = _window(trace, since, until)
    if within is not None:
        end = min(end, since + within)
    seen = trace.events_of(kind, since=since, until=end)
    for e in seen:
        if all(getattr(e.event, name, _MISSING) == value for name, value in fields.items()):
            return e
    want = ", ".join(f"{n}={v!r}" for n, v in fields.items())
    others = trace.events_of(None, since=since, until=end)
    shown = "; ".join(str(e) for e in others[:5]) or "none"
    raise EmulationAssertion(
        f"no '{kind}' event{f' with {want}' if want else ''} in cycles [{since}, {end}) "
        f"({len(others)} events there: {shown})"
    )


def assert_no_event(
    trace: Trace, kind: str | None = None, *, since: int = 0, until: int | None = None
) -> None:
    """No event of kind ``kind`` (None: none at all) in cycles [``since``, ``until``)."""
    since, end = _window(trace, since, until)
    seen = trace.events_of(kind, since=since, until=end)
    if seen:
        raise EmulationAssertion(
            f"{len(seen)} {'events' if kind is None else repr(kind) + ' events'} in cycles [{since}, {end}): "
            + "; ".join(str(e) for e in seen[:5])
        )


def assert_no_target_jump(
    trace: Trace,
    group: str,
    max_step: float | npt.ArrayLike,
    *,
    output: str = "target_position",
    since: int = 0,
    until: int | None = None,
) -> int:
    """While an axis of ``group`` is enabled, its ``output`` never moves more than ``max_step`` (engineering
    units; a number, or one per axis) from one sent frame to the next. "Enabled": the statusword read the
    cycle before (the state the drive had when the frame reached it) was OPERATION ENABLED. Returns how
    many axis-cycles were checked; none fails (no axis was enabled: it proves nothing)."""
    since, end = _window(trace, max(since, 1), until)
    inputs, outputs = trace.inputs(group), trace.outputs(group)
    if "statusword" not in (inputs.dtype.names or ()):
        raise EmulationAssertion(f"group '{group}' has no statusword input (not CiA 402 drives)")
    if output not in (outputs.dtype.names or ()):
        raise EmulationAssertion(
            f"group '{group}' has no output '{output}' (have: {', '.join(outputs.dtype.names or ())})"
        )
    states = np.empty(inputs.shape, dtype=np.int8)
    decode_states(inputs["statusword"].astype(np.intp).ravel(), states.ravel())
    enabled = states[since - 1 : end - 1] == int(State402.OPERATION_ENABLED)
    values = outputs[output].astype(np.float64)
    step = np.abs(values[since:end] - values[since - 1 : end - 1])
    limit = np.broadcast_to(np.asarray(max_step, dtype=np.float64), step.shape[1:])
    bad = np.argwhere(enabled & ~(step <= limit))
    if bad.size:
        k, axis = int(bad[0][0]), int(bad[0][1])
        c = since + k
        raise EmulationAssertion(
            f"group '{group}' axis {axis}: {output} jumped by {step[k, axis]:g} in cycle {c} while enabled "
            f"(from {values[c - 1, axis]:g} to {values[c, axis]:g}; bound {limit[axis]:g}); "
            f"{len(bad)} such axis-cycles"
        )
    checked = int(enabled.sum())
    if not checked:
        raise EmulationAssertion(
            f"group '{group}': no axis enabled in cycles [{since}, {end}): nothing checked"
        )
    return checked


def assert_drive_states(
    source: Operational | Trace,
    states: State402 | Iterable[State402],
    group: str | None = None,
    *,
    since: int = 0,
    until: int | None = None,
) -> int:
    """Every CiA 402 axis (of ``group``, or of every group with a statusword) is in one of ``states``:
    now (``source`` an :class:`~fieldbus.Operational`), or in every cycle of the window (a
    :class:`~fieldbus.testing.Trace`). Returns how many axis-cycles were checked."""
    allowed = {states} if isinstance(states, State402) else set(states)
    names = _cia402_groups(source, group)
    checked = 0
    bad: list[str] = []
    for g in names:
        if isinstance(source, Trace):
            lo, end = _window(source, since, until)
            words = source.inputs(g)["statusword"][lo:end]
        else:
            lo, words = 0, source[g].inputs["statusword"][None, :]
        codes = np.empty(words.shape, dtype=np.int8)
        decode_states(words.astype(np.intp).ravel(), codes.ravel())
        ok = np.isin(codes, [int(s) for s in allowed])
        checked += ok.size
        for k, axis in np.argwhere(~ok)[:5]:
            state = decode_state(int(words[k, axis]))
            when = f" in cycle {lo + int(k)}" if isinstance(source, Trace) else ""
            bad.append(
                f"{g}[{int(axis)}] {state.name if state else 'UNKNOWN'} (0x{int(words[k, axis]):04X}){when}"
            )
    if bad:
        want = ", ".join(sorted(s.name for s in allowed))
        raise EmulationAssertion(f"not in {want}: " + ", ".join(bad))
    return checked


def _cia402_groups(source: Operational | Trace, group: str | None) -> list[str]:
    if isinstance(source, Trace):
        every = list(source.group_names)
        has = [g for g in every if "statusword" in (source.inputs(g).dtype.names or ())]
    else:
        every = list(source)
        has = [g for g in every if "statusword" in source[g].inputs.names]
    if group is not None:
        if group not in every:
            raise EmulationAssertion(f"no axis group '{group}' (have: {', '.join(every)})")
        if group not in has:
            raise EmulationAssertion(f"group '{group}' has no statusword input")
        return [group]
    if not has:
        raise EmulationAssertion("no axis group has a statusword (not CiA 402 drives)")
    return has


_MISSING = object()
