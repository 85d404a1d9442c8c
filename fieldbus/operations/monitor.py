"""``--monitor``: a live view of a running network, drawn from a side thread with rich.

:class:`Monitor` reads what the cycle already keeps - each bus's
:class:`~fieldbus.network.BusStatus` and working-counter policy counters, each
slave's freshness, its AL or NMT state where the backend knows it, its CiA 402
state from the statusword in the process image, the last EMCY, the last clamp
(the newest command value the output path refused: channel, reason, asked,
sent) - and the cycle's latency histograms. It takes no lock and writes
nothing the cycle reads: the cycle does not know it is watched. rich's own refresh thread calls
:meth:`Monitor.render` at most ``refresh_hz`` times a second (default 10).
"""

from __future__ import annotations

import contextlib
import time
from contextlib import AbstractContextManager
from typing import Any, Self

from fieldbus.core.cia402 import decode_state
from fieldbus.core.esc_errors import format_rise
from fieldbus.core.status_fields import as_plain
from fieldbus.errors import BackendUnavailableError
from fieldbus.network import Operational
from fieldbus.platform.timing import CycleLatency

REFRESH_HZ = 10.0
# BusStatus fields a bus's entry leaves out (every other one is in it, by name: derived from the dataclass)
EXCLUDED = {"fresh": "slaves[i].fresh"}


class Monitor:
    """Live view of ``op``; use as a context manager around the cycle loop."""

    def __init__(
        self,
        op: Operational,
        *,
        latency: CycleLatency | None = None,
        refresh_hz: float = REFRESH_HZ,
        console: Any = None,
    ) -> None:
        self.op = op
        self.latency = latency
        self.refresh_hz = min(refresh_hz, REFRESH_HZ)
        self._console = console
        self._live: Any = None
        self._t0 = time.monotonic()
        self._cycle0 = op.result.cycle

    def snapshot(self) -> dict[str, Any]:
        """What the view shows, as plain data (also for tests and ``--json`` consumers)."""
        op = self.op
        res = op.result
        elapsed = max(time.monotonic() - self._t0, 1e-9)
        out: dict[str, Any] = {
            "cycle": res.cycle,
            "rate_hz": (res.cycle - self._cycle0) / elapsed,
            "exchange_us": res.exchange_ns / 1e3,
            "safe_stop": res.safe_stop,
            "buses": [],
        }
        if self.latency is not None:
            out["latency_us"] = self.latency.to_json()
        for view in op.buses:
            b, policy, st = view.backend, view.policy, view.status
            slaves = []
            watch = b.error_watch  # EtherCAT with error_counters: ESC counters in OP
            rises = watch.since_baseline() if watch is not None else None
            for i, area in enumerate(b.areas):
                group = b.groups[area.group]
                sw = _statusword(group.image, area.row)
                emcy = b.last_emergency_name(i)
                slaves.append(
                    {
                        "name": area.slave.name,
                        "state": view.slave_state(i),
                        "cia402": _name402(sw),
                        "fresh": bool(policy.fresh[i]),
                        "stale_cycles": int(policy.stale_cycles[i]),
                        "last_emcy": emcy,
                        "esc_errors": format_rise(rises[i]) if rises is not None and i < len(rises) else None,
                        "last_clamp": _last_clamp(view.rules, area),
                    }
                )
            out["buses"].append(
                {
                    **as_plain(st, exclude=EXCLUDED),  # name, verdict (by name), wkc, safe_stop, ...
                    "type": b.kind,
                    "misses": policy.stats.misses,
                    "counters": view.counters(),
                    "suspect_link": _suspect(watch, [a.slave.name for a in b.areas]),
                    "slaves": slaves,
                }
            )
        return out

    def render(self) -> Any:
        """The view as a rich renderable (called by rich's refresh thread)."""
        from rich.console import Group
        from rich.table import Table

        snap = self.snapshot()
        head = (
            f"cycle {snap['cycle']}  {snap['rate_hz']:.0f} cycles/s  exchange {snap['exchange_us']:.0f} µs"
            + ("  [bold red]SAFE STOP[/]" if snap["safe_stop"] else "")
        )
        lat = snap.get("latency_us")
        if lat:
            w, x = lat["wakeup"], lat["exchange"]
            head += f"  wake-up p99 {w['p99']:g} max {w['max']:g} µs  exchange p99 {x['p99']:g} max {x['max']:g} µs"
        parts: list[Any] = [head]
        for bus in snap["buses"]:
            t = Table(
                title=(
                    f"{bus['name']} ({bus['type']}): {bus['verdict']}  WKC {bus['wkc']}/{bus['expected_wkc']}  "
                    f"misses {bus['misses']} (in a row {bus['consecutive_misses']})"
                    + ("  recovering" if bus["recovering"] else "")
                    + (f"  recoveries {bus['recoveries']}" if bus["recoveries"] else "")
                    + (f"\n[red]{bus['recovery_error']}[/]" if bus["recovery_error"] else "")
                    + (f"\n[red]suspect: {bus['suspect_link']}[/]" if bus.get("suspect_link") else "")
                ),
                title_justify="left",
                expand=False,
            )
            counted = any(s["esc_errors"] is not None for s in bus["slaves"])
            clamped = any(s["last_clamp"] is not None for s in bus["slaves"])
            for col in (
                ("slave", "AL/NMT", "CiA 402", "inputs", "last EMCY")
                + (("ESC errors",) if counted else ())
                + (("last clamp",) if clamped else ())
            ):
                t.add_column(col)
            for s in bus["slaves"]:
                fresh = "[green]fresh[/]" if s["fresh"] else f"[red]stale {s['stale_cycles']}[/]"
                row = [s["name"], s["state"], s["cia402"], fresh, s["last_emcy"] or ""]
                row += [s["esc_errors"] or ""] if counted else []
                row += [_clamp_text(s["last_clamp"])] if clamped else []
                t.add_row(*row)
            parts.append(t)
        return Group(*parts)

    def __enter__(self) -> Self:
        from rich.console import Console
        from rich.live import Live

        console = self._console or Console(stderr=True)
        self._t0 = time.monotonic()
        self._cycle0 = self.op.result.cycle
        self._live = Live(
            get_renderable=self.render,
            console=console,
            refresh_per_second=self.refresh_hz,
            auto_refresh=True,
            transient=False,
        )
        self._live.start()
        return self

    def __exit__(self, *exc: object) -> None:
        if self._live is not None:
            self._live.stop()
            self._live = None


