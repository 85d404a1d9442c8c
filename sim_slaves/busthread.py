"""Serving an emulator's python-can bus: one daemon thread per emulator, or several emulators in one thread."""

from __future__ import annotations

import select
import threading
from collections.abc import Sequence
from typing import Any, Self

JOIN_TIMEOUT_S = 2.0


class BusThread:
    """Base of the CAN emulators: :meth:`serve` handles one frame; the thread loops on it until stopped."""

    thread_name = "bus-emulator"
    idle_wait_s = 0.05  # longest wait for a frame before the loop looks at its stop flag (and timers)
    bus: Any

    def __init__(self) -> None:
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    def _on_start(self) -> None:
        """Called before the emulator serves (e.g. boot-up messages)."""

    def serve(self, timeout: float) -> bool:
        """Wait at most ``timeout`` s for a frame and handle it, then what is due; True if a frame came."""
        raise NotImplementedError

    def idle(self) -> None:
        """What is due without a frame (timers); :func:`serve_together` calls it on every wake-up."""

    def _run(self) -> None:
        while not self._stop.is_set():
            self.serve(self.idle_wait_s)

    def start(self) -> Self:
        self._on_start()
        self._stop.clear()
        self._thread = threading.Thread(target=self._run, name=self.thread_name, daemon=True)
        self._thread.start()
        return self

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=JOIN_TIMEOUT_S)
            self._thread = None
        log = getattr(self, "log", None)  # an emulator's frame log (fieldbus.wire.canlog)
        if log is not None:
            log.close()

    def __enter__(self) -> Self:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()


def serve_together(emulators: Sequence[BusThread], stop: threading.Event) -> None:
    """Serve every emulator's bus from the calling thread until ``stop`` is set.

    One ``select`` over the buses' descriptors, then every frame queued on each
    readable bus, in order, before the next bus's: a single thread, so the emulators of several buses take one CPU and
    no interpreter-lock hand-over between threads. Boots each first (as
    :meth:`BusThread.start` does). Raises ``ValueError`` for a bus without a
    descriptor (python-can's ``fileno()``: the ``virtual`` interface has none).
    """
    by_fd: dict[int, BusThread] = {}
    for e in emulators:
        try:
            fd = e.bus.fileno()
        except NotImplementedError:
            fd = -1
        if not isinstance(fd, int) or fd < 0:
            raise ValueError(
                f"serve_together: bus {e.bus!r} has no file descriptor; give each emulator its thread"
            )
        by_fd[fd] = e
    fds = list(by_fd)
    wait = min(e.idle_wait_s for e in emulators)
    for e in emulators:
        e._on_start()
    while not stop.is_set():
        ready, _, _ = select.select(fds, [], [], wait)
        for fd in ready:
            e = by_fd[fd]
            while e.serve(0.0):  # a bus's frames in the order they came, before the next bus's
                pass
        for e in emulators:
            e.idle()
