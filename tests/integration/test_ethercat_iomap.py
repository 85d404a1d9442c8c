"""The EtherCAT backend's cycle through one view of SOEM's IO map (fieldbus.backends.soem_iomap).

Real pysoem over a veth pair, the emulator in its own process. pysoem's own
per-slave getters (``slave.output`` / ``slave.input``: copies SOEM makes of its
IO map) are the independent witness of what the cycle wrote and read.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from fieldbus.commands.demo import DEMO_MAP
from fieldbus.network import open_network

pysoem = pytest.importorskip("pysoem")

pytestmark = [pytest.mark.veth, pytest.mark.timeout(300), pytest.mark.usefixtures("generous_pysoem_timeouts")]

GENERIC = Path(__file__).resolve().parents[2] / "pdo_maps" / "generic_cia402.yaml"


def _net(tmp_path: Path, iface: str, groups: list[tuple[Path, int]]) -> Path:
    slaves = ", ".join(f"{{name: 'g{k}_{{i}}', map: '{m}', count: {n}}}" for k, (m, n) in enumerate(groups))
    f = tmp_path / "net.yaml"
    f.write_text(
        "cycle_time_us: 1000\nreceive_timeout_us: 20000\nbuses:\n"
        f"  - {{name: bus, type: ethercat, interface: {iface}, slaves: [{slaves}]}}\n"
    )
    return f


def _until_fresh(op: Any, cycles: int = 200) -> None:
    for _ in range(cycles):
        if op.exchange().fresh:
            return
    pytest.fail(f"no fresh cycle in {cycles}")


@pytest.mark.parametrize("iomap", ["view", "bytes"])
def test_the_cycle_moves_each_groups_process_data_through_soems_io_map(
    ethercat_emulator: Callable[..., Any], tmp_path: Path, iomap: str
) -> None:
    """Two axis groups (two maps): outputs the controller wrote are in SOEM's IO map as pysoem reads it
    per slave, and the inputs received are what pysoem reads per slave; "view": one copy per group."""
    emu = ethercat_emulator([DEMO_MAP, DEMO_MAP, GENERIC, GENERIC, GENERIC])
    net_file = _net(tmp_path, emu.iface, [(DEMO_MAP, 2), (GENERIC, 3)])
    with open_network(net_file, backend="ethercat", iomap=iomap) as net:
        op = net.bring_up()
        backend: Any = net.backends[0]
        if iomap == "view":
            assert backend.iomap is not None  # found and proven at SAFE-OP (pysoem 1.1.13, CPython)
            assert len(backend._out_copies) == len(backend._in_copies) == 2  # one per group, not per slave
        else:
            assert backend.iomap is None
        for k, group in enumerate(backend.groups):
            wire = group.image.outputs.wire
            wire[:] = np.arange(wire.size, dtype=np.uint32).reshape(wire.shape) * (k + 3) % 251
        _until_fresh(op)
        slaves = backend._slaves
        for i, s in enumerate(slaves):
            assert bytes(s.output) == backend.out_row(i).tobytes(), i
            assert bytes(s.input) == backend.in_row(i).tobytes(), i
        # the emulated drives report their statusword: inputs really came from the wire
        assert any(backend.in_row(i).any() for i in range(len(slaves)))


def test_a_bad_iomap_option_is_a_clear_error(tmp_path: Path) -> None:
    from fieldbus.errors import FieldbusError

    net_file = _net(tmp_path, "lo", [(DEMO_MAP, 1)])
    with pytest.raises(FieldbusError, match="iomap 'fast' is not one of"):
        open_network(net_file, backend="ethercat", iomap="fast")
