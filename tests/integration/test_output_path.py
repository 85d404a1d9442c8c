"""The one output path on every bus: NaN, inf and out-of-limit commands never reach a drive (docs/safety.md S11).

Each test writes the bad value through the public API and reads what reached the drive from outside
fieldbus's codec: the emulated ESC's SM2 memory (EtherCAT, unpacked with ``struct`` per the map's
CiA 402 layout), the emulated CANopen node's object dictionary as its RPDO wrote it, and on raw CAN a
listener on the virtual bus decoding each frame with ``struct`` per the vendor layout (CubeMars servo:
big-endian int32 deg x 10000; Damiao: little-endian float32) or with odrive-can's DBC (ODrive
Set_Input_Vel). The emulators are our own code; the decoders are not fieldbus's.
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

import fieldbus
from fieldbus import PDO_MAPS, open_network
from fieldbus.commands.demo import DEMO_MAP
from fieldbus.core.pdo import load_drive_map

can = pytest.importorskip("can")

pytestmark = pytest.mark.timeout(120)
INT32_MAX, INT32_MIN = 2**31 - 1, -(2**31)
COUNTS_PER_RAD = 20860.7568  # demo_joint's target_position factor
WINDOW = (-41721, 62582)  # 0x607D:01..02 in counts: -2 rad .. 3 rad
_channels = itertools.count()


def windowed_demo_map(tmp_path: Path, extra: str = "") -> Path:
    """demo_joint with a software position limit 0x607D written at start-up (and ``extra`` map keys)."""
    text = DEMO_MAP.read_text().replace(
        "sdo:\n",
        "sdo:\n"
        f"  - {{index: 0x607D, sub_index: 1, type: int32, value: {WINDOW[0]}}}\n"
        f"  - {{index: 0x607D, sub_index: 2, type: int32, value: {WINDOW[1]}}}\n",
        1,
    )
    f = tmp_path / "joint.yaml"
    f.write_text(text + extra)
    return f


def drain(bus: can.BusABC) -> list[can.Message]:
    out = []
    while (msg := bus.recv(timeout=0)) is not None:
        out.append(msg)
    return out


# -- EtherCAT on the in-process emulator -----------------------------------------------------------------


@pytest.fixture
def sim_net(tmp_path: Path) -> Iterator[fieldbus.Network]:
    drive = windowed_demo_map(tmp_path)
    f = tmp_path / "net.yaml"
    f.write_text(
        "cycle_time_us: 1000\nreceive_timeout_us: 5000\nbuses:\n"
        f"  - {{name: arm, type: ethercat, interface: sim0, slaves: [{{name: 'j{{i}}', map: {drive}, count: 3}}]}}\n"
    )
    with open_network(f, backend="sim") as net:
        yield net


def received_targets(net: fieldbus.Network) -> list[int]:
    """target_position as each emulated ESC holds it in its SM2 memory (controlword u16, then int32)."""
    chain = net.backends[0].chain  # type: ignore[attr-defined]
    return [struct.unpack_from("<Hi", esc.mem, esc.sm[2][0])[1] for esc in chain.slaves]


def test_ethercat_inf_nan_and_out_of_window_targets_never_reach_the_drive(sim_net: fieldbus.Network) -> None:
    op = sim_net.bring_up()
    out = op["arm"].outputs
    out["target_position"][:] = 0.5
    op.exchange()
    assert received_targets(sim_net) == [round(0.5 * COUNTS_PER_RAD)] * 3
    out["target_position"][:] = [math.inf, math.nan, 1e6]
    res = op.exchange()
    got = received_targets(sim_net)
    assert got == [WINDOW[1], round(0.5 * COUNTS_PER_RAD), WINDOW[1]], (
        got
    )  # before: INT32_MAX, held, INT32_MAX
    assert INT32_MAX not in got and INT32_MIN not in got
    clamps = [e for e in res.events if isinstance(e, fieldbus.OutputClamp)]
    assert [(e.axis, e.reason.name, e.channel) for e in clamps] == [
        (0, "INF", "target_position"),
        (1, "NAN", "target_position"),
        (2, "RANGE", "target_position"),
    ]
    assert clamps[2].asked == 1e6 and clamps[2].sent == pytest.approx(3.0, abs=1e-4)
    assert op.output_rules["arm"].counts.sum(axis=1).tolist() == [1, 1, 1]
    assert op.buses[0].counters()["output_clamps"] == 3  # what the monitor and the DDS diagnostics show
    out["target_position"][:] = -1e9
    op.exchange()
    assert received_targets(sim_net) == [WINDOW[0]] * 3


def test_a_recording_keeps_each_clamp_as_an_event(sim_net: fieldbus.Network, tmp_path: Path) -> None:
    from fieldbus.recording import load as load_recording

    op = sim_net.bring_up()
    rec = op.record(tmp_path / "run.mcap")
    out = op["arm"].outputs
    for k in range(20):
        out["target_position"][:] = math.nan if k == 5 else 0.1
        op.exchange()
    rec.close()
    events = [e for e in load_recording(tmp_path / "run.mcap").events if e["kind"] == "output_clamp"]
    assert [(e["cycle"], e["axis"], e["name"], e["sent"]) for e in events] == [
        (5, a, "NAN", pytest.approx(0.1, abs=1e-4)) for a in range(3)
    ]


# -- CANopen on python-can's virtual bus --------------------------------------------------------------------


def test_canopen_rpdo_never_carries_an_inf_or_out_of_window_target(tmp_path: Path) -> None:
    from sim_slaves.canopen import CanopenSimulator

    channel = f"fb-op-co-{os.getpid()}-{next(_channels)}"
    drive_file = windowed_demo_map(tmp_path)
    f = tmp_path / "net.yaml"
    f.write_text(
        "cycle_time_us: 5000\nreceive_timeout_us: 20000\nsafe_stop_after: 50\nbuses:\n"
        f"  - {{name: arm, type: canopen, interface: {channel}, can_interface: virtual,\n"
        f"     slaves: [{{name: 'n{{i}}', map: {drive_file}, node_id: 1, count: 2}}]}}\n"
    )
    drive = load_drive_map(drive_file)
    with (
        can.Bus(interface="virtual", channel=channel) as listener,
        can.Bus(interface="virtual", channel=channel) as sim_bus,
        CanopenSimulator(sim_bus, [(drive, n) for n in (1, 2)], dt_s=0.005) as sim,
        open_network(f) as net,
    ):
        op = net.bring_up()
        out = op["arm"].outputs
        drain(listener)
        out["target_position"][:] = [math.inf, 1e6]
        for _ in range(3):
            op.exchange()
        out["target_position"][:] = [math.nan, -math.inf]
        for _ in range(3):
            op.exchange()
        # every RPDO1 on the bus (0x200 + node: controlword u16, target_position i32), decoded with struct
        sent = [
            (m.arbitration_id - 0x200, struct.unpack_from("<Hi", bytes(m.data))[1])
            for m in drain(listener)
            if m.arbitration_id in (0x201, 0x202)
        ]
        assert len(sent) == 12
        assert all(WINDOW[0] <= v <= WINDOW[1] for _, v in sent), sent
        assert [v for n, v in sent if n == 1] == [WINDOW[1]] * 6  # inf saturates; NaN then keeps it
        assert [v for n, v in sent if n == 2] == [WINDOW[1]] * 3 + [WINDOW[0]] * 3
        for node in (1, 2):  # the node's own dictionary, as its RPDO wrote it
            assert WINDOW[0] <= int(sim.node(node).od.get_value(0x607A, 0)) <= WINDOW[1]


# -- raw CAN: each family ------------------------------------------------------------------------------------


def rawcan_net(tmp_path: Path, channel: str, drive: Path, nodes: int = 2) -> Path:
    f = tmp_path / "net.yaml"
    f.write_text(
        "cycle_time_us: 1000\nreceive_timeout_us: 20000\nsafe_stop_after: 50\nbuses:\n"
        f"  - {{name: arm, type: rawcan, interface: {channel}, can_interface: virtual,\n"
        f"     slaves: [{{name: 'j{{i}}', map: {drive}, node_id: 1, count: {nodes}}}]}}\n"
    )
    return f


def test_cubemars_servo_nan_position_never_goes_out_as_int32_max(tmp_path: Path) -> None:
    """The reproduced failure: NaN in servo mode became INT32_MAX (+3748 rad) on the wire."""
    from sim_slaves.cubemars import CubemarsServoSimulator

    servo = Path(PDO_MAPS) / "cubemars_ak80_9_servo.yaml"
    channel = f"fb-op-cm-{os.getpid()}-{next(_channels)}"
    drive = load_drive_map(servo)
    with (
        can.Bus(interface="virtual", channel=channel) as listener,
        can.Bus(interface="virtual", channel=channel) as sim_bus,
        CubemarsServoSimulator(sim_bus, [(drive, n) for n in (1, 2)], dt_s=0.001) as sim,
        open_network(rawcan_net(tmp_path, channel, servo)) as net,
    ):
        op = net.bring_up()
        out = op["arm"].outputs
        out["mode"][:] = 4  # position loop: int32 deg x 10000
        out["position"][:] = 0.2
        for _ in range(300):  # the motors settle at 0.2 rad
            op.exchange()
        drain(listener)
        start = [sim.motor(n).position for n in (1, 2)]
        out["position"][0] = math.nan
        out["position"][1] = math.inf
        for _ in range(300):
            op.exchange()
        frames = [m for m in drain(listener) if m.is_extended_id and m.arbitration_id >> 8 == 4]
        raw = [struct.unpack(">i", bytes(m.data[:4]))[0] for m in frames]
        assert len(raw) == 600 and INT32_MAX not in raw and INT32_MIN not in raw
        assert set(raw) == {round(0.2 * 572957.795)}  # the last value sent, held
        for n, p0 in zip((1, 2), start, strict=True):
            assert abs(sim.motor(n).position - p0) < 0.02  # before: 1.48 rad in 300 ms toward +3748 rad


def test_damiao_mode_frames_never_carry_nan_nor_more_than_vmax(tmp_path: Path) -> None:
    from sim_slaves.damiao import DamiaoSimulator

    dm = Path(PDO_MAPS) / "damiao_dm_j4310.yaml"
    channel = f"fb-op-dm-{os.getpid()}-{next(_channels)}"
    drive = load_drive_map(dm)
    with (
        can.Bus(interface="virtual", channel=channel) as listener,
        can.Bus(interface="virtual", channel=channel) as sim_bus,
        DamiaoSimulator(sim_bus, [(drive, n) for n in (1, 2)], dt_s=0.001) as sim,
        open_network(rawcan_net(tmp_path, channel, dm)) as net,
    ):
        op = net.bring_up()
        backend = net.backends[0]
        out = op["arm"].outputs
        backend.set_mode("j0", "velocity")  # float32 rad/s on 0x200 + id
        backend.set_mode("j1", "position_velocity")  # float32 rad, float32 rad/s on 0x100 + id
        vel, pv_pos, pv_vel = "velocity.velocity", "position_velocity.position", "position_velocity.velocity"
        out[vel][0], out[pv_vel][1] = 1000.0, 2.0
        out[pv_pos][1] = math.nan
        for _ in range(3):
            op.exchange()
        out[vel][0], out[pv_vel][1] = math.nan, -math.inf
        out[pv_pos][1] = math.inf
        for _ in range(3):
            op.exchange()
        frames = drain(listener)
        vel = [struct.unpack("<f", bytes(m.data[:4]))[0] for m in frames if m.arbitration_id == 0x201]
        pv = [struct.unpack("<ff", bytes(m.data[:8])) for m in frames if m.arbitration_id == 0x102]
        assert vel == [30.0] * 6  # VMAX, then NaN keeps it (before: 1000.0, then NaN)
        assert all(math.isfinite(p) and math.isfinite(v) for p, v in pv) and len(pv) == 6
        assert pv[-1] == (12.5, -30.0)  # inf: PMAX; -inf: -VMAX
        assert all(abs(v) <= 30.0 and abs(p) <= 12.5 for p, v in pv)
        assert math.isfinite(sim.motor(1).velocity) and math.isfinite(sim.motor(2).position)


def test_odrive_set_input_vel_never_carries_nan_and_the_emulator_refuses_one(tmp_path: Path) -> None:
    odrive_can = pytest.importorskip("odrive_can")
    from sim_slaves.odrive import OdriveSimulator

    od = Path(PDO_MAPS) / "odrive_s1.yaml"
    channel = f"fb-op-od-{os.getpid()}-{next(_channels)}"
    drive = load_drive_map(od)
    dbc = odrive_can.get_dbc()  # odriverobotics' CANSimple DBC: the independent decoder
    with (
        can.Bus(interface="virtual", channel=channel) as listener,
        can.Bus(interface="virtual", channel=channel) as sim_bus,
        OdriveSimulator(sim_bus, [(drive, n) for n in (1, 2)], dt_s=0.001, heartbeat_ms=10) as sim,
        open_network(rawcan_net(tmp_path, channel, od)) as net,
    ):
        op = net.bring_up()
        backend = net.backends[0]
        out = op["arm"].outputs
        backend.set_mode("j0", "velocity")
        out["velocity"][:] = 1.5
        for _ in range(3):
            op.exchange()
        out["velocity"][0] = math.nan
        for _ in range(3):
            op.exchange()
        vel = [
            dbc.decode_message(0x0D, bytes(m.data))["Input_Vel"]
            for m in drain(listener)
            if m.arbitration_id == 1 << 5 | 0x0D
        ]
        assert vel == [1.5] * 6, vel  # before: NaN on the wire from the 4th frame
        assert math.isfinite(sim.motor(1).velocity)
        # a NaN set-point sent past fieldbus: the emulated ODrive refuses it, its state stays finite
        listener.send(
            can.Message(
                arbitration_id=2 << 5 | 0x0C, data=struct.pack("<fhh", math.nan, 0, 0), is_extended_id=False
            )
        )
        for _ in range(5):
            op.exchange()
        assert sim.axes[2].refused == 1
        assert math.isfinite(sim.motor(2).position) and math.isfinite(sim.motor(2).velocity)


def test_mit_position_step_is_clamped_to_the_maps_max_step(tmp_path: Path) -> None:
    from sim_slaves.mit_motor import MitMotorSimulator

    mit = tmp_path / "mit.yaml"
    mit.write_text(
        (Path(PDO_MAPS) / "cubemars_ak80_9_mit.yaml").read_text() + "limits:\n  position: {max_step: 0.01}\n"
    )
    channel = f"fb-op-mit-{os.getpid()}-{next(_channels)}"
    drive = load_drive_map(mit)
    pos = next(f for f in drive.rawcan.command if f.name == "position")  # type: ignore[union-attr]
    with (
        can.Bus(interface="virtual", channel=channel) as listener,
        can.Bus(interface="virtual", channel=channel) as sim_bus,
        MitMotorSimulator(sim_bus, [(drive, n) for n in (1, 2)], dt_s=0.001),
        open_network(rawcan_net(tmp_path, channel, mit)) as net,
    ):
        op = net.bring_up()
        out = op["arm"].outputs
        op.exchange()
        drain(listener)
        out["position"][:] = [2.0, 0.005]
        res = op.exchange()
        frames = {m.arbitration_id: bytes(m.data) for m in drain(listener) if len(m.data) == 8}
        span = pos.max - pos.min  # type: ignore[operator]
        got = [
            (int.from_bytes(frames[n][:2], "big") / 0xFFFF) * span + pos.min  # MIT p16, big-endian
            for n in (1, 2)
        ]
        assert got == [pytest.approx(0.01, abs=span / 0xFFFF), pytest.approx(0.005, abs=span / 0xFFFF)]
        assert [(e.axis, e.reason.name) for e in res.events if isinstance(e, fieldbus.OutputClamp)] == [
            (0, "STEP")
        ]
        assert np.isclose(out["position"][0], 0.01)


def test_a_profile_move_to_inf_goes_to_the_window_edge_never_int32_max(tmp_path: Path) -> None:
    """ProfileMove writes its targets into the image: they pass the same rules (PP: not ramped)."""
    from fieldbus import Cia402Controller, Goal, Mode, ProfileMove
    from fieldbus.testing import emulate

    joint = windowed_demo_map(
        tmp_path, "motion_profile: {velocity: 200000, acceleration: 1000000, deceleration: 1000000}\n"
    )
    net = tmp_path / "arm.yaml"
    net.write_text(
        "cycle_time_us: 1000\nreceive_timeout_us: 5000\nsafe_stop_after: 10\nbuses:\n"
        f"  - {{name: arm, type: ethercat, interface: sim0, slaves: [{{name: 'j{{i}}', map: {joint}, count: 2}}]}}\n"
    )
    with emulate(net) as emu:
        op = emu.op
        img = op["arm"]
        ctrl = Cia402Controller(img.n_axes, mode=Mode.CSP)
        ctrl.set_goal(Goal.ENABLE)
        moves = ProfileMove.from_maps(ctrl, [s.map for s in op.groups["arm"].slaves], op.cycle_time_us)
        seen: list[list[int]] = []

        def step(k: int) -> bool:
            if op.exchange().fresh:
                ctrl.step_image(img)
                moves.step_image(img)
            seen.append(received_targets(op.network))
            return False

        emu.run(step, cycles=50)
        assert ctrl.all_reached
        moves.move_to([math.inf, math.nan])
        emu.run(step, cycles=1500)
        flat = [v for row in seen for v in row]
        assert INT32_MAX not in flat and all(WINDOW[0] <= v <= WINDOW[1] for v in flat)
        assert seen[-1][0] == WINDOW[1]  # inf: the window's edge (0x607D:02)
        assert abs(seen[-1][1]) < 1000  # NaN: the target sent last (where the axis stood)
        assert moves.done and img.inputs["position_actual_value"][0] == pytest.approx(3.0, abs=0.01)
