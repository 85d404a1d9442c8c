"""CubeMars AK motors (family cubemars) through the public API against the CubeMars emulators.

What the master puts on the bus is read by a listener on the virtual bus and decoded here from the
layouts the CubeMars AK manual publishes (servo packets: big-endian int32 / int16 on the 29-bit id
``packet << 8 | id``, status ``0x29 << 8 | id``: int16 deg x 10, int16 erpm / 10, int16 A x 100, int8 °C,
uint8 error; MIT frame p16 v12 kp12 kd12 t12), not by fieldbus's codec. The emulators are our own code
(no independent CubeMars driver talks to a python-can virtual bus without hardware).
"""

from __future__ import annotations

import itertools
import math
import os
import struct
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest

can = pytest.importorskip("can")

from fieldbus import PDO_MAPS, open_network  # noqa: E402
from fieldbus.core.pdo import load_drive_map  # noqa: E402
from sim_slaves.cubemars import CubemarsMitSimulator, CubemarsServoSimulator  # noqa: E402

pytestmark = pytest.mark.timeout(120)
SERVO = Path(PDO_MAPS) / "cubemars_ak80_9_servo.yaml"
MIT = Path(PDO_MAPS) / "cubemars_ak10_9_mit.yaml"
NODES = (1, 2, 3)
ERPM_PER_RAD_S = 21 * 9 * 60 / (2 * math.pi)  # AK80-9: 21 pole pairs, 9:1 gear
_channels = itertools.count()


def drain(bus: can.BusABC) -> list[can.Message]:
    out = []
    while (msg := bus.recv(timeout=0)) is not None:
        out.append(msg)
    return out


def net_text(channel: str, drive: Path, extra: str = "") -> str:
    return (
        "cycle_time_us: 1000\nreceive_timeout_us: 20000\nsafe_stop_after: 4\nbuses:\n"
        f"  - {{name: arm, type: rawcan, interface: {channel}, can_interface: virtual,{extra}\n"
        f"     slaves: [{{name: 'j{{i}}', map: {drive}, node_id: 1, count: {len(NODES)}}}]}}\n"
    )


@pytest.fixture
def channel() -> str:
    return f"fb-cm-{os.getpid()}-{next(_channels)}"


@pytest.fixture
def servo_net(tmp_path: Path, channel: str) -> Iterator[Path]:
    net = tmp_path / "net.yaml"
    net.write_text(net_text(channel, SERVO))
    yield net


def _fresh_or_held(res: object) -> bool:
    """Fresh, or a miss the policy held (the threaded virtual bus can stall on a loaded host)."""
    return bool(res.fresh) or not res.safe_stop  # type: ignore[attr-defined]


