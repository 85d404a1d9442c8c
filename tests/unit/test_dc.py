"""Distributed-clock model: delays, drift compensation, SYNC0, host PI, CLI (fieldbus.core.dc)."""

from __future__ import annotations

import json

import numpy as np
import pytest

from fieldbus.cli import main
from fieldbus.core.dc import (
    DcRegister,
    EscTiming,
    HostSyncConfig,
    SyncActivation,
    line_propagation_delays,
    line_timing,
    simulate,
    simulate_host_sync,
    soem_offsets,
    sync0_start_time,
)
from fieldbus.core.dc.sim import convergence_bound_ms
from sim_slaves.ethercat.dc_clock import DcSegment, DcSlaveClock

# Hand-computed 3-slave line: A -(10 m)- B -(5 m)- C, 5 ns/m.
TP, TF = 600, 560  # processing (port 0 -> EPU -> port 1) and forwarding (port 1 -> port 0) delays
W1, W2 = 50, 25  # cable A-B 10 m, B-C 5 m
# Frame reaches A port 0 at 0, B port 0 at TP+W1 = 650, C port 0 at 650+TP+W2 = 1275; C turns it
# round through its processing unit (TP) -> B port 1 at 1275+600+25 = 1900 -> A port 1 at
# 1900+TF+W1 = 2510.
A0, B0, C0, B1, A1 = 0, 650, 1275, 1900, 2510


def test_line_timing_matches_hand_computation() -> None:
    esc = EscTiming(processing_ns=TP, forwarding_ns=TF)
    lt = line_timing(0.0, [esc] * 3, [0.0, 10.0, 5.0])
    assert list(lt.port0_ns) == [A0, B0, C0]
    assert list(lt.port1_ns[:2]) == [A1, B1]
    assert np.isnan(lt.port1_ns[2])


def test_soem_delays_three_slave_line() -> None:
    # SOEM: delay_B = ((A1-A0) - (B1-B0)) / 2 = (2510 - 1250) / 2 = 630
    #       delay_C = delay_B + ((B1-B0) - 0) / 2 = 630 + 1250 / 2 = 1255
    # true EPU-to-EPU delays are 650 and 1275: SOEM is t_Diff/2 = 20 ns short per forwarding slave.
    assert line_propagation_delays([A0, B0, C0], [A1, B1, None]) == [0, 630, 1255]
    # with the ESC datasheet's t_Diff correction (40 ns) the delays are exact
    assert line_propagation_delays([A0, B0, C0], [A1, B1, None], t_diff_ns=TP - TF) == [0, 650, 1275]


