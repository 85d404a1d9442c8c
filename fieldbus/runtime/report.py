"""Cycle-run statistics as the CLI prints them (``demo``, ``run``): one dict, stable keys."""

from __future__ import annotations

from typing import Any

from fieldbus.network import Operational
from fieldbus.runtime.timing import CycleTimer


def run_report(op: Operational, timer: CycleTimer, cycle_time_us: float) -> dict[str, Any]:
    """``cycles``, ``missed``, ``safe_stops``, ``cycle_time_us: {mean, p99, max}`` and per-bus detail.

    ``cycle_time_us`` is the time spent in each cycle's work (exchange plus the
    controller step), not the period; ``period_us`` is the period.
    """
    s = timer.summary()
    buses = []
    missed = 0
    safe_stops = 0
    for b, policy in zip(op._net.backends, op._net.policies, strict=True):
        st = policy.stats
        missed += st.misses
        safe_stops += st.safe_stops
        buses.append(
            {
                "name": b.bus.name,
                "type": b.kind,
                "slaves": b.n_slaves,
                "expected_wkc": b.expected_wkc,
                "cycles": st.cycles,
                "missed": st.misses,
                "timeouts": st.timeouts,
                "short": st.short,
                "longest_streak": st.longest_streak,
                "recoveries": st.recoveries,
                "safe_stops": st.safe_stops,
            }
        )
    return {
        "cycles": s.cycles,
        "missed": missed,
        "safe_stops": safe_stops,
        "period_us": cycle_time_us,
        "cycle_time_us": s.to_json(),
        "overruns": s.overruns,
        "buses": buses,
    }
