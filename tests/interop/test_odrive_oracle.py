"""Independent oracle for the ODrive family: the ``odrive-can`` package (PyPI, MIT licence; a test dependency).

Its ``ODriveCAN`` driver arms our emulator, drives it in position control and reads its encoder
estimates on python-can's virtual bus; its copies of odriverobotics' DBC files (CANSimple 0.5.6 and
0.6.10, read with cantools) decode the frames our master sends to the values we commanded.
"""

from __future__ import annotations

import asyncio
import itertools
import os
import struct
import time
from collections.abc import Callable
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


SET_POINTS = 400
WAIT_S = 60.0  # the most a frame may take to be handled on a loaded machine (a bound, not a judgement)


def _handled(sim: OdriveSimulator, node: int, seen: Callable[[list[tuple[int, bytes, bool]]], bool]) -> bool:
    """Wait (bounded) until the frames axis ``node`` has handled satisfy ``seen``; its verdict."""
    deadline = time.monotonic() + WAIT_S
    while not seen(sim.axes[node].frames) and time.monotonic() < deadline:
        time.sleep(0.01)
    return seen(sim.axes[node].frames)


def test_odrive_can_drives_the_emulator() -> None:
    """odrive-can arms the emulator, sends 400 Set_Input_Pos and reads Get_Encoder_Estimates.

    Judged in the emulator's own time, not the machine's: with ``dt_s`` the physics advance 1 ms per
    set-point handled (no time passes between frames), so the estimate is the rotor after 400 ms of
    following 0.75 turn however slowly a loaded machine delivers the frames. The driver's 0.5 s answer
    time-out is wall-clock: a request it gave up on is asked again (no set-point in between: the same
    answer); the driver's stop() is judged once the emulator has handled its Set_Axis_State."""
    channel = f"fb-odo-{os.getpid()}-{next(_channels)}"
    drive = load_drive_map(Path(PDO_MAPS) / "odrive_s1.yaml")
    idle = drive.rawcan.odrive.idle if drive.rawcan and drive.rawcan.odrive else 1

    async def estimates_of(driver: ODriveCAN) -> dict[str, float]:
        for _ in range(20):  # bounded: 20 asks
            try:
                return dict(await driver.get_encoder_estimates())
            except TimeoutError:
                continue
        raise AssertionError("no Get_Encoder_Estimates answer in 20 asks")

    async def run(driver: ODriveCAN) -> dict[str, float]:
        await driver.start()  # waits for a heartbeat
        driver.set_controller_mode("POSITION_CONTROL", "PASSTHROUGH")
        await driver.set_axis_state("CLOSED_LOOP_CONTROL")  # returns once the heartbeat says so
        for _ in range(SET_POINTS):  # each set-point handled moves the emulator's physics 1 ms on
            driver.set_input_pos(0.75)
            await asyncio.sleep(0)
        estimates = await estimates_of(driver)
        driver.stop()  # sends Set_Axis_State IDLE
        return estimates

    with (
        can.Bus(interface="virtual", channel=channel) as sim_bus,
        OdriveSimulator(sim_bus, [(drive, 5)], dt_s=0.001, heartbeat_ms=20) as sim,
    ):
        driver_bus = can.Bus(interface="virtual", channel=channel)  # the driver shuts it down itself
        try:
            estimates = asyncio.run(run(ODriveCAN(axis_id=5, can_bus=driver_bus)))
        finally:
            driver_bus.shutdown()
        state_cmd = 5 << 5 | 0x07
        assert _handled(
            sim, 5, lambda fs: any(c == 0x07 and d[:4] == struct.pack("<I", idle) for c, d, _ in fs)
        ), f"the driver's IDLE (id 0x{state_cmd:X}) was not handled within {WAIT_S} s"
        setpoints = [d for c, d, remote in sim.axes[5].frames if c == 0x0C and not remote]
        assert len(setpoints) == SET_POINTS and sim.motor(5).commands >= SET_POINTS
        assert {struct.unpack_from("<f", d)[0] for d in setpoints} == {0.75}
        assert estimates["Pos_Estimate"] == pytest.approx(0.75, abs=0.01)
        assert abs(estimates["Vel_Estimate"]) < 0.05  # settled, not passing through
        assert sim.axes[5].control_mode == 3 and sim.axes[5].state == idle  # the driver's stop(): IDLE
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
