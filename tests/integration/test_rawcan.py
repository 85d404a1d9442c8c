"""Raw-CAN MIT-mode motors: golden frames and the emulated motors through the Network API."""

from __future__ import annotations

import itertools
import os
import time
from collections.abc import Iterator
from pathlib import Path

import can
import numpy as np
import pytest

from fieldbus.core.pdo import load_drive_map
from fieldbus.core.pdo.image import ProcessImage
from fieldbus.core.pdo.layout import layout
from fieldbus.core.safety import Verdict
from fieldbus.network import open_network
from sim_slaves.mit_motor import MitMotorSimulator

MAP = Path(__file__).resolve().parents[2] / "pdo_maps" / "cubemars_ak80_9_mit.yaml"
_channels = itertools.count()


def frame(img_dir: object) -> bytes:
    """The CAN data of axis 0: the byte-reversed wire row."""
    return bytes(img_dir.wire[0, ::-1])  # type: ignore[attr-defined]


def value(raw: int, lo: float, hi: float, bits: int) -> float:
    """bgkatz uint_to_float: the engineering value of a raw field."""
    return raw * (hi - lo) / ((1 << bits) - 1) + lo


def test_command_frame_matches_the_published_mit_layout() -> None:
    img = ProcessImage(layout(load_drive_map(MAP)), 1)
    out = img.outputs
    out["position"][0] = value(0x1234, -12.5, 12.5, 16)
    out["velocity"][0] = value(0x567, -50, 50, 12)
    out["kp"][0] = value(0x89A, 0, 500, 12)
    out["kd"][0] = value(0xBCD, 0, 5, 12)
    out["torque"][0] = value(0xEF0, -18, 18, 12)
    out.to_wire()
    assert frame(out) == bytes.fromhex("12 34 56 78 9A BC DE F0")
    # range ends: max position, min velocity, max kp, zero kd, max torque
    out["position"][0], out["velocity"][0], out["kp"][0], out["kd"][0], out["torque"][0] = (
        12.5,
        -50,
        500,
        0,
        18,
    )
    out.to_wire()
    assert frame(out) == bytes.fromhex("FF FF 00 0F FF 00 0F FF")
    # out of range saturates instead of wrapping
    out["position"][0], out["torque"][0] = 99.0, -99.0
    out.to_wire()
    assert frame(out)[:2] == b"\xff\xff" and frame(out)[6] & 0x0F == 0 and frame(out)[7] == 0


def test_reply_frame_decodes_per_the_published_layout() -> None:
    img = ProcessImage(layout(load_drive_map(MAP)), 1)
    img.inputs.wire[0, ::-1] = np.frombuffer(bytes.fromhex("05 12 34 56 78 9A"), dtype=np.uint8)
    img.inputs.from_wire()
    v = img.inputs.values[0]
    assert v["motor_id"] == 5
    assert v["position"] == pytest.approx(value(0x1234, -12.5, 12.5, 16))
    assert v["velocity"] == pytest.approx(value(0x567, -50, 50, 12))
    assert v["torque"] == pytest.approx(value(0x89A, -18, 18, 12))


@pytest.fixture
def network(tmp_path: Path) -> Iterator[tuple[Path, str]]:
    channel = f"fb-mit-{os.getpid()}-{next(_channels)}"
    net = tmp_path / "net.yaml"
    net.write_text(
        "cycle_time_us: 2000\nreceive_timeout_us: 20000\nsafe_stop_after: 4\nbuses:\n"
        f"  - {{name: legs, type: rawcan, interface: {channel}, can_interface: virtual,\n"
        f"     slaves: [{{name: 'm{{i}}', map: {MAP}, node_id: 1, count: 4}}]}}\n"
    )
    yield net, channel


