"""``fieldbus plot FILE -o out.png``: a recording at a glance.

Per axis group: targets (outputs, dashed) and actuals (inputs) of every axis,
and the tracking error (actual minus the target sent one cycle earlier); then
the wake-up latency and ``exchange()`` time histograms ("not measured" where the
recording has none), and the misses over time per bus with the recording's events
marked, a colour and line style per kind (:data:`EVENT_STYLES`) and a legend.
"""

from __future__ import annotations

import argparse
from collections import Counter
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from fieldbus.commands.cycleopts import draw_histogram
from fieldbus.commands.outputs import check_plot
from fieldbus.commands.usage import add_command
from fieldbus.errors import BackendUnavailableError
from fieldbus.recording import Recording, load
from fieldbus.recording.summary import histogram

PREFERRED = ("position", "velocity", "torque")


def register(sub: Any) -> None:
    p = add_command(
        sub,
        "plot",
        help="plot a recording (--record) into a PNG",
        doc=__doc__,
        codes=[
            (0, "the plot was written"),
            (1, "the recording cannot be read, the output cannot be written, or matplotlib is missing"),
        ],
        json=False,
    )
    p.add_argument("file", metavar="FILE.mcap", help="a recording (demo, run or soak --record)")
    p.add_argument(
        "-o", "--output", required=True, metavar="OUT.png", help="the image (.png; .pdf, .svg, ... by suffix)"
    )
    p.set_defaults(func=run)


def tracked(rec: Recording, group: str) -> tuple[str, str] | None:
    """(output, input) channel names of the group's tracked quantity: ``target_position`` and
    ``position_actual_value`` (CiA 402), or one name in both directions (MIT mode); position first."""
    arr = rec.groups[group]
    outs = arr.dtype["outputs"].base.names or ()
    ins = arr.dtype["inputs"].base.names or ()
    pairs = []
    for o in outs:
        q = o.removeprefix("target_")
        for i in (f"{q}_actual_value", f"{q}_actual", q):
            if i in ins:
                pairs.append((o, i))
                break
    if not pairs:
        return None
    pairs.sort(key=lambda p: next((k for k, w in enumerate(PREFERRED) if w in p[1]), len(PREFERRED)))
    return pairs[0]


def _seconds(rec: Recording) -> npt.NDArray[np.float64]:
    t = rec.cycles["t_ns"]
    return (t - t[0]) / 1e9 if t.size else np.zeros(0)


def run(args: argparse.Namespace) -> int:
    check_plot(args.output, "-o")
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError as exc:
        raise BackendUnavailableError("fieldbus plot needs matplotlib: pip install 'fieldbus[plot]'") from exc
    rec = load(args.file)
    fig = plt.figure(figsize=figure_size(rec), dpi=90)
    draw_recording(fig, rec)
    fig.tight_layout()
    fig.savefig(args.output)
    plt.close(fig)
    print(f"wrote {args.output}")
    return 0


# how each event kind is marked on the misses panel: (colour, line style, width); safe stops solid red,
# recoveries green, bus and device messages in their own colours; a kind not listed is grey
EVENT_STYLES: dict[str, tuple[str, str, float]] = {
    "safe_stop": ("tab:red", "-", 1.4),
    "safe_stop_cleared": ("tab:pink", "--", 1.0),
    "recovery_started": ("tab:orange", "-.", 1.0),
    "recovery_finished": ("tab:olive", "--", 1.0),
    "recovered": ("tab:green", "-", 1.2),
    "recovery_error": ("tab:brown", ":", 1.2),
    "emcy": ("tab:purple", ":", 1.0),
    "nmt_state": ("tab:blue", "-.", 0.8),
    "sdo_abort": ("tab:cyan", "--", 0.8),
    "fault": ("tab:red", ":", 0.8),  # a bus fault's kind changed (BusStatus.fault)
    "gap": ("black", ":", 0.8),
}
OTHER_EVENT = ("tab:gray", ":", 0.8)
UNMARKED_EVENTS = ("cia402_state",)  # one per axis and step: too many to mark


