"""What every command's ``--help`` says: a plain-text description and its exit codes.

Exit codes common to every command (see :data:`COMMON_EXITS`): 2 a refused command line,
130 interrupted, 141 stdout closed early (``| head``), 143 terminated (SIGTERM). A command adds its own 0, 1 and 3.
"""

from __future__ import annotations

import argparse
import re
from typing import Any

OK = 0
ERROR = 1  # a file, a bus or a device refused: one line on stderr naming it
USAGE = 2  # the command line was refused (argparse, or a combination the command cannot do)
FAILED = 3  # the command ran but its check failed (a miss, an axis not enabled, ...)
INTERRUPTED = 130  # Ctrl-C (128 + SIGINT)
PIPE_CLOSED = 141  # stdout closed by the reader (128 + SIGPIPE), as a shell reports `yes | head`
TERMINATED = 143  # SIGTERM (128 + 15): unwound as Ctrl-C is (drives stopped, buses closed)

COMMON_EXITS = (
    (USAGE, "the command line was refused (an unknown option, a value out of range); one line on stderr"),
    (PIPE_CLOSED, "stdout was closed early (e.g. piped into head): the rest of the output was dropped"),
    (TERMINATED, "terminated by SIGTERM; like Ctrl-C, a live bus's drives were stopped and its buses closed"),
)
JSON_ERRORS = (
    'with --json an error is also one JSON object on stdout: {"ok": false, "error": "...", "exit": N}'
)


LIVE_BUS_INTERRUPTED = "interrupted (Ctrl-C); the drives were stopped and the buses closed"


def epilog(
    codes: list[tuple[int, str]], *, live_bus: bool = False, json: bool = False, interrupted: str = ""
) -> str:
    """``exit codes:`` and one line per code: ``codes`` (the command's own), then the common ones
    (a common code the command gives a meaning of its own is not repeated)."""
    why = interrupted or (LIVE_BUS_INTERRUPTED if live_bus else "interrupted (Ctrl-C)")
    own = {code for code, _ in codes}
    rows = sorted([*codes, *(c for c in COMMON_EXITS if c[0] not in own), (INTERRUPTED, why)])
    lines = ["exit codes:"]
    for code, text in rows:
        first, *rest = text.split("\n")
        lines.append(f"  {code:<2d} {first}")
        lines += [f"     {r}" for r in rest]
    if json:
        lines.append(JSON_ERRORS)
    return "\n".join(lines)


def plain(doc: str | None) -> str:
    """A docstring as help text: RST roles and double backquotes removed, paragraphs kept."""
    text = re.sub(r":\w+:`~?([^`]+)`", r"\1", doc or "")
    return text.replace("``", "").strip()


def add_command(
    sub: Any,
    name: str,
    *,
    help: str,
    doc: str | None,
    codes: list[tuple[int, str]],
    live_bus: bool = False,
    json: bool = True,
    **kwargs: Any,
) -> argparse.ArgumentParser:
    """``sub.add_parser(name)`` with ``doc`` (plain) as the description and the exit codes as the epilog."""
    parser: argparse.ArgumentParser = sub.add_parser(
        name,
        help=help,
        description=plain(doc),
        epilog=epilog(codes, live_bus=live_bus, json=json),
        formatter_class=argparse.RawDescriptionHelpFormatter,
        **kwargs,
    )
    return parser