def test_motors_follow_commands_through_the_network_api(network: tuple[Path, str]) -> None:
    net_file, channel = network
    drive = load_drive_map(MAP)
    with (
        can.Bus(interface="virtual", channel=channel) as sim_bus,
        MitMotorSimulator(sim_bus, [(drive, n) for n in range(1, 5)], dt_s=0.002) as sim,
        open_network(net_file) as net,
    ):
        op = net.bring_up()
        assert all(sim.motor(n).enabled for n in range(1, 5))
        legs = op["legs"]
        out, inp = legs.outputs, legs.inputs
        out["kp"][:] = 40.0
        out["kd"][:] = 1.5
        target = np.array([0.5, -0.5, 1.0, 0.0])
        errors: list[float] = []
        misses = 0
        for k in range(
            600
        ):  # 300 fresh cycles; the motors' physics advance per command (dt_s), not wall time
            if len(errors) == 300:
                break
            out["position"][:] = target * min(1.0, len(errors) / 100)
            before = inp["position"].copy()
            res = op.exchange()
            st = res.bus("legs")
            if not res.fresh:
                # the simulator answers from a thread on the wall clock: a loaded machine can deschedule it past
                # receive_timeout_us. That is a miss, and the contract's verdict for it is what we check: named,
                # the late motors' inputs held (stale never reads fresh), no safe stop below safe_stop_after (4)
                misses += 1
                assert st.verdict is not Verdict.OK and st.fault is not None, (k, st)
                late = ~st.fresh
                assert np.array_equal(inp["position"][late], before[late]), (k, st)
                assert res.safe_stop == (st.consecutive_misses >= 4), (k, st)
                assert not res.safe_stop, (
                    k,
                    st,
                )  # 4 misses in a row: the simulator starved for 80 ms or more
                continue
            assert st.verdict is Verdict.OK and st.consecutive_misses == 0
            errors.append(float(np.abs(inp["position"] - out["position"]).max()))
        assert len(errors) == 300, (misses, st)  # at most as many misses as fresh cycles
        assert max(errors[-50:]) < 0.02, max(errors[-50:])  # rad, after the ramp settles
        assert list(inp["motor_id"]) == [1, 2, 3, 4]
        assert not sim.errors
    assert not any(sim.motor(n).enabled for n in range(1, 5))  # exit motor mode on close


def test_missing_replies_are_stale_and_held(network: tuple[Path, str]) -> None:
    net_file, channel = network
    drive = load_drive_map(MAP)
    with (
        can.Bus(interface="virtual", channel=channel) as sim_bus,
        MitMotorSimulator(sim_bus, [(drive, n) for n in range(1, 5)], dt_s=0.002) as sim,
        open_network(net_file) as net,
    ):
        op = net.bring_up()
        legs = op["legs"]
        legs.outputs["kp"][:] = 20.0
        legs.outputs["position"][:] = 0.3
        for _ in range(20):
            op.exchange()
        held = float(legs.inputs["position"][2])
        legs.outputs["position"][:] = -0.3
        sim.drop_replies(3, 2)  # node 3 is row 2
        for _ in range(2):
            res = op.exchange()
            st = res.bus("legs")
            assert not res.fresh and list(st.fresh) == [True, True, False, True]
            assert float(legs.inputs["position"][2]) == held  # stale row keeps its last value
        res = op.exchange()
        assert res.fresh and float(legs.inputs["position"][2]) != held
        # a silent motor escalates to a safe stop after safe_stop_after (4) misses
        sim.silence(4)
        stops = [op.exchange().safe_stop for _ in range(5)]
        assert stops == [False, False, False, True, True]


