"""What the library asks for time: a :class:`Clock` (the protocol; the clocks are in :mod:`fieldbus.platform.clock`).

The core reads no clock: it takes times as parameters. Everything above it
that paces or times out asks a :class:`Clock` instead of :mod:`time`, so a
test can pass a virtual one.
"""

from __future__ import annotations

from typing import Protocol, runtime_checkable


@runtime_checkable
class Clock(Protocol):
    """A monotonic time source, ns, and a way to let time pass, s."""

    def now_ns(self) -> int:
        """Monotonic time, ns."""
        ...

    def sleep(self, seconds: float) -> None:
        """Let ``seconds`` pass (a wall clock sleeps; a virtual clock advances)."""
        ...


def is_virtual(clock: object) -> bool:
    """True for a clock that only moves when told (its ``virtual`` attribute)."""
    return bool(getattr(clock, "virtual", False))
