"""Recording (fieldbus.recording): the cycle's ring allocates nothing, a stalled writer drops the oldest
blocks without holding the cycle, a full disk stops the recording with one warning, a cut file loads up
to its last complete block, bad paths and bad files are named, and the official mcap reader reads it."""

from __future__ import annotations

import errno
import io
import threading
import time
import warnings
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from fieldbus.commands.demo import demo_network
from fieldbus.errors import FieldbusError
from fieldbus.network import Operational, open_network
from fieldbus.platform.allocs import net_blocks
from fieldbus.recording import RecordingWarning, load

pytestmark = pytest.mark.timeout(300)
AXES = 3


@pytest.fixture
def op(tmp_path: Path) -> Iterator[Operational]:
    """The demo's CiA 402 joints on the in-process EtherCAT emulator, in OP."""
    with (
        demo_network("sim", AXES, 1000.0, tmp_path) as setup,
        open_network(setup.net_file, backend="sim") as net,
    ):
        yield net.bring_up()


IO16 = Path(__file__).resolve().parents[1] / "data" / "io16.yaml"


@pytest.fixture
def io_op(tmp_path: Path) -> Iterator[Operational]:
    """Four 16-bit I/O slaves on the in-process EtherCAT emulator (no drive physics: a cheap cycle)."""
    f = tmp_path / "io.yaml"
    f.write_text(
        "cycle_time_us: 1000\nbuses:\n  - {name: io, type: ethercat, interface: sim, "
        f"slaves: [{{name: 'io{{i}}', map: '{IO16}', count: 4}}]}}\n"
    )
    with open_network(f, backend="sim") as net:
        yield net.bring_up()


def _steps(op: Operational, n: int) -> None:
    for _ in range(n):
        op.exchange()


def test_a_cycle_with_recording_on_allocates_nothing(io_op: Operational, tmp_path: Path) -> None:
    # blocks longer than the measurement: the writer thread (whose work tracemalloc also sees) stays idle,
    # so what is counted is the cycle's copy into the ring
    op = io_op
    rec = op.record(tmp_path / "a.mcap", raw=True, block_cycles=8192, ring_blocks=2)
    # a per-cycle allocation would leave >= 4000 blocks (the next test shows it does); tracemalloc also
    # traces the (idle) writer thread, the in-process emulator and its own machinery, whose transient
    # objects at a snapshot show as a few blocks now and then (4, then 17 once, in full runs): so
    # "0 per cycle" is asserted as under 1 % of the cycles, with the lines that held them on failure
    sites: list[str] = []
    blocks = net_blocks(op.exchange, cycles=4000, warmup=500, sites=sites)
    assert blocks < 40, (blocks, sites[:10])
    assert rec.ring.count == 5000  # every cycle went through capture()
    rec.close()
    assert load(tmp_path / "a.mcap").cycles.size == 5000


def test_the_ring_copy_itself_is_measured(io_op: Operational, tmp_path: Path) -> None:
    """The same measurement sees a capture that keeps one object per cycle (the check can fail)."""
    op = io_op
    rec = op.record(tmp_path / "b.mcap", block_cycles=8192, ring_blocks=2)
    kept: list[object] = []
    inner = rec.capture

    def leaky(res: Any, t0: int) -> None:
        inner(res, t0)
        kept.append(object())

    rec.capture = leaky
    assert net_blocks(op.exchange, cycles=1000, warmup=100) >= 1000
    rec.close()


class _SlowFile(io.BytesIO):
    """A file whose writes stall while ``gate`` is closed (a writer far behind the cycle)."""

    def __init__(self, path: Path, gate: threading.Event) -> None:
        super().__init__()
        self.path, self.gate, self.started = path, gate, False

    def write(self, data: Any) -> int:
        if self.started:
            self.gate.wait(30)
        return super().write(data)

    def flush(self) -> None:
        self.started = True  # the header went through; blocks stall from now on

    def close(self) -> None:
        self.path.write_bytes(self.getvalue())
        super().close()


def test_a_stalled_writer_drops_the_oldest_blocks_and_never_holds_the_cycle(
    op: Operational, tmp_path: Path
) -> None:
    gate = threading.Event()
    path = tmp_path / "slow.mcap"
    rec = op.record(path, block_cycles=16, ring_blocks=4, open_file=lambda p: _SlowFile(p, gate))
    longest = 0
    for _ in range(600):
        t = time.perf_counter_ns()
        op.exchange()
        longest = max(longest, time.perf_counter_ns() - t)
    assert longest < 100e6  # the writer waits on the gate; the cycle never does
    gate.set()
    rec.close()
    assert rec.dropped_blocks > 0
    r = load(path)
    cyc = r.cycles["cycle"]
    assert r.dropped_blocks == rec.dropped_blocks
    assert cyc.size + 16 * rec.dropped_blocks == 600
    assert np.all(np.diff(cyc) > 0) and cyc[-1] == 599  # the newest cycles survive, in order
    gaps = [e for e in r.events if e["kind"] == "gap"]
    assert gaps and all(int(np.flatnonzero(cyc == g["cycle"])[0]) % 16 == 0 for g in gaps)


