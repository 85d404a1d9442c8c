"""One daemon thread serving an emulator's python-can bus: start/stop and the context manager."""

from __future__ import annotations

import threading
from typing import Self

JOIN_TIMEOUT_S = 2.0


class BusThread:
    """Base of the CAN emulators: :meth:`_run` loops until :attr:`_stop` is set."""

    thread_name = "bus-emulator"

    def __init__(self) -> None:
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    def _on_start(self) -> None:
        """Called by :meth:`start` before the thread runs (e.g. boot-up messages)."""

    def _run(self) -> None:
        raise NotImplementedError

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
        log = getattr(self, "log", None)  # an emulator's frame log (fieldbus.backends.canlog)
        if log is not None:
            log.close()

    def __enter__(self) -> Self:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()
