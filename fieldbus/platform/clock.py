"""Clocks the cycle reads: the machine's own, or a virtual one that a test advances.

The protocol, :class:`~fieldbus.core.clock.Clock`, is the core's; the clocks
that implement it are here, below the backends that read them.

Everything that paces or times out inside the library asks a :class:`Clock`
instead of :mod:`time`, so a test can run a 10 s scenario at 1 kHz as fast as
the CPU allows with the same result on a busy or a quiet machine.

A :class:`VirtualClock` moves only when told (:meth:`VirtualClock.advance`,
``sleep``). In-process emulators that have timers of their own (CANopen
heartbeats, event timers) watch it with :meth:`VirtualClock.watch`: while time
passes they are called at every step of at most ``step_ns``, in order, so a
10 ms sleep lets a 1 ms timer fire ten times at the right instants.
"""

from __future__ import annotations

import ctypes
import sys
import time
from collections.abc import Callable

from fieldbus.core.clock import Clock as Clock
from fieldbus.core.clock import is_virtual as is_virtual


class WallClock:
    """The machine's monotonic clock (``time.monotonic_ns``) and ``time.sleep``."""

    virtual = False

    def now_ns(self) -> int:
        return time.monotonic_ns()

    def sleep(self, seconds: float) -> None:
        if seconds > 0:
            time.sleep(seconds)


