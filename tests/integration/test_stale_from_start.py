"""S2 from the first cycle: a raw-CAN motor silent since bring-up keeps its never-accepted inputs.

Found by the model-based test (tests/integration/test_safety_model.py): the image's input values started
as 0.0 while its wire bytes decode to the fields' minimum (MIT: raw 0 is -12.5 rad); the first cycle in
which another motor was fresh decoded every row, so the silent motor's position went 0.0 -> -12.5 rad
while it was stale. Now the inputs start as the decode of their wire bytes.
"""

from __future__ import annotations

import itertools
import os
from pathlib import Path

import pytest

from fieldbus import PDO_MAPS, load_drive_map, open_network

can = pytest.importorskip("can")
pytestmark = pytest.mark.timeout(60)
_channels = itertools.count()


def test_a_motor_silent_from_bring_up_keeps_its_inputs_bit_for_bit(tmp_path: Path) -> None:
    from sim_slaves.mit_motor import MitMotorSimulator

    mit = Path(PDO_MAPS) / "cubemars_ak80_9_mit.yaml"
    channel = f"fb-s2-{os.getpid()}-{next(_channels)}"
    f = tmp_path / "net.yaml"
    f.write_text(
        "cycle_time_us: 2000\nreceive_timeout_us: 20000\nsafe_stop_after: 50\nbuses:\n"
        f"  - {{name: bus, type: rawcan, interface: {channel}, can_interface: virtual,\n"
        f"     slaves: [{{name: 'm{{i}}', map: {mit}, node_id: 1, count: 2}}]}}\n"
    )
    drive = load_drive_map(mit)
    with (
        can.Bus(interface="virtual", channel=channel) as sim_bus,
        MitMotorSimulator(sim_bus, [(drive, n) for n in (1, 2)], dt_s=0.002) as sim,
        open_network(f) as net,
    ):
        op = net.bring_up()
        inputs = op["bus"].inputs
        sim.silence(2, True)
        before = inputs.values[1:2].tobytes()
        fresh_seen = False
        for _ in range(5):
            res = op.exchange()
            assert not res.buses[0].fresh[1]
            fresh_seen = fresh_seen or bool(res.buses[0].fresh[0])
            assert inputs.values[1:2].tobytes() == before  # before: position 0.0 -> -12.5 rad while stale
        assert fresh_seen
