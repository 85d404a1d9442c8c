"""Distributed clocks: the real pysoem master configures the emulated ESCs' clocks over a veth pair.

The emulated clocks follow ``fieldbus.core.dc`` (drift, line delays, the ESC
time-control loop). pysoem reads and writes the registers itself
(``config_dc``, ``dc_sync``, the FRMW in every cycle frame, ``Slave._fprd``);
the emulator's ``dc`` control command reports every slave's system time at one
instant of its own time line, which no master can read over the wire.

Line in the emulator: t_P = 320 ns, t_F = 280 ns, 1 m (5 ns) per hop. SOEM
assumes t_P = t_F, so each slave that sends the frame back through its
forwarder makes SOEM's delays t_Diff/2 = 20 ns short, summed down the line:
slave i's error is -20 x min(i, n - 2) ns (docs/dc.md).
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

import pytest

pysoem = pytest.importorskip("pysoem")

INTEROP = Path(__file__).resolve().parents[1] / "data" / "ethercat_driver_ros2"
MAXON = INTEROP / "maxon_epos4_50_5.yaml"
MS = 1_000_000
SOEM_SYNC_DELAY_NS = 100 * MS  # ecx_dcsync0: first pulse 100 ms after the system time read

pytestmark = [pytest.mark.veth, pytest.mark.timeout(300), pytest.mark.usefixtures("generous_pysoem_timeouts")]


def _u(slave: Any, ado: int, size: int) -> int:
    return int.from_bytes(slave._fprd(ado, size, 20_000), "little")


def _configure(emu: Any, n: int) -> Any:
    master = pysoem.Master()
    master.open(emu.iface)
    assert master.config_init() == n
    master.config_map()
    assert master.state_check(pysoem.SAFEOP_STATE, 2_000_000) == pysoem.SAFEOP_STATE
    return master


def _dc(emu: Any) -> list[dict[str, Any]]:
    answer = emu.command(cmd="dc")
    assert answer["ok"], answer
    slaves: list[dict[str, Any]] = answer["dc"]["slaves"]
    return slaves


def _run_cycles(master: Any, seconds: float) -> int:
    """Process-data cycles of about 0.5 ms (each frame carries SOEM's FRMW of the reference's 0x0910)."""
    end = time.monotonic() + seconds
    n = 0
    while time.monotonic() < end:
        master.send_processdata()
        master.receive_processdata(10_000)
        n += 1
        time.sleep(0.0005)
    return n


@pytest.mark.parametrize("n", [4, 12])
def test_config_dc_offsets_and_delays_make_clocks_agree(ethercat_emulator: Any, n: int) -> None:
    emu = ethercat_emulator([MAXON], count=n, app="none")
    master = _configure(emu, n)
    try:
        assert master.config_dc()
        status = _dc(emu)
        # what pysoem wrote is what the emulated ESCs hold, and what the master reads back
        for s, st in zip(master.slaves, status, strict=True):
            assert _u(s, 0x0920, 8) == st["offset"]
            assert _u(s, 0x0928, 4) == st["delay"]
        assert status[0]["delay"] == 0  # the reference clock
        true_delays = [st["port0_ns"] - status[0]["port0_ns"] for st in status]
        assert true_delays[1:4] == [325, 650, 975]
        # SOEM's offsets: every slave's system time lags the reference's by its propagation delay,
        # so at one instant system time + written delay = reference time, up to SOEM's t_Diff error
        ref = status[0]["system_time"]
        residual = [st["system_time"] + st["delay"] - ref for st in status]
        expected = [-20 * min(i, n - 2) for i in range(n)]
        assert residual == pytest.approx(expected, abs=3), residual
        if n == 4:
            assert max(abs(r) for r in residual) < 100
        # ESCs whose forwarding delay equals the processing delay (SOEM's assumption): all n agree
        emu.command(cmd="dc_config", processing_ns=300, forwarding_ns=300)
        assert master.config_dc()
        status = _dc(emu)
        ref = status[0]["system_time"]
        residual = [
            st["system_time"] + _u(s, 0x0928, 4) - ref for s, st in zip(master.slaves, status, strict=True)
        ]
        assert max(abs(r) for r in residual) < 100, residual
        # the FRMW in the cycle frames lets the slaves' loops take the lag out
        _run_cycles(master, 1.0)
        times = [st["system_time"] for st in _dc(emu)]
        assert max(times) - min(times) < 100, [t - times[0] for t in times]
    finally:
        master.close()


def test_frmw_keeps_drifting_clocks_within_100ns(ethercat_emulator: Any) -> None:
    n = 4
    emu = ethercat_emulator([MAXON], count=n, app="none")
    drifts = [100.0, -100.0, 60.0, -40.0]
    assert emu.command(cmd="dc_config", drift_ppm=drifts)["ok"]
    master = _configure(emu, n)
    try:
        assert master.config_dc()
        cycles = _run_cycles(master, 0.3)
        early = [st["system_time"] for st in _dc(emu)]
        cycles += _run_cycles(master, 1.5)
        assert cycles > 300  # about 0.5-2 ms each, depending on the load
        status = _dc(emu)
        times = [st["system_time"] for st in status]
        assert max(early) - min(early) > max(times) - min(times)
        # SOEM's delay error (0, -20, -40, -40 ns) stays, the drift is compensated
        assert max(times) - min(times) < 100, [t - times[0] for t in times]
        assert [st["rate_ppm"] for st in status] == pytest.approx([100.0] * n, abs=0.5)
        # the FRMW's answer is the reference's system time: pysoem keeps the last one as dc_time
        master.send_processdata()
        master.receive_processdata(10_000)
        after = _dc(emu)[0]["system_time"]
        assert 0 < after - master.dc_time < 500 * MS  # the status comes a little later (loaded machine)
    finally:
        master.close()


def test_dc_sync_sets_the_sync0_registers(ethercat_emulator: Any) -> None:
    n = 3
    emu = ethercat_emulator([MAXON], count=n, app="none")
    master = _configure(emu, n)
    try:
        assert master.config_dc()
        _run_cycles(master, 1.0)  # the loops take out the propagation delays
        for s in master.slaves:
            before = _u(s, 0x0910, 8)
            s.dc_sync(True, MS, 0)
            after = _u(s, 0x0910, 8)
            assert _u(s, 0x0980, 1) == 0  # cyclic unit under EtherCAT control
            assert _u(s, 0x0981, 1) == 0x03  # cyclic operation + SYNC0
            assert _u(s, 0x09A0, 4) == MS
            # SOEM: the next whole cycle after (system time read + 100 ms), plus one cycle, plus the shift
            start = _u(s, 0x0990, 8)
            assert start % MS == 0
            assert before + SOEM_SYNC_DELAY_NS < start <= after + SOEM_SYNC_DELAY_NS + MS
        time.sleep(0.15)  # every slave's first pulse has passed
        status = _dc(emu)
        for s, st in zip(master.slaves, status, strict=True):
            assert (st["activation"], st["sync0_cycle"], st["start_time"]) == (3, MS, _u(s, 0x0990, 8))
        pulses = [st["sync0_next_ns"] for st in status]
        assert max(pulses) - min(pulses) < 100  # the SYNC0 pulses agree as the clocks do
        # SYNC0 + SYNC1 (ecx_dcsync01): 0x0981 = 7, SYNC1 300 us after SYNC0, shifted by 20 us
        s0 = master.slaves[0]
        s0.dc_sync(True, MS, 20_000, 300_000)
        assert (_u(s0, 0x0981, 1), _u(s0, 0x09A0, 4), _u(s0, 0x09A4, 4)) == (0x07, MS, 300_000)
        assert _u(s0, 0x0990, 8) % MS == 20_000
        s0.dc_sync(False, MS)
        assert _u(s0, 0x0981, 1) == 0
        assert _dc(emu)[0]["sync0_next_ns"] is None
    finally:
        master.close()
