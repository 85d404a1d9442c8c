"""The ``fieldbus`` command. Each subcommand lives in ``fieldbus.commands.<name>``.

A command module defines ``register(subparsers)``, which adds its parser and sets
``func`` to a callable ``(args) -> int`` (the exit code). ``--json`` output is
one JSON object on stdout; its key names are a stable surface.

Exit codes every command shares (:mod:`fieldbus.commands.usage`): 1 a
:class:`~fieldbus.errors.FieldbusError` (one line on stderr), 2 a refused command
line, 130 Ctrl-C, 143 SIGTERM (handled as Ctrl-C is: the drives are stopped and the
buses closed first), 141 stdout closed by its reader (``| head``). No traceback
reaches the user for any of them; with ``--json`` an error is also one JSON
object on stdout, ``{"ok": false, "error": ..., "exit": N}``.
"""

from __future__ import annotations

import argparse
import importlib
import json
import os
import select
import signal
import sys
import threading
from collections.abc import Sequence
from typing import NoReturn

from fieldbus import __version__
from fieldbus.commands.argtypes import UsageError
from fieldbus.commands.usage import ERROR, INTERRUPTED, PIPE_CLOSED, TERMINATED, USAGE, epilog
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
    "firmware",
    "register",
    "eeprom",
    "plot",
    "report",
    "import_",
    "serve",
    "monitor",
)

DESCRIPTION = """\
fieldbus: an EtherCAT and CANopen master for robots. Describe each drive once
in YAML (a drive map), check it, bring a network of drives up and run its
cycle; emulated drives to try it all on ('fieldbus demo')."""
TOP_EPILOG = (
    epilog(
        [
            (0, "the command did what it was asked"),
            (1, "an error the command found (a file, a bus, a device): one line on stderr naming it"),
            (3, "the command ran but its check failed (see the command's --help)"),
        ],
        interrupted="interrupted (Ctrl-C); a command on a live bus stopped the drives and closed the buses",
        json=True,
    )
    + "\n\n'fieldbus COMMAND --help' for a command's options and exit codes."
)


class Parser(argparse.ArgumentParser):
    """argparse that reports a refused command line in one line (and, with ``--json``, as JSON too)."""

    json_errors = False  # set by main(): was --json on the command line

    def error(self, message: str) -> NoReturn:
        _fail(f"{self.prog}: error: ", f"{message} (see '{self.prog} --help')", USAGE, self.json_errors)
        self.exit(USAGE)


def build_parser() -> argparse.ArgumentParser:
    parser = Parser(
        prog="fieldbus",
        description=DESCRIPTION,
        epilog=TOP_EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
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


def _fail(prefix: str, message: str, code: int, as_json: bool) -> int:
    """``prefix message`` on stderr and, ``as_json``, ``{"ok": false, "error": message, "exit": code}``
    on stdout; returns ``code``."""
    lines = [(sys.stderr, prefix + message)]
    if as_json:
        lines.append((sys.stdout, json.dumps({"ok": False, "error": message, "exit": code})))
    for stream, line in lines:
        try:
            print(line, file=stream, flush=True)
        except BrokenPipeError:  # its reader went away: nothing more for it, not even at exit
            if stream is sys.stdout:
                _drop_stdout()
        except ValueError:  # the stream was closed
            pass
    return code


def _drop_stdout() -> None:
    """After the reader of stdout went away: point stdout at /dev/null, so exiting flushes nothing."""
    try:
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
        os.close(devnull)
    except (OSError, ValueError, AttributeError):  # no real file behind sys.stdout (a test's capture)
        pass


def _pipe_gone(stream: object) -> bool:
    """The reader of ``stream`` (a pipe or socket) has closed its end."""
    try:
        fd = stream.fileno()  # type: ignore[attr-defined]
        poll = select.poll()
        poll.register(fd, select.POLLOUT)
        return any(ev & (select.POLLERR | select.POLLHUP) for _, ev in poll.poll(0))
    except (OSError, ValueError, AttributeError):
        return False


class Terminated(KeyboardInterrupt):
    """SIGTERM, raised in the main thread: it unwinds as Ctrl-C does, so every drive gets its controlled stop."""


def _on_sigterm(signum: int, frame: object) -> None:
    raise Terminated("terminated (SIGTERM)")


def main(argv: Sequence[str] | None = None) -> int:
    if threading.current_thread() is not threading.main_thread():
        return _main(argv)
    previous = signal.signal(signal.SIGTERM, _on_sigterm)
    try:
        return _main(argv)
    finally:
        signal.signal(signal.SIGTERM, previous)


def _main(argv: Sequence[str] | None = None) -> int:
    words = list(sys.argv[1:] if argv is None else argv)
    as_json = Parser.json_errors = "--json" in words
    try:
        parser = build_parser()
        try:
            args = parser.parse_args(words)
        except SystemExit:  # --help, --version, a refused command line: their text flushed here
            sys.stdout.flush()
            raise
        if not getattr(args, "func", None):
            parser.print_help(sys.stderr)
            return USAGE
        try:
            code = int(args.func(args))
            sys.stdout.flush()  # here, not at exit: a closed pipe is then caught below
            return code
        except UsageError as exc:
            return _fail(f"fieldbus {args.command}: error: ", str(exc), USAGE, as_json)
        except FieldbusError as exc:
            return _fail("error: ", str(exc), ERROR, as_json)
    except Terminated:
        return _fail("", "terminated (SIGTERM): drives stopped, buses closed", TERMINATED, as_json)
    except KeyboardInterrupt as exc:
        return _fail("", f"interrupted: {exc}" if str(exc) else "interrupted", INTERRUPTED, as_json)
    except BrokenPipeError as exc:
        if not (_pipe_gone(sys.stdout) or _pipe_gone(sys.stderr)):
            return _fail("error: ", str(exc), ERROR, as_json)  # a socket of ours, not the output
        _drop_stdout()
        return PIPE_CLOSED


if __name__ == "__main__":
    sys.exit(main())
