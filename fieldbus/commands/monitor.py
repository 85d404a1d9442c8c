"""``fieldbus monitor --dds --namespace NS``: a served robot live, from its DDS state and diagnostics.

Needs no bus access: it reads what ``fieldbus serve`` publishes (per group the
joints, their freshness and drive states, the command gate and its counters;
per bus the verdict and counters; per axis its newest drive fault by name)
and never claims a group. For the live view of a cycle in this process, use ``--monitor`` on
``fieldbus run``, ``demo`` or ``soak``.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from typing import Any

from fieldbus.commands.usage import add_command

CLEAR = "\x1b[H\x1b[J"  # cursor home, clear to the end of the screen


def register(sub: Any) -> None:
    p = add_command(
        sub,
        "monitor",
        help="show a served robot (fieldbus serve) live from its DDS topics",
        doc=__doc__,
        codes=[
            (0, "the view was shown (once with --once, N times with --refreshes N)"),
            (1, "no served bus answered in that namespace and domain, or cyclonedds is missing"),
        ],
    )
    p.add_argument("--dds", action="store_true", required=True, help="watch a bus served over DDS")
    p.add_argument("--namespace", required=True, help="the served namespace (fieldbus serve --namespace)")
    p.add_argument("--domain", type=int, metavar="N", help="DDS domain id (default $ROS_DOMAIN_ID, else 0)")
    p.add_argument("--interface", metavar="IF", help="network interface for DDS (as fieldbus serve)")
    p.add_argument("--peer", action="append", default=[], metavar="ADDR", help="unicast discovery peer")
    p.add_argument("--once", action="store_true", help="print one view (with diagnostics) and exit")
    p.add_argument(
        "--refreshes", type=int, default=0, metavar="N", help="stop after N views (default: Ctrl-C)"
    )
    p.add_argument("--rate", type=float, default=2.0, metavar="HZ", help="views per second (at most 10)")
    p.add_argument("--timeout", type=float, default=10.0, metavar="S", help="wait for the server at most S s")
    p.add_argument("--json", action="store_true", help="each view as one JSON object")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from fieldbus import dds
    from fieldbus.errors import FieldbusError

    dds.require()
    from fieldbus.operations.served_view import ServedView, render

    if args.refreshes < 0 or not 0 < args.rate <= 10:
        raise FieldbusError("--refreshes must be >= 0 and --rate within (0, 10] views per second")
    views = 1 if args.once else args.refreshes
    view = ServedView(
        args.namespace, domain=args.domain, interface=args.interface, peers=args.peer, timeout_s=args.timeout
    )
    live = sys.stdout.isatty() and not args.json and views != 1
    try:
        view.wait_diagnostics(min(args.timeout, 3.0))
        shown = 0
        period = 1.0 / args.rate
        while views == 0 or shown < views:
            t0 = time.monotonic()
            view.refresh()
            snap = view.snapshot()
            text = json.dumps(snap) if args.json else render(snap)
            print(f"{CLEAR}{text}" if live else text, flush=True)
            shown += 1
            if views == 0 or shown < views:
                time.sleep(max(0.0, period - (time.monotonic() - t0)))
    finally:
        view.close()
    return 0
