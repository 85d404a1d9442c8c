"""Emulated ESC distributed clocks, sans-IO: frames through EscChain with hand-computed expectations.

Line used throughout (default ESC timing t_P = 320 ns, t_F = 280 ns, 1 m =
5 ns of cable per hop), a frame sent by the master at t:

    slave      0      1      2      3
    port 0   t+5   t+330  t+655  t+980    (+5 cable, +320 through each ESC)
    port 1  t+1875 t+1590 t+1305   -      (last turns round: 980+320, +5 cable, +280 back)

Slave i's local clock reads i ms + true time (drift 0) unless a test sets
drifts. SOEM's delays (t_P = t_F assumed): slave 1 = (1870 - 1260) / 2 = 305,
slave 2 = 305 + (1260 - 650) / 2 = 610, slave 3 = 610 + 650 / 2 = 935; the
true ones are 325, 650, 975.
"""

from __future__ import annotations

import struct
from pathlib import Path

import numpy as np
import pytest

from fieldbus.core.dc import (
    DcRegister,
    EscTiming,
    LoopConfig,
    LoopState,
    line_propagation_delays,
    loop_step,
    soem_offsets,
    sync0_start_time,
)
from fieldbus.core.ecat import Command, Datagram, build_master_frame, decode_frame
from fieldbus.core.pdo.load import drive_map_from_text
from sim_slaves.ethercat import EscChain
from sim_slaves.ethercat.dc import DcLine, EscDc
from sim_slaves.ethercat.dc_clock import ClockArrays, DcSlaveClock
from sim_slaves.ethercat.runner import handle_control

IO16 = (Path(__file__).resolve().parents[1] / "data" / "io16.yaml").read_text()
P0 = [5, 330, 655, 980]
P1 = [1875, 1590, 1305, None]
SOEM_DELAYS = [0, 305, 610, 935]
TRUE_DELAYS = [0, 325, 650, 975]
MS = 1_000_000
STATION = 0x1001
MASTER_TIME = 800_000_000_000_000_000  # about 25 years after 2000-01-01, in ns
U32 = 0xFFFF_FFFF


def make_chain(n: int = 4, drift_ppm: list[float] | None = None, min_sample_ns: int = 500_000) -> EscChain:
    maps = [drive_map_from_text(IO16)] * n
    chain = EscChain.from_maps(maps, app=None, drift_ppm=drift_ppm, dc_min_sample_interval_ns=min_sample_ns)
    for i in range(n):
        exchange(chain, [Datagram.physical(Command.APWR, -i, 0x0010, struct.pack("<H", STATION + i))], 0)
    return chain


def exchange(chain: EscChain, dgs: list[Datagram], now_ns: int) -> tuple[Datagram, ...]:
    reply = chain.process(build_master_frame(dgs), now_ns)
    assert reply is not None
    return decode_frame(reply).datagrams


def fprd(chain: EscChain, i: int, ado: int, size: int, now_ns: int) -> bytes:
    (d,) = exchange(chain, [Datagram.physical(Command.FPRD, STATION + i, ado, bytes(size))], now_ns)
    assert d.wkc == 1
    return d.data


def fpwr(chain: EscChain, i: int, ado: int, data: bytes, now_ns: int) -> None:
    (d,) = exchange(chain, [Datagram.physical(Command.FPWR, STATION + i, ado, data)], now_ns)
    assert d.wkc == 1


def bwr(chain: EscChain, ado: int, data: bytes, now_ns: int) -> int:
    (d,) = exchange(chain, [Datagram.physical(Command.BWR, 0, ado, data)], now_ns)
    return d.wkc


def frmw(chain: EscChain, now_ns: int, station: int = STATION, size: int = 8) -> Datagram:
    (d,) = exchange(chain, [Datagram.physical(Command.FRMW, station, 0x0910, bytes(size))], now_ns)
    return d


def soem_init_defaults(chain: EscChain, now_ns: int) -> None:
    """What ecx_config_init broadcasts to the DC registers: 0x0981 = 0, 0x0910 = 0, 0x0930, 0x0934."""
    bwr(chain, 0x0981, bytes(1), now_ns)
    bwr(chain, 0x0910, bytes(4), now_ns)
    bwr(chain, 0x0930, struct.pack("<H", 0x1000), now_ns)
    bwr(chain, 0x0934, struct.pack("<H", 0x0C00), now_ns)


