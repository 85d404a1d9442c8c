"""ESC error counters read in OP (``error_counters: True``): one datagram per cycle at most, rotating over
the slaves; a counter's rise is an event naming the suspect cable.

On the in-process EtherCAT emulator in virtual time (1 ms per exchange), 12 slaves, bit errors on the
cable between slaves 4 and 5 (0-based wire positions; our emulator's fault model, so this checks our
master against our own emulator). The cycle's budget is counted in frames and datagram bytes the
chain saw per exchange(), not in wall time.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import pytest

import fieldbus
from fieldbus.core.esc_errors import ERRORS_SIZE, Link
from fieldbus.platform.clock import VirtualClock

REPO = Path(__file__).resolve().parents[2]
GENERIC = REPO / "fieldbus" / "pdo_maps" / "generic_cia402.yaml"
CYCLES = 1500
acyclic_bytes: list[int] = []  # per cycle of the last _run: bytes of the frames beside the process data
# one FPRD of 20 data bytes: Ethernet header 14 + EtherCAT header 2 + datagram header 10 + 20 + WKC 2
WATCH_FRAME_BYTES = 14 + 2 + 10 + ERRORS_SIZE + 2
PD_FRAMES = 1  # 12 generic drives' process data: one LRW frame (checked without the option below)


class _Tick:
    def __init__(self, clock: VirtualClock) -> None:
        self.clock = clock

    def capture(self, res: fieldbus.CycleResult, t0_ns: int) -> None:
        self.clock.advance(1_000_000)

    def note_events(self, events: list[Any]) -> None:
        pass

    def close(self) -> None:
        pass


def _open(tmp_path: Path, **options: Any) -> tuple[fieldbus.Network, VirtualClock]:
    f = tmp_path / "net.yaml"
    m = json.dumps(str(GENERIC))
    f.write_text(
        "cycle_time_us: 1000\nreceive_timeout_us: 5000\nbuses:\n"
        f"  - {{name: arm, type: ethercat, interface: sim0, slaves: [{{name: 'j{{i}}', map: {m}, count: 12}}]}}\n"
    )
    clock = VirtualClock()
    return fieldbus.open_network(f, backend="sim", clock=clock, **options), clock


def _run(
    tmp_path: Path, seed: int, cycles: int, **options: Any
) -> tuple[Any, list[Any], list[int], list[int], int]:
    net, clock = _open(tmp_path, **options)
    try:
        op = net.bring_up()
        op.add_observer(_Tick(clock))
        b = net.backend("arm")
        chain = b.chain  # type: ignore[attr-defined]
        events: list[Any] = []
        sizes: list[int] = []  # bytes of every frame besides the process data (chain.process: not the LRW)
        process = chain.process

        def counted(frame: Any, now_ns: int) -> Any:
            sizes.append(len(frame))
            return process(frame, now_ns)

        chain.process = counted
        per_cycle: list[int] = []
        diags: list[int] = []
        acyclic_bytes.clear()
        for k in range(cycles):
            if k == 100:
                chain.bit_errors(4, 0.02, seed=seed)
            before, diag = chain.frames, b.diag_datagrams
            sizes.clear()
            res = op.exchange()
            acyclic_bytes.append(sum(sizes))
            per_cycle.append(chain.frames - before)
            diags.append(b.diag_datagrams - diag)
            events += res.events
        return b, events, per_cycle, diags, chain.faults.link_corrupted
    finally:
        net.close()


@pytest.mark.parametrize("seed", [11, 12, 13])
def test_bit_errors_between_slaves_4_and_5_are_named_and_the_cycle_keeps_its_budget(
    tmp_path: Path, seed: int
) -> None:
    b, events, per_cycle, diags, corrupted = _run(tmp_path, seed, CYCLES, error_counters=True)
    assert corrupted > 0
    watch = b.error_watch
    assert watch is not None
    assert watch.suspects()[0].link == Link(4, 1, 5, 0)
    assert len(watch.suspects()) == 1
    rises = [e for e in events if e.kind == "esc_errors"]
    assert rises, [str(e) for e in events][:10]
    named = [e for e in rises if "suspect:" in e.detail]
    assert named and all(
        "cable between slave 4 (j4) port 1 and slave 5 (j5) port 0" in e.detail for e in named
    )
    # budget: at most one datagram of <= 20 data bytes per cycle, and only in a cycle whose acyclic
    # datagram nothing else took (recovery after a lost frame goes first: the watch then waits)
    pd_frames = PD_FRAMES
    assert max(diags) == 1
    assert all(n == pd_frames + 1 for n, d in zip(per_cycle, diags, strict=True) if d)
    assert b.diag_datagrams <= CYCLES
    assert watch.reads == b.diag_datagrams and watch.reads > CYCLES // 2
    assert set(per_cycle[:100]) == {pd_frames + 1}  # before the fault: the watch's datagram in every cycle
    assert all(n <= WATCH_FRAME_BYTES for n, d in zip(acyclic_bytes, diags, strict=True) if d)
    assert max(acyclic_bytes[:100]) == WATCH_FRAME_BYTES
    assert ERRORS_SIZE == 20


def test_without_the_option_nothing_is_read(tmp_path: Path) -> None:
    b, events, per_cycle, diags, _ = _run(tmp_path, 1, 300)
    assert b.error_watch is None and b.diag_datagrams == 0
    assert not [e for e in events if e.kind == "esc_errors"] and not any(diags)
    assert set(per_cycle[:100]) == {PD_FRAMES}  # before the fault: the process data alone


def test_monitor_recording_report_and_the_run_command_show_them(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    from fieldbus.operations.monitor import Monitor
    from fieldbus.recording.load import load
    from fieldbus.recording.summary import describe, summary

    net, clock = _open(tmp_path, error_counters=True)
    rec_path = tmp_path / "run.mcap"
    try:
        op = net.bring_up()
        op.add_observer(_Tick(clock))
        rec = op.record(rec_path)
        chain = net.backend("arm").chain  # type: ignore[attr-defined]
        for k in range(600):
            if k == 60:
                chain.bit_errors(4, 0.05, seed=5)
            op.exchange()
        snap = Monitor(op).snapshot()
        rec.close()
    finally:
        net.close()
    bus = snap["buses"][0]
    assert bus["suspect_link"].startswith("cable between slave 4 (j4) port 1 and slave 5 (j5) port 0")
    assert bus["slaves"][5]["esc_errors"].startswith("p0 ")  # invalid frames at port 0 of slave 5
    recording = load(rec_path)
    kinds = [e["kind"] for e in recording.events]
    assert "esc_errors" in kinds
    text = describe(summary(recording), max_events=1000)
    assert "esc_errors" in text and "suspect: cable between slave 4" in text
    # the command line: --error-counters on the emulator (no fault: no event, exit 0)
    from fieldbus.cli import main

    code = main(
        [
            "run",
            str(tmp_path / "net.yaml"),
            "--backend",
            "sim",
            "--cycles",
            "50",
            "--error-counters",
            "--json",
        ]
    )
    assert code in (0, 3), capsys.readouterr().err


def test_a_period_reads_in_one_free_cycle_of_n_and_a_bad_value_is_refused(tmp_path: Path) -> None:
    _b, _events, _per_cycle, diags, _ = _run(tmp_path, 1, 100, error_counters=10)
    assert sum(diags) == 10 and all(diags[k] == (k % 10 == 9) for k in range(100))
    with pytest.raises(fieldbus.FieldbusError, match="error_counters"):
        _open(tmp_path, error_counters="yes")


def test_bring_up_names_a_slave_whose_eeprom_checksum_is_wrong(tmp_path: Path) -> None:
    net, _clock = _open(tmp_path)
    try:
        chain = net.backend("arm").chain  # type: ignore[attr-defined]
        chain.slaves[3].sii.data[14] ^= 0xFF  # the configuration area's checksum wrong
        chain.power_cycle(3)
        with pytest.raises(fieldbus.StateTransitionError) as info:
            net.bring_up()
    finally:
        net.close()
    text = str(info.value)
    assert "position 3 (j3): INIT" in text and "did not load the EEPROM" in text
    assert "position 2" not in text