def test_a_change_inside_a_dropped_first_block_is_still_an_event(
    op: Operational, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    # the writer's first look comes after the ring has wrapped: the first blocks are gone
    monkeypatch.setattr("fieldbus.recording.writer.POLL_S", 0.5)
    rec = op.record(tmp_path / "late.mcap", block_cycles=4, ring_blocks=2)
    backend: Any = op._net.backends[0]
    for k in range(40):
        if k == 2:  # an EMCY in cycle 2 (as the backend's mailbox keeps one), which the writer never sees
            backend._emcy(0, 0x2310, 0x02)
        op.exchange()
    time.sleep(0.7)  # the writer takes what is left
    rec.close()
    r = load(tmp_path / "late.mcap")
    assert r.dropped_blocks > 0 and int(r.cycles["cycle"][0]) > 2
    emcys = [e for e in r.events if e["kind"] == "emcy"]
    assert [(e["old"], e["new"]) for e in emcys] == [(0, 1)]
    assert emcys[0]["cycle"] == int(r.cycles["cycle"][0])  # reported at the first cycle recorded


class _FullDisk(io.RawIOBase):
    """A file on a disk with ``room`` bytes left: the write that does not fit writes what fits, then ENOSPC."""

    def __init__(self, path: Path, room: int) -> None:
        self.f = open(path, "wb")  # noqa: SIM115
        self.room = room

    def writable(self) -> bool:
        return True

    def write(self, data: Any) -> int:
        b = bytes(data)
        if len(b) > self.room:
            self.f.write(b[: self.room])
            self.f.flush()
            self.room = 0
            raise OSError(errno.ENOSPC, "No space left on device")
        self.room -= len(b)
        return self.f.write(b)

    def tell(self) -> int:
        return self.f.tell()

    def close(self) -> None:
        self.f.close()
        super().close()


def test_a_full_disk_stops_the_recording_with_one_warning_and_the_cycle_goes_on(
    op: Operational, tmp_path: Path
) -> None:
    path = tmp_path / "full.mcap"
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        rec = op.record(path, block_cycles=32, open_file=lambda p: _FullDisk(p, 40_000))
        for _ in range(3000):
            res = op.exchange()
        deadline = time.monotonic() + 5
        while rec.active and time.monotonic() < deadline:
            time.sleep(0.01)
        for _ in range(100):
            res = op.exchange()
        assert res.fresh and res.cycle == 3100
        rec.close()
    mine = [w for w in caught if issubclass(w.category, RecordingWarning)]
    assert len(mine) == 1, [str(w.message) for w in mine]
    assert str(path) in str(mine[0].message) and "No space left" in str(mine[0].message)
    assert isinstance(rec.error, OSError) and rec.error.errno == errno.ENOSPC
    r = load(path)
    assert not r.complete
    assert 0 < r.cycles.size < 3000 and r.cycles.size % 32 == 0  # up to the last complete block
    assert r.cycles.size == rec.cycles


def test_a_cut_file_loads_up_to_its_last_complete_block(op: Operational, tmp_path: Path) -> None:
    path = tmp_path / "whole.mcap"
    rec = op.record(path, block_cycles=64)
    _steps(op, 1000)
    rec.close()
    whole = load(path)
    assert whole.complete and whole.cycles.size == 1000
    data = path.read_bytes()
    seen = set()
    head = tmp_path / "head.mcap"
    head.write_bytes(data[:100])  # cut before its first block: nothing to load, and the error says which file
    with pytest.raises(FieldbusError, match=str(head)):
        load(head)
    for cut in range(len(data) // 20, len(data), len(data) // 37):
        part = tmp_path / "cut.mcap"
        part.write_bytes(data[:cut])
        r = load(part)
        n = r.cycles.size
        assert not r.complete and (n % 64 == 0 or n == 1000), (cut, n)  # the last block has 1000 % 64 rows
        seen.add(n)
        assert np.array_equal(r.cycles, whole.cycles[:n])
        for g in whole.groups:
            assert np.array_equal(r.groups[g], whole.groups[g][:n])
        for b in whole.buses:
            assert np.array_equal(r.buses[b], whole.buses[b][:n])
        assert all(e["cycle"] < n for e in r.events)
    assert len(seen) > 5  # the cuts landed in many different blocks


def test_bad_paths_and_bad_files_are_named(op: Operational, tmp_path: Path) -> None:
    missing = tmp_path / "no" / "such" / "dir" / "x.mcap"
    with pytest.raises(FieldbusError, match=str(missing)):
        op.record(missing)
    assert op.recorders == ()
    garbage = tmp_path / "garbage.mcap"
    garbage.write_bytes(b"not an mcap file at all" * 10)
    with pytest.raises(FieldbusError, match=str(garbage)):
        load(garbage)
    with pytest.raises(FieldbusError, match=str(tmp_path / "absent.mcap")):
        load(tmp_path / "absent.mcap")


def test_unwritable_record_path_fails_before_any_bus_starts(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    from fieldbus.backends.sim import SimBackend
    from fieldbus.cli import main

    opened: list[object] = []
    real_open = SimBackend.open

    def spy(self: SimBackend) -> None:
        opened.append(self)
        real_open(self)

    monkeypatch.setattr(SimBackend, "open", spy)
    bad = tmp_path / "missing-dir" / "r.mcap"
    assert main(["demo", "--cycles", "5", "--axes", "1", "--json", "--record", str(bad)]) == 1
    assert opened == []
    assert (
        main(["demo", "--cycles", "100", "--axes", "1", "--json", "--record", str(tmp_path / "ok.mcap")]) == 0
    )
    assert opened  # the spy sees a bus that does start


def test_the_official_mcap_reader_reads_the_file(op: Operational, tmp_path: Path) -> None:
    from mcap.reader import make_reader

    from fieldbus.recording import schema

    path = tmp_path / "r.mcap"
    rec = op.record(path, raw=True, block_cycles=100)
    _steps(op, 450)
    rec.close()
    with open(path, "rb") as f:
        reader = make_reader(f)
        summary = reader.get_summary()
        assert summary is not None
        topics = {c.topic: c for c in summary.channels.values()}
        assert set(topics) == {"/cycle", "/bus/joints", "/group/joints", "/events"}
        rows: dict[str, int] = {}
        for sch, ch, msg in reader.iter_messages():
            if ch.topic == "/events":
                assert sch is not None and sch.encoding == "jsonschema"
                continue
            assert sch is not None and sch.encoding == schema.SCHEMA_ENCODING
            dt = schema.dtype_from_json(ch.metadata["dtype"])
            rows[ch.topic] = rows.get(ch.topic, 0) + len(msg.data) // dt.itemsize
        assert rows == {"/cycle": 450, "/bus/joints": 450, "/group/joints": 450}
        meta = {m.name: m.metadata for m in reader.iter_metadata()}
        assert meta["fieldbus"]["format"] == schema.FORMAT and meta["fieldbus.stats"]["cycles"] == "450"


def _serve(op: Operational, request: Any, most: int = 100) -> int:
    """Exchanges until ``request`` is answered (an SDO in OP takes a datagram per cycle on EtherCAT);
    the cycle that answered it (``op.result.cycle`` before that exchange)."""
    for _ in range(most):
        at = op.result.cycle
        _steps(op, 1)
        if request.done():
            return int(at)
    raise AssertionError(f"not answered in {most} cycles")


def test_an_sdo_abort_in_op_is_an_event_at_the_cycle_that_served_it(op: Operational, tmp_path: Path) -> None:
    from fieldbus.errors import SdoAbortError, abort_name

    path = tmp_path / "sdo.mcap"
    rec = op.record(path, block_cycles=64)
    _steps(op, 100)
    missing = op.submit_sdo_read("joints", "j1", 0x2FFF, 0)  # no such object
    at_read = _serve(op, missing)
    fine = op.submit_sdo_read("joints", "j0", 0x1000, 0)  # answered: no event
    _steps(op, 30)
    read_only = op.submit_sdo_write("joints", "j2", 0x1000, 0, b"\0\0\0\0")
    at_write = _serve(op, read_only)
    _steps(op, 200)
    rec.close()
    assert isinstance(missing.exception(0), SdoAbortError) and isinstance(
        read_only.exception(0), SdoAbortError
    )
    assert fine.result(0)
    r = load(path)
    aborts = [e for e in r.events if e["kind"] == "sdo_abort"]
    assert [
        (e["cycle"], e["bus"], e["slave"], e["access"], e["index"], e["sub_index"], e["code"]) for e in aborts
    ] == [
        (at_read, "joints", "j1", "read", 0x2FFF, 0, 0x06020000),
        (at_write, "joints", "j2", "write", 0x1000, 0, 0x06010002),
    ]
    assert [e["name"] for e in aborts] == [abort_name(0x06020000), abort_name(0x06010002)]
    assert "Object does not exist" in aborts[0]["name"] and "0x2FFF" in aborts[0]["detail"]
    assert [e["t_ns"] for e in aborts] == [int(r.cycles["t_ns"][at_read]), int(r.cycles["t_ns"][at_write])]


def test_an_sdo_abort_before_recording_is_not_an_event(op: Operational, tmp_path: Path) -> None:
    """Only what the recorded cycles served: an abort served before record() is not in the file."""
    before = op.submit_sdo_read("joints", "j1", 0x2FFF, 0)
    _serve(op, before)
    assert before.exception(0) is not None
    rec = op.record(tmp_path / "none.mcap")
    _steps(op, 50)
    rec.close()
    assert [e for e in load(tmp_path / "none.mcap").events if e["kind"] == "sdo_abort"] == []
