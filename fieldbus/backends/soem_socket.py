"""Make SOEM's receive wait end at the timeout: its packet sockets, found and set non-blocking.

SOEM's Linux NIC layer reads with ``recv`` on a blocking AF_PACKET socket whose
``SO_RCVTIMEO`` is 1 µs; the kernel rounds that up to a whole scheduler tick
(4 ms at HZ=250), and SOEM loops until its own timer (the receive timeout)
has expired. So a lost frame costs 4-10 ms instead of the timeout: measured
on the veth emulator, ``receive_processdata(500)`` on a dropped frame returned
after 4.6-10.6 ms.

With the socket non-blocking, ``recv`` returns at once (EAGAIN) and SOEM's
own loop - ``ecx_waitinframe``: read, compare the frame index, check the
timer - polls until the reply or the timer, so the wait ends within the
timeout. Nothing else in SOEM changes: frames are still matched by index,
frames for other indexes are still parked in their buffers, and with a
redundant port both sockets are set the same way. The cost is CPU: the
thread that waits spins (with the GIL released) for as long as the reply
takes - the round trip, typically tens to hundreds of µs - or the whole
timeout when a frame is lost. And a reply that comes later than its
timeout stays queued until it is read: :func:`drain` drops those before each
cycle's frame is sent (SOEM would match it to a later frame that reuses its
index).

pysoem does not expose the socket, so :func:`packet_sockets` compares this
process's open sockets before and after ``Master.open`` and keeps the new
AF_PACKET ones.
"""

from __future__ import annotations

import fcntl
import os
import socket

FD_DIR = "/proc/self/fd"
MAX_FRAME = 1518  # bytes of an Ethernet frame (without FCS)


def open_sockets() -> set[int]:
    """File descriptors of this process that are sockets (Linux, from /proc/self/fd)."""
    fds = set()
    for name in os.listdir(FD_DIR):
        try:
            if os.readlink(f"{FD_DIR}/{name}").startswith("socket:"):
                fds.add(int(name))
        except OSError:  # closed meanwhile
            continue
    return fds


def packet_sockets(fds: set[int]) -> list[int]:
    """Those of ``fds`` that are AF_PACKET sockets (SOEM's), in order."""
    out = []
    for fd in sorted(fds):
        try:
            dup = socket.socket(fileno=os.dup(fd))
        except OSError:
            continue
        try:
            if dup.family == socket.AF_PACKET:
                out.append(fd)
        finally:
            dup.close()
    return out


def set_nonblocking(fd: int) -> None:
    flags = fcntl.fcntl(fd, fcntl.F_GETFL)
    fcntl.fcntl(fd, fcntl.F_SETFL, flags | os.O_NONBLOCK)


def is_nonblocking(fd: int) -> bool:
    return bool(fcntl.fcntl(fd, fcntl.F_GETFL) & os.O_NONBLOCK)


def drain(fds: list[int], buf: list[bytearray]) -> int:
    """Read and drop every frame queued on the (non-blocking) sockets ``fds``; returns how many.

    Called just before a cycle's frame is sent: SOEM has nothing in flight then,
    so whatever is queued is a reply that came too late (or an echo of a
    frame already handled). SOEM matches replies by frame index alone, and
    with 16 indexes a reply late by 16 frames would otherwise be taken for
    the current frame's. ``buf``: a preallocated one-buffer list (no allocation).
    """
    n = 0
    for fd in fds:
        while True:
            try:
                os.readv(fd, buf)
            except BlockingIOError:
                break
            n += 1
    return n
