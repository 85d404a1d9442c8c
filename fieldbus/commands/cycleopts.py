"""What ``demo``, ``run`` and ``soak`` share: the real-time and recording flags, latency histograms, their plot."""

from __future__ import annotations

import argparse
import sys
import time
from collections.abc import Callable
from contextlib import AbstractContextManager
from typing import TYPE_CHECKING, Any

from fieldbus.commands.argtypes import integer
from fieldbus.errors import BackendUnavailableError
from fieldbus.network import Operational
from fieldbus.operations.monitor import monitor_context
from fieldbus.platform.clock import Clock
from fieldbus.platform.loop import default_status_stream, run_cycles
from fieldbus.platform.rt import RtConfig, RtState, realtime
from fieldbus.platform.timing import CycleLatency, CycleTimer, LatencyHistogram

if TYPE_CHECKING:
    from fieldbus.recording import Recorder
    from fieldbus.recording.ring import Ring


def add_arguments(p: argparse.ArgumentParser, *, plot: bool = True) -> None:
    """``--rt-priority``, ``--cpu``, ``--lock-memory``, ``--rt-strict``, ``--record`` (and ``--plot``)."""
    r = p.add_argument_group("recording")
    r.add_argument(
        "--record",
        metavar="FILE",
        help="record every cycle to this MCAP file (fieldbus plot / report read it; needs fieldbus[record])",
    )
    r.add_argument("--record-raw", action="store_true", help="with --record: also the wire bytes")
    g = p.add_argument_group("real time (the cycle thread)")
    g.add_argument(
        "--rt-priority",
        type=integer(1, 99),
        metavar="N",
        help="run the cycle at SCHED_FIFO priority N (1-99)",
    )
    g.add_argument("--cpu", type=integer(0), metavar="N", help="pin the cycle thread to CPU N")
    g.add_argument(
        "--lock-memory", action="store_true", help="mlockall(MCL_CURRENT|MCL_FUTURE) and prefault the heap"
    )
    g.add_argument(
        "--rt-strict",
        action="store_true",
        help="a refused real-time setting is an error (default: a warning line)",
    )
    if plot:
        p.add_argument(
            "--plot",
            metavar="FILE",
            help="PNG of the wake-up latency and exchange() time histograms (needs matplotlib)",
        )


def rt_config(args: argparse.Namespace) -> RtConfig:
    return RtConfig(
        priority=args.rt_priority, cpu=args.cpu, lock_memory=args.lock_memory, strict=args.rt_strict
    )


def rt_context(args: argparse.Namespace, *, fifo_later: bool = False) -> AbstractContextManager[RtState]:
    """The real-time settings the flags ask for, warnings to stderr (one line each); ``fifo_later``: the
    priority when the caller calls :meth:`RtState.start_fifo` (see :func:`realtime`)."""
    return realtime(rt_config(args), warn=lambda line: print(line, file=sys.stderr), fifo_later=fifo_later)


def cycle_priority(rt: RtState, before: set[int], *, others_below: int) -> None:
    """The cycle thread at its SCHED_FIFO priority now (``realtime(..., fifo_later=True)``), and the
    threads made since ``before`` (thread ids: a DDS participant's, an in-process emulator's) at that
    priority less ``others_below`` (serve: 1, so that a command is in the reader before the cycle that
    takes it; the demo: 0, the priority they inherited when the whole set-up ran at SCHED_FIFO). Called
    after the set-up (seconds of Python that, at SCHED_FIFO, used up the kernel's real-time budget of
    their second and got the first cycles throttled, docs/realtime.md) and before the bring-up."""
    from fieldbus.platform.rt import raise_threads, thread_ids

    rt.start_fifo()
    if rt.fifo is not None:
        where = "below the cycle" if others_below else "at the cycle's priority"
        rt.applied.append(raise_threads(set(thread_ids()) - before, rt.fifo - others_below, where=where))


def check_record(args: argparse.Namespace) -> None:
    """``--record FILE``: create the file now, before any bus starts (:class:`FieldbusError` naming it)."""
    if getattr(args, "record", None):
        from fieldbus.recording import check_writable

        check_writable(args.record)