def _groups(rec: Recording) -> list[tuple[str, tuple[str, str]]]:
    return [(g, pair) for g in rec.groups if (pair := tracked(rec, g)) is not None]


def figure_size(rec: Recording) -> tuple[float, float]:
    """(width, height) in inches of :func:`draw_recording`'s figure."""
    return 10.0, 2.4 * (2 * len(_groups(rec)) + 2)


def title(rec: Recording) -> str:
    """The figure's title: the recording's file name and its network file's name where that file
    still exists (a demo's or a soak's generated network is a temporary file, gone by now)."""
    network = rec.meta.get("network", "")
    if network and Path(network).is_file():
        return f"{rec.path.name}: network {Path(network).name}"
    return rec.path.name


def draw_recording(fig: Any, rec: Recording) -> None:
    """The recording at a glance on matplotlib figure ``fig`` (see the module docstring)."""
    t = _seconds(rec)
    groups = _groups(rec)
    rows = 2 * len(groups) + 2
    spec = fig.add_gridspec(rows, 2)
    r = 0
    for g, (o, i) in groups:
        arr = rec.groups[g]
        target, actual = arr["outputs"][o], arr["inputs"][i]
        unit = rec.units.get(g, {}).get("inputs", {}).get(i, "")
        ax = fig.add_subplot(spec[r, :])
        for j, name in enumerate(rec.axes[g]):
            line = ax.plot(t, actual[:, j], lw=0.8, label=name)[0]
            ax.plot(t, target[:, j], lw=0.8, ls="--", color=line.get_color())
        ax.set_title(f"{g}: {o} (dashed) and {i}", fontsize=9)
        ax.set_ylabel(unit)
        if len(rec.axes[g]) <= 12:
            ax.legend(fontsize=6, ncol=6, loc="upper right")
        ax = fig.add_subplot(spec[r + 1, :], sharex=ax)
        if t.size > 1:
            ax.plot(t[1:], actual[1:] - target[:-1], lw=0.6)
        ax.set_title(f"{g}: tracking error ({i} minus the {o} sent one cycle earlier)", fontsize=9)
        ax.set_ylabel(unit)
        r += 2
    for col, (name, key) in enumerate((("wake-up latency", "wakeup_ns"), ("exchange() time", "exchange_ns"))):
        draw_histogram(fig.add_subplot(spec[r, col]), name, histogram(rec.cycles[key]))
    ax = fig.add_subplot(spec[r + 1, :])
    for bus, b in rec.buses.items():
        missed = np.cumsum((b["verdict"] != 0) & b["ran"])
        ax.step(t, missed, where="post", label=f"{bus}: {int(missed[-1]) if missed.size else 0} misses")
    _mark_events(ax, rec, t)
    first = int(rec.cycles["cycle"][0]) if t.size else 0
    ax.set_title(
        f"misses over time (cumulative; cycles {first}..{first + t.size - 1}) and events", fontsize=9
    )
    ax.set_xlabel("s since the first recorded cycle")
    ax.set_ylabel("cycles")
    ax.legend(fontsize=7, loc="upper left", ncol=2)
    fig.suptitle(title(rec), fontsize=10)


def _mark_events(ax: Any, rec: Recording, t: npt.NDArray[np.float64]) -> None:
    """A vertical line per event at its cycle, styled by kind; one legend entry per kind with its count."""
    counts = Counter(e["kind"] for e in rec.events if e["kind"] not in UNMARKED_EVENTS)
    labelled: set[str] = set()
    for e in rec.events:
        kind = e["kind"]
        if kind in UNMARKED_EVENTS:
            continue
        k = int(np.searchsorted(rec.cycles["cycle"], e["cycle"]))
        if k >= t.size:
            continue
        colour, style, width = EVENT_STYLES.get(kind, OTHER_EVENT)
        label = None if kind in labelled else f"{kind.replace('_', ' ')} ({counts[kind]})"
        ax.axvline(t[k], color=colour, ls=style, lw=width, label=label)
        labelled.add(kind)
