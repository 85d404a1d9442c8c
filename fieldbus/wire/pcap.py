"""EtherCAT frames of one network card to a pcap file, from a side thread.

:class:`EthercatCapture` opens its own AF_PACKET socket on the master's card,
for every protocol (Linux hands a card's outgoing frames only to those), and
keeps the EtherCAT frames (EtherType 0x88A4): the ones SOEM sends and the
replies, bring-up included, without touching SOEM. The thread blocks in
``recv`` (the GIL released) and writes each frame with the time it read it;
the cycle is not involved, it only shares the CPU and the GIL for a few µs per
frame (every frame of the card, EtherCAT or not, is looked at). Needs the same rights as the master (root or
CAP_NET_RAW). Classic pcap, linktype 1 (Ethernet): tshark and Wireshark decode
it with their EtherCAT dissector.
"""

from __future__ import annotations

import contextlib
import socket
import struct
import sys
import threading
import time
from pathlib import Path
from typing import BinaryIO

from fieldbus.errors import FieldbusError
from fieldbus.wire.packet_socket import ETH_P_ALL, bound_packet_socket

ETH_P_ECAT = 0x88A4
PCAP_LINKTYPE_ETHERNET = 1
_PCAP_HEADER = struct.Struct("<IHHiIII")
_PCAP_RECORD = struct.Struct("<IIII")
_SNAPLEN = 65535
DRAIN_S = 5.0  # at close, the capture thread writes the frames still queued for at most this long
CAPTURE_BUFFER = 4 << 20  # the capture socket's receive buffer [bytes]: a thread kept off the CPU for a
# while (a loaded machine) finds the frames of that while queued, not dropped (the default is ~200 kB)
SOL_PACKET = 263
PACKET_STATISTICS = 6  # struct tpacket_stats {unsigned tp_packets, tp_drops}: read resets them


class PcapWriter:
    """Classic pcap file (microsecond timestamps, linktype 1 = Ethernet)."""

    def __init__(self, path: str | Path) -> None:
        self._f: BinaryIO = open(path, "wb")  # noqa: SIM115 - closed in close()
        self._f.write(_PCAP_HEADER.pack(0xA1B2C3D4, 2, 4, 0, 0, _SNAPLEN, PCAP_LINKTYPE_ETHERNET))

    def write(self, frame: bytes | memoryview, t_s: float) -> None:
        """One frame received or sent at ``t_s`` (seconds since the epoch)."""
        sec = int(t_s)
        self._f.write(_PCAP_RECORD.pack(sec, int((t_s - sec) * 1e6), len(frame), len(frame)))
        self._f.write(frame)

    def flush(self) -> None:
        self._f.flush()

    def close(self) -> None:
        if not self._f.closed:
            self._f.close()


class EthercatCapture:
    """Capture every EtherCAT frame on ``iface`` into ``path`` until :meth:`close`.

    The file is created at construction (an unwritable path fails before any
    bus starts); the socket opens with :meth:`start`.
    """

    def __init__(self, path: str | Path, iface: str) -> None:
        self.path = Path(path)
        self.iface = iface
        try:
            self._writer = PcapWriter(self.path)
        except OSError as exc:
            raise FieldbusError(f"pcap {self.path}: cannot write ({exc.strerror or exc})") from exc
        self.frames = 0
        self.dropped = 0  # frames the kernel dropped before the capture thread read them
        self.error: str | None = None
        self._sock: socket.socket | None = None
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    def start(self) -> None:
        """Open the capture socket on the card and start the thread (idempotent)."""
        if self._thread is not None:
            return
        try:
            # ETH_P_ALL: Linux hands a card's outgoing frames only to sockets of every protocol
            sock = bound_packet_socket(self.iface, ETH_P_ALL)
        except OSError as exc:
            raise FieldbusError(
                f"pcap on '{self.iface}': cannot open a packet socket ({exc.strerror or exc}); "
                "it needs root or CAP_NET_RAW, like the master"
            ) from exc
        with contextlib.suppress(OSError):  # a smaller buffer still captures; drops are then counted
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, CAPTURE_BUFFER)
        sock.settimeout(0.1)  # to see close() without a frame
        self._sock = sock
        self._thread = threading.Thread(target=self._run, name=f"pcap-{self.iface}", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        assert self._sock is not None
        buf = bytearray(_SNAPLEN)
        view = memoryview(buf)
        drain_until = 0.0  # closing: the frames still queued are written, for at most DRAIN_S
        while True:
            try:
                n = self._sock.recv_into(buf)
            except TimeoutError:
                if self._stop.is_set():
                    return  # closing, and the socket read empty: every frame before close() is written
                continue
            except OSError:
                return  # closed
            if self._stop.is_set():
                if not drain_until:
                    drain_until = time.monotonic() + DRAIN_S
                elif time.monotonic() > drain_until:
                    return  # frames keep coming (another master on the card): stop anyway
            if n < 14 or (buf[12] << 8 | buf[13]) != ETH_P_ECAT:
                continue
            try:
                self._writer.write(view[:n], time.time())
            except OSError as exc:  # disk full: stop capturing, the bus goes on
                self.error = f"pcap {self.path}: stopped after {self.frames} frames ({exc.strerror or exc})"
                print(f"warning: {self.error}", file=sys.stderr)
                return
            self.frames += 1

    def close(self) -> None:
        """Stop the thread, close the socket and the file (idempotent); frames the kernel dropped (the
        thread behind by more than the socket's buffer) are counted in :attr:`dropped` and :attr:`error`."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=DRAIN_S + 1.0)
            self._thread = None
        if self._sock is not None:
            with contextlib.suppress(OSError):
                _, drops = struct.unpack("II", self._sock.getsockopt(SOL_PACKET, PACKET_STATISTICS, 8))
                self.dropped += drops
            self._sock.close()
            self._sock = None
            if self.dropped and self.error is None:
                self.error = (
                    f"pcap {self.path}: the kernel dropped {self.dropped} frames (the capture thread fell "
                    "behind); the file lacks them"
                )
        try:
            self._writer.close()
        except OSError as exc:
            self.error = self.error or f"pcap {self.path}: closing failed ({exc.strerror or exc})"
