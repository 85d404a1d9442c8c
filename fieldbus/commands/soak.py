"""``fieldbus soak``: the cycle against emulated drives under injected faults; every fault accounted for.

    fieldbus soak --demo [--backend sim|ethercat] [--axes N] --cycles N --faults SPEC [--seed S] [--phases] [--json]
    fieldbus soak NETWORK.yaml --cycles N --faults SPEC   (its single EtherCAT bus, emulated in-process)

SPEC: ``loss=0.01,delay=0.001,wkc=0.001,power_cycles=3,bursts=1,sdo_aborts=1``
(rates per cycle and counts per run; docs/reliability.md). Exit status 0 only
when every injected fault was detected and no invariant was violated. Ctrl-C
stops the drives, closes the bus and says what the emulator reports after
that (every drive down, every slave out of OP), exit 130.
"""

from __future__ import annotations

import argparse
import json
import tempfile
from contextlib import ExitStack, suppress
from pathlib import Path
from typing import Any

from fieldbus.commands import cycleopts
from fieldbus.commands.argtypes import SEED, UsageError, integer, non_negative, number
from fieldbus.commands.demo import check_axes
from fieldbus.commands.usage import add_command
from fieldbus.network import Network, Operational, open_network
from fieldbus.operations.soak import DEFAULT_MARGIN_US, Control, FaultSpec, Soak
from fieldbus.platform.loop import default_status_stream

DEFAULT_FAULTS = "loss=0.01,power_cycles=3,bursts=1,sdo_aborts=1"


def register(sub: Any) -> None:
    p = add_command(
        sub,
        "soak",
        help="run the cycle under injected faults and check invariants",
        doc=__doc__,
        codes=[
            (0, "every injected fault was detected and no invariant was violated"),
            (1, "bring-up, file or fault-spec error"),
            (3, "a fault went undetected or an invariant was violated (listed in the output)"),
        ],
        live_bus=True,
    )
    p.add_argument(
        "network", nargs="?", metavar="NETWORK.yaml", help="a network with one EtherCAT bus (run on sim)"
    )
    p.add_argument("--demo", action="store_true", help="the demo's joints instead of a network file")
    p.add_argument(
        "--backend", choices=("sim", "ethercat", "canopen"), default="sim", help="with --demo (default sim)"
    )
    p.add_argument("--axes", type=integer(1), default=12, help="with --demo (default 12)")
    p.add_argument(
        "--cycles",
        type=integer(1),
        default=10_000,
        help="cycles to run under the fault plan, after bring-up (default 10000)",
    )
    p.add_argument("--faults", default=DEFAULT_FAULTS, help=f"fault spec (default {DEFAULT_FAULTS})")
    p.add_argument(
        "--seed",
        type=SEED,
        default=0,
        help="seed of the fault plan: which cycles and slaves get a fault; the same seed, the same plan "
        "(default 0)",
    )
    p.add_argument(
        "--rate",
        type=non_negative("Hz"),
        default=None,
        help="pace the cycle at this rate in Hz (default: the network's cycle time; 0: as fast as it goes)",
    )
    p.add_argument(
        "--margin-us",
        type=number(unit="us"),
        default=DEFAULT_MARGIN_US,
        help="a cycle may take the receive timeout plus this (negative: less than the timeout), else it is a "
        f"violation (default {DEFAULT_MARGIN_US:g})",
    )
    p.add_argument("--json", action="store_true", help="one JSON object on stdout")
    p.add_argument(
        "--phases",
        action="store_true",
        help="time exchange() phase by phase (encode, send, wait, judge, accept, contract, acyclic, "
        "observers): medians per kind of cycle in the report",
    )
    cycleopts.add_arguments(p, plot=False)
    cycleopts.add_monitor_argument(p)
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    if bool(args.network) == bool(args.demo):
        raise UsageError("give either NETWORK.yaml or --demo")
    if args.demo:
        check_axes(args.backend, args.axes)
    cycleopts.check_record(args)
    spec = FaultSpec.parse(args.faults)
    report = soak(args, spec)
    if args.json:
        print(json.dumps(report))
    else:
        print(describe(report))
    ok = report["violation_count"] == 0 and report["injected"] == report["detected"]
    return 0 if ok else 3