def monitor_context(
    op: Operational, latency: CycleLatency | None, enabled: bool
) -> AbstractContextManager[Any]:
    """The live view (``--monitor``) around a cycle loop, or nothing; a clear error without rich."""
    if not enabled:
        return contextlib.nullcontext()
    try:
        import rich  # noqa: F401
    except ImportError as exc:
        raise BackendUnavailableError("--monitor needs rich: pip install 'fieldbus[monitor]'") from exc
    return Monitor(op, latency=latency)


def _suspect(watch: Any, names: list[str]) -> str | None:
    """The cable where most errors started since the watch's first read (None: none, or no watch)."""
    if watch is None:
        return None
    found = watch.suspects()
    return str(found[0].link.describe(names)) + f" ({found[0].errors} errors)" if found else None


def _last_clamp(rules: Any, area: Any) -> dict[str, Any] | None:
    """The newest command value the output path refused on ``area``'s rows (S11), as plain data, or None."""
    if area.group >= len(rules):
        return None
    group = rules[area.group]
    found = [c for r in range(area.row, area.row + area.axes) if (c := group.last_clamp(r)) is not None]
    if not found:
        return None
    c = max(found, key=lambda e: e.cycle)
    return {
        "cycle": c.cycle,
        "axis": c.axis,
        "channel": c.channel,
        "reason": c.reason.name,
        "asked": c.asked,
        "sent": c.sent,
    }


def _clamp_text(c: dict[str, Any] | None) -> str:
    """``target_position RANGE: asked 1e+06, sent 3 (cycle 12)``."""
    if c is None:
        return ""
    return f"{c['channel']} {c['reason']}: asked {c['asked']:g}, sent {c['sent']:g} (cycle {c['cycle']})"


def _statusword(image: Any, row: int) -> int | None:
    try:
        return int(image.inputs["statusword"][row])
    except (KeyError, Exception):  # no statusword channel in this map
        return None


def _name402(sw: int | None) -> str:
    if sw is None:
        return "-"
    state = decode_state(sw)
    return state.name.replace("_", " ").lower() if state is not None else f"0x{sw:04X}"