def test_servo_mode_trajectory_mode_switch_fault_and_safe_stop(servo_net: Path, channel: str) -> None:
    drive = load_drive_map(SERVO)
    with (
        can.Bus(interface="virtual", channel=channel) as listener,
        can.Bus(interface="virtual", channel=channel) as sim_bus,
        CubemarsServoSimulator(sim_bus, [(drive, n) for n in NODES], dt_s=0.001) as sim,
        open_network(servo_net) as network,
    ):
        op = network.bring_up()
        backend = network.backends[0]
        out, inp = op["arm"].outputs, op["arm"].inputs
        assert list(out["mode"]) == [6, 6, 6]  # the map's mode: position-speed loop
        out["speed_limit"][:], out["accel_limit"][:] = 5.0, 50.0
        target = np.array([0.6, -0.4, 1.0])
        for k in range(1000):  # 1 s of 1 kHz cycles
            out["position"][:] = target * min(1.0, k / 400)
            assert _fresh_or_held(op.exchange()), k
        assert np.abs(inp["position"] - target).max() < 0.01, inp["position"]
        frames = drain(listener)
        for n, goal in zip(NODES, target, strict=True):
            sent = [m for m in frames if m.is_extended_id and m.arbitration_id == 6 << 8 | n]
            assert len(sent) >= 1000 - 3  # one packet a cycle (a stalled cycle may miss)
            pos, spd, acc = struct.unpack(">ihh", bytes(sent[-1].data))
            assert pos == round(math.degrees(goal) * 10000)
            assert spd == round(5.0 * ERPM_PER_RAD_S / 10) and acc == round(50.0 * ERPM_PER_RAD_S / 10)
            status = [m for m in frames if m.is_extended_id and m.arbitration_id == 0x29 << 8 | n][-1]
            p10, _, _, temp, err = struct.unpack(">hhhbB", bytes(status.data))
            assert (temp, err) == (30, 0)
            assert math.radians(p10 / 10) == pytest.approx(float(inp["position"][n - 1]), abs=0.01)

        # mode switch at run time: j0 to speed (packet 3), then current (1), then brake (2)
        backend.set_mode("j0", "velocity")
        assert backend.mode("j0") == "velocity" and int(out["mode"][0]) == 3
        out["velocity"][0] = 3.0
        for _ in range(300):
            assert _fresh_or_held(op.exchange())
        sent = [bytes(m.data) for m in drain(listener) if m.is_extended_id and m.arbitration_id == 0x301]
        assert len(sent) >= 297 and struct.unpack(">i", sent[-1]) == (round(3.0 * ERPM_PER_RAD_S),)
        assert float(inp["velocity"][0]) == pytest.approx(3.0, abs=0.05)
        backend.set_mode("j0", "current")
        out["current"][0] = 2.0
        op.exchange()
        sent = [bytes(m.data) for m in drain(listener) if m.is_extended_id and m.arbitration_id == 0x101]
        assert struct.unpack(">i", sent[-1]) == (2000,)
        backend.set_mode("j0", "brake")
        out["brake_current"][0] = 10.0
        for _ in range(500):
            op.exchange()
        sent = [bytes(m.data) for m in drain(listener) if m.is_extended_id and m.arbitration_id == 0x201]
        assert struct.unpack(">i", sent[-1]) == (10000,)
        assert abs(float(inp["velocity"][0])) < 0.05  # braked to a stand-still

        # a named fault, counted
        sim.inject_error(3, 2)
        op.exchange()
        assert backend.motor_faults == 1 and int(inp["error"][2]) == 2
        assert str(backend.faults[-1]) == "j2: motor error 0x2 over-current"

        # safe stop after safe_stop_after (4) silent cycles: current packets of 0 A to every motor
        for n in NODES:
            sim.drop_replies(n, 4)
        assert [op.exchange().safe_stop for _ in range(4)] == [False, False, False, True]
        drain(listener)
        out["mode"][:], out["position"][:] = 4, 2.0  # the controller keeps asking for a move
        op.exchange()
        sent = {m.arbitration_id: bytes(m.data) for m in drain(listener) if m.is_extended_id}
        assert {k: v for k, v in sent.items() if k >> 8 != 0x29} == {0x100 | n: bytes(4) for n in NODES}
        assert not sim.errors
        network.close()  # stop: a current of 0 A to every motor
        seen = [m for m in drain(listener) if m.is_extended_id and m.arbitration_id >> 8 != 0x29]
        assert {m.arbitration_id: bytes(m.data) for m in seen[-3:]} == {0x100 | n: bytes(4) for n in NODES}


def test_mit_mode_unwraps_positions_across_the_wrap(tmp_path: Path, channel: str) -> None:
    net = tmp_path / "net.yaml"
    net.write_text(net_text(channel, MIT))
    drive = load_drive_map(MIT)
    with (
        can.Bus(interface="virtual", channel=channel) as sim_bus,
        CubemarsMitSimulator(sim_bus, [(drive, n) for n in NODES], dt_s=0.001) as sim,
        open_network(net) as network,
    ):
        op = network.bring_up()
        out, inp = op["arm"].outputs, op["arm"].inputs
        out["kd"][:] = 2.0
        wrapped, total = [], []
        for speed, cycles in ((20.0, 1500), (-20.0, 3000)):  # +30 rad (one wrap), then -60 rad (two)
            out["velocity"][:] = speed
            for _ in range(cycles):
                assert _fresh_or_held(op.exchange())
                wrapped.append(float(inp["position"][0]))
                total.append(float(inp["position_total"][0]))
        truth = sim.motor(1).position  # the emulated rotor: about 30 - 60 = -30 rad
        assert truth < -25.0
        assert float(inp["position_total"][0]) == pytest.approx(truth, abs=0.05)  # a reply lags one command
        assert max(total) > 25.0 and min(total) < -25.0
        assert all(-12.5 <= w <= 12.5 for w in wrapped)  # what the wire carries wraps
        jumps = sum(abs(b - a) > 12.5 for a, b in itertools.pairwise(wrapped))
        assert jumps >= 3  # the counter wrapped (at least) three times; the total never jumped
        assert max(abs(b - a) for a, b in itertools.pairwise(total)) < 0.1
        assert list(inp["temperature"]) == [30.0] * 3 and list(inp["error"]) == [0] * 3
        assert not sim.errors


