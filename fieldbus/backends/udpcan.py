"""``fieldbus_udp``: a lean python-can interface for CAN frames between processes on one host.

Every bus instance on a channel (an IPv4 multicast group, with its own UDP
``port``) sees the frames of every other instance on it, like python-can's
``virtual`` bus but across processes: emulated nodes in a child process, the
master in this one. Datagrams go over the loopback only (``127.0.0.1``, TTL 0).

Each frame is one fixed-size 24-byte datagram (:data:`FRAME`): magic, flags
(extended / remote / error), DLC, the sender instance's 64-bit tag, CAN id and
8 data bytes. No serializer, one ``send`` per frame; receiving reads into one
preallocated buffer. The multicast loopback hands every frame back to its
sender as well: a socket filter on the tag drops the instance's own frames in
the kernel, so they never queue nor cost a read (where the filter is refused,
the tag is checked before any ``can.Message`` is built), unless
``receive_own_messages=True``. Classic CAN only (no FD).

    can.Bus(interface="fieldbus_udp", channel="239.74.163.2", port=43114)

Registered for python-can through the ``can.interface`` entry point group
(``pyproject.toml``). Linux delivers a group's datagrams to every socket bound
to its port and joined to it; the receiving socket here is bound to the group
address itself, so only that group's datagrams arrive, but give each bus its own
port anyway (``sim_slaves.can_process.udp_bus``). One thread may receive on an
instance at a time (the receive buffer is shared); sending is thread-safe.
"""

from __future__ import annotations

import contextlib
import ipaddress
import math
import os
import select
import socket
import struct
import time
from typing import Any

import can
from can.typechecking import AutoDetectedConfig

from fieldbus.wire.sockfilter import attach_filter, drop_udp_payload_u64

INTERFACE = "fieldbus_udp"
DEFAULT_GROUP = "239.74.163.2"
DEFAULT_PORT = 43113
LOOPBACK = "127.0.0.1"
MAGIC = 0xCA7F
#: magic (u16), flags (u8), DLC (u8), sender tag (u64), CAN id (u32), 8 data bytes; little-endian, 24 bytes
FRAME = struct.Struct("<HBBQI8s")
_HEADER = struct.Struct("<HBBQI")  # FRAME without the data: parsed in place, data sliced after
DATA_OFFSET = _HEADER.size
TAG_OFFSET = 4  # the sender tag's place in a datagram
FRAME_TAG = struct.Struct("<Q")
FLAG_EXTENDED, FLAG_REMOTE, FLAG_ERROR = 1, 2, 4
_SELECT_MAX_FD = 1024  # select() takes descriptors below FD_SETSIZE only; above, poll() (1 ms steps)