def soem_config_dc(chain: EscChain, t_latch: int, t_diff_ns: int = 0) -> list[int]:
    """ecx_configdc through frames: latch, offsets = master time - 0x0918, delays from port times."""
    assert bwr(chain, 0x0900, bytes(4), t_latch) == len(chain)
    t = t_latch + 50_000
    p0, p1, epu = [], [], []
    for i in range(len(chain)):
        p0.append(struct.unpack("<I", fprd(chain, i, 0x0900, 4, t))[0])
        epu.append(struct.unpack("<Q", fprd(chain, i, 0x0918, 8, t))[0])
        p1.append(struct.unpack("<I", fprd(chain, i, 0x0904, 4, t))[0])
    delays = line_propagation_delays(p0, [*p1[:-1], None], t_diff_ns)
    for i, off in enumerate(soem_offsets(MASTER_TIME, epu)):
        fpwr(chain, i, 0x0920, struct.pack("<Q", off % 2**64), t)
        if i:
            fpwr(chain, i, 0x0928, struct.pack("<I", delays[i]), t)
    return delays


def system_times(chain: EscChain, now_ns: int) -> list[int]:
    return [s["system_time"] for s in chain.dc_status(now_ns)]


# ---------------------------------------------------------------- line and latching


def test_slaves_sit_on_the_line_as_hand_computed() -> None:
    chain = make_chain()
    assert [s.dc.port0_ns for s in chain.slaves] == P0
    assert [s.dc.port1_ns for s in chain.slaves] == P1
    # equal delays, 10 m cables (50 ns): 50, 50+500+50 = 600, ...; last out at 1700 + 500 = 2200
    chain.set_dc_line(EscTiming(processing_ns=500, forwarding_ns=500), 10.0)
    assert [s.dc.port0_ns for s in chain.slaves] == [50, 600, 1150, 1700]
    assert [s.dc.port1_ns for s in chain.slaves] == [3350, 2800, 2250, None]


def test_bwr_0900_latches_port_and_epu_times_along_the_line() -> None:
    chain = make_chain()
    t = 2**32 - 505  # slave 0's port 0 time is 2^32 - 500: its 32-bit port 1 time wraps
    assert bwr(chain, 0x0900, bytes(4), t) == 4
    for i in range(4):
        local = i * MS + t
        ports = struct.unpack("<4I", fprd(chain, i, 0x0900, 16, t + 10_000))
        p1 = P1[i]
        assert ports == ((local + P0[i]) & U32, 0 if p1 is None else (local + p1) & U32, 0, 0)
        assert struct.unpack("<Q", fprd(chain, i, 0x0918, 8, t + 10_000))[0] == local + P0[i]
    assert struct.unpack("<I", fprd(chain, 0, 0x0904, 4, t))[0] == 1370  # 2^32 - 500 + 1870, wrapped
    # the master's arithmetic on these gives SOEM's delays; with t_Diff = 40 ns the true ones
    p0 = [struct.unpack("<I", fprd(chain, i, 0x0900, 4, t))[0] for i in range(4)]
    p1s = [struct.unpack("<I", fprd(chain, i, 0x0904, 4, t))[0] for i in range(3)]
    assert line_propagation_delays(p0, [*p1s, None]) == SOEM_DELAYS
    assert line_propagation_delays(p0, [*p1s, None], 40) == TRUE_DELAYS


def test_write_spanning_the_dc_block_latches_and_compares() -> None:
    chain = make_chain(2)
    assert bwr(chain, 0x0900, bytes(0x20), 7 * MS) == 2  # 0x0900-0x091F: latch + time-control input 0
    assert struct.unpack("<Q", fprd(chain, 1, 0x0918, 8, 8 * MS))[0] == MS + 7 * MS + P0[1]
    assert fprd(chain, 1, 0x092C, 4, 8 * MS) != bytes(4)  # the loop took the zeros as a received time


# ---------------------------------------------------------------- SOEM's offsets and delays


