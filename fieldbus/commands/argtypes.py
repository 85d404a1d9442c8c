"""Argument types for the CLI: numbers refused by argparse (exit 2) when NaN, infinite or out of range.

``number(low, high)`` and ``integer(low, high)`` return argparse ``type=`` callables;
:class:`UsageError` is a refused combination of arguments found after parsing (also exit 2).
"""

from __future__ import annotations

import argparse
import math
from collections.abc import Callable

from fieldbus.errors import FieldbusError


class UsageError(FieldbusError):
    """The command line asks for something the command cannot do (exit 2, like argparse's own errors)."""


def _bounds(low: float | None, high: float | None, low_open: bool, unit: str) -> str:
    u = f" {unit}" if unit else ""
    if low is not None and high is not None:
        return f"a number from {low:g} to {high:g}{u}"
    if low is not None:
        return f"a number {'>' if low_open else '>='} {low:g}{u}"
    if high is not None:
        return f"a number <= {high:g}{u}"
    return f"a finite number of {unit}" if unit else "a finite number"


def number(
    low: float | None = None, high: float | None = None, *, low_open: bool = False, unit: str = ""
) -> Callable[[str], float]:
    """A finite float in ``[low, high]`` (``low_open``: ``> low``); NaN and inf are refused."""
    want = _bounds(low, high, low_open, unit)

    def parse(text: str) -> float:
        try:
            v = float(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"must be {want}, not {text!r}") from None
        if (
            not math.isfinite(v)
            or (low is not None and (v <= low if low_open else v < low))
            or (high is not None and v > high)
        ):
            raise argparse.ArgumentTypeError(f"must be {want}, not {text!r}")
        return v

    parse.__name__ = "number"  # argparse names the type in its own messages
    return parse


def positive(unit: str = "") -> Callable[[str], float]:
    """A finite float > 0."""
    return number(0.0, low_open=True, unit=unit)


def non_negative(unit: str = "") -> Callable[[str], float]:
    """A finite float >= 0."""
    return number(0.0, unit=unit)


def integer(low: int | None = None, high: int | None = None) -> Callable[[str], int]:
    """An integer in ``[low, high]``; decimal, or hex/octal/binary with a prefix (``0x7F``)."""
    if low is not None and high is not None:
        want = f"an integer from {low} to {high}"
    elif low is not None:
        want = f"an integer >= {low}"
    else:
        want = "an integer"

    def parse(text: str) -> int:
        try:
            v = int(text) if text.strip().lstrip("+-").isdigit() else int(text, 0)
        except ValueError:
            raise argparse.ArgumentTypeError(f"must be {want}, not {text!r}") from None
        if (low is not None and v < low) or (high is not None and v > high):
            raise argparse.ArgumentTypeError(f"must be {want}, not {text!r}")
        return v

    parse.__name__ = "integer"
    return parse


NODE_ID = integer(1, 127)  # a CANopen node id (CiA 301)
SEED = integer(0)  # numpy's generators take a non-negative seed
