"""Fuzzing the wire: random and mutated EtherCAT frames into the ESC chain and the frame decoder.

Nothing may crash or hang: a frame is answered, dropped, or refused with
:class:`~fieldbus.core.ecat.FrameError` (a FieldbusError). CI runs 2,000
cases per test (``FIELDBUS_FUZZ_EXAMPLES`` raises it; docs/reliability.md).
"""

from __future__ import annotations

import contextlib
import os
import struct

from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from fieldbus.commands.demo import DEMO_MAP
from fieldbus.core.ecat import Command, Datagram, FrameError, build_master_frame, decode_frame
from fieldbus.core.pdo import load_drive_map
from sim_slaves.ethercat.bringup import bring_up
from sim_slaves.ethercat.chain import EscChain

EXAMPLES = int(os.environ.get("FIELDBUS_FUZZ_EXAMPLES", "2000"))
SETTINGS = settings(max_examples=EXAMPLES, deadline=None, suppress_health_check=list(HealthCheck))
DRIVE = load_drive_map(DEMO_MAP)


def _chain() -> tuple[EscChain, bytes]:
    chain = EscChain.from_maps([DRIVE] * 3)
    plan = bring_up(chain)
    return chain, plan.lrw()


CHAIN, LRW = _chain()
VALID = [
    LRW,
    build_master_frame([Datagram.physical(Command.BRD, 0, 0x0130, bytes(2))]),
    build_master_frame([Datagram.physical(Command.FPRD, 0x1001, 0x1000, bytes(128))]),  # mailbox area
    build_master_frame(
        [
            Datagram.physical(Command.FPWR, 0x1002, 0x0120, struct.pack("<H", 0x08)),
            Datagram.physical(Command.FRMW, 0x1001, 0x0910, bytes(8)),
            Datagram.physical(Command.APRD, 0, 0x0000, bytes(4)),
        ]
    ),
]


def _feed(frame: bytes) -> None:
    try:
        reply = CHAIN.process(frame, 0)
    except FrameError:
        return
    if reply is not None:
        assert len(reply) == len(frame)  # a reply has the request's length
        decode_frame(reply)  # and is itself a well-formed frame


@SETTINGS
@given(st.binary(min_size=0, max_size=1600))
def test_random_bytes_into_the_chain(frame: bytes) -> None:
    _feed(frame)


@SETTINGS
@given(
    st.sampled_from(VALID),
    st.lists(st.tuples(st.integers(0, 1599), st.integers(0, 255)), min_size=1, max_size=12),
    st.integers(-40, 40),
)
def test_mutated_frames_into_the_chain(base: bytes, flips: list[tuple[int, int]], resize: int) -> None:
    frame = bytearray(base)
    for pos, value in flips:
        if frame:
            frame[pos % len(frame)] = value
    frame = frame[: max(0, len(frame) + resize)] if resize < 0 else frame + bytes(resize)
    _feed(bytes(frame))


@SETTINGS
@given(st.binary(min_size=0, max_size=200))
def test_decoder_refuses_garbage_with_frame_error(frame: bytes) -> None:
    with contextlib.suppress(FrameError):
        decode_frame(frame)


def test_the_fuzzed_chain_still_works() -> None:
    """The chain the tests above fed (they run first, in file order) still serves a master.

    Legal writes among the fuzz (AL control, station addresses, SM/FMMU
    registers) may have changed its state, so a master brings it up again from
    INIT; corruption inside the emulator would break that bring-up or the cycle.
    """
    assert CHAIN.frames > 0  # it really is the chain the fuzz tests fed
    plan = bring_up(CHAIN)
    reply = CHAIN.process(plan.lrw(), 0)
    assert reply is not None and decode_frame(reply).datagrams[0].wkc == 9
