"""fieldbus.dds.cdr against cyclonedds's own serializer (the oracle): the same bytes for every message
type the served bus writes, on random samples, and a fallback for what it cannot encode."""

# no ``from __future__ import annotations``: cyclonedds resolves the test types' annotations at run time
import contextlib
import dataclasses
import math
import os
import random
import time
import typing
from typing import Any

import pytest

pytest.importorskip("cyclonedds")

from cyclonedds.domain import DomainParticipant
from cyclonedds.idl import IdlStruct
from cyclonedds.idl import types as t
from cyclonedds.idl.annotations import appendable
from cyclonedds.idl.types import array, sequence
from cyclonedds.internal import InvalidSample
from cyclonedds.pub import DataWriter
from cyclonedds.sub import DataReader
from cyclonedds.topic import Topic

from fieldbus.dds import cdr
from fieldbus.dds import messages as m
from fieldbus.dds import ros_types as r

RANGES = {
    "int8": (-128, 127),
    "uint8": (0, 255),
    "int16": (-(2**15), 2**15 - 1),
    "uint16": (0, 2**16 - 1),
    "int32": (-(2**31), 2**31 - 1),
    "uint32": (0, 2**32 - 1),
    "int64": (-(2**63), 2**63 - 1),
    "uint64": (0, 2**64 - 1),
}
FLOATS = (0.0, -0.0, 1.5, -1e300, 5e-324, math.inf, -math.inf, math.nan)
TEXTS = ("", "j", "joint_0", "Gelenk ä", "軸", "x" * 37)


def _value(hint: Any, rng: random.Random) -> Any:
    if hint is bool:
        return rng.random() < 0.5
    if hint is str:
        return rng.choice(TEXTS)
    meta = getattr(hint, "__metadata__", ())
    if meta and isinstance(meta[0], str):
        if meta[0] in RANGES:
            lo, hi = RANGES[meta[0]]
            return rng.choice((lo, hi, 0, rng.randint(lo, hi)))
        return rng.choice((*FLOATS, rng.uniform(-10, 10)))  # float32/float64
    if meta and isinstance(meta[0], sequence):
        return [_value(meta[0].subtype, rng) for _ in range(rng.choice((0, 1, 2, 3, 7)))]
    if meta and isinstance(meta[0], array):
        return [_value(meta[0].subtype, rng) for _ in range(meta[0].length)]
    return _sample(hint, rng)


def _sample(cls: type, rng: random.Random) -> Any:
    hints = typing.get_type_hints(cls, include_extras=True)
    return cls(**{f.name: _value(hints[f.name], rng) for f in dataclasses.fields(cls)})


def _types(module: Any) -> list[type]:
    return [
        v
        for v in vars(module).values()
        if isinstance(v, type) and issubclass(v, IdlStruct) and v is not IdlStruct
    ]


ENCODABLE = [c for c in _types(m) + _types(r) if cdr.plan(c) is not None]


def test_the_messages_the_cycle_writes_are_all_encodable() -> None:
    names = {c.__name__ for c in ENCODABLE}
    assert {"JointState", "AxisState", "DiagnosticArray", "Odometry", "TFMessage", "Reply"} <= names


@pytest.mark.parametrize("cls", ENCODABLE, ids=lambda c: c.__name__)
def test_random_samples_encode_to_exactly_cyclonedds_bytes(cls: type) -> None:
    rng = random.Random(cls.__name__)
    ops = cdr.plan(cls)
    assert ops is not None
    for _ in range(200):
        sample = _sample(cls, rng)
        theirs = sample.serialize(use_version_2=False)
        ours = cdr.encode(ops, sample)
        assert ours == theirs.ljust((len(theirs) + 3) & ~3, b"\x00"), sample


@dataclasses.dataclass
class Bounded(IdlStruct, typename="test::Bounded"):
    name: t.bounded_str[8] = ""


@dataclasses.dataclass
@appendable
class Appendable(IdlStruct, typename="test::Appendable"):
    x: t.int32 = 0


def test_a_type_with_a_member_it_does_not_know_is_left_to_cyclonedds() -> None:
    assert cdr.plan(Bounded) is None
    assert cdr.plan(Appendable) is None
    assert cdr.plan(int) is None


def test_a_wrong_array_length_is_an_error_not_a_short_message() -> None:
    ops = cdr.plan(r.PoseWithCovariance)
    assert ops is not None
    with pytest.raises(ValueError, match="covariance: 35 values for an array of 36"):
        cdr.encode(ops, r.PoseWithCovariance(covariance=[0.0] * 35))


