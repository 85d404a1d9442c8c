"""CAN FD on a raw-CAN bus: Damiao's CAN FD variants through the public API against the Damiao emulator.

A bus with a ``data_bitrate`` carries every frame of the bring-up (register reads and writes, enable) and
of the cycle as CAN FD with bit-rate switching, the emulated motors answering in FD. Frames are read by a listener on python-can's virtual bus (which carries
the FD flags); the emulator is our own code.
"""

from __future__ import annotations

import itertools
import os
from pathlib import Path

import pytest

can = pytest.importorskip("can")

from fieldbus import PDO_MAPS, open_network  # noqa: E402
from fieldbus.core.pdo import load_drive_map  # noqa: E402
from sim_slaves.damiao import DamiaoSimulator  # noqa: E402

pytestmark = pytest.mark.timeout(120)
MAP = Path(PDO_MAPS) / "damiao_dm_j4310.yaml"
NODES = (1, 2, 3)
_channels = itertools.count()


def test_damiao_over_can_fd(tmp_path: Path) -> None:
    channel = f"fb-fd-{os.getpid()}-{next(_channels)}"
    rates = " bitrate: 1000000, data_bitrate: 5000000,"
    net = tmp_path / "net.yaml"
    net.write_text(
        "cycle_time_us: 1000\nreceive_timeout_us: 20000\nsafe_stop_after: 4\nbuses:\n"
        f"  - {{name: arm, type: rawcan, interface: {channel}, can_interface: virtual,{rates}\n"
        f"     slaves: [{{name: 'j{{i}}', map: {MAP}, node_id: 1, count: {len(NODES)}}}]}}\n"
    )
    drive = load_drive_map(MAP)
    with (
        can.Bus(interface="virtual", channel=channel) as listener,
        can.Bus(interface="virtual", channel=channel) as sim_bus,
        DamiaoSimulator(sim_bus, [(drive, n) for n in NODES], dt_s=0.001) as sim,
        open_network(net) as network,
    ):
        op = network.bring_up()
        out, inp = op["arm"].outputs, op["arm"].inputs
        out["kp"][:], out["kd"][:], out["position"][:] = 30.0, 1.0, 0.4
        fresh = sum(bool(op.exchange().fresh) for _ in range(300))
        assert fresh >= 270  # a loaded host may stall a few cycles past their time-out
        # the FD replies are taken in (tracking is test_damiao's: the emulator's timing on a loaded host)
        assert list(inp["motor_id"]) == list(NODES) and float(inp["position"].min()) > 0.0
        frames = []
        while (msg := listener.recv(timeout=0)) is not None:
            frames.append(msg)
        registers = [m for m in frames if m.arbitration_id == 0x7FF]
        replies = [m for m in frames if m.arbitration_id in (0x11, 0x12, 0x13)]
        commands = [m for m in frames if m.arbitration_id in NODES]
        assert registers and len(replies) >= 3 * 270 and len(commands) >= 3 * 300
        assert all(m.is_fd and m.bitrate_switch for m in frames)
        assert all(len(m.data) == 8 for m in commands + replies)  # the family's layouts, in FD frames
        assert not sim.errors
