"""``fieldbus bandwidth NETWORK.yaml [--rate HZ] [--json] [--plot FILE]``.

Per bus: frames and bytes per cycle, wire time, bus load at the cycle rate and
the highest cycle rate the bus sustains; then the bottleneck bus. Assumptions
and sources: docs/bandwidth.md.

Exit codes: 0 every bus fits its cycle; 1 file or argument error; 3 a bus
needs more than 100 % of its bus time at the rate (the figures are printed all
the same, ``overloaded`` in ``--json``).
"""

from __future__ import annotations

import argparse
import json
import sys
from typing import Any

from fieldbus.commands.argtypes import positive
from fieldbus.commands.outputs import check_plot
from fieldbus.commands.usage import add_command
from fieldbus.core.bandwidth import BusResult, NetworkResult, network_bandwidth, overload
from fieldbus.errors import BackendUnavailableError

EXIT_OVERLOADED = 3  # a bus needs more than its bus time: the network cannot run at that rate


def register(sub: Any) -> None:
    p = add_command(
        sub,
        "bandwidth",
        help="wire time, bus load and max cycle rate of every bus of a network",
        doc=__doc__,
        codes=[
            (0, "the table (or JSON) was printed: every bus fits its cycle"),
            (1, "the network file or a map in it is invalid"),
            (EXIT_OVERLOADED, "a bus is over 100 % load at the rate (the figures still print)"),
        ],
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
    fig = plt.figure()
    draw_cycles(fig, result)
    fig.savefig(path)
    plt.close(fig)


# chart geometry in inches: the bars' area is fixed before any label is measured, so that a label
# found to fit its bar still fits in the saved figure
_WIDTH, _LEFT, _RIGHT = 10.0, 1.7, 0.3
_ROW, _TOP, _AXIS = 1.0, 0.45, 0.55  # height per bus; title above; x axis and its label below
_KEY_ROW, _KEY_COLUMNS = 0.14, 3  # legend: height per line, entries per line


def draw_cycles(fig: Any, result: NetworkResult) -> None:
    """One cycle per bus on matplotlib figure ``fig`` (sized here): a bar per frame (µs from the
    cycle start), the first bus on top, the cycle period dashed red. A frame's label sits in its bar,
    across or else upright, where it fits there; the others are named in a legend under the chart
    (colour, bus, label, duration), so no two labels ever overlap."""
    from matplotlib import colormaps
    from matplotlib.patches import Patch

    n = max(1, len(result.buses))
    chart_h = _ROW * n
    fig.set_size_inches(_WIDTH, _TOP + chart_h + _AXIS)
    ax = fig.add_axes((_LEFT / _WIDTH, 0.0, 1 - (_LEFT + _RIGHT) / _WIDTH, 0.5))  # placed again below
    tab20 = colormaps["tab20"]
    colours = [tab20(i) for i in range(20)]  # 20 colours: neighbouring frames never share one
    end = max(
        [1e6 / b.rate_hz for b in result.buses]
        + [s.start_us + s.duration_us for b in result.buses for s in b.timeline]
        + [1.0]
    )
    ax.set_xlim(0, end * 1.02)
    ax.set_ylim(n - 0.5, -0.5)  # bus 0 on top
    ax.set_yticks(range(n), [f"{b.name} ({b.type})" for b in result.buses])
    ax.set_xlabel("time from cycle start (µs); red dashes: cycle period")
    ax.set_title(f"one cycle per bus, bottleneck: {result.bottleneck}")
    renderer = _renderer(fig)
    dpi = fig.dpi
    bar_px = 0.7 * _ROW * dpi
    keyed: list[Any] = []
    for row, b in enumerate(result.buses):
        slots = [s for s in b.timeline if s.duration_us > 0]
        for k, s in enumerate(slots):
            colour = colours[k % len(colours)]
            ax.broken_barh([(s.start_us, s.duration_us)], (row - 0.35, 0.7), facecolors=colour)
            left, right = (
                ax.transData.transform((x, 0))[0] for x in (s.start_us, s.start_us + s.duration_us)
            )
            width_px = 0.9 * (right - left)
            text = ax.text(s.start_us + s.duration_us / 2, row, s.label, ha="center", va="center", fontsize=6)
            box = text.get_window_extent(renderer)
            if box.width <= width_px and box.height <= bar_px:
                continue  # across the bar
            if box.height <= width_px and box.width <= 0.9 * bar_px:
                text.set_rotation(90)  # upright in a narrow bar
                continue
            text.remove()
            keyed.append(Patch(color=colour, label=f"{b.name}: {s.label} ({s.duration_us:.1f} µs)"))
        ax.plot([1e6 / b.rate_hz] * 2, [row - 0.5, row + 0.5], color="red", linestyle="--")
    lines = -(-len(keyed) // _KEY_COLUMNS)
    key_h = _KEY_ROW * lines + (0.25 if keyed else 0.0)
    height = _TOP + chart_h + _AXIS + key_h
    fig.set_size_inches(_WIDTH, height)  # taller, not wider: the bars keep their widths in pixels
    ax.set_position(
        (_LEFT / _WIDTH, (key_h + _AXIS) / height, 1 - (_LEFT + _RIGHT) / _WIDTH, chart_h / height)
    )
    if keyed:
        fig.legend(
            handles=keyed, fontsize=6, ncol=_KEY_COLUMNS, loc="lower left", frameon=False,
            bbox_to_anchor=(_LEFT / _WIDTH, 0.05 / height), borderaxespad=0.0,
        )  # fmt: skip


def _renderer(fig: Any) -> Any:
    """The figure's renderer (text sizes in pixels); an Agg canvas where the figure has none yet."""
    get = getattr(fig.canvas, "get_renderer", None)
    if get is None:
        from matplotlib.backends.backend_agg import FigureCanvasAgg

        get = FigureCanvasAgg(fig).get_renderer
    return get()


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
    over = result.overloaded
    if over:
        worst = max(over, key=lambda b: b.load_percent)
        more = f" ({len(over) - 1} more bus(es) over 100 %)" if len(over) > 1 else ""
        print(f"error: {args.network}: {overload(worst)}{more}", file=sys.stderr)
        return EXIT_OVERLOADED
    return 0