def test_soem_offsets_and_delays_make_system_times_agree() -> None:
    chain = make_chain()
    t_latch = 3 * 10**9
    delays = soem_config_dc(chain, t_latch)
    assert delays == SOEM_DELAYS
    # each system time reads the master time when the latch frame passed it: one FPRD per slave
    # in one frame returns the same value everywhere (each slave lags by exactly its true delay)
    t = t_latch + 2 * MS
    reads = [Datagram.physical(Command.FPRD, STATION + i, 0x0910, bytes(8)) for i in range(4)]
    dgs = exchange(chain, reads, t)
    assert [struct.unpack("<Q", d.data)[0] for d in dgs] == [MASTER_TIME + t - t_latch] * 4
    for i in range(4):
        assert struct.unpack("<I", fprd(chain, i, 0x0928, 4, t))[0] == delays[i]
    # at one instant: system time + delay = reference time, up to SOEM's missing t_Diff/2 per hop
    sys_t = system_times(chain, t)
    assert [s + d - sys_t[0] for s, d in zip(sys_t, delays, strict=True)] == [0, -20, -40, -40]
    # a master that knows t_Diff writes the true delays: exact
    chain2 = make_chain()
    delays2 = soem_config_dc(chain2, t_latch, t_diff_ns=40)
    sys2 = system_times(chain2, t)
    assert [s + d - sys2[0] for s, d in zip(sys2, delays2, strict=True)] == [0, 0, 0, 0]


# ---------------------------------------------------------------- FRMW and the time-control loop


def test_frmw_returns_the_reference_time_and_feeds_the_loops_downstream() -> None:
    chain = make_chain()
    t_latch = 3 * 10**9
    soem_init_defaults(chain, t_latch - MS)
    soem_config_dc(chain, t_latch)
    t = t_latch + 5 * MS
    d = frmw(chain, t)
    assert d.wkc == 4  # the reference reads, three slaves write
    assert struct.unpack("<Q", d.data)[0] == MASTER_TIME + t - t_latch
    assert chain.slaves[0].dc.clock.system_time(t + P0[0]) == MASTER_TIME + t - t_latch
    # each later slave: delta = system time as the frame passes - delay - received = -SOEM delay
    for i in range(4):
        diff = struct.unpack("<I", fprd(chain, i, 0x092C, 4, t))[0]
        assert diff == (0 if i == 0 else 0x8000_0000 | SOEM_DELAYS[i])  # bit 31: local copy smaller
    # a 4-byte FRMW gets the lower half
    d4 = frmw(chain, t + MS, size=4)
    assert struct.unpack("<I", d4.data)[0] == (MASTER_TIME + t + MS - t_latch) & U32


def test_loop_samples_are_queued_until_idle_or_an_access() -> None:
    chain = make_chain()
    soem_config_dc(chain, 10**9)
    buf0 = build_master_frame([Datagram.physical(Command.FRMW, STATION, 0x0910, bytes(8))])
    replies = []
    for k in (1, 2):  # the runner's way: process_into(cycles=False), send, run_cycles
        buf = bytearray(buf0)
        chain.process_into(buf, len(buf), 10**9 + k * MS, cycles=False)
        chain.run_cycles(10**9 + k * MS)
        replies.append(struct.unpack("<Q", decode_frame(buf).datagrams[0].data)[0])
    assert replies == [MASTER_TIME + k * MS for k in (1, 2)]  # the reference read needs no flush
    assert len(chain.dc_line.pending) == 2  # nothing computed yet
    assert not chain.slaves[3].dc._clock.loop_state.primed[0]
    chain.dc_line.flush()  # what the runner does when no frame is waiting
    assert not chain.dc_line.pending and chain.slaves[3].dc._clock.loop_state.primed[0]
    # any access to a unit of the line applies the queue first; the result is the same either way
    other = make_chain()
    soem_config_dc(other, 10**9)
    for k in (1, 2):
        frmw(other, 10**9 + k * MS)  # process(): applied before it returns
    assert not other.dc_line.pending
    chain.process_into(bytearray(buf0), len(buf0), 10**9 + 3 * MS, cycles=False)
    frmw(other, 10**9 + 3 * MS)
    assert fprd(chain, 3, 0x092C, 4, 10**9 + 4 * MS) == fprd(other, 3, 0x092C, 4, 10**9 + 4 * MS)
    assert chain.dc_status(10**9 + 5 * MS) == other.dc_status(10**9 + 5 * MS)