def test_mit_mode_short_replies_fault_and_close(tmp_path: Path, channel: str) -> None:
    net = tmp_path / "net.yaml"
    net.write_text(net_text(channel, MIT))
    drive = load_drive_map(MIT)
    with (
        can.Bus(interface="virtual", channel=channel) as listener,
        can.Bus(interface="virtual", channel=channel) as sim_bus,
        CubemarsMitSimulator(sim_bus, [(drive, n) for n in NODES], dt_s=0.001) as sim,
        open_network(net) as network,
    ):
        op = network.bring_up()
        backend = network.backends[0]
        out, inp = op["arm"].outputs, op["arm"].inputs
        out["kp"][:], out["kd"][:], out["position"][:] = 50.0, 1.0, 0.5
        for _ in range(300):
            assert _fresh_or_held(op.exchange())
        assert float(inp["temperature"][0]) == 30.0
        sim.short_replies = True  # older firmware: 6-byte replies, still fresh
        out["position"][:] = -0.5
        fresh = sum(bool(op.exchange().fresh) for _ in range(300))
        assert fresh >= 270  # a loaded host may stall a few cycles past their time-out
        assert np.abs(inp["position_total"] + 0.5).max() < 0.01
        assert {
            len(m.data) for m in drain(listener) if m.arbitration_id in NODES and m.data[:2] != b"\xff\xff"
        } == {
            6,
            8,
        }
        sim.short_replies = False
        sim.inject_error(2, 1)
        op.exchange()
        assert str(backend.faults[-1]) == "j1: motor error 0x1 over-temperature" and backend.motor_faults == 1
        drain(listener)
        assert sim.motor(1).command is not None and sim.motor(1).command[2] == pytest.approx(
            50.0, abs=0.2
        )  # kp 50 till now
        backend.stop()  # without the network's wind-down: a zero-gain MIT command, then exit, to every motor
        seen = drain(listener)
        for n in NODES:
            # commands and replies share the CAN id: the emulator tells which command came last
            command = sim.motor(n).command
            assert command is not None
            _, _, kp, kd, torque = command
            assert kp == 0.0 and kd == 0.0 and abs(torque) < 130 / 4095  # zero gains, torque 0 (one step)
            assert bytes([0xFF] * 7 + [0xFD]) in [bytes(m.data) for m in seen if m.arbitration_id == n]
            assert not sim.motor(n).enabled


def test_can_fd_frames_round_trip_through_backend_and_emulator(tmp_path: Path, channel: str) -> None:
    """A bus with a data_bitrate: the master's commands and the motors' replies are CAN FD, bit-rate switched."""
    net = tmp_path / "net.yaml"
    net.write_text(net_text(channel, MIT, " bitrate: 1000000, data_bitrate: 5000000,"))
    drive = load_drive_map(MIT)
    with (
        can.Bus(interface="virtual", channel=channel) as listener,
        can.Bus(interface="virtual", channel=channel) as sim_bus,
        CubemarsMitSimulator(sim_bus, [(drive, n) for n in NODES], dt_s=0.001),
        open_network(net) as network,
    ):
        op = network.bring_up()
        out, inp = op["arm"].outputs, op["arm"].inputs
        out["kp"][:], out["kd"][:], out["position"][:] = 50.0, 1.0, 0.3
        fresh = sum(bool(op.exchange().fresh) for _ in range(200))
        assert fresh >= 180
        assert np.abs(inp["position_total"] - 0.3).max() < 0.01
        frames = drain(listener)
        commands = [m for m in frames if m.arbitration_id in NODES and m.data[0] != 0xFF and len(m.data) == 8]
        assert len(commands) >= 3 * 180
        assert all(m.is_fd and m.bitrate_switch for m in frames)  # enter, commands, replies alike
