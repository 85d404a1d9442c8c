"""Figures of a loaded recording, as ``fieldbus report`` prints them and ``fieldbus plot`` titles them."""

from __future__ import annotations

from collections import Counter
from typing import Any

import numpy as np
import numpy.typing as npt

from fieldbus.platform.timing import LatencyHistogram
from fieldbus.recording.load import Recording
from fieldbus.recording.schema import NO_VALUE


def histogram(ns: npt.NDArray[np.int64], max_us: int = 20_000) -> LatencyHistogram:
    """The recorded durations (ns; :data:`NO_VALUE` left out) in a :class:`LatencyHistogram` (1 µs bins)."""
    hist = LatencyHistogram(max_us)
    v = ns[ns != NO_VALUE]
    if v.size:
        us = np.clip(v // 1000, 0, max_us)
        hist.counts += np.bincount(us, minlength=max_us + 1)[: max_us + 1]
        hist.n = int(v.size)
        hist.max_ns = int(v.max())
    return hist


def summary(rec: Recording) -> dict[str, Any]:
    """``cycles``, ``seconds``, per-bus misses, event counts and events, latency p50/p99/p99.9/max (µs)."""
    c = rec.cycles
    n = int(c.size)
    seconds = float(c["t_ns"][-1] - c["t_ns"][0]) / 1e9 if n > 1 else 0.0
    first = int(c["cycle"][0]) if n else 0
    missing = int(c["cycle"][-1]) - first + 1 - n if n else 0  # cycles not recorded (dropped blocks)
    buses = {}
    for name, b in rec.buses.items():
        ran = b["ran"]
        buses[name] = {
            "cycles": int(ran.sum()),
            "missed": int(((b["verdict"] != 0) & ran).sum()),
            "timeouts": int(((b["verdict"] == 2) & ran).sum()),
            "short": int(((b["verdict"] == 1) & ran).sum()),
            "longest_streak": int(b["consecutive_misses"].max()) if b.size else 0,
            "recoveries": int(b["recoveries"][-1] - b["recoveries"][0]) if b.size else 0,
        }
    return {
        "file": str(rec.path),
        "network": rec.meta.get("network", ""),
        "cycle_time_us": float(rec.meta.get("cycle_time_us", 0) or 0),
        "cycles": n,
        "first_cycle": first,
        "seconds": round(seconds, 3),
        "not_recorded": missing,
        "complete": rec.complete,
        "dropped_blocks": rec.dropped_blocks,
        "missed": sum(b["missed"] for b in buses.values()),
        "buses": buses,
        "events": dict(Counter(e["kind"] for e in rec.events)),
        "event_list": rec.events,
        "latency_us": {
            "wakeup": histogram(c["wakeup_ns"]).to_json(),
            "exchange": histogram(c["exchange_ns"]).to_json(),
        },
    }


def describe(s: dict[str, Any], max_events: int = 20) -> str:
    """The summary as text."""
    lines = [
        f"{s['file']}: {s['cycles']} cycles in {s['seconds']} s (network {s['network']}, "
        f"cycle {s['cycle_time_us']:g} us){'' if s['complete'] else ', file cut short'}",
    ]
    if s["not_recorded"] or s["dropped_blocks"]:
        lines.append(f"  not recorded: {s['not_recorded']} cycles ({s['dropped_blocks']} blocks dropped)")
    for name, b in s["buses"].items():
        lines.append(
            f"  bus {name}: missed {b['missed']} of {b['cycles']} (timeouts {b['timeouts']}, short {b['short']}), "
            f"longest streak {b['longest_streak']}, recoveries {b['recoveries']}"
        )
    for key, title in (("wakeup", "wake-up latency"), ("exchange", "exchange() time")):
        h = s["latency_us"][key]
        if h["cycles"]:
            lines.append(f"  {title}: p50 {h['p50']:g} us, p99 {h['p99']:g} us, max {h['max']:g} us")
        else:
            lines.append(f"  {title}: not measured")
    counts = ", ".join(f"{k} {v}" for k, v in sorted(s["events"].items())) or "none"
    lines.append(f"  events: {counts}")
    for e in s["event_list"][:max_events]:
        who = " ".join(str(e[k]) for k in ("bus", "slave") if e.get(k))
        change = f" {e.get('old')} -> {e.get('new')}" if "new" in e else ""
        detail = f" ({e['detail']})" if e.get("detail") else ""
        lines.append(f"    cycle {e['cycle']}: {e['kind']} {who}{change}{detail}")
    if len(s["event_list"]) > max_events:
        lines.append(f"    ... {len(s['event_list']) - max_events} more (--json lists all)")
    return "\n".join(lines)
