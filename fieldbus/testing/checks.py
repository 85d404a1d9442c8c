"""Assertions a controller's tests need often, on a :class:`~fieldbus.testing.Trace` or the live network.

Each raises :class:`EmulationAssertion` (an ``AssertionError``: pytest shows
its message) that says what was expected and what the cycles showed; each
returns what it found, for further checks. Windows are cycle indices of the
trace: ``since`` inclusive, ``until`` exclusive (default: the last cycle run).
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

import numpy as np

from fieldbus.core.cia402 import State402, decode_state

if TYPE_CHECKING:
    from fieldbus.network import Operational
    from fieldbus.testing.trace import Trace


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