def soak(args: argparse.Namespace, spec: FaultSpec) -> dict[str, Any]:
    from fieldbus.commands.demo import demo_network

    with ExitStack() as stack:
        tmp = Path(stack.enter_context(tempfile.TemporaryDirectory(prefix="fieldbus-soak-")))
        if args.demo:
            setup = stack.enter_context(demo_network(args.backend, args.axes, 1000.0, tmp))
            net_file, backend = setup.net_file, setup.backend

            def control_for(net: Network) -> Control:
                return lambda **msg: setup.control(net, **msg)
        else:
            net_file, backend = Path(args.network), "sim"

            def control_for(net: Network) -> Control:
                from fieldbus.emulators import emulator_part

                handle_control = emulator_part("ethercat_control")
                return lambda **msg: handle_control(net.backends[0].chain, msg)  # type: ignore[attr-defined]

        def opener() -> tuple[Network, Control]:
            net = open_network(net_file, backend=backend)
            return net, control_for(net)

        runner = (RecordingSoak if args.record else Soak)(
            opener,
            spec,
            seed=args.seed,
            cycle_time_us=None if args.rate is None else (1e6 / args.rate if args.rate else 0.0),
            margin_us=args.margin_us,
        )
        if isinstance(runner, RecordingSoak):
            runner.args = args
        try:
            with cycleopts.rt_context(args) as rt:
                runner.monitor = args.monitor
                runner.phases = args.phases
                rep = runner.run(
                    args.cycles, status=default_status_stream(not args.json and not args.monitor)
                )
        except KeyboardInterrupt:
            raise KeyboardInterrupt(close_interrupted(runner)) from None
        except BaseException:
            with suppress(Exception):  # the error that stopped the run is the one to report
                runner.close()
            raise
        runner.close()
        out = rep.to_json()
        out["faults"] = args.faults
        out["backend"] = args.backend if args.demo else "sim"
        out["cycle_time_us"] = runner.timer.summary().to_json()
        out["realtime"] = rt.to_json()
        return out


def close_interrupted(runner: Soak) -> str:
    """Close the soak's network after Ctrl-C; what the emulator says after it, in one line."""
    seen = runner.report.violation_count
    where = f"after {runner.report.cycles} cycles"
    try:
        runner.close()  # the drives down (quick stop, disable voltage), then the emulator asked
    except KeyboardInterrupt:
        return f"{where}, again while stopping the drives; the bus was closed"
    except Exception as exc:
        return f"{where}; stopping the drives: {type(exc).__name__}: {exc}"
    if runner.report.violation_count > seen:
        return f"{where}; {runner.report.violations[-1]}"
    can = runner.net.backends[0].kind == "canopen"
    return (
        f"{where}; drives stopped: none in OPERATION ENABLED and every slave "
        f"{'out of OPERATIONAL' if can else 'in INIT'} (the emulator's status), bus closed"
    )


class RecordingSoak(Soak):
    """A soak that records its cycles (``--record``) from OP on."""

    args: argparse.Namespace

    def bring_up(self) -> Operational:
        op = super().bring_up()
        cycleopts.start_recording(op, self.args)
        return op


def describe(r: dict[str, Any]) -> str:
    kinds = sorted(set(r["injected"]) | set(r["detected"]))
    lines = [
        f"soak on '{r['backend']}': {r['cycles']} cycles in {r['seconds']} s, faults {r['faults']}",
        "  "
        + ", ".join(
            f"{k}: injected {r['injected'].get(k, 0)}, detected {r['detected'].get(k, 0)}" for k in kinds
        ),
        f"  missed {r['missed']}, safe stops {r['safe_stops']} (re-enabled {r['reenabled_after_safe_stop']}), "
        f"power cycles recovered {r['recovered_power_cycles']}",
        "  exchange() time, us: "
        + "; ".join(
            f"{k} {v['cycles']} cycles p50 {v['p50']} p99 {v['p99']} max {v['max']}"
            for k, v in r["exchange_us"].items()
            if v["cycles"]
        ),
        f"  invariant violations: {r['violation_count']}",
    ]
    for kind, ph in r.get("phases_us", {}).items():
        lines.insert(
            -1,
            f"  {kind} ({ph['cycles']} cycles) p50 us: "
            + ", ".join(f"{k} {v}" for k, v in ph.items() if k != "cycles"),
        )
    lines += [f"    {v}" for v in r["violations"]]
    return "\n".join(lines)