@pytest.mark.parametrize("soem_delays", [True, False])
def test_drifting_clocks_converge_within_100ns_with_repeated_frmw(soem_delays: bool) -> None:
    drifts = [100.0, -100.0, 33.0, -66.0]
    chain = make_chain(drift_ppm=drifts)
    t_latch = 10**9
    soem_init_defaults(chain, t_latch - MS)
    soem_config_dc(chain, t_latch, t_diff_ns=0 if soem_delays else 40)
    spreads = []
    t = t_latch + MS
    for k in range(3000):  # 3 s of 1 ms cycles
        ref = chain.slaves[0].dc.clock.system_time(t + P0[0])
        d = frmw(chain, t)
        assert struct.unpack("<Q", d.data)[0] == ref
        if k % 10 == 0:
            s = system_times(chain, t)
            spreads.append(max(s) - min(s))
        t += MS
    spreads_ns = np.array(spreads)
    assert spreads_ns[0] > 900  # right after configuration slave 3 lags by about its delay
    # converged after well under a second; from 1 s on every sample is inside 100 ns
    assert np.all(spreads_ns[100:] < 100), spreads_ns[100:].max()
    final = system_times(chain, t)
    if soem_delays:  # what stays is SOEM's delay error (-20, -40, -40 ns)
        assert [x - final[0] for x in final] == pytest.approx([0, -20, -40, -40], abs=3)
    else:
        assert max(final) - min(final) <= 3
    rates = [s["rate_ppm"] for s in chain.dc_status(t)]
    assert rates == pytest.approx([100.0] * 4, abs=0.05)  # everybody runs at the reference's speed


def test_frmw_faster_than_the_sample_interval_gives_the_same_clocks() -> None:
    """At 10 kHz the loops take every 5th FRMW (0.5 ms apart); their course is the same within ns."""
    runs = {}
    for min_ns in (0, 500_000):
        chain = make_chain(drift_ppm=[100.0, -100.0, 33.0, -66.0], min_sample_ns=min_ns)
        soem_init_defaults(chain, 10**9 - MS)
        soem_config_dc(chain, 10**9, t_diff_ns=40)
        t = 10**9 + MS
        rows = []
        for k in range(15_000):  # 1.5 s of 100 us cycles
            ref = chain.slaves[0].dc.clock.system_time(t + P0[0])
            assert struct.unpack("<Q", frmw(chain, t).data)[0] == ref  # answered every time
            if k % 100 == 0:
                s = system_times(chain, t)
                rows.append([x - s[0] for x in s])
            t += 100_000
        runs[min_ns] = np.array(rows)
        assert (chain.dc_line.samples, chain.dc_line.skipped) == (
            (15_000, 0) if min_ns == 0 else (3_000, 12_000)
        )
    every, thinned = runs[0], runs[500_000]
    assert np.abs(every[100:]).max() <= 2 and np.abs(thinned[100:]).max() <= 2  # converged after 1 s
    diff = np.abs(thinned - every)
    assert diff.max() <= 25 and diff[50:].max() <= 2  # the transient differs by ns, then nothing


def test_without_frmw_the_drift_shows() -> None:
    chain = make_chain(drift_ppm=[100.0, -100.0, 0.0, 0.0])
    soem_config_dc(chain, 10**9, t_diff_ns=40)
    s = system_times(chain, 10**9 + 10**9)  # one second after the latch: 200 ppm apart
    assert s[0] - (s[1] + TRUE_DELAYS[1]) == pytest.approx(200_000, abs=2)
    assert s[0] - (s[2] + TRUE_DELAYS[2]) == pytest.approx(100_000, abs=2)


def test_frmw_to_a_later_reference_and_armw() -> None:
    chain = make_chain()
    soem_config_dc(chain, 10**9, t_diff_ns=40)
    t = 10**9 + MS
    ref_time = chain.slaves[1].dc.clock.system_time(t + P0[1])
    d = frmw(chain, t, station=STATION + 1)
    assert d.wkc == 4 and struct.unpack("<Q", d.data)[0] == ref_time
    # slave 0 (before the reference) compared the master's zeros: a huge difference
    assert struct.unpack("<I", fprd(chain, 0, 0x092C, 4, t))[0] & 0x7FFF_FFFF > 10**6
    # slaves 2 and 3 got slave 1's time, which as the frame passes equals theirs (SOEM's offsets):
    # the loop sees minus their delay, as with slave 0 as the reference
    for i in (2, 3):
        assert struct.unpack("<I", fprd(chain, i, 0x092C, 4, t))[0] == 0x8000_0000 | TRUE_DELAYS[i]
    # ARMW at position 1 (ADP = -1) is the same datagram addressed by position
    (a,) = exchange(chain, [Datagram.physical(Command.ARMW, -1, 0x0910, bytes(8))], t + MS)
    assert a.wkc == 4
    assert struct.unpack("<Q", a.data)[0] == chain.slaves[1].dc.clock.system_time(t + MS + P0[1])


