"""Single datagrams of our own on SOEM's packet sockets: what pysoem has no call for (position addressing).

pysoem reaches a slave's registers only at its configured station address
(``_fprd`` / ``_fpwr``). A power-cycled slave has lost that address, and SOEM
finds it again by position in ``ecx_recover_slave``, one call of many frames
with 20 ms EEPROM timeouts. Recovery here sends those datagrams itself, one
per cycle: each frame is built with :mod:`fieldbus.core.ecat`, written to
SOEM's primary socket, and its reply polled for (``select`` with a zero
timeout, which releases the GIL each time) for at most the timeout given: a
spin, as SOEM's own wait on its non-blocking socket, because a thread that
sleeps in ``select`` wakes up later than a spinner notices on a loaded
machine (docs/reliability.md, "A redundant port").

Frames carry indexes from 0x80 up: SOEM uses 0..15 (``EC_MAXBUF``) and drops
a frame with another index, so neither takes the other's reply. Other frames
read while waiting (a late reply of an earlier cycle) are dropped and counted
in :attr:`RawDatagrams.dropped`, as :func:`~fieldbus.backends.soem_socket.drain`
would have. The sockets are duplicates of SOEM's, read with ``MSG_DONTWAIT``:
SOEM's own blocking or non-blocking mode is left as it is. With a redundant
port a frame goes out of the primary port only and its reply is taken from
either.
"""

from __future__ import annotations

import os
import select
import socket
import time

from fieldbus.backends.soem_socket import MAX_FRAME
from fieldbus.core.ecat import Datagram, FrameError, build_master_frame, decode_frame

FIRST_INDEX = 0x80  # frame indexes 0x80..0x8F: outside SOEM's 0..15


class RawDatagrams:
    """One datagram per call on SOEM's sockets ``fds`` (primary first), its reply awaited a bounded time."""

    def __init__(self, fds: list[int]) -> None:
        self._socks = [socket.socket(fileno=os.dup(fd)) for fd in fds]
        self._buf = bytearray(MAX_FRAME)
        self._n = 0
        self.sent = 0  # frames sent
        self.dropped = 0  # frames read while waiting that were not the awaited reply

    def txrx(self, datagram: Datagram, timeout_us: int) -> Datagram | None:
        """Send ``datagram`` alone in a frame; its reply, or None when none came within ``timeout_us``."""
        idx = FIRST_INDEX + self._n
        self._n = (self._n + 1) % 16
        d = Datagram(datagram.cmd, idx, datagram.address, datagram.data)
        frame = build_master_frame([d])
        deadline = time.perf_counter_ns() + timeout_us * 1000
        self._socks[0].send(frame)
        self.sent += 1
        while time.perf_counter_ns() < deadline:
            ready, _, _ = select.select(self._socks, [], [], 0)
            for s in ready:
                got = self._read(s, d)
                if got is not None:
                    return got
        return None

    def _read(self, s: socket.socket, sent: Datagram) -> Datagram | None:
        """Every frame queued on ``s``; the reply to ``sent`` if among them (the rest dropped)."""
        found = None
        while True:
            try:
                n = s.recv_into(self._buf, MAX_FRAME, socket.MSG_DONTWAIT)
            except BlockingIOError:
                return found
            try:
                dgs = decode_frame(memoryview(self._buf)[:n]).datagrams
            except FrameError:
                dgs = ()
            if (
                found is None
                and len(dgs) == 1
                and (dgs[0].cmd, dgs[0].idx, dgs[0].ado) == (sent.cmd, sent.idx, sent.ado)  # ADP: incremented
                and self._buf[6] & 0x02  # source MAC marked by a slave on the way back (not our own frame)
            ):
                found = dgs[0]
            else:
                self.dropped += 1

    def close(self) -> None:
        for s in self._socks:
            s.close()
        self._socks = []
