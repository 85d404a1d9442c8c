"""``fieldbus dc-sim [--slaves N] [--drift-ppm X] [--seconds S] [--json] [--plot FILE]``.

Simulates the distributed clocks of one EtherCAT line (slave 0 = reference
clock) configured the way SOEM does it, with one FRMW of the reference time per
cycle, and reports how far apart the slaves' system times and SYNC0 pulses
are. Model and assumptions: docs/dc.md.
"""

from __future__ import annotations

import argparse
import json
from typing import Any

from fieldbus.commands.argtypes import SEED, UsageError, integer, non_negative, number, positive
from fieldbus.commands.outputs import check_plot
from fieldbus.commands.usage import add_command
from fieldbus.core.dc.sim import DcSimResult, convergence_bound_ms, simulate
from fieldbus.errors import BackendUnavailableError

# The simulation keeps per slave and cycle a SYNC0 edge and a noise draw (2 x float64): bound their
# product so that a mistyped --seconds is refused instead of allocating terabytes.
BYTES_PER_SAMPLE = 16
MAX_SAMPLES = 10_000_000  # 160 MB: 1250 s of 1 kHz cycles with 8 slaves


def register(sub: Any) -> None:
    p = add_command(
        sub,
        "dc-sim",
        help="simulate distributed-clock drift compensation on a line of slaves",
        doc=__doc__,
        codes=[(0, "the simulation ran and its report was printed"), (1, "the plot could not be written")],
    )
    p.add_argument("--slaves", type=integer(1), default=8, metavar="N", help="slaves (default 8)")
    p.add_argument(
        "--drift-ppm",
        type=non_negative("ppm"),
        default=50.0,
        metavar="X",
        help="crystal drifts spread over ±X ppm (default 50)",
    )
    p.add_argument(
        "--seconds",
        type=positive("s"),
        default=2.0,
        metavar="S",
        help=f"simulated time (default 2; at most {MAX_SAMPLES:.0e} slave-cycles, --slaves x cycles)",
    )
    p.add_argument(
        "--cycle-us",
        type=number(0.001, unit="us"),
        default=1000.0,
        metavar="US",
        help="cycle time (default 1000)",
    )
    p.add_argument(
        "--cable-m", type=non_negative("m"), default=1.0, metavar="M", help="cable per hop (default 1)"
    )
    p.add_argument("--no-compensation", action="store_true", help="slaves ignore the distributed time")
    p.add_argument(
        "--soem-delays", action="store_true", help="compute delays exactly like SOEM (ignores t_Diff)"
    )
    p.add_argument("--seed", type=SEED, default=0, help="random seed, >= 0 (default 0)")
    p.add_argument("--json", action="store_true", help="one JSON object on stdout")
    p.add_argument(
        "--plot", metavar="FILE", default=None, help="write a PNG of the spreads (needs matplotlib)"
    )
    p.set_defaults(func=run)


def check_size(args: argparse.Namespace) -> int:
    """The number of simulated cycles; :class:`UsageError` when slaves x cycles passes :data:`MAX_SAMPLES`."""
    cycle_ns: int = max(1, round(args.cycle_us * 1000))
    cycles: int = max(1, round(args.seconds * 1e9 / cycle_ns))
    if cycles * args.slaves > MAX_SAMPLES:
        per_slave = MAX_SAMPLES // args.slaves
        most = (
            f"at most {per_slave * cycle_ns / 1e9:g} s here" if per_slave else f"at most {MAX_SAMPLES} slaves"
        )
        raise UsageError(
            f"--seconds {args.seconds:g} at --cycle-us {args.cycle_us:g} with --slaves {args.slaves} is "
            f"{cycles * args.slaves:.3g} slave-cycles; the limit is {MAX_SAMPLES:.0e} "
            f"(about {MAX_SAMPLES * BYTES_PER_SAMPLE / 1e6:.0f} MB of samples): {most}"
        )
    return cycles


