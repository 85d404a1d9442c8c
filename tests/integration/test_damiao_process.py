"""Damiao motors in an emulator process (``sim_slaves.can_process --kind damiao``): the seed's layout, 4
``fieldbus_udp`` buses of 3 DM-J4310, served by one process, as benchmarks/can_transport.py runs it.

The bring-up crosses processes (MST_ID and PMAX/VMAX/TMAX read, CTRL_MODE and TIMEOUT written and read
back); then the cycle runs until every bus had 200 cycles with a reply from each motor, a bound in cycles
for a loaded machine (the emulator answers on the wall clock in its own process).
"""

from __future__ import annotations

from pathlib import Path

import pytest

pytest.importorskip("can")

from fieldbus import PDO_MAPS
from fieldbus.network import open_network
from sim_slaves.can_process import can_emulator_process, udp_bus

pytestmark = pytest.mark.timeout(180)
DAMIAO_MAP = Path(PDO_MAPS) / "damiao_dm_j4310.yaml"


def test_four_buses_of_three_damiao_motors_in_one_emulator_process(tmp_path: Path) -> None:
    buses = [udp_bus(40 + i, interface="fieldbus_udp") for i in range(4)]
    net_file = tmp_path / "robot.yaml"
    net_file.write_text(
        "cycle_time_us: 1000\nreceive_timeout_us: 20000\nsafe_stop_after: 100000\nbuses:\n"
        + "".join(
            f"  - {{name: leg{i}, type: rawcan, {b.network_keys()},\n"
            f"     slaves: [{{name: 'leg{i}_m{{i}}', map: '{DAMIAO_MAP}', node_id: 1, count: 3}}]}}\n"
            for i, b in enumerate(buses)
        )
    )
    with (
        can_emulator_process("damiao", DAMIAO_MAP, [1, 2, 3], buses, dt_s=0.001),
        open_network(net_file) as net,
    ):
        op = net.bring_up()  # refused (StateTransitionError) if a register did not read back
        modes = {net.backends[k].mode(f"leg{k}_m{j}") for k in range(4) for j in range(3)}
        assert modes == {"mit"}
        fresh = [0] * 4
        for _ in range(3000):
            res = op.exchange()
            for i, st in enumerate(res.buses):
                fresh[i] += st.verdict.name == "OK"
            if min(fresh) >= 200:
                break
        assert min(fresh) >= 200, fresh
        # the replies are the Damiao status frames: the motor id in the low nibble of byte 0
        assert [list(op[f"leg{i}"].inputs["motor_id"]) for i in range(4)] == [[1, 2, 3]] * 4
