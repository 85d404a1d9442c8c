"""``fieldbus run NETWORK.yaml --cycles N``: bring a network up and run its cycle.

Outputs keep their defaults (no controller): this checks that every bus comes
up and exchanges cleanly at its cycle time, and reports misses and timing.
"""

from __future__ import annotations

import argparse
import json
import sys
from typing import Any

from fieldbus.commands import buslogs, cycleopts
from fieldbus.commands.argtypes import integer
from fieldbus.commands.outputs import check_plot
from fieldbus.commands.usage import add_command
from fieldbus.core.network import load_network
from fieldbus.errors import FieldbusError
from fieldbus.network import open_network
from fieldbus.operations.report import run_report


def register(sub: Any) -> None:
    p = add_command(
        sub,
        "run",
        help="bring a network up and run N cycles",
        doc=__doc__,
        codes=[
            (0, "every cycle fresh on every bus"),
            (1, "bring-up or file error (the message names file, drive, object)"),
            (3, "at least one miss (late, lost or short frame; counted per bus in the output)"),
        ],
        live_bus=True,
    )
    cycleopts.add_arguments(p)
    buslogs.add_arguments(p)
    cycleopts.add_monitor_argument(p)
    p.add_argument("network", metavar="NETWORK.yaml", help="network file (buses, slaves and their maps)")
    p.add_argument("--cycles", type=integer(1), default=1000, help="number of cycles, >= 1 (default 1000)")
    p.add_argument("--backend", help="run every bus on this backend instead (e.g. sim)")
    p.add_argument(
        "--error-counters",
        action="store_true",
        help="EtherCAT: read each slave's ESC error counters and link state in OP (one datagram in a cycle "
        "nothing else uses); a rise is an event naming the suspect cable (docs/diagnostics.md)",
    )
    p.add_argument("--json", action="store_true", help="one JSON object on stdout")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    check_plot(args.plot, "--plot")
    buslogs.check_outputs(args)
    model = load_network(args.network)
    for text in model.warnings:  # what validate prints too (e.g. a receive timeout longer than the cycle)
        print(f"warning: {text}", file=sys.stderr)
    logs = buslogs.bus_options(args, model, args.backend)
    if args.error_counters:
        ecat = [b.name for b in model.buses if b.type == "ethercat"]
        if not ecat:
            raise FieldbusError(f"{args.network}: --error-counters needs an ethercat bus")
        logs = {**logs, **{name: {**logs.get(name, {}), "error_counters": True} for name in ecat}}
    cycleopts.check_record(args)
    with (
        open_network(model, backend=args.backend, bus_options=logs) as net,
        cycleopts.rt_context(args) as rt,
    ):
        op = net.bring_up()
        cycleopts.start_recording(op, args)
        period = float(op.cycle_time_us)

        def step(_k: int) -> None:
            op.exchange()

        timer, latency = cycleopts.run_timed(
            op, step, period, args.cycles, status=not args.json, monitor=args.monitor
        )
        report = run_report(op, timer, period)
        report.update(cycleopts.latency_report(latency, rt))
    if args.plot:
        cycleopts.plot_latency(latency, args.plot, f"fieldbus run {args.network}")
    if args.json:
        print(json.dumps(report))
    else:
        t = report["cycle_time_us"]
        print(
            f"{report['cycles']} cycles at {period:g} us: missed {report['missed']}, "
            f"safe stops {report['safe_stops']}, cycle work mean {t['mean']} us p99 {t['p99']} us max {t['max']} us"
        )
        for b in report["buses"]:
            print(
                f"  {b['name']} ({b['type']}, {b['slaves']} slaves, WKC {b['expected_wkc']}): missed {b['missed']} "
                f"(timeouts {b['timeouts']}, short {b['short']}), longest streak {b['longest_streak']}"
            )
    return 0 if report["missed"] == 0 else 3
