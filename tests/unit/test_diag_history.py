"""ETG.1020 diagnosis history (0x10F3) messages and their reader.

The messages here are packed by hand with ``struct`` from the ETG.1020 layout (diag code UDINT, flags
UINT, text id UINT, time stamp ULINT, then per parameter a UINT flags word and the value), not with
our encoder, so the decoder is judged against the layout itself.
"""

from __future__ import annotations

import struct
from concurrent.futures import Future

import pytest

from fieldbus.diagnosis import DiagnosisReader, decode_diag_message, encode_diag_message, error_code
from fieldbus.errors import FieldbusError


def _message(code: int, flags: int, text: int, stamp: int, params: bytes = b"") -> bytes:
    return struct.pack("<IHHQ", code, flags, text, stamp) + params


def test_an_emergency_diag_code_is_named_from_the_cia402_table() -> None:
    # 0xE800 in the low word: the high word is a CiA 301 / 402 error code (0x8611 following error);
    # flags: error (2), local time stamp (bit 4), 2 parameters (bits 8-15)
    raw = _message(
        0x8611E800, 0x0212, 7, 123_456_789, struct.pack("<HH", 0x0006, 0x8611) + struct.pack("<HB", 5, 2)
    )
    m = decode_diag_message(raw)
    assert (m.code, m.emcy_code, m.name, m.severity, m.local_time) == (
        0x8611E800, 0x8611, "following error", "error", True
    )  # fmt: skip
    assert (m.text_id, m.timestamp_ns, m.params) == (7, 123_456_789, (0x8611, 2))
    assert (
        encode_diag_message(0x8611E800, 123_456_789, ((0x0006, 0x8611), (0x0005, 2)))
        == raw[:6] + b"\x00\x00" + raw[8:]
    )


@pytest.mark.parametrize(
    ("code", "name"),
    [(0x1234E123, "manufacturer diag code 0x1234E123"), (0x0001EE01, "profile diag code 0x0001EE01")],
)
def test_other_diag_codes_keep_their_number(code: int, name: str) -> None:
    m = decode_diag_message(_message(code, 0x0001, 0, 0))
    assert (m.name, m.severity, m.emcy_code) == (name, "warning", None)


def test_signed_and_byte_array_parameters() -> None:
    params = struct.pack("<Hh", 0x0003, -5) + struct.pack("<H", 0x1003) + b"abc"
    assert decode_diag_message(_message(0x7300E800, 0x0202, 0, 0, params)).params == (-5, b"abc")


@pytest.mark.parametrize(
    ("raw", "words"),
    [
        (b"\x00" * 15, "15 bytes"),
        (_message(0x7300E800, 0x0102, 0, 0), "parameter 1 of 1 is missing"),
        (_message(0x7300E800, 0x0102, 0, 0, struct.pack("<HB", 0x0006, 1)), "cannot be read"),
    ],
)
def test_a_short_message_is_an_error(raw: bytes, words: str) -> None:
    with pytest.raises(FieldbusError, match=words):
        decode_diag_message(raw)


def test_the_reader_walks_the_ring_newest_first() -> None:
    """A ring of 3 whose newest is sub 6 (it wrapped): 6, then 8, then 7."""
    od = {
        1: bytes([3]),
        2: bytes([6]),
        6: _message(0x3000E800, 2, 0, 30),
        7: _message(0x1000E800, 2, 0, 10),
        8: _message(0x2000E800, 2, 0, 20),
    }
    asked: list[tuple[int, int]] = []

    def submit(index: int, sub: int) -> Future[bytes | None]:
        asked.append((index, sub))
        f: Future[bytes | None] = Future()
        f.set_result(od[sub])
        return f

    messages = DiagnosisReader(submit, last=8).poll()
    assert messages is not None and [m.timestamp_ns for m in messages] == [30, 20, 10]
    assert asked == [(0x10F3, 1), (0x10F3, 2), (0x10F3, 6), (0x10F3, 8), (0x10F3, 7)]


def test_the_reader_stops_at_an_empty_slot_and_waits_for_pending_reads() -> None:
    od = {1: bytes([16]), 2: bytes([7]), 7: _message(0x7300E800, 2, 0, 2), 6: _message(0x8611E800, 2, 0, 1)}
    futures: list[tuple[int, Future[bytes | None]]] = []

    def submit(index: int, sub: int) -> Future[bytes | None]:
        f: Future[bytes | None] = Future()
        futures.append((sub, f))
        return f

    reader = DiagnosisReader(submit)
    messages = None
    for _ in range(10):  # one answer per cycle; nothing before it comes
        assert reader.poll() is None
        sub, f = futures[-1]
        f.set_result(od.get(sub, b""))
        messages = reader.poll()
        if messages is not None:
            break
    assert messages is not None and [m.name for m in messages] == ["sensor error", "following error"]
    assert [sub for sub, _ in futures] == [1, 2, 7, 6, 21]  # 21: the ring's last slot, empty


def test_error_codes_by_name() -> None:
    assert error_code("Sensor error") == 0x7300
    with pytest.raises(FieldbusError, match="did you mean 'following error'"):
        error_code("folowing eror")


def test_the_new_drive_fault_fields_are_keyword_only() -> None:
    """A subclass's own fields (a raw-CAN motor fault's reason) stay positional right after ``code``."""
    from dataclasses import dataclass

    from fieldbus.core.drivefault import DriveFault

    @dataclass(frozen=True)
    class Reasoned(DriveFault):
        reason: str = ""

    fault = Reasoned(3, "g", 1, "s", 0x10, "overload")
    assert (fault.reason, fault.slave_axis, fault.history) == ("overload", 0, None)
    assert DriveFault(3, "g", 1, "s", None, slave_axis=1).slave_axis == 1
