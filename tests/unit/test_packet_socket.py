"""A packet socket receives from its one interface only, from its first frame on
(:mod:`fieldbus.wire.packet_socket`), on two veth pairs of this test's own."""

from __future__ import annotations

import select
import socket
from collections.abc import Iterator

import pytest

from fieldbus.wire import packet_socket
from fieldbus.wire.packet_socket import ETH_P_ALL, bound_packet_socket
from sim_slaves.ethercat.veth import VethUnavailable, delete_link, make_veth_pair

ETHERTYPE_ECAT = b"\x88\xa4"


def _frame(marker: bytes) -> bytes:
    """An EtherCAT-typed frame from a made-up source MAC that carries ``marker``."""
    return b"\xff" * 6 + b"\x02\x00\x00\x00\x00\x07" + ETHERTYPE_ECAT + marker + bytes(60 - 14 - len(marker))


def _received(sock: socket.socket, wait_s: float = 0.2) -> list[bytes]:
    """Every frame queued on ``sock`` (waiting ``wait_s`` [s] for the first)."""
    got = []
    sock.setblocking(False)
    while select.select([sock], [], [], wait_s if not got else 0.0)[0]:
        got.append(sock.recv(2048))
    return got


@pytest.fixture
def two_pairs() -> Iterator[tuple[tuple[str, str], tuple[str, str]]]:
    """Two veth pairs (master end, peer end); skips only when the machine refuses a pair, saying why."""
    made: list[str] = []
    try:
        pairs = []
        for _ in range(2):
            pairs.append(make_veth_pair())
            made.append(pairs[-1][0])
    except VethUnavailable as exc:
        for name in made:
            delete_link(name)
        pytest.skip(str(exc))
    try:
        yield pairs[0], pairs[1]
    finally:
        for name in made:
            delete_link(name)


def _window_sender(monkeypatch: pytest.MonkeyPatch, iface: str, frame: bytes) -> None:
    """Every packet socket bound from now on first sends ``frame`` on ``iface``: a frame of another
    segment in the window between the socket's making and its bind."""
    sender = socket.socket(socket.AF_PACKET, socket.SOCK_RAW, 0)
    sender.bind((iface, 0))
    real_bind = socket.socket.bind

    def bind(self: socket.socket, address: object) -> None:
        sender.send(frame)
        real_bind(self, address)

    monkeypatch.setattr(socket.socket, "bind", bind)


def test_a_socket_made_with_its_protocol_keeps_another_interface_s_frame_from_before_its_bind(
    two_pairs: tuple[tuple[str, str], tuple[str, str]], monkeypatch: pytest.MonkeyPatch
) -> None:
    """The kernel's behaviour that the helper avoids (packet(7)), shown: this is how a test's raw port
    read a reply of the 30-drive demo running beside it."""
    (mine, _), (other, _) = two_pairs
    _window_sender(monkeypatch, other, _frame(b"other"))
    sock = socket.socket(socket.AF_PACKET, socket.SOCK_RAW, socket.htons(ETH_P_ALL))
    try:
        sock.bind((mine, ETH_P_ALL))
        assert any(b"other" in f for f in _received(sock))
    finally:
        sock.close()


def test_the_bound_socket_takes_nothing_from_another_interface_and_its_own_frames(
    two_pairs: tuple[tuple[str, str], tuple[str, str]], monkeypatch: pytest.MonkeyPatch
) -> None:
    (mine, my_peer), (other, _) = two_pairs
    _window_sender(monkeypatch, other, _frame(b"other"))
    sock = bound_packet_socket(mine)
    monkeypatch.undo()
    try:
        assert sock.proto == 0  # made without a protocol: it received nothing before its bind
        with socket.socket(socket.AF_PACKET, socket.SOCK_RAW, 0) as peer:
            peer.bind((my_peer, 0))
            peer.send(_frame(b"mine"))
        got = _received(sock)
        assert any(b"mine" in f for f in got), got  # its own interface's frames, every protocol
        assert not any(b"other" in f for f in got), got
    finally:
        sock.close()


def test_a_missing_interface_is_an_os_error() -> None:
    with pytest.raises(OSError):
        packet_socket.bound_packet_socket("fbnone0")
