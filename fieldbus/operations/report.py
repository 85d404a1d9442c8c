"""Cycle-run statistics as the CLI prints them (``demo``, ``run``): one dict, stable keys."""

from __future__ import annotations

from typing import Any

from fieldbus.network import Operational
from fieldbus.platform.timing import CycleTimer


def run_report(op: Operational, timer: CycleTimer, cycle_time_us: float) -> dict[str, Any]:
    """``cycles``, ``missed``, ``safe_stops``, ``cycle_time_us: {mean, p99, max}`` and per-bus detail.

    ``cycle_time_us`` is the time spent in each cycle's work (exchange plus the
    controller step), not the period; ``period_us`` is the period.
    """
    s = timer.summary()
    buses = []
    missed = 0
    safe_stops = 0
    for view in op.buses:
        b, st = view.backend, view.policy.stats
        missed += st.misses
        safe_stops += st.safe_stops
        counters = view.counters()
        buses.append(
            {
                "name": view.name,
                "type": view.kind,
                "slaves": b.n_slaves,
                "expected_wkc": b.expected_wkc,
                "cycles": st.cycles,
                "missed": st.misses,
                "timeouts": st.timeouts,
                "short": st.short,
                "errors": st.errors,
                "longest_streak": st.longest_streak,
                "recoveries": st.recoveries,
                "safe_stops": st.safe_stops,
                "releases": st.releases,
                "last_error": view.status.last_error,
                "late_replies": counters["late_replies"],
                "stale_frames": counters["stale_frames"],
                "late_frames": counters["late_frames"],
                "extra_frames": counters["extra_frames"],
                "tx_errors": counters["tx_errors"],
                "bus_off": counters["bus_off"],
                "drive_faults": {
                    g.name: [int(x) for x in op.result.drive_faults[g.name]]
                    for g in b.groups
                    if g.name in op.result.drive_faults
                },
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
