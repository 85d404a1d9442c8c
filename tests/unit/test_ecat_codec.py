"""EtherCAT frame/datagram codec: golden bytes written out by hand, malformed frames, round trips."""

from __future__ import annotations

import pytest
from hypothesis import given
from hypothesis import strategies as st

from fieldbus.core.ecat import (
    Command,
    Datagram,
    Frame,
    FrameError,
    build_master_frame,
    datagram_offsets,
    decode_frame,
)
from fieldbus.errors import FieldbusError


def hx(text: str) -> bytes:
    return bytes.fromhex(text.replace("|", " "))


ETH = "ff ff ff ff ff ff | 01 01 01 01 01 01 | 88 a4"

# BRD of 2 bytes at 0x0130 (AL status): ecat header length 14 = 10 + 2 + 2, type 1.
BRD_ALSTATUS = hx(f"{ETH} | 0e 10 | 07 05 00 00 30 01 02 00 00 00 | 00 00 | 00 00")
# FPWR of 0x1001 register 0x0120 = 0x0002, then (more bit) FPRD of 6 bytes at 0x0130; length 14 + 18 = 32.
TWO = hx(
    f"{ETH} | 20 10"
    "| 05 01 01 10 20 01 02 80 00 00 | 02 00 | 00 00"
    "| 04 02 01 10 30 01 06 00 00 00 | 00 00 00 00 00 00 | 00 00"
)
# LRW of 4 bytes at logical 0x00010000.
LRW = hx(f"{ETH} | 10 10 | 0c 7f 00 00 01 00 04 00 00 00 | de ad be ef | 03 00")


def test_decode_golden_brd() -> None:
    f = decode_frame(BRD_ALSTATUS)
    assert f.dst == b"\xff" * 6 and f.src == b"\x01" * 6
    (d,) = f.datagrams
    assert (d.cmd, d.idx, d.adp, d.ado, d.data, d.wkc, d.more) == (
        Command.BRD,
        5,
        0,
        0x0130,
        b"\0\0",
        0,
        False,
    )


def test_decode_golden_two_datagrams() -> None:
    a, b = decode_frame(TWO).datagrams
    assert (a.cmd, a.adp, a.ado, a.data, a.more) == (Command.FPWR, 0x1001, 0x0120, b"\x02\x00", True)
    assert (b.cmd, b.idx, b.adp, b.ado, len(b.data), b.more) == (Command.FPRD, 2, 0x1001, 0x0130, 6, False)


def test_decode_golden_lrw() -> None:
    (d,) = decode_frame(LRW).datagrams
    assert (d.cmd, d.idx, d.address, d.data, d.wkc) == (Command.LRW, 0x7F, 0x00010000, hx("de ad be ef"), 3)


def test_encode_matches_golden() -> None:
    assert build_master_frame([Datagram(Command.BRD, 5, 0x0130 << 16, b"\0\0")]) == BRD_ALSTATUS
    two = [
        Datagram.physical(Command.FPWR, 0x1001, 0x0120, b"\x02\x00", idx=1),
        Datagram.physical(Command.FPRD, 0x1001, 0x0130, bytes(6), idx=2),
    ]
    assert build_master_frame(two) == TWO
    assert build_master_frame([Datagram(Command.LRW, 0x7F, 0x10000, hx("de ad be ef"), wkc=3)]) == LRW


def test_flags_circulating_and_irq() -> None:
    d = Datagram(Command.NOP, 0, 0, b"", irq=0x1234, circulating=True)
    raw = build_master_frame([d])
    assert raw[16 + 6 : 16 + 10] == hx("00 40 34 12")
    back = decode_frame(raw).datagrams[0]
    assert back.circulating and back.irq == 0x1234


def test_padding_after_datagrams_is_ignored() -> None:
    padded = BRD_ALSTATUS + bytes(60 - len(BRD_ALSTATUS))
    assert decode_frame(padded) == decode_frame(BRD_ALSTATUS)


@pytest.mark.parametrize(
    ("frame", "message"),
    [
        (BRD_ALSTATUS[:15], "shorter"),
        (BRD_ALSTATUS[:12] + b"\x08\x00" + BRD_ALSTATUS[14:], "ethertype"),
        (BRD_ALSTATUS[:14] + hx("0e 50") + BRD_ALSTATUS[16:], "type 5"),
        (BRD_ALSTATUS[:14] + hx("20 10") + BRD_ALSTATUS[16:], "announces"),
        (BRD_ALSTATUS[:14] + hx("0c 10") + BRD_ALSTATUS[16:], "runs past"),
        (BRD_ALSTATUS[:16] + b"\x20" + BRD_ALSTATUS[17:], "unknown command"),
        (BRD_ALSTATUS[:14] + hx("10 10") + BRD_ALSTATUS[16:] + b"\0\0", "after the last"),
        (BRD_ALSTATUS[:22] + hx("02 80") + BRD_ALSTATUS[24:], "runs past"),
    ],
)
def test_malformed_frames_raise_frame_error(frame: bytes, message: str) -> None:
    with pytest.raises(FrameError, match=message) as exc:
        decode_frame(frame)
    assert isinstance(exc.value, FieldbusError)


def test_encode_rejects_bad_datagrams() -> None:
    with pytest.raises(FrameError):
        build_master_frame([Datagram(Command.LRD, 256, 0, b"")])
    with pytest.raises(FrameError):
        build_master_frame([Datagram(Command.LRD, 0, 0, bytes(2048))])
    with pytest.raises(FrameError):
        build_master_frame([])


datagrams = st.builds(
    Datagram,
    cmd=st.sampled_from(list(Command)),
    idx=st.integers(0, 255),
    address=st.integers(0, 0xFFFFFFFF),
    data=st.binary(max_size=40),
    wkc=st.integers(0, 0xFFFF),
    irq=st.integers(0, 0xFFFF),
    circulating=st.booleans(),
)


@given(st.lists(datagrams, min_size=1, max_size=8))
def test_round_trip(dgs: list[Datagram]) -> None:
    raw = build_master_frame(dgs)
    f = decode_frame(raw)
    assert len(datagram_offsets(raw)) == len(dgs)
    assert [d.more for d in f.datagrams] == [True] * (len(dgs) - 1) + [False]
    assert [d.__class__(**{**d.__dict__, "more": False}) for d in f.datagrams] == dgs
    assert Frame(f.dst, f.src, f.datagrams).encode() == raw