def start_recording(op: Operational, args: argparse.Namespace) -> Recorder | None:
    """``op.record(FILE)`` when ``--record FILE`` was given (stops when the network closes)."""
    if not getattr(args, "record", None):
        return None
    return op.record(args.record, raw=args.record_raw)


class WakeupTap(LatencyHistogram):
    """The wake-up histogram that also hands each cycle's latency (ns) to the recordings' rings."""

    def __init__(self, rings: list[Ring], max_us: int = 20_000) -> None:
        super().__init__(max_us)
        self.rings = rings

    def add(self, duration_ns: int) -> None:
        super().add(duration_ns)
        for ring in self.rings:
            ring.wakeup_ns = duration_ns


def run_timed(
    op: Operational,
    step: Callable[[int], bool | None],
    period_us: float,
    cycles: int,
    *,
    status: bool,
    describe: Callable[[], str] | None = None,
    monitor: bool = False,
    clock: Clock | None = None,
) -> tuple[CycleTimer, CycleLatency]:
    """:func:`run_cycles` with wake-up latency and ``exchange()`` time histograms.

    ``status``: a progress line on a terminal; ``monitor``: the live view instead; ``clock``: how the
    loop waits (default: a relative sleep and a spin).
    """
    latency = CycleLatency()
    if op.recorders:
        latency.wakeup = WakeupTap([r.ring for r in op.recorders])
    exchange = latency.exchange

    def timed(k: int) -> bool | None:
        stop = step(k)
        exchange.add(op.result.exchange_ns)
        return stop

    with monitor_context(op, latency, monitor):
        timer = run_cycles(
            timed,
            period_us,
            cycles,
            status=default_status_stream(status and not monitor),
            describe=describe,
            latency=latency,
            clock=clock if clock is not None else time.perf_counter_ns,
        )
    return timer, latency


def add_monitor_argument(p: argparse.ArgumentParser) -> None:
    """``--monitor``."""
    p.add_argument(
        "--monitor",
        action="store_true",
        help="live view of every bus and slave on the terminal, 10 times a second (needs rich)",
    )


def plot_latency(latency: CycleLatency, path: str, title: str) -> None:
    """Both histograms (log counts over µs) into a PNG at ``path``."""
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError as exc:
        raise BackendUnavailableError("--plot needs matplotlib: pip install 'fieldbus[plot]'") from exc
    fig, axes = plt.subplots(1, 2, figsize=(9.6, 3.4), dpi=90)
    for ax, (name, hist) in zip(
        axes, (("wake-up latency", latency.wakeup), ("exchange() time", latency.exchange)), strict=True
    ):
        draw_histogram(ax, name, hist)
    fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


def draw_histogram(ax: Any, name: str, hist: LatencyHistogram) -> None:
    """One latency histogram (log counts over µs, 1 µs bins) on matplotlib axes ``ax``; an empty one
    (no cycle measured) is titled "not measured", never as percentiles of 0 µs."""
    import numpy as np

    nz = np.flatnonzero(hist.counts)
    if nz.size:
        hi = min(int(nz[-1]) + 2, hist.counts.size)  # the last bin counts everything from max_us on
        edges = np.arange(hi + 1) + 1.0  # bin k covers [k, k+1) µs; shifted by 1 for the log axis
        ax.stairs(hist.counts[:hi], edges, fill=True, color="tab:blue")
        ax.set_xscale("log")
        ax.set_yscale("log")
    s = hist.to_json()
    if not s["cycles"]:  # nothing measured (e.g. a soak in virtual time): say so, as `report` does
        ax.set_title(f"{name}: not measured", fontsize=9)
        ax.text(0.5, 0.5, "not measured", transform=ax.transAxes, ha="center", va="center", color="tab:gray")
    else:
        ax.set_title(f"{name}: p50 {s['p50']:g}, p99 {s['p99']:g}, max {s['max']:g} µs", fontsize=9)
    ax.set_xlabel("µs (+1, log)")
    ax.set_ylabel("cycles")


def latency_report(latency: CycleLatency, rt: RtState) -> dict[str, Any]:
    """``latency_us: {wakeup, exchange}`` (p50, p99, p99.9, max) and ``realtime: {applied, refused}``."""
    return {"latency_us": latency.to_json(), "realtime": rt.to_json()}
