"""RawDatagrams (fieldbus.backends.ecat_raw): one frame out, its reply matched, the rest dropped, the wait bounded.

A UNIX datagram socket pair stands in for SOEM's packet socket (the code
only sends and receives whole frames on it); the far end answers as the
emulated ESC chain would (sim_slaves' EscChain), or not at all. Over a real
packet socket it runs in tests/integration/test_bounded_steps.py.
"""

from __future__ import annotations

import socket
import threading
from collections.abc import Iterator

import pytest

from fieldbus.backends.ecat_raw import FIRST_INDEX, RawDatagrams
from fieldbus.commands.demo import DEMO_MAP
from fieldbus.core.ecat import Command, Datagram, build_master_frame, decode_frame
from fieldbus.core.pdo import load_drive_map
from sim_slaves.ethercat import EscChain


@pytest.fixture
def pair() -> Iterator[tuple[socket.socket, socket.socket]]:
    a, b = socket.socketpair(socket.AF_UNIX, socket.SOCK_DGRAM)
    yield a, b
    a.close()
    b.close()


def _answer(far: socket.socket, chain: EscChain, before: list[bytes]) -> None:
    """Send ``before`` (frames that are not the reply), then the chain's reply to the frame that came."""
    frame = far.recv(2000)
    for junk in before:
        far.send(junk)
    reply = chain.process(frame, 0)
    assert reply is not None
    far.send(reply)


def test_the_reply_is_found_among_other_frames(pair: tuple[socket.socket, socket.socket]) -> None:
    near, far = pair
    chain = EscChain.from_maps([load_drive_map(DEMO_MAP)] * 2)
    raw = RawDatagrams([near.fileno()])
    late_lrw = build_master_frame([Datagram(Command.LRW, 3, 0, bytes(8))])  # a late reply SOEM would want
    echo = build_master_frame([Datagram.physical(Command.APRD, -1, 0x0130, bytes(2), FIRST_INDEX)])
    t = threading.Thread(target=_answer, args=(far, chain, [late_lrw, echo]))
    t.start()
    got = raw.txrx(Datagram.physical(Command.APRD, -1, 0x0130, bytes(2)), 500_000)
    t.join()
    assert got is not None and got.wkc == 1 and got.idx == FIRST_INDEX
    assert int.from_bytes(got.data, "little") & 0x0F == 0x01  # the second slave, in INIT
    assert raw.dropped == 2  # the late LRW and our own frame without a slave's mark
    raw.close()


def test_no_reply_ends_at_the_timeout_and_indexes_stay_out_of_soems(
    pair: tuple[socket.socket, socket.socket],
) -> None:
    near, far = pair
    raw = RawDatagrams([near.fileno()])
    for _ in range(20):
        assert raw.txrx(Datagram.physical(Command.BRD, 0, 0x0130, bytes(2)), 200) is None
    sent = [decode_frame(far.recv(2000)).datagrams[0].idx for _ in range(20)]
    assert all(FIRST_INDEX <= i < FIRST_INDEX + 16 for i in sent)  # SOEM uses 0..15
    assert raw.sent == 20
    raw.close()
