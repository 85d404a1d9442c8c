"""fieldbus.dds.callers: the participant behind a sample, judged against cyclonedds's own discovery data."""

import os
import time
from typing import Any

import pytest

pytest.importorskip("cyclonedds")

from cyclonedds.domain import DomainParticipant
from cyclonedds.pub import DataWriter
from cyclonedds.sub import DataReader
from cyclonedds.topic import Topic

from fieldbus.dds import callers
from fieldbus.dds import messages as m


def _take_one(reader: Any) -> Any:
    for _ in range(400):  # delivery between two participants of one process: normally within ms
        got = reader.take(N=1)
        if got:
            return got[0]
        time.sleep(0.005)
    raise AssertionError("no sample arrived")


@pytest.fixture
def pair() -> Any:
    """A reader in one participant and a writer in another, matched, one Request taken."""
    domain = 1 + (os.getpid() * 17 + 5) % 200
    ours, theirs = DomainParticipant(domain), DomainParticipant(domain)
    reader = DataReader(ours, Topic(ours, "fieldbus_test_callers", m.Request))
    writer = DataWriter(theirs, Topic(theirs, "fieldbus_test_callers", m.Request))
    for _ in range(400):
        if reader.get_matched_publications():
            break
        time.sleep(0.005)
    writer.write(m.Request(client_id="forged-label", request_id=1))
    yield reader, _take_one(reader), theirs
    del writer, reader, ours, theirs


def test_the_writer_s_participant_is_the_one_cyclonedds_names(pair: Any) -> None:
    reader, sample, theirs = pair
    handle = callers.publication_handle(sample)
    oracle = reader.get_matched_publication_data(handle)  # cyclonedds's whole discovery sample
    who = callers.Callers().of(reader, sample)
    assert who == oracle.participant_key.hex == theirs.guid.hex  # the writer's participant, not ours
    assert len(who) == 32 and sample.client_id == "forged-label"


def test_the_lookup_does_not_build_the_discovery_sample_in_python(
    pair: Any, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The cycle that takes a new writer's first sample pays 10-20 µs, not the 0.2-0.7 ms of the whole
    sample: the public method is not called (it fails here if it is)."""
    reader, sample, _ = pair
    oracle = reader.get_matched_publication_data(callers.publication_handle(sample)).participant_key.hex

    def whole(*_a: Any) -> Any:
        raise AssertionError("the whole discovery sample was built")

    monkeypatch.setattr(reader, "get_matched_publication_data", whole)
    if callers._matched_data is None:  # pragma: no cover - another cyclonedds binding
        pytest.skip("this cyclonedds has no ddspy_get_matched_publication_data: the public method is used")
    assert callers.Callers().of(reader, sample) == oracle


def test_without_the_c_call_the_public_method_gives_the_same_participant(
    pair: Any, monkeypatch: pytest.MonkeyPatch
) -> None:
    reader, sample, _ = pair
    fast = callers.Callers().of(reader, sample)
    monkeypatch.setattr(callers, "_matched_data", None)
    assert callers.Callers().of(reader, sample) == fast is not None


def test_a_writer_the_reader_does_not_know_has_no_participant(pair: Any) -> None:
    reader, _, _ = pair

    class Forged:
        class sample_info:  # the shape of cyclonedds's SampleInfo
            publication_handle = 12345

    assert callers.Callers().of(reader, Forged()) is None
    assert callers.Callers().of(reader, object()) is None  # no sample info at all
