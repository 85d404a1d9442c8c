"""The ``fieldbus`` command. Each subcommand lives in ``fieldbus.commands.<name>``.

A command module defines ``register(subparsers)``, which adds its parser and sets
``func`` to a callable ``(args) -> int`` (the exit code). ``--json`` output is
one JSON object on stdout; its key names are a stable surface.
"""

from __future__ import annotations

import argparse
import importlib
import sys
from collections.abc import Sequence

from fieldbus import __version__
from fieldbus.errors import FieldbusError

COMMANDS = (
    "validate",
    "bandwidth",
    "dc_sim",
    "demo",
    "run",
    "soak",
    "latency",
    "decode",
    "scan",
    "sdo",
    "plot",
    "report",
    "import_",
    "serve",
)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="fieldbus", description=__doc__.splitlines()[0])
    parser.add_argument("--version", action="version", version=f"fieldbus {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name in COMMANDS:
        try:
            module = importlib.import_module(f"fieldbus.commands.{name}")
        except ModuleNotFoundError as exc:
            if exc.name == f"fieldbus.commands.{name}":
                continue  # command not built yet
            raise
        module.register(sub)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if not getattr(args, "func", None):
        parser.print_help(sys.stderr)
        return 2
    try:
        return int(args.func(args))
    except FieldbusError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