class UdpCanBus(can.BusABC):
    """Classic CAN frames as fixed-size UDP multicast datagrams on the loopback (see the module)."""

    def __init__(
        self,
        channel: Any = DEFAULT_GROUP,
        port: int = DEFAULT_PORT,
        receive_own_messages: bool = False,
        can_filters: Any = None,
        fd: bool = False,
        **kwargs: object,
    ) -> None:
        """Join ``channel`` (IPv4 multicast group) on UDP ``port``; other python-can arguments
        (``bitrate``, ...) are accepted and ignored: the loopback has no bit rate.

        Raises :class:`can.CanInitializationError` for a channel that is not a
        multicast group, a bad port, ``fd=True``, or a socket the host refuses.
        """
        group = str(channel)
        try:
            is_multicast = ipaddress.IPv4Address(group).is_multicast
        except ValueError:
            is_multicast = False
        if not is_multicast:
            raise can.CanInitializationError(
                f"{INTERFACE}: channel must be an IPv4 multicast group (224.0.0.0 - 239.255.255.255), "
                f"e.g. '{DEFAULT_GROUP}', got '{channel}'"
            )
        if isinstance(port, bool) or not isinstance(port, int) or not 0 < port < 65536:
            raise can.CanInitializationError(f"{INTERFACE}: port must be an integer 1-65535, got {port!r}")
        if fd:
            raise can.CanInitializationError(f"{INTERFACE}: classic CAN only, CAN FD is not supported")
        self.channel = group
        self.port = port
        self.channel_info = f"{INTERFACE} {group}:{port}"
        self.receive_own_messages = bool(receive_own_messages)
        self._tag = int.from_bytes(os.urandom(8), "little")  # this instance's frames, as sent
        self._buf = bytearray(FRAME.size + 1)  # one spare byte: a longer datagram is seen as too long
        self._rx: socket.socket | None = None
        self._tx: socket.socket | None = None
        try:
            rx = self._rx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
            rx.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)  # every instance on the channel
            rx.bind((group, port))  # the group's address: other groups on this port stay out
            membership = socket.inet_aton(group) + socket.inet_aton(LOOPBACK)
            rx.setsockopt(socket.IPPROTO_IP, socket.IP_ADD_MEMBERSHIP, membership)
            if not self.receive_own_messages:  # the loopback's copies of own frames never queue
                with contextlib.suppress(OSError):  # refused: the tag check below still drops them
                    attach_filter(rx, drop_udp_payload_u64(TAG_OFFSET, FRAME_TAG.pack(self._tag)))
            rx.setblocking(False)
            tx = self._tx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
            tx.setsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_IF, socket.inet_aton(LOOPBACK))
            tx.setsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_LOOP, 1)
            tx.setsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_TTL, 0)  # never leaves this host
            tx.connect((group, port))  # send() without an address to resolve per frame
            tx.setblocking(False)
        except OSError as exc:
            self._close_sockets()
            raise can.CanInitializationError(
                f"{INTERFACE}: cannot open channel {group} port {port}: {exc}"
            ) from exc
        self._rx_fd = rx.fileno()
        self._poll: select.poll | None = None
        if self._rx_fd >= _SELECT_MAX_FD:
            self._poll = select.poll()
            self._poll.register(self._rx_fd, select.POLLIN)
        super().__init__(channel=group, can_filters=can_filters, **kwargs)

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        """Send ``msg`` to every other instance on the channel; waits at most ``timeout`` s
        (None: for ever) for room in the socket's send buffer.

        Raises :class:`can.CanOperationError` for a CAN FD frame, more than 8 data
        bytes, a closed bus, or a full send buffer after ``timeout``.
        """
        if msg.is_fd:
            raise can.CanOperationError(f"{INTERFACE}: classic CAN only, cannot send a CAN FD frame")
        flags = (
            (FLAG_EXTENDED if msg.is_extended_id else 0)
            | (FLAG_REMOTE if msg.is_remote_frame else 0)
            | (FLAG_ERROR if msg.is_error_frame else 0)
        )
        dlc = msg.dlc if msg.is_remote_frame else len(msg.data)
        if not 0 <= dlc <= 8:
            raise can.CanOperationError(f"{INTERFACE}: at most 8 data bytes in a classic frame, got {dlc}")
        datagram = FRAME.pack(
            MAGIC, flags, dlc, self._tag, msg.arbitration_id, b"" if msg.is_remote_frame else msg.data
        )
        tx = self._tx
        if tx is None:
            raise can.CanOperationError(f"{INTERFACE}: the bus is shut down")
        try:
            tx.send(datagram)
            return
        except BlockingIOError:
            pass
        except OSError as exc:
            raise can.CanOperationError(f"{INTERFACE}: send failed: {exc}") from exc
        try:  # the send buffer is full: wait for room, at most timeout
            _, writable, _ = select.select([], [tx], [], timeout)
            if not writable:
                raise can.CanOperationError(f"{INTERFACE}: send buffer still full after {timeout} s")
            tx.send(datagram)
        except OSError as exc:
            raise can.CanOperationError(f"{INTERFACE}: send failed: {exc}") from exc

    def _recv_internal(self, timeout: float | None) -> tuple[can.Message | None, bool]:
        """The next frame from another instance (or own, if asked), waiting at most ``timeout`` s
        (None: for ever, 0: not at all); ``(None, False)`` when none came in time."""
        rx = self._rx
        if rx is None:
            raise can.CanOperationError(f"{INTERFACE}: the bus is shut down")
        buf = self._buf
        deadline = time.perf_counter() + timeout if timeout else 0.0
        while True:
            try:
                n = rx.recv_into(buf)
            except BlockingIOError:
                if timeout is None:
                    self._wait(None)
                    continue
                remaining = deadline - time.perf_counter()
                if remaining <= 0.0 or not self._wait(remaining):
                    return None, False
                continue
            except OSError as exc:
                raise can.CanOperationError(f"{INTERFACE}: receive failed: {exc}") from exc
            if n != FRAME.size:
                continue  # not one of ours
            magic, flags, dlc, tag, can_id = _HEADER.unpack_from(buf)
            if magic != MAGIC or (tag == self._tag and not self.receive_own_messages) or dlc > 8:
                continue
            remote = bool(flags & FLAG_REMOTE)
            msg = can.Message(
                timestamp=time.time(),
                arbitration_id=can_id,
                is_extended_id=bool(flags & FLAG_EXTENDED),
                is_remote_frame=remote,
                is_error_frame=bool(flags & FLAG_ERROR),
                channel=self.channel,
                dlc=dlc,
                data=None if remote else buf[DATA_OFFSET : DATA_OFFSET + dlc],  # a copy (bytearray)
                is_rx=True,
            )
            return msg, self._filters is None  # no filters: BusABC.recv need not call the matcher

    def _wait(self, timeout: float | None) -> bool:
        """Wait until a datagram can be read, at most ``timeout`` s (None: for ever); True if one can."""
        if self._poll is None:
            readable, _, _ = select.select([self._rx_fd], [], [], timeout)
            return bool(readable)
        return bool(self._poll.poll(None if timeout is None else math.ceil(timeout * 1000)))

    def fileno(self) -> int:
        """The receiving socket's descriptor (readable when a datagram is waiting)."""
        if self._rx is None:
            raise can.CanOperationError(f"{INTERFACE}: the bus is shut down")
        return self._rx_fd

    def flush_tx_buffer(self) -> None:
        """Nothing to flush: each frame is handed to the kernel by :meth:`send`."""

    def shutdown(self) -> None:
        """Leave the group and close both sockets (safe to call again)."""
        super().shutdown()
        self._close_sockets()

    def _close_sockets(self) -> None:
        for sock in (self._rx, self._tx):
            if sock is not None:
                sock.close()
        self._rx = self._tx = None

    @staticmethod
    def _detect_available_configs() -> list[AutoDetectedConfig]:
        """The default channel (any multicast group works, with a port of its own per bus)."""
        return [{"interface": INTERFACE, "channel": DEFAULT_GROUP}]