class DeadlineClock(WallClock):
    """The monotonic clock, waiting by an absolute sleep (``clock_nanosleep`` with ``TIMER_ABSTIME`` on
    ``CLOCK_MONOTONIC``) to ``spin_ns`` before each deadline, then spinning only that long.

    A cycle thread at SCHED_FIFO that spins for long counts as busy: past
    ``/proc/sys/kernel/sched_rt_runtime_us`` (950 ms in every 1 s by default)
    the kernel throttles every real-time thread on the CPU for the rest of the
    period, a stall of tens of ms. An absolute sleep does not drift with the
    time the call takes to start; elsewhere than Linux it is ``time.sleep``.
    """

    def __init__(self, spin_ns: int = 30_000) -> None:
        self.spin_ns = spin_ns
        self._nanosleep = _clock_nanosleep()

    def sleep_until_ns(self, deadline_ns: int) -> None:
        """Sleep until the monotonic clock reads ``deadline_ns`` (an OS sleep: it may wake a little late)."""
        if self._nanosleep is None:
            self.sleep((deadline_ns - self.now_ns()) / 1e9)
            return
        ts = _Timespec(deadline_ns // 1_000_000_000, deadline_ns % 1_000_000_000)
        while self._nanosleep(_CLOCK_MONOTONIC, _TIMER_ABSTIME, ctypes.byref(ts), None) == _EINTR:
            pass  # a signal woke it: sleep on to the same deadline


_CLOCK_MONOTONIC, _TIMER_ABSTIME, _EINTR = 1, 1, 4  # Linux's values (time.h, errno.h)


class _Timespec(ctypes.Structure):
    _fields_ = [("tv_sec", ctypes.c_long), ("tv_nsec", ctypes.c_long)]


def _clock_nanosleep() -> Callable[..., int] | None:
    """libc's ``clock_nanosleep`` (which returns the error number), or None where there is none."""
    if not sys.platform.startswith("linux"):
        return None
    try:
        fn = ctypes.CDLL(None).clock_nanosleep
    except (OSError, AttributeError):
        return None
    fn.argtypes = [ctypes.c_int, ctypes.c_int, ctypes.POINTER(_Timespec), ctypes.c_void_p]
    fn.restype = ctypes.c_int
    return fn


Watcher = Callable[[int], None]
"""Called with the virtual time (ns) each time a :class:`VirtualClock` has moved by one step."""

DEFAULT_STEP_NS = 1_000_000  # watchers see time pass in steps of at most 1 ms


class VirtualClock:
    """Time that passes only when told: :meth:`advance` or :meth:`sleep`. Starts at ``start_ns``.

    ``step_ns``: the largest step in which watchers (:meth:`watch`) see time pass.
    """

    virtual = True

    def __init__(self, start_ns: int = 0, *, step_ns: int = DEFAULT_STEP_NS) -> None:
        if step_ns <= 0:
            raise ValueError(f"step_ns must be > 0, got {step_ns}")
        self._t = int(start_ns)
        self.step_ns = int(step_ns)
        self._watchers: list[Watcher] = []
        self._advancing = False

    def now_ns(self) -> int:
        return self._t

    def sleep(self, seconds: float) -> None:
        self.advance(round(seconds * 1e9))

    def advance(self, ns: int) -> None:
        """Move time forward by ``ns`` (>= 0); watchers are called after every step of at most ``step_ns``."""
        if ns < 0:
            raise ValueError(f"a virtual clock does not go backwards ({ns} ns)")
        self.advance_to(self._t + int(ns))

    def advance_to(self, t_ns: int) -> None:
        """Move time forward to ``t_ns`` (nothing happens when it is already there or later)."""
        if not self._watchers or self._advancing:
            # a watcher that sleeps (an emulator waiting) moves time without calling watchers again
            self._t = max(self._t, int(t_ns))
            return
        self._advancing = True
        try:
            while self._t < t_ns:
                self._t = min(int(t_ns), self._t + self.step_ns)
                for w in tuple(self._watchers):
                    w(self._t)
        finally:
            self._advancing = False

    def watch(self, watcher: Watcher) -> None:
        """Call ``watcher(now_ns)`` after every step of time from now on (in the order they were added)."""
        self._watchers.append(watcher)

    def unwatch(self, watcher: Watcher) -> None:
        """Stop calling ``watcher`` (quiet when it is not watching)."""
        if watcher in self._watchers:
            self._watchers.remove(watcher)


def sleep_until(clock: Clock, deadline_ns: int, spin_ns: int = 0) -> None:
    """Let time pass until ``clock.now_ns() >= deadline_ns``.

    A wall clock sleeps until ``spin_ns`` before the deadline, then spins (an
    OS sleep overshoots); a virtual clock jumps to the deadline at once.
    """
    if is_virtual(clock):
        now = clock.now_ns()
        if now < deadline_ns:
            advance_to = getattr(clock, "advance_to", None)
            if callable(advance_to):
                advance_to(deadline_ns)
            else:
                clock.sleep((deadline_ns - now) / 1e9)
        return
    absolute = getattr(clock, "sleep_until_ns", None)
    if callable(absolute):  # a DeadlineClock: an absolute sleep, then its own (short) spin
        spin_ns = clock.spin_ns  # type: ignore[attr-defined]
        if deadline_ns - clock.now_ns() > spin_ns:
            absolute(deadline_ns - spin_ns)
    else:
        remaining = deadline_ns - clock.now_ns()
        if remaining > spin_ns:
            clock.sleep((remaining - spin_ns) / 1e9)
    while clock.now_ns() < deadline_ns:
        pass


def as_clock(clock: object | None) -> Clock:
    """``clock`` as a :class:`Clock`: None is the wall clock; an object with ``now_ns`` and ``sleep`` is one."""
    if clock is None:
        return WALL
    if isinstance(clock, Clock):
        return clock
    raise TypeError(f"not a Clock (needs now_ns() and sleep()): {clock!r}")


WALL = WallClock()


def monotonic_s(clock: object | None) -> Callable[[], float]:
    """Seconds on ``clock`` (a :class:`Clock`), or ``time.monotonic`` when it is None or not one.

    For backends that count time in seconds: ``self._now = monotonic_s(options.get("clock"))``.
    """
    if isinstance(clock, Clock):
        now_ns = clock.now_ns
        return lambda: now_ns() / 1e9
    return time.monotonic