def _take(reader: Any, cls: type, want: int) -> list[Any]:
    got: list[Any] = []
    for _ in range(400):  # delivery inside one participant: normally at once
        got += reader.take(N=16)
        if len(got) >= want:
            break
        time.sleep(0.005)
    return got


def test_plain_writers_and_readers_interwork_with_cyclonedds_ones_keys_included() -> None:
    dp = DomainParticipant(1 + (os.getpid() * 13 + 3) % 200)
    try:
        tp = Topic(dp, "fieldbus_test_cdr_axis_state", m.AxisState)
        reader = DataReader(dp, tp)
        writer = cdr.PlainWriter(dp, tp)
        assert writer.fast
        sent = _sample(m.AxisState, random.Random(7))
        sent.inputs = [0.5, -1.25]  # NaN would not compare equal below
        sent.header.frame_id = "base"
        writer.write(sent)
        assert _take(reader, m.AxisState, 1) == [sent]

        # a keyed type: the C writer derives the key from our bytes as from cyclonedds's
        cmd = Topic(dp, "fieldbus_test_cdr_command", m.JointCommand)
        theirs, ours = DataWriter(dp, cmd), cdr.PlainWriter(dp, cmd)
        plain_reader, their_reader = cdr.PlainReader(dp, cmd), DataReader(dp, cmd)
        assert ours.fast
        ours.write(m.JointCommand(client_id="a", sequence=1, position=[1.0]))
        theirs.write(m.JointCommand(client_id="a", sequence=2, position=[2.0]))
        ours.write(m.JointCommand(client_id="b", sequence=3, velocity=[3.0, 4.0]))
        for rd in (plain_reader, their_reader):  # history keep-last 1 per instance (the default)
            got = _take(rd, m.JointCommand, 2)
            # "a" 1 (our bytes) was replaced by "a" 2 (cyclonedds's): one instance per client_id
            assert [(c.client_id, c.sequence, c.position, c.velocity) for c in got] == [
                ("a", 2, [2.0], []),
                ("b", 3, [], [3.0, 4.0]),
            ]
            assert got[0].sample_info.instance_handle != got[1].sample_info.instance_handle
        ours.dispose(m.JointCommand(client_id="b"))
        gone = _take(plain_reader, m.JointCommand, 1)
        assert len(gone) == 1 and isinstance(gone[0], InvalidSample) and gone[0].key_sample.client_id == "b"
    finally:
        del dp


DECODABLE = [c for c in _types(m) + _types(r) if cdr.plan(c) is not None]


def test_a_reader_decodes_the_keyed_command_too() -> None:
    assert m.JointCommand in DECODABLE and m.JointState in DECODABLE


@pytest.mark.parametrize("cls", DECODABLE, ids=lambda c: c.__name__)
def test_cyclonedds_bytes_decode_to_the_sample_they_came_from(cls: type) -> None:
    rng = random.Random("decode " + cls.__name__)
    ops = cdr.plan(cls)
    assert ops is not None
    for _ in range(200):
        raw = _sample(cls, rng).serialize(use_version_2=False)
        got = cdr.decode(cls, ops, raw)
        assert type(got) is cls
        assert got.serialize(use_version_2=False) == raw  # NaN-proof equality: the same bytes again


@pytest.mark.parametrize("cls", [m.JointCommand, m.AxisState, m.DiagnosticArray], ids=lambda c: c.__name__)
def test_a_cut_or_damaged_message_is_a_value_error_never_another_exception(cls: type) -> None:
    rng = random.Random("damage " + cls.__name__)
    ops = cdr.plan(cls)
    assert ops is not None
    for _ in range(30):
        raw = _sample(cls, rng).serialize(use_version_2=False)
        for cut in range(len(raw) - 4):  # every shorter message
            with pytest.raises(ValueError):
                cdr.decode(cls, ops, raw[:cut])
        for _ in range(50):  # a damaged byte: the sample it makes, or a ValueError
            bad = bytearray(raw)
            bad[rng.randrange(4, len(raw))] = rng.randrange(256)
            with contextlib.suppress(ValueError):
                cdr.decode(cls, ops, bytes(bad))
    with pytest.raises(ValueError, match="not little-endian plain CDR"):
        cdr.decode(cls, ops, b"\x00\x00\x00\x00" + raw[4:])  # big-endian CDR: cyclonedds's own path
