"""DC in the EtherCAT backend: config_dc, SYNC0 per the map, DC time and sync error per cycle, host sync.

Real pysoem over veth against the emulator (whose DC registers follow
fieldbus.core.dc). The EPOS4 map asks for SYNC0 (assign_activate 0x0300).

The emulator is another process on the wall clock: on a loaded machine a reply
may come later than the receive timeout (a miss), and the phase the host PI
holds is as good as the machine's wake-ups. So this test asserts what the
backend does with every cycle that came back - the DC time read, its phase
error, the PI's correction handed to the loop - and that DC time runs at the
host's rate; how close the PI holds the phase is measured side by side, PI on
and off, in ``benchmarks/dc_host_sync.py``, and its convergence on a modelled
host in ``tests/unit/test_dc.py``.
"""

from __future__ import annotations

import json
import time
from pathlib import Path
from typing import Any

import pytest

from fieldbus.core.dc.master import HostSync, HostSyncConfig
from fieldbus.network import open_network
from fieldbus.platform.loop import run_cycles

pytestmark = [pytest.mark.veth, pytest.mark.timeout(300)]
pysoem = pytest.importorskip("pysoem")
EPOS4 = Path(__file__).resolve().parents[2] / "pdo_maps" / "maxon_epos4.yaml"
CYCLE_NS = 1_000_000
OK_CYCLES = 1000  # cycles that came back in time, to judge
MAX_CYCLES = 20_000


def _phase_error(dc_time_ns: int, offset_ns: int) -> int:
    """Where ``dc_time_ns`` falls in its DC cycle, minus ``offset_ns``, folded into (-cycle/2, cycle/2]."""
    d = (dc_time_ns - offset_ns) % CYCLE_NS
    return d - CYCLE_NS if d > CYCLE_NS // 2 else d


def _pi_replays(
    corrections: list[int], times: list[int], offset_ns: int, max_integral: int = 100_000
) -> bool:
    """True when some integral the PI may have had at the start makes it give exactly ``corrections``
    for the DC ``times`` (SOEM's ec_sync, fieldbus.core.dc.master.HostSync)."""
    for start in range(-max_integral, max_integral + 1):
        pi = HostSync(HostSyncConfig(cycle_ns=CYCLE_NS, offset_ns=offset_ns), integral=start)
        first = pi.step(times[0])
        if first != corrections[0]:
            continue
        if all(pi.step(t) == c for t, c in zip(times[1:], corrections[1:], strict=True)):
            return True
    return False


def test_dc_time_sync_error_and_host_sync(ethercat_emulator: Any, tmp_path: Path) -> None:
    emu = ethercat_emulator([EPOS4], count=4)
    net_file = tmp_path / "net.yaml"
    net_file.write_text(
        "cycle_time_us: 1000\nreceive_timeout_us: 20000\nbuses:\n"
        f"  - {{name: bus, type: ethercat, interface: {emu.iface},"
        f" slaves: [{{name: 'j{{i}}', map: {json.dumps(str(EPOS4))}, count: 4}}]}}\n"
    )
    with open_network(net_file) as net:
        op = net.bring_up()
        times: list[int] = []  # DC time read in each cycle that came back in time
        errors: list[int] = []  # its sync error as the backend reports it
        walls: list[int] = []  # the host's clock when that cycle returned
        in_time: list[bool] = []  # per cycle
        corrections: list[int] = []  # per cycle: what the loop added to its next deadline

        def step(_k: int) -> bool:
            bus = op.exchange().buses[0]
            in_time.append(bus.verdict == 0)
            if bus.verdict == 0:
                assert bus.dc_time_ns is not None and bus.dc_sync_error_ns is not None
                times.append(bus.dc_time_ns)
                errors.append(bus.dc_sync_error_ns)
                walls.append(time.monotonic_ns())
            return len(times) >= OK_CYCLES

        def adjust() -> int:
            corrections.append(op.dc_correction_ns())
            return corrections[-1]

        run_cycles(step, CYCLE_NS / 1000, MAX_CYCLES, adjust=adjust)
        # every SYNC0 unit holds what the map asked for, through SOEM's dc_sync
        status = emu.command(cmd="dc")["dc"]["slaves"]
        assert [s["activation"] for s in status] == [3] * 4
        assert [s["sync0_cycle"] for s in status] == [CYCLE_NS] * 4
        # SOEM picks each start from that slave's time when dc_sync runs: whole cycles apart, same phase,
        # so every SYNC0 fires at the same instant
        assert {s["start_time"] % CYCLE_NS for s in status} == {0}
    assert len(times) >= OK_CYCLES, f"{len(times)} of {len(in_time)} cycles came back in time"
    # the sync error of a cycle is the phase of its DC time against the host's target, half a cycle in
    offset = CYCLE_NS // 2
    assert errors == [_phase_error(t, offset) for t in times]
    # the host PI stepped once per cycle that came back, and its correction went to the loop's next deadline
    # (a cycle without a DC time corrects nothing); its integral starts where bring-up's cycles left it
    got = [c for c, ok in zip(corrections, in_time, strict=True) if ok]
    assert _pi_replays(got, times, offset), got[:20]
    assert not any(c for c, ok in zip(corrections, in_time, strict=True) if not ok)
    assert any(corrections), "the PI never corrected the loop"
    # DC time runs with the host's clock: over >= 1 s, within what a late return costs on a loaded machine
    assert times == sorted(times)
    rate = (times[-1] - times[0]) / (walls[-1] - walls[0])
    assert abs(rate - 1.0) < 0.05, rate
