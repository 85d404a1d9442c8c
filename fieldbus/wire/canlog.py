"""CAN frame logs in python-can's formats, written beside the cycle, never in it.

:class:`LoggedBus` wraps a python-can bus: every frame sent or received through
it is copied into a preallocated :class:`FrameRing` (numpy arrays, no object
kept per frame), and a :class:`CanLogWriter` thread turns the ring's frames into
``can.Message`` objects for one of python-can's writers, chosen by the file's
suffix (``.log`` candump, ``.asc`` Vector ASC, ``.blf`` Vector BLF, ``.csv``,
``.trc``). The cycle only copies a frame (at most 64 data bytes); a full ring
drops the newest frames and counts them, a failing disk stops the log with one
warning. Directions are the logging side's: ``is_rx`` for a frame it received.
"""

from __future__ import annotations

import sys
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np

from fieldbus.errors import FieldbusError

FORMATS = (".log", ".asc", ".blf", ".csv", ".trc")
RING_FRAMES = 1 << 16  # about 6 s of a saturated 1 Mbit/s bus
FLUSH_S = 0.05  # the writer thread wakes this often
MAX_DATA = 64  # CAN FD

_EXT, _RX, _FD, _RTR, _ERR = 1, 2, 4, 8, 16


class FrameRing:
    """Single-writer ring of CAN frames: time (s), id, flags, length, data."""

    def __init__(self, capacity: int = RING_FRAMES) -> None:
        self.capacity = capacity
        self.t = np.zeros(capacity, dtype=np.float64)
        self.can_id = np.zeros(capacity, dtype=np.uint32)
        self.flags = np.zeros(capacity, dtype=np.uint8)
        self.length = np.zeros(capacity, dtype=np.uint8)
        self.data = np.zeros((capacity, MAX_DATA), dtype=np.uint8)
        self.head = 0  # frames put (ever)
        self.tail = 0  # frames taken by the writer (ever)
        self.dropped = 0  # frames not logged because the ring was full
        self._put_lock = (
            threading.Lock()
        )  # between producers only (e.g. an emulator's hooks); never the writer

    def put(self, msg: Any, rx: bool, t: float | None = None) -> None:
        """Copy one ``can.Message`` into the ring (no object kept); a full ring drops it and counts it.

        ``t``: the frame's time (s since the epoch), else the message's own timestamp.
        """
        with self._put_lock:
            head = self.head
            if head - self.tail >= self.capacity:
                self.dropped += 1
                return
            i = head % self.capacity
            n = min(len(msg.data), MAX_DATA)
            self.t[i] = msg.timestamp if t is None else t
            self.can_id[i] = msg.arbitration_id
            self.flags[i] = (
                (_EXT if msg.is_extended_id else 0)
                | (_RX if rx else 0)
                | (_FD if msg.is_fd else 0)
                | (_RTR if msg.is_remote_frame else 0)
                | (_ERR if msg.is_error_frame else 0)
            )
            self.length[i] = n
            if n:
                self.data[i, :n] = msg.data[:n]
            self.head = head + 1  # published last: the writer reads up to here


class CanLogWriter:
    """Thread draining a :class:`FrameRing` into a python-can writer for ``path``.

    The file is opened at construction: a path that cannot be written fails
    here, before any bus starts (:class:`~fieldbus.errors.FieldbusError`).
    """

    def __init__(self, path: str | Path, ring: FrameRing, *, name: str = "can-log") -> None:
        import can

        self.path = Path(path)
        if self.path.suffix.lower() not in FORMATS:
            raise FieldbusError(
                f"CAN log {self.path}: unknown format '{self.path.suffix}' (one of {', '.join(FORMATS)})"
            )
        try:
            self._out: Any = can.Logger(str(self.path))
        except OSError as exc:
            raise FieldbusError(f"CAN log {self.path}: cannot write ({exc.strerror or exc})") from exc
        self.ring = ring
        self.written = 0
        self.error: str | None = None  # why logging stopped early (e.g. disk full)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name=name, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.wait(FLUSH_S):
            self._drain()
        self._drain()

    def _drain(self) -> None:
        import can

        ring = self.ring
        head = ring.head
        while ring.tail < head and self.error is None:
            i = ring.tail % ring.capacity
            flags = int(ring.flags[i])
            n = int(ring.length[i])
            msg = can.Message(
                timestamp=float(ring.t[i]),
                arbitration_id=int(ring.can_id[i]),
                is_extended_id=bool(flags & _EXT),
                is_rx=bool(flags & _RX),
                is_fd=bool(flags & _FD),
                is_remote_frame=bool(flags & _RTR),
                is_error_frame=bool(flags & _ERR),
                dlc=n,
                data=bytes(ring.data[i, :n]),
                channel=None,
            )
            ring.tail += 1
            try:
                self._out.on_message_received(msg)
            except OSError as exc:  # disk full, device gone: the cycle goes on without the log
                self.error = (
                    f"CAN log {self.path}: stopped after {self.written} frames ({exc.strerror or exc})"
                )
                print(f"warning: {self.error}", file=sys.stderr)
                ring.tail = ring.head  # nothing more will be written
                return
            self.written += 1

    def close(self) -> None:
        """Write what is left and close the file (idempotent)."""
        if self._stop.is_set():
            return
        self._stop.set()
        self._thread.join(timeout=5.0)
        try:
            self._out.stop()
        except OSError as exc:
            if self.error is None:
                self.error = f"CAN log {self.path}: closing failed ({exc.strerror or exc})"
                print(f"warning: {self.error}", file=sys.stderr)


class LoggedBus:
    """A python-can bus whose every sent and received frame also goes to ``log``."""

    def __init__(self, bus: Any, log: CanLogWriter) -> None:
        self.bus = bus
        self.log = log
        self._ring = log.ring

    def send(self, msg: Any, timeout: float | None = None) -> None:
        self.bus.send(msg, timeout)
        self._ring.put(msg, rx=False, t=time.time())  # a sent message carries no time of its own

    def recv(self, timeout: float | None = None) -> Any:
        msg = self.bus.recv(timeout)
        if msg is not None:
            self._ring.put(msg, rx=True)
        return msg

    def __getattr__(self, name: str) -> Any:
        return getattr(self.bus, name)


def open_log(path: str | Path | None) -> CanLogWriter | None:
    """A running log writer for ``path`` (None: no log); fails at once if it cannot be written."""
    return CanLogWriter(path, FrameRing()) if path else None
