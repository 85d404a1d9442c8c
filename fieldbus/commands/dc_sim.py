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

from fieldbus.core.dc.sim import DcSimResult, convergence_bound_ms, simulate
from fieldbus.errors import BackendUnavailableError


def register(sub: Any) -> None:
    p: argparse.ArgumentParser = sub.add_parser(
        "dc-sim", help="simulate distributed-clock drift compensation on a line of slaves"
    )
    p.add_argument("--slaves", type=_int_at_least(1), default=8, metavar="N", help="slaves (default 8)")
    p.add_argument(
        "--drift-ppm",
        type=_non_negative,
        default=50.0,
        metavar="X",
        help="crystal drifts spread over ±X ppm (default 50)",
    )
    p.add_argument("--seconds", type=_positive, default=2.0, metavar="S", help="simulated time (default 2)")
    p.add_argument(
        "--cycle-us", type=_positive, default=1000.0, metavar="US", help="cycle time (default 1000)"
    )
    p.add_argument(
        "--cable-m", type=_non_negative, default=1.0, metavar="M", help="cable per hop (default 1)"
    )
    p.add_argument("--no-compensation", action="store_true", help="slaves ignore the distributed time")
    p.add_argument(
        "--soem-delays", action="store_true", help="compute delays exactly like SOEM (ignores t_Diff)"
    )
    p.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    p.add_argument("--json", action="store_true", help="one JSON object on stdout")
    p.add_argument(
        "--plot", metavar="FILE", default=None, help="write a PNG of the spreads (needs matplotlib)"
    )
    p.set_defaults(func=run)


def _positive(text: str) -> float:
    v = float(text)
    if not 0 < v < float("inf"):
        raise argparse.ArgumentTypeError(f"must be a positive number, not {text!r}")
    return v


def _non_negative(text: str) -> float:
    v = float(text)
    if not 0 <= v < float("inf"):
        raise argparse.ArgumentTypeError(f"must be a number >= 0, not {text!r}")
    return v


def _int_at_least(low: int) -> Any:
    def parse(text: str) -> int:
        v = int(text)
        if v < low:
            raise argparse.ArgumentTypeError(f"must be an integer >= {low}, not {text!r}")
        return v

    return parse


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
