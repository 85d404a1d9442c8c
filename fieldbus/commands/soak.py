"""``fieldbus soak``: the cycle against emulated drives under injected faults; every fault accounted for.

    fieldbus soak --demo [--backend sim|ethercat] [--axes N] --cycles N --faults SPEC [--seed S] [--json]
    fieldbus soak NETWORK.yaml --cycles N --faults SPEC   (its single EtherCAT bus, emulated in-process)

SPEC: ``loss=0.01,delay=0.001,wkc=0.001,power_cycles=3,bursts=1,sdo_aborts=1``
(see :mod:`fieldbus.runtime.soak`). Exit status 0 only when every injected
fault was detected and no invariant was violated.
"""

from __future__ import annotations

import argparse
import json
import tempfile
from contextlib import ExitStack
from pathlib import Path
from typing import Any

from fieldbus.commands import cycleopts
from fieldbus.errors import FieldbusError
from fieldbus.network import Network, Operational, open_network
from fieldbus.runtime.loop import default_status_stream
from fieldbus.runtime.soak import DEFAULT_MARGIN_US, Control, FaultSpec, Soak

DEFAULT_FAULTS = "loss=0.01,power_cycles=3,bursts=1,sdo_aborts=1"


def register(sub: Any) -> None:
    p: argparse.ArgumentParser = sub.add_parser(
        "soak", help="run the cycle under injected faults and check invariants"
    )
    p.add_argument(
        "network", nargs="?", metavar="NETWORK.yaml", help="a network with one EtherCAT bus (run on sim)"
    )
    p.add_argument("--demo", action="store_true", help="the demo's joints instead of a network file")
    p.add_argument(
        "--backend", choices=("sim", "ethercat", "canopen"), default="sim", help="with --demo (default sim)"
    )
    p.add_argument("--axes", type=int, default=12, help="with --demo (default 12)")
    p.add_argument("--cycles", type=int, default=10_000)
    p.add_argument("--faults", default=DEFAULT_FAULTS, help=f"fault spec (default {DEFAULT_FAULTS})")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument(
        "--rate",
        type=float,
        default=None,
        help="pace the cycle at this rate in Hz (default: the network's cycle time; 0: as fast as it goes)",
    )
    p.add_argument(
        "--margin-us",
        type=float,
        default=DEFAULT_MARGIN_US,
        help=f"a cycle may take the receive timeout plus this, else it is a violation (default {DEFAULT_MARGIN_US:g})",
    )
    p.add_argument("--json", action="store_true", help="one JSON object on stdout")
    cycleopts.add_arguments(p, plot=False)
    cycleopts.add_monitor_argument(p)
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    if bool(args.network) == bool(args.demo):
        raise FieldbusError("give either NETWORK.yaml or --demo")
    if args.cycles < 1 or args.axes < 1:
        raise FieldbusError("--cycles and --axes must be >= 1")
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
                from sim_slaves.ethercat.runner import handle_control

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
                rep = runner.run(
                    args.cycles, status=default_status_stream(not args.json and not args.monitor)
                )
        finally:
            runner.close()
        out = rep.to_json()
        out["faults"] = args.faults
        out["backend"] = args.backend if args.demo else "sim"
        out["cycle_time_us"] = runner.timer.summary().to_json()
        out["realtime"] = rt.to_json()
        return out


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
    lines += [f"    {v}" for v in r["violations"]]
    return "\n".join(lines)