def test_a_late_reply_is_counted_and_never_taken_for_the_next_cycles(network: tuple[Path, str]) -> None:
    net_file, channel = network
    drive = load_drive_map(MAP)
    cfg = drive.rawcan
    assert cfg is not None
    reply_id = cfg.reply_id if cfg.reply_id is not None else cfg.command_id + 3
    with (
        can.Bus(interface="virtual", channel=channel) as sim_bus,
        can.Bus(interface="virtual", channel=channel) as late_bus,
        MitMotorSimulator(sim_bus, [(drive, n) for n in range(1, 5)], dt_s=0.002) as sim,
        open_network(net_file) as net,
    ):
        op = net.bring_up()
        legs = op["legs"]
        for _ in range(5):
            op.exchange()
        sim.drop_replies(3, 1)
        assert list(op.exchange().bus("legs").fresh) == [True, True, False, True]
        # node 3's reply to that cycle turns up after the timeout: position at the top of its range
        late = bytes([3, 0xFF, 0xFF, 0x80, 0x08, 0x00])
        late_bus.send(can.Message(arbitration_id=reply_id, data=late, is_extended_id=False))
        time.sleep(0.01)  # it is queued before the next cycle starts
        res = op.exchange()
        assert res.fresh  # this cycle's own reply, from the motor
        assert abs(float(legs.inputs["position"][2])) < 1.0  # not the late frame's 12.5 rad
        assert net.backends[0].late_replies == 1


def test_safe_stop_zeroes_gains_and_torque_of_every_motor(network: tuple[Path, str]) -> None:
    """MIT-mode motors have no controlword: the safe stop sends kp = kd = 0 and zero torque.

    Read from the emulated motors: the command they receive in the cycle after
    the safe stop latches, whatever the controller keeps writing; then close
    takes them out of motor mode.
    """
    net_file, channel = network
    drive = load_drive_map(MAP)
    lsb = {"kp": 500 / 4095, "kd": 5 / 4095, "torque": 36 / 4095}  # one raw step of each field
    with (
        can.Bus(interface="virtual", channel=channel) as sim_bus,
        MitMotorSimulator(sim_bus, [(drive, n) for n in range(1, 5)], dt_s=0.002) as sim,
        open_network(net_file) as net,
    ):
        op = net.bring_up()
        out = op["legs"].outputs
        for _ in range(10):
            out["kp"][:], out["kd"][:], out["torque"][:], out["position"][:] = 40.0, 1.5, 2.0, 0.4
            assert op.exchange().fresh
        assert all(sim.motor(n).command[2] > 39 for n in range(1, 5))  # type: ignore[index]
        for n in range(1, 5):
            sim.drop_replies(n, 4)  # a burst: 4 cycles (safe_stop_after) without any reply
        stops = []
        for _ in range(4):
            out["kp"][:], out["kd"][:], out["torque"][:] = 40.0, 1.5, 2.0  # the controller keeps pushing
            stops.append(op.exchange().safe_stop)
        assert stops == [False, False, False, True]
        out["kp"][:], out["kd"][:], out["torque"][:] = 40.0, 1.5, 2.0
        op.exchange()  # the cycle after the safe stop: what the motors got
        for n in range(1, 5):
            _, _, kp, kd, torque = sim.motor(n).command  # type: ignore[misc]
            assert abs(kp) < lsb["kp"] and abs(kd) < lsb["kd"] and abs(torque) < lsb["torque"], (
                n,
                kp,
                kd,
                torque,
            )
        assert op.safe_stops["legs"].plan.kind == "mit"
        assert not sim.errors
    assert not any(sim.motor(n).enabled for n in range(1, 5))  # exit motor mode on close


def test_a_map_must_say_what_its_safe_stop_sends() -> None:
    from fieldbus.core.pdo import drive_map_from_text
    from fieldbus.errors import PdoMapError

    text = MAP.read_text()
    no_names = text.replace("name: kp,", "name: gain_p,").replace("name: kd,", "name: gain_d,")
    no_names = no_names.replace(
        "{name: torque, bits: 12, min: -18.0, max: 18.0, unit: N·m}\n  reply",
        "{name: t_cmd, bits: 12, min: -18.0, max: 18.0, unit: N·m}\n  reply",
    )
    with pytest.raises(PdoMapError, match="no command field has a safe_value"):
        drive_map_from_text(no_names, "m.yaml")
    explicit = no_names.replace("{name: gain_d, bits: 12,", "{name: gain_d, safe_value: 1.0, bits: 12,")
    drive = drive_map_from_text(explicit, "m.yaml")
    from fieldbus.core.safestop import safe_stop_plan

    assert safe_stop_plan(drive, layout(drive)).values == (("gain_d", 1.0),)
