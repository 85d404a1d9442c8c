"""Finding SOEM's packet socket among the process's sockets, making it non-blocking, draining late frames."""

from __future__ import annotations

import socket

import pytest

from fieldbus.backends import soem_socket
from fieldbus.platform import capabilities


def test_the_new_packet_socket_is_found_among_others() -> None:
    if capabilities.missing(capabilities.CAP_NET_RAW):
        pytest.skip("an AF_PACKET socket needs CAP_NET_RAW, which this process lacks")
    before = soem_socket.open_sockets()
    udp = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    raw = socket.socket(socket.AF_PACKET, socket.SOCK_RAW, socket.htons(0x88A4))
    try:
        new = soem_socket.open_sockets() - before
        assert {udp.fileno(), raw.fileno()} <= new
        assert soem_socket.packet_sockets(new) == [raw.fileno()]
        assert not soem_socket.is_nonblocking(raw.fileno())
        soem_socket.set_nonblocking(raw.fileno())
        assert soem_socket.is_nonblocking(raw.fileno())
    finally:
        udp.close()
        raw.close()


def test_drain_reads_every_queued_frame_and_stops_at_an_empty_queue() -> None:
    a, b = socket.socketpair(socket.AF_UNIX, socket.SOCK_DGRAM)
    try:
        soem_socket.set_nonblocking(b.fileno())
        for k in range(3):
            a.send(bytes([k]) * 60)
        buf = [bytearray(soem_socket.MAX_FRAME)]
        assert soem_socket.drain([b.fileno()], buf) == 3
        assert soem_socket.drain([b.fileno()], buf) == 0
    finally:
        a.close()
        b.close()