def test_speed_counter_start_write_resets_the_loop() -> None:
    chain = make_chain(drift_ppm=[0.0, 50.0, 0.0, 0.0])
    soem_config_dc(chain, 10**9)
    frmw(chain, 10**9 + MS)
    frmw(chain, 10**9 + 2 * MS)
    assert chain.dc_status(10**9 + 2 * MS)[1]["rate_ppm"] != pytest.approx(50.0, abs=1)
    assert bwr(chain, 0x0930, struct.pack("<H", 0x1000), 10**9 + 3 * MS) == 4
    st = chain.dc_status(10**9 + 3 * MS)[1]
    assert st["rate_ppm"] == pytest.approx(50.0) and st["system_time_diff"] == 0
    assert st["speed_counter_start"] == 0x1000


# ---------------------------------------------------------------- SYNC0 registers


def test_sync0_registers_hold_what_dc_sync_wrote() -> None:
    chain = make_chain(3)
    soem_config_dc(chain, 10**9)
    t = 10**9 + MS
    for _ in range(1000):  # let the loops take out the propagation delays
        frmw(chain, t)
        t += MS
    starts = []
    for i in range(3):  # ecx_dcsync0(slave, TRUE, 1 ms, 0)
        fpwr(chain, i, 0x0981, bytes([0]), t)
        fpwr(chain, i, 0x0980, bytes([0]), t)
        t1 = struct.unpack("<Q", fprd(chain, i, 0x0910, 8, t))[0]
        start = sync0_start_time(t1, MS, 0)
        assert start % MS == 0 and 100 * MS < start - t1 <= 101 * MS
        fpwr(chain, i, 0x0990, struct.pack("<Q", start), t)
        fpwr(chain, i, 0x09A0, struct.pack("<I", MS), t)
        fpwr(chain, i, 0x0981, bytes([3]), t)
        starts.append(start)
        t += 200_000
    for i in range(3):
        assert fprd(chain, i, 0x0980, 2, t) == bytes([0, 3])
        assert struct.unpack("<Q", fprd(chain, i, 0x0990, 8, t))[0] == starts[i]
        assert struct.unpack("<II", fprd(chain, i, 0x09A0, 8, t)) == (MS, 0)
    later = t + 150 * MS  # all three are cycling by then
    status = chain.dc_status(later)
    nxt = [s["sync0_next_ns"] for s in status]
    assert max(nxt) - min(nxt) < 100  # the pulses agree as the system times do
    c0 = chain.slaves[0].dc.clock
    assert c0.system_time(nxt[0]) % MS in (0, MS - 1)  # on the 1 ms grid of system time
    assert c0.sync0_edges(later, later + 3 * MS)[0] == nxt[0]
    # SYNC1 as ecx_dcsync01 writes it: 0x0981 = 7, 0x09A4 = SYNC1 cycle
    fpwr(chain, 0, 0x09A4, struct.pack("<I", 300_000), later)
    fpwr(chain, 0, 0x0981, bytes([7]), later)
    st = chain.dc_status(later)[0]
    assert (st["activation"], st["sync0_cycle"], st["sync1_cycle"]) == (7, MS, 300_000)
    fpwr(chain, 0, 0x0981, bytes([0]), later)
    assert chain.dc_status(later)[0]["sync0_next_ns"] is None


def test_power_cycle_clears_the_dc_registers() -> None:
    chain = make_chain(2, drift_ppm=[0.0, 20.0])
    soem_config_dc(chain, 10**9)
    fpwr(chain, 1, 0x0981, bytes([3]), 10**9 + MS)
    chain.power_cycle(1)
    st = chain.dc_status(10**9 + 2 * MS)[1]
    assert (st["offset"], st["delay"], st["activation"]) == (0, 0, 0)
    assert st["drift_ppm"] == 20.0 and st["port0_ns"] == P0[1]


# ---------------------------------------------------------------- the model underneath


