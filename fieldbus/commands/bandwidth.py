"""``fieldbus bandwidth NETWORK.yaml [--rate HZ] [--json] [--plot FILE]``.

Per bus: frames and bytes per cycle, wire time, bus load at the cycle rate and
the highest cycle rate the bus sustains; then the bottleneck bus. Assumptions
and sources: docs/bandwidth.md.
"""

from __future__ import annotations

import argparse
import json
from typing import Any

from fieldbus.commands.argtypes import positive
from fieldbus.commands.outputs import check_plot
from fieldbus.commands.usage import add_command
from fieldbus.core.bandwidth import BusResult, NetworkResult, network_bandwidth
from fieldbus.errors import BackendUnavailableError


def register(sub: Any) -> None:
    p = add_command(
        sub,
        "bandwidth",
        help="wire time, bus load and max cycle rate of every bus of a network",
        doc=__doc__,
        codes=[(0, "the table (or JSON) was printed"), (1, "the network file or a map in it is invalid")],
    )
    p.add_argument("network", metavar="NETWORK.yaml", help="network file")
    p.add_argument(
        "--rate",
        type=positive("Hz"),
        default=None,
        metavar="HZ",
        help="cycle rate (default: the cycle times)",
    )
    p.add_argument("--json", action="store_true", help="one JSON object on stdout")
    p.add_argument("--plot", metavar="FILE", default=None, help="draw one cycle per bus (needs matplotlib)")
    p.set_defaults(func=run)


def _fmt(x: float | None, spec: str = ".1f") -> str:
    return "-" if x is None else format(x, spec)


def table(result: NetworkResult) -> str:
    """Human-readable table of ``result``: one row per bus, then the bottleneck."""
    head = (
        f"{'bus':<12} {'type':<9} {'rate Hz':>8} {'frames':>6} {'bytes':>6} "
        f"{'wire us':>9} {'load %':>7} {'max Hz':>9} {'extra'}"
    )
    lines = [head, "-" * len(head)]
    for b in result.buses:
        lines.append(
            f"{b.name:<12} {b.type:<9} {b.rate_hz:>8.0f} {b.frames_per_cycle:>6d} {b.bytes_per_cycle:>6d} "
            f"{b.wire_time_us:>9.1f} {b.load_percent:>7.1f} {_fmt(b.max_rate_hz, '.0f'):>9} {_extra(b)}"
        )
    worst = result.bottleneck
    if worst is not None:
        b = next(x for x in result.buses if x.name == worst)
        verdict = "OK" if b.load_percent <= 100.0 else "OVERLOADED"
        lines.append(f"bottleneck: {worst} ({b.load_percent:.1f} % at {b.rate_hz:.0f} Hz, {verdict})")
    return "\n".join(lines)


def _extra(b: BusResult) -> str:
    if b.type == "ethercat":
        rtt = b.extra("round_trip_us")
        return f"round trip {_fmt(rtt if isinstance(rtt, float) else None)} us"
    if b.type in ("canopen", "rawcan"):
        resp = b.extra("worst_response_us")
        bits = b.extra("worst_case_bits")
        r = _fmt(resp if isinstance(resp, float) else None)
        return f"{bits} bits worst case, lowest-priority response {r} us"
    return ""


def plot(result: NetworkResult, path: str) -> None:
    """Draw one cycle of every bus as a timeline (µs) into ``path``."""
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError as exc:
        raise BackendUnavailableError("pip install 'fieldbus[plot]'") from exc
    n = max(1, len(result.buses))
    fig, ax = plt.subplots(figsize=(10, 1.0 + 0.8 * n))
    colours = plt.get_cmap("tab20")
    for row, b in enumerate(result.buses):
        bars = [(s.start_us, s.duration_us) for s in b.timeline]
        ax.broken_barh(bars, (row - 0.35, 0.7), facecolors=[colours(i % 20) for i in range(len(bars))])
        for s in b.timeline:
            if s.duration_us > 0:
                ax.text(s.start_us + s.duration_us / 2, row, s.label, ha="center", va="center",
                        fontsize=6, rotation=90 if len(b.timeline) > 8 else 0)  # fmt: skip
        ax.axvline(1e6 / b.rate_hz, ymin=row / n, ymax=(row + 1) / n, color="red", linestyle="--")
    ax.set_yticks(range(n), [f"{b.name} ({b.type})" for b in result.buses])
    ax.set_xlabel("time from cycle start (µs); red dashes: cycle period")
    ax.set_title(f"one cycle per bus, bottleneck: {result.bottleneck}")
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


def run(args: argparse.Namespace) -> int:
    from fieldbus.core.network import load_network

    check_plot(args.plot, "--plot")
    net = load_network(args.network)
    result = network_bandwidth(net, args.rate)
    if args.plot:
        plot(result, args.plot)
    if args.json:
        print(json.dumps(result.to_json()))
    else:
        print(table(result))
    return 0
