"""Independent oracle for the ODrive family: the ``odrive-can`` package (PyPI, MIT licence; a test dependency).

Its ``ODriveCAN`` driver arms our emulator, drives it in position control and reads its encoder
estimates on python-can's virtual bus; its copies of odriverobotics' DBC files (CANSimple 0.5.6 and
0.6.10, read with cantools) decode the frames our master sends to the values we commanded.
"""

from __future__ import annotations

import asyncio
import itertools
import os
from pathlib import Path

import pytest

can = pytest.importorskip("can")
odrive_can = pytest.importorskip("odrive_can")

from odrive_can.odrive import ODriveCAN  # noqa: E402
from odrive_can.utils import get_dbc  # noqa: E402

from fieldbus import PDO_MAPS, open_network  # noqa: E402
from fieldbus.core.pdo import load_drive_map  # noqa: E402
from sim_slaves.odrive import OdriveSimulator  # noqa: E402

pytestmark = pytest.mark.timeout(120)
_channels = itertools.count()


def test_odrive_can_drives_the_emulator() -> None:
    channel = f"fb-odo-{os.getpid()}-{next(_channels)}"
    drive = load_drive_map(Path(PDO_MAPS) / "odrive_s1.yaml")

    async def run(driver: ODriveCAN) -> dict[str, float]:
        await driver.start()  # waits for a heartbeat
        driver.set_controller_mode("POSITION_CONTROL", "PASSTHROUGH")
        await driver.set_axis_state("CLOSED_LOOP_CONTROL")  # returns once the heartbeat says so
        for _ in range(400):  # each set-point acts for 1 ms in the emulator
            driver.set_input_pos(0.75)
            await asyncio.sleep(0)
        estimates = await driver.get_encoder_estimates()
        driver.stop()  # sends Set_Axis_State IDLE
        return dict(estimates)

    with (
        can.Bus(interface="virtual", channel=channel) as sim_bus,
        OdriveSimulator(sim_bus, [(drive, 5)], dt_s=0.001, heartbeat_ms=20) as sim,
    ):
        driver_bus = can.Bus(interface="virtual", channel=channel)  # the driver shuts it down itself
        try:
            estimates = asyncio.run(run(ODriveCAN(axis_id=5, can_bus=driver_bus)))
        finally:
            driver_bus.shutdown()
        assert estimates["Pos_Estimate"] == pytest.approx(0.75, abs=0.01)
        assert sim.axes[5].control_mode == 3 and sim.axes[5].state == 1  # the driver's stop(): IDLE
        assert sim.motor(5).commands >= 400
        assert not sim.errors


@pytest.mark.parametrize(
    ("name", "dbc"),
    [("odrive_s1.yaml", "odrive-cansimple-0.6.10"), ("odrive_3_6.yaml", "odrive-cansimple-0.5.6")],
)
def test_the_dbc_decodes_our_masters_frames(tmp_path: Path, name: str, dbc: str) -> None:
    channel = f"fb-odo-{os.getpid()}-{next(_channels)}"
    path = Path(PDO_MAPS) / name
    net = tmp_path / "net.yaml"
    net.write_text(
        "cycle_time_us: 1000\nreceive_timeout_us: 20000\nbuses:\n"
        f"  - {{name: b, type: rawcan, interface: {channel}, can_interface: virtual,\n"
        f"     slaves: [{{name: ax, map: {path}, node_id: 3}}]}}\n"
    )
    db = get_dbc(dbc)
    with (
        can.Bus(interface="virtual", channel=channel) as listener,
        can.Bus(interface="virtual", channel=channel) as sim_bus,
        OdriveSimulator(sim_bus, [(load_drive_map(path), 3)], dt_s=0.001, heartbeat_ms=20),
        open_network(net) as network,
    ):
        op = network.bring_up()
        out = op["b"].outputs
        out["position"][0], out["velocity"][0], out["torque"][0] = 0.25, 1.5, -0.2
        op.exchange()
        network.backends[0].set_mode("ax", "velocity")
        assert (out["velocity"][0], out["torque"][0]) == (0.0, 0.0)  # a mode switch starts no motion (S12)
        out["velocity"][0], out["torque"][0] = 1.5, -0.2  # the controller's command in the new mode
        op.exchange()
        network.close()
        decoded = []
        while (m := listener.recv(timeout=0)) is not None:
            if not m.is_remote_frame and m.arbitration_id >> 5 == 3:
                msg = db.get_message_by_frame_id(m.arbitration_id)
                decoded.append((msg.name.split("_", 1)[1], msg.decode(bytes(m.data), decode_choices=False)))
    names = [n for n, _ in decoded]
    mode = [v for n, v in decoded if n == "Set_Controller_Mode"]
    assert [(v["Control_Mode"], v["Input_Mode"]) for v in mode] == [(3, 1), (2, 1)]
    states = [v["Axis_Requested_State"] for n, v in decoded if n == "Set_Axis_State"]
    assert states[0] == 8 and set(states[1:]) == {1}  # closed loop at op(), IDLE at close
    pos = [v for n, v in decoded if n == "Set_Input_Pos"][-1]
    assert pos["Input_Pos"] == pytest.approx(0.25) and pos["Vel_FF"] == pytest.approx(1.5)
    assert pos["Torque_FF"] == pytest.approx(-0.2)
    vel = [v for n, v in decoded if n == "Set_Input_Vel"][-1]
    assert vel["Input_Vel"] == pytest.approx(1.5) and vel["Input_Torque_FF"] == pytest.approx(-0.2)
    assert names.index("Set_Input_Vel") > names.index("Set_Input_Pos")