def test_time_control_input_is_the_vectorised_loop_step() -> None:
    rng = np.random.default_rng(7)
    cfg = LoopConfig(speed_counter_start=0x0800, diff_filter_depth=2)
    clock = DcSlaveClock(drift_ppm=-30.0, initial_local_ns=2**32 - 5 * MS, loop=cfg)
    clock.write_register(DcRegister.SYSTEM_TIME_DELAY, (700).to_bytes(4, "little"), 0)
    state = LoopState.reset(1)
    t = 0
    last_local: int | None = None
    for k in range(400):
        t += int(rng.uniform(100_000, 3_000_000))
        delta = int(rng.normal(0, 5_000 if k < 50 else 50))
        local = clock.local_time(t)
        received = (clock.system_time(t) - 700 - delta) % 2**64
        clock.time_control_input(received, t)
        interval = 0.0 if last_local is None else float(local - last_local)
        last_local = local
        state = loop_step(state, np.array([float(delta)]), interval, cfg)
        got = clock.loop_state
        assert got.diff_ns[0] == state.diff_ns[0]
        assert got.integral_frac[0] == state.integral_frac[0]
        assert got.correction_frac[0] == state.correction_frac[0]
    assert clock.rate == (1.0 - 30e-6) * (1.0 + float(state.correction_frac[0]))


def test_set_drift_keeps_local_time_continuous() -> None:
    clock = DcSlaveClock(drift_ppm=0.0, initial_local_ns=1_000)
    clock.set_drift(100.0, 10 * MS)
    assert clock.local_time(10 * MS) == 1_000 + 10 * MS
    assert clock.local_time(20 * MS) == 1_000 + 20 * MS + 1_000  # 100 ppm of 10 ms
    assert clock.rate == pytest.approx(1.0001)


def test_registers_0930_0934_as_soem_writes_them() -> None:
    clock = DcSlaveClock()
    clock.write_register(DcRegister.SYSTEM_TIME_DIFF_FILTER_DEPTH, bytes([0x00, 0x0C]), 0)
    assert clock.loop_config.diff_filter_depth == 0 and clock.loop_config.speed_filter_depth == 0x0C


# ---------------------------------------------------------------- runner control commands


def test_control_commands_report_and_configure_the_clocks() -> None:
    chain = make_chain()
    soem_config_dc(chain, 10**9, t_diff_ns=40)
    now = 10**9 + 5 * MS
    ans = handle_control(chain, {"cmd": "dc"}, now_ns=now)
    assert ans["ok"] and ans["dc"]["now_ns"] == now
    slaves = ans["dc"]["slaves"]
    assert [s["delay"] for s in slaves] == TRUE_DELAYS
    assert [s["system_time"] + s["delay"] for s in slaves] == [slaves[0]["system_time"]] * 4
    assert slaves[3]["port1_ns"] is None and slaves[0]["receive_time_ports"][2:] == [0, 0]
    ans = handle_control(chain, {"cmd": "dc_config", "drift_ppm": 100, "seed": 1}, now_ns=now)
    drifts = sorted(s["drift_ppm"] for s in ans["dc"]["slaves"])
    assert drifts == pytest.approx([-100, -100 / 3, 100 / 3, 100])
    ans = handle_control(chain, {"cmd": "dc_config", "drift_ppm": [1, 2, 3, 4]}, now_ns=now)
    assert [s["drift_ppm"] for s in ans["dc"]["slaves"]] == [1, 2, 3, 4]
    # same instant, drift changed from now on: the clocks did not jump
    assert [s["system_time"] for s in ans["dc"]["slaves"]] == [s["system_time"] for s in slaves]
    ans = handle_control(chain, {"cmd": "dc_config", "processing_ns": 300, "forwarding_ns": 300}, now_ns=now)
    assert [s["port0_ns"] for s in ans["dc"]["slaves"]] == [5, 310, 615, 920]
    frmw(chain, now)
    frmw(chain, now + 100_000)  # within 0.5 ms of the last sample: answered, not given to the loops
    ans = handle_control(chain, {"cmd": "dc_config", "min_sample_interval_ns": 0}, now_ns=now + MS)
    assert (ans["dc"]["samples"], ans["dc"]["skipped"], ans["dc"]["min_sample_interval_ns"]) == (1, 1, 0)
    with pytest.raises(ValueError, match="need 4 drifts"):
        handle_control(chain, {"cmd": "dc_config", "drift_ppm": [1.0]}, now_ns=now)


