"""``fieldbus report FILE [--json]``: what a recording holds (cycles, misses per bus, events, latency)."""

from __future__ import annotations

import argparse
import json
from typing import Any

from fieldbus.commands.usage import add_command
from fieldbus.recording import load
from fieldbus.recording.summary import describe, summary


def register(sub: Any) -> None:
    p = add_command(
        sub,
        "report",
        help="summarise a recording (--record): cycles, misses, events, latency",
        doc=__doc__,
        codes=[(0, "the summary was printed"), (1, "the recording cannot be read")],
    )
    p.add_argument("file", metavar="FILE.mcap", help="a recording (demo, run or soak --record)")
    p.add_argument("--json", action="store_true", help="one JSON object on stdout (every event listed)")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    s = summary(load(args.file))
    print(json.dumps(s) if args.json else describe(s))
    return 0