def test_soem_delays_wrap_at_32_bits_and_truncate_like_c() -> None:
    base = 2**32 - 700  # receive times wrap inside the round trip
    p0 = [(base + t) % 2**32 for t in (A0, B0, C0)]
    p1 = [(base + A1) % 2**32, (base + B1 + 1) % 2**32, None]  # B1 one ns later: 1251 / 2 -> 625
    assert line_propagation_delays(p0, p1) == [0, (2510 - 1251) // 2, (2510 - 1251) // 2 + 625]


def test_register_level_configuration_gives_the_same_delays() -> None:
    esc = EscTiming(processing_ns=TP, forwarding_ns=TF)
    clocks = [DcSlaveClock(timing=esc, initial_local_ns=v) for v in (5_000, 2**32 - 100, 123_456_789)]
    seg = DcSegment(clocks, [0.0, 10.0, 5.0])
    seg.latch_receive_times(1_000)
    rd = [int.from_bytes(c.read_register(0x0900, 8, 10_000)[:4], "little") for c in clocks]
    p1 = [int.from_bytes(c.read_register(0x0904, 4, 10_000), "little") for c in clocks]
    assert line_propagation_delays(rd, [p1[0], p1[1], None]) == [0, 630, 1255]
    # SOEM's offsets put every system time at the master time when the latch frame passed
    epu = [int.from_bytes(c.read_register(0x0918, 8, 10_000), "little") for c in clocks]
    offsets = soem_offsets(7_000_000, epu)
    for c, off in zip(clocks, offsets, strict=True):
        c.write_register(DcRegister.SYSTEM_TIME_OFFSET, (off % 2**64).to_bytes(8, "little"), 20_000)
    lt = seg.timing(1_000)
    for i, c in enumerate(clocks):
        assert c.system_time(round(lt.epu_ns[i])) == 7_000_000


def _converge_bound(n: int, drift: float) -> float:
    lt = line_timing(0.0, [EscTiming()] * n, [1.0] * n)
    return convergence_bound_ms(2 * drift, float(lt.epu_ns[-1] - lt.epu_ns[0]))


@pytest.mark.parametrize(
    ("n", "drift", "seed"), [(3, 100.0, 1), (16, 100.0, 2), (64, 100.0, 0), (8, 20.0, 3)]
)
def test_compensation_keeps_spread_within_100ns(n: int, drift: float, seed: int) -> None:
    r = simulate(n, drift, 3.0, seed=seed)
    assert r.converged_after_ms is not None
    bound = _converge_bound(n, drift)
    assert r.converged_after_ms <= 1.25 * bound  # docs/dc.md: estimate + 25 % for filter lag and noise
    assert r.max_spread_after_convergence_ns is not None and r.max_spread_after_convergence_ns < 100.0
    assert r.final_spread_ns < 30.0
    # the last second is steady: every sample under 100 ns, SYNC0 pulses too
    last = r.times_ms >= r.times_ms[-1] - 1000
    assert np.all(r.spread_ns[last] < 100.0)
    assert np.all(r.sync0_spread_ns[last] < 100.0)


def test_convergence_bound_numbers() -> None:
    # tau = 0x1000 x 16 us = 65.536 ms; x e^-x = 100 / (200e-6 x 65.536e6) = 0.00763 -> x = 6.81;
    # slew 20 us / (781.25 - 200 ppm) = 34.4 ms  ->  34.4 + 6.81 x 65.5 = 481 ms
    assert convergence_bound_ms(200.0, 20_000.0) == pytest.approx(34.4 + 6.81 * 65.536, rel=0.01)


def test_without_compensation_spread_grows_with_drift() -> None:
    r = simulate(3, 100.0, 2.0, compensation=False)
    assert r.converged_after_ms is None
    t_ns = (r.times_ms - r.times_ms[0] + 1.0) * 1e6  # time since configuration (first frame 1 ms later)
    expected = 2 * 100e-6 * t_ns  # fastest minus slowest: 200 ppm of elapsed time
    initial = 1_300.0  # at most the largest propagation delay (SOEM offsets lag by it)
    assert np.all(np.abs(r.spread_ns - expected) <= initial)
    assert r.final_spread_ns == pytest.approx(400_000, rel=0.01)


def test_soem_plain_delays_leave_a_static_spread() -> None:
    r = simulate(16, 50.0, 2.0, master_t_diff_ns=0)
    # 14 forwarding slaves x t_Diff/2 = 14 x 20 = 280 ns of delay error that the loop cannot see
    assert r.max_delay_error_ns == pytest.approx(280, abs=8)
    assert r.final_spread_ns == pytest.approx(280, abs=20)


def test_sync0_edges_follow_start_plus_k_cycles() -> None:
    clock = DcSlaveClock(initial_local_ns=1_000)
    clock.write_register(DcRegister.SYSTEM_TIME_OFFSET, (5_000_000 - 1_000).to_bytes(8, "little"), 0)
    assert clock.system_time(0) == 5_000_000
    start = sync0_start_time(clock.system_time(0), 1_000_000, shift_ns=250_000)
    # SOEM: ((5 ms + 100 ms) // 1 ms) x 1 ms + 1 ms + 250 us
    assert start == 105_000_000 + 1_000_000 + 250_000
    clock.write_register(DcRegister.START_TIME_CYCLIC, start.to_bytes(8, "little"), 0)
    clock.write_register(DcRegister.SYNC0_CYCLE_TIME, (1_000_000).to_bytes(4, "little"), 0)
    assert clock.sync0_edges(0, 200_000_000) == []  # not activated yet
    clock.write_register(
        DcRegister.ACTIVATION, bytes([SyncActivation.CYCLIC_OPERATION | SyncActivation.SYNC0]), 0
    )
    edges = clock.sync0_edges(0, 110_000_000)
    # system time = true time + 5 ms, so pulse k is at start + k ms - 5 ms of true time
    assert edges == [start - 5_000_000 + k * 1_000_000 for k in range(len(edges))]
    assert len(edges) == 9  # 101.25, 102.25, ..., 109.25 ms
    # with SYNC1 at 300 us after SYNC0
    clock.write_register(DcRegister.SYNC1_CYCLE_TIME, (300_000).to_bytes(4, "little"), 0)
    clock.write_register(DcRegister.ACTIVATION, bytes([7]), 0)
    assert clock.sync1_edges(0, 103_000_000) == [101_550_000, 102_550_000]


def test_sync0_edges_of_a_drifting_clock() -> None:
    clock = DcSlaveClock(drift_ppm=100.0)  # local runs 100 ppm fast: 1 ms of system time = 1 ms / 1.0001
    clock.write_register(DcRegister.START_TIME_CYCLIC, (10_000_000).to_bytes(8, "little"), 0)
    clock.write_register(DcRegister.SYNC0_CYCLE_TIME, (1_000_000).to_bytes(4, "little"), 0)
    clock.write_register(DcRegister.ACTIVATION, bytes([3]), 0)
    edges = clock.sync0_edges(0, 12_100_000)
    assert edges == [round((10_000_000 + k * 1_000_000) / 1.0001) for k in range(3)]


def test_registers_round_trip_and_time_control_input() -> None:
    clock = DcSlaveClock(drift_ppm=50.0)
    assert clock.read_register(DcRegister.SPEED_COUNTER_START, 2, 0) == (0x1000).to_bytes(2, "little")
    clock.write_register(DcRegister.SYSTEM_TIME_DELAY, (300).to_bytes(4, "little"), 0)
    assert clock.read_register(DcRegister.SYSTEM_TIME_DELAY, 4, 0) == (300).to_bytes(4, "little")
    # a received time 1000 ns ahead of (system time - delay): local copy smaller -> bit 31 set, speeds up
    now = 1_000_000
    received = clock.system_time(now) - 300 + 1_000
    clock.write_register(DcRegister.SYSTEM_TIME, received.to_bytes(8, "little"), now)
    diff = int.from_bytes(clock.read_register(DcRegister.SYSTEM_TIME_DIFF, 4, now), "little")
    assert diff == 0x8000_0000 | 1_000
    assert clock.rate > 1.0 + 50e-6
    # writing Speed Counter Start resets the loop
    clock.write_register(DcRegister.SPEED_COUNTER_START, (0x1000).to_bytes(2, "little"), now)
    assert clock.read_register(DcRegister.SYSTEM_TIME_DIFF, 4, now) == bytes(4)
    assert clock.rate == pytest.approx(1.0 + 50e-6)
    with pytest.raises(ValueError, match="DC registers"):
        clock.read_register(0x0A00, 2, now)


def test_register_level_segment_converges() -> None:
    drifts = (0.0, 100.0, -100.0)
    clocks = [
        DcSlaveClock(drift_ppm=d, initial_local_ns=v)
        for d, v in zip(drifts, (7, 9_999_999, 2**40), strict=True)
    ]
    seg = DcSegment(clocks, [1.0, 1.0, 1.0])
    seg.latch_receive_times(0)
    rx = [c.port_rx_local for c in clocks]
    delays = line_propagation_delays(
        [r[0] & 0xFFFFFFFF for r in rx], [rx[0][1] & 0xFFFFFFFF, rx[1][1] & 0xFFFFFFFF, None], 40
    )
    for c, d, off in zip(clocks, delays, soem_offsets(0, [c.epu_rx_local for c in clocks]), strict=True):
        c.write_register(DcRegister.SYSTEM_TIME_OFFSET, (off % 2**64).to_bytes(8, "little"), 1_000)
        c.write_register(DcRegister.SYSTEM_TIME_DELAY, d.to_bytes(4, "little"), 1_000)
        c.write_register(DcRegister.SPEED_COUNTER_START, (0x1000).to_bytes(2, "little"), 1_000)
    for n in range(1, 1500):
        seg.distribute_system_time(n * 1_000_000)
    t = 1500 * 1_000_000
    times = [c.system_time(t) for c in clocks]
    assert max(times) - min(times) < 100


def test_host_pi_converges_to_requested_offset() -> None:
    cfg = HostSyncConfig(cycle_ns=1_000_000, offset_ns=50_000)
    deltas = simulate_host_sync(20_000, host_drift_ppm=50.0, initial_phase_ns=400_000, config=cfg)
    assert abs(deltas[0]) > 300_000  # starts 350 us off
    assert np.max(np.abs(deltas[-2000:])) < 1_000  # within 1 us of the requested 50 us offset
    deltas = simulate_host_sync(
        20_000, host_drift_ppm=-80.0, initial_phase_ns=900_000, jitter_ns=5_000, seed=1
    )
    assert abs(float(np.mean(deltas[-2000:]))) < 1_000


def test_cli_json(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["dc-sim", "--json", "--slaves", "4", "--drift-ppm", "100", "--seconds", "1"]) == 0
    out = json.loads(capsys.readouterr().out)
    for key in (
        "final_spread_ns",
        "converged_after_ms",
        "slaves",
        "drift_ppm",
        "seconds",
        "sync0_spread_ns",
        "max_spread_after_convergence_ns",
    ):
        assert key in out
    assert out["slaves"] == 4 and out["drift_ppm"] == 100.0 and out["seconds"] == 1.0
    assert out["final_spread_ns"] < 100.0 and out["converged_after_ms"] is not None


def test_cli_no_compensation_and_table(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["dc-sim", "--json", "--no-compensation", "--seconds", "0.5"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["converged_after_ms"] is None and out["max_spread_after_convergence_ns"] is None
    assert main(["dc-sim", "--seconds", "0.2", "--slaves", "2"]) == 0
    assert "final spread" in capsys.readouterr().out


def test_cli_rejects_bad_input(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit):
        main(["dc-sim", "--slaves", "0"])
    assert "must be an integer >= 1" in capsys.readouterr().err