def summary(r: DcSimResult, drift_ppm: float) -> dict[str, Any]:
    """The JSON object of ``dc-sim --json`` (key names are a stable surface)."""
    span = float(r.drifts_ppm.max() - r.drifts_ppm.min())
    try:
        bound: float | None = convergence_bound_ms(span, float(r.true_delays_ns.max()), r.threshold_ns)
    except ValueError:
        bound = None
    return {
        "slaves": r.n_slaves,
        "drift_ppm": drift_ppm,
        "seconds": r.seconds,
        "cycle_us": r.cycle_ns / 1000.0,
        "compensation": r.compensation,
        "threshold_ns": r.threshold_ns,
        "final_spread_ns": round(r.final_spread_ns, 3),
        "converged_after_ms": r.converged_after_ms,
        "convergence_bound_ms": None if bound is None or not r.compensation else round(bound, 1),
        "max_spread_after_convergence_ns": (
            None if r.max_spread_after_convergence_ns is None else round(r.max_spread_after_convergence_ns, 3)
        ),
        "sync0_spread_ns": None if r.final_sync0_spread_ns is None else round(r.final_sync0_spread_ns, 3),
        "initial_spread_ns": round(float(r.spread_ns[0]), 3),
        "max_delay_error_ns": r.max_delay_error_ns,
        "delays_ns": [int(d) for d in r.delays_ns],
        "drifts_ppm_list": [round(float(d), 6) for d in r.drifts_ppm],
    }


def table(s: dict[str, Any]) -> str:
    """Short human-readable report of a ``summary``."""

    def f(v: Any, unit: str) -> str:
        return "never" if v is None else f"{v:.1f} {unit}"

    rows = [
        ("slaves", str(s["slaves"])),
        ("drift", f"±{s['drift_ppm']:g} ppm"),
        ("simulated", f"{s['seconds']:g} s at {s['cycle_us']:g} us cycle"),
        ("compensation", "on" if s["compensation"] else "off"),
        ("initial spread", f(s["initial_spread_ns"], "ns")),
        (f"converged (< {s['threshold_ns']:g} ns)", f(s["converged_after_ms"], "ms")),
        (
            "convergence bound",
            "-" if s["convergence_bound_ms"] is None else f(s["convergence_bound_ms"], "ms"),
        ),
        (
            "max spread after",
            "-"
            if s["max_spread_after_convergence_ns"] is None
            else f(s["max_spread_after_convergence_ns"], "ns"),
        ),
        ("final spread", f(s["final_spread_ns"], "ns")),
        ("final SYNC0 spread", "-" if s["sync0_spread_ns"] is None else f(s["sync0_spread_ns"], "ns")),
        ("delay error (max)", f(s["max_delay_error_ns"], "ns")),
    ]
    width = max(len(k) for k, _ in rows)
    return "\n".join(f"{k:<{width}}  {v}" for k, v in rows)


def plot(r: DcSimResult, path: str) -> None:
    """Spread of system times and of SYNC0 pulses over time (log scale) into a PNG at ``path``."""
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError as exc:
        raise BackendUnavailableError("pip install 'fieldbus[plot]'") from exc
    fig, ax = plt.subplots(figsize=(6.4, 3.2), dpi=90)
    ax.semilogy(r.times_ms, r.spread_ns, lw=1, label="system time spread")
    ax.semilogy(r.times_ms, r.sync0_spread_ns, lw=1, ls="--", label="SYNC0 spread")
    ax.axhline(r.threshold_ns, color="k", lw=0.6, ls=":", label=f"{r.threshold_ns:g} ns")
    if r.converged_after_ms is not None:
        ax.axvline(r.converged_after_ms, color="g", lw=0.6, ls=":")
    ax.set_xlabel("time after DC configuration [ms]")
    ax.set_ylabel("spread [ns]")
    comp = "on" if r.compensation else "off"
    span = (r.drifts_ppm.max() - r.drifts_ppm.min()) / 2
    ax.set_title(f"{r.n_slaves} slaves, ±{span:g} ppm, compensation {comp}", fontsize=9)
    ax.legend(fontsize=7)
    ax.grid(True, which="both", lw=0.3)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


def run(args: argparse.Namespace) -> int:
    check_size(args)
    check_plot(args.plot, "--plot")
    result = simulate(
        args.slaves,
        args.drift_ppm,
        args.seconds,
        cycle_ns=max(1, round(args.cycle_us * 1000)),
        seed=args.seed,
        compensation=not args.no_compensation,
        cable_m=args.cable_m,
        master_t_diff_ns=0 if args.soem_delays else None,
    )
    s = summary(result, args.drift_ppm)
    if args.plot:
        plot(result, args.plot)
    if args.json:
        print(json.dumps(s))
    else:
        print(table(s))
        if args.plot:
            print(f"plot written to {args.plot}")
    return 0
