"""Clocks the cycle reads: the machine's own, or a virtual one that a test advances.

Everything that paces or times out inside the library asks a :class:`Clock`
instead of :mod:`time`, so a test can run a 10 s scenario at 1 kHz as fast as
the CPU allows with the same result on a busy or a quiet machine.
"""

from __future__ import annotations

import time
from typing import Protocol


class Clock(Protocol):
    """A monotonic time source, ns, and a way to let time pass, s."""

    def now_ns(self) -> int:
        """Monotonic time, ns."""
        ...

    def sleep(self, seconds: float) -> None:
        """Let ``seconds`` pass (a wall clock sleeps; a virtual clock advances)."""
        ...


class WallClock:
    """The machine's monotonic clock (``time.monotonic_ns``) and ``time.sleep``."""

    virtual = False

    def now_ns(self) -> int:
        return time.monotonic_ns()

    def sleep(self, seconds: float) -> None:
        if seconds > 0:
            time.sleep(seconds)


class VirtualClock:
    """Time that passes only when told: :meth:`advance` or :meth:`sleep`. Starts at ``start_ns``."""

    virtual = True

    def __init__(self, start_ns: int = 0) -> None:
        self._t = int(start_ns)

    def now_ns(self) -> int:
        return self._t

    def sleep(self, seconds: float) -> None:
        self.advance(round(seconds * 1e9))

    def advance(self, ns: int) -> None:
        """Move time forward by ``ns`` (>= 0)."""
        if ns < 0:
            raise ValueError(f"a virtual clock does not go backwards ({ns} ns)")
        self._t += int(ns)


WALL = WallClock()
