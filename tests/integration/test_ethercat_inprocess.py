"""The EtherCAT backend's own code (fieldbus/backends/ethercat.py) on the in-process transport.

``transport="in-process"`` puts :class:`fieldbus.backends.ecat_inprocess.InProcessMaster` (pysoem's
API on the emulated ESC chain) under the backend. Witness: the emulator's own state (its AL
states, DC registers and true frame times), not our master's view of it. The cyclic API tests
(test_cyclic_api.py, kind ``ecat-inprocess``) run the same way.
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

import pytest

from fieldbus.commands.demo import DEMO_MAP
from fieldbus.core.pdo import load_drive_map
from fieldbus.errors import FieldbusError
from fieldbus.network import open_network

pytest.importorskip("pysoem")

EPOS4 = Path(__file__).resolve().parents[1] / "data" / "ethercat_driver_ros2" / "maxon_epos4_50_5.yaml"
CYCLE_NS = 1_000_000


def _net(tmp_path: Path, map_file: Path, count: int) -> Path:
    f = tmp_path / "net.yaml"
    f.write_text(
        "cycle_time_us: 1000\nreceive_timeout_us: 5000\nbuses:\n"
        f"  - {{name: bus, type: ethercat, interface: none0, slaves: [{{name: 'j{{i}}', map: '{map_file}', "
        f"count: {count}}}]}}\n"
    )
    return f


def test_the_ethercat_backend_reaches_op_and_exchanges_in_process(tmp_path: Path) -> None:
    with open_network(_net(tmp_path, DEMO_MAP, 4), backend="ethercat", transport="in-process") as net:
        op = net.bring_up()
        backend: Any = net.backends[0]
        assert type(backend).__name__ == "EthercatBackend" and backend.iomap is not None
        chain = backend.master.chain
        assert [int(s.state) for s in chain.slaves] == [0x08] * 4  # the emulated ESCs are in OP
        res = op.exchange()
        assert res.fresh and res.buses[0].wkc == res.buses[0].expected_wkc == 12
        # SOEM's sizes read from the slaves' PDO assignment (0x1C12/0x1C13) equal the map's layout
        assert [len(s.output) for s in backend.master.slaves] == [a.out_size for a in backend.areas]
        assert [len(s.input) for s in backend.master.slaves] == [a.in_size for a in backend.areas]


def test_dc_is_set_up_as_soem_does_and_the_cycle_reads_the_reference_clock(tmp_path: Path) -> None:
    """EPOS4 maps ask for SYNC0: the emulated ESCs get propagation delays matching the line's true
    frame times, SYNC0 on at the bus cycle and shift; the cycle's FRMW brings DC time back."""
    drive = load_drive_map(EPOS4)
    with open_network(_net(tmp_path, EPOS4, 3), backend="ethercat", transport="in-process") as net:
        op = net.bring_up()
        chain: Any = net.backends[0].master.chain  # type: ignore[attr-defined]
        times = []
        for _ in range(20):
            times.append(op.exchange().buses[0].dc_time_ns)
        status = chain.dc_status(time.monotonic_ns())
    assert all(t is not None for t in times) and times == sorted(times) and len(set(times)) > 10
    assert [s["activation"] for s in status] == [0x03] * 3  # cyclic operation + SYNC0
    assert [s["sync0_cycle"] for s in status] == [CYCLE_NS] * 3
    assert all((s["start_time"] - drive.ethercat.sync0_shift_ns) % CYCLE_NS == 0 for s in status)
    true_delays = [s["port0_ns"] - status[0]["port0_ns"] for s in status]  # the emulator's truth
    assert true_delays[2] > true_delays[1] > 0
    assert all(abs(s["delay"] - d) <= 20 for s, d in zip(status, true_delays, strict=True)), status


def test_a_bad_transport_option_is_a_clear_error(tmp_path: Path) -> None:
    with pytest.raises(FieldbusError, match="transport 'pcie' is not one of"):
        open_network(_net(tmp_path, DEMO_MAP, 1), backend="ethercat", transport="pcie")


def test_clock_and_chain_maps_are_only_for_the_in_process_transport(tmp_path: Path) -> None:
    from fieldbus.testing import VirtualClock, WallClock

    net_file = _net(tmp_path, DEMO_MAP, 1)
    with pytest.raises(FieldbusError, match="a virtual clock needs transport='in-process'"):
        open_network(net_file, backend="ethercat", clock=VirtualClock())
    open_network(net_file, backend="ethercat", clock=WallClock())  # a real segment's clock: accepted
    with pytest.raises(FieldbusError, match="option chain_maps needs transport='in-process'"):
        open_network(net_file, backend="ethercat", chain_maps=[load_drive_map(DEMO_MAP)])
    with pytest.raises(FieldbusError, match="option clock is not a "):
        open_network(net_file, backend="ethercat", transport="in-process", clock=12)