@pytest.mark.parametrize("c_loop", [True, False], ids=["c", "python"])
def test_a_line_steps_its_loops_together_as_each_clock_would_alone(
    c_loop: bool, monkeypatch: pytest.MonkeyPatch
) -> None:
    """DcLine.flush (the C loop over the line's records, or clock by clock) gives every clock its own bits."""
    if c_loop:
        assert ClockArrays.loop is not None, (
            "sim_slaves._dcloop is not built (python setup.py build_ext --inplace)"
        )
    else:
        monkeypatch.setattr(ClockArrays, "loop", None)
    rng = np.random.default_rng(11)
    n = 9
    drifts = rng.uniform(-80, 80, n)
    starts = [int(x) for x in rng.integers(0, 2**63, n - 1)] + [2**64 - 3 * MS]  # one wraps soon
    units = [EscDc(drift_ppm=drifts[i], initial_local_ns=starts[i]) for i in range(n)]
    line = DcLine(units, min_sample_interval_ns=0)
    line.place(EscTiming(), 2.0)
    alone = [DcSlaveClock(drift_ppm=drifts[i], initial_local_ns=starts[i]) for i in range(n)]
    port0 = [u.port0_ns for u in units]

    def write(i: int, reg: int, value: int, size: int, t: int) -> None:
        units[i].write(reg, value.to_bytes(size, "little"), t)
        alone[i].write_register(reg, value.to_bytes(size, "little"), t + port0[i])

    for i in range(n):  # system times lined up to within 20 us (as SOEM does), delays, two own loops
        offset = (MASTER_TIME - alone[i].local_time(port0[i]) + int(rng.integers(-20_000, 20_000))) % 2**64
        write(i, DcRegister.SYSTEM_TIME_OFFSET, offset, 8, 0)
        write(i, DcRegister.SYSTEM_TIME_DELAY, port0[i], 4, 0)
    write(4, DcRegister.SYSTEM_TIME_DIFF_FILTER_DEPTH, 2, 1, 0)
    write(6, DcRegister.SPEED_COUNTER_START, 0x0400, 2, 0)
    t = 0
    for k in range(300):
        t += int(rng.integers(50_000, 2_000_000))
        ref = 0 if k % 5 else int(rng.integers(0, n))
        ref_time = units[ref].clock.system_time(t + port0[ref])
        sent = (MASTER_TIME + t + int(rng.normal(0, 2_000))) % 2**64  # the master's own idea of the time
        if k == 100:  # one sample far off: the loops saturate and hold their integrals
            ref_time = (ref_time + 2**31 - 1) % 2**64
        line.distribute(ref, sent, ref_time, t)
        for i in range(n):
            if i != ref:
                alone[i].time_control_input(sent if i < ref else ref_time, t + port0[i])
        if k == 150:  # a power cycle: the new clock takes its place on the line
            units[2].power_on()
            alone[2] = DcSlaveClock(drift_ppm=drifts[2], initial_local_ns=starts[2])
        if k % 3 == 0 or k == 299:
            line.flush()
            for i in range(n):
                got, want = units[i].clock, alone[i]
                assert got.local_time(t) == want.local_time(t), (k, i)
                assert got.rate == want.rate, (k, i)
                assert got.loop_state == want.loop_state, (k, i)
    assert all(units[i].clock.loop_state.primed[0] for i in range(n))


def test_a_clock_moved_to_another_line_keeps_its_state() -> None:
    """A LineClock taken over by a new line (its state read from the old line's records) runs on as before."""
    units = [EscDc(drift_ppm=10.0 * i, initial_local_ns=MS * i) for i in range(3)]
    line = DcLine(units, min_sample_interval_ns=0)
    line.place(EscTiming(), 1.0)
    for k in range(1, 50):
        line.distribute(0, MASTER_TIME + k * MS, units[0].clock.system_time(k * MS), k * MS)
    line.flush()
    before = [(u.clock.local_time(60 * MS), u.clock.rate, u.clock.loop_state) for u in units]
    moved = DcLine(units, min_sample_interval_ns=0)
    assert moved.clocks is not line.clocks and all(u.clock.arrays is moved.clocks for u in units)  # type: ignore[attr-defined]
    assert [(u.clock.local_time(60 * MS), u.clock.rate, u.clock.loop_state) for u in units] == before
