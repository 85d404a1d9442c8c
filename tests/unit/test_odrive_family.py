"""The ODrive family on the family protocol, sans I/O: its frames, heartbeats, bounded bring-up steps and
endpoint access, fed by hand (frame layouts from the CANSimple DBC: id = node << 5 | command, little-endian).

Our own code judged against hand-packed frames; the odrive-can oracle is tests/interop/test_odrive_oracle.py.
"""

from __future__ import annotations

import struct
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from fieldbus import PDO_MAPS
from fieldbus.core.canfamily import FamilyMotor, Remote, StepRefused, families
from fieldbus.core.odrive import ConfigItem
from fieldbus.core.odrivefamily import OdriveFamily
from fieldbus.core.pdo import load_drive_map

NODE = 3


def _family(
    map_name: str = "odrive_s1.yaml", nodes: tuple[int, ...] = (NODE,), config: tuple[ConfigItem, ...] = ()
) -> OdriveFamily:
    cfg = load_drive_map(Path(PDO_MAPS) / map_name).rawcan
    assert cfg is not None and cfg.odrive is not None
    if config:
        cfg = replace(cfg, odrive=replace(cfg.odrive, config=config))
    out_bytes, in_bytes = sum(f.bits for f in cfg.command) // 8, sum(f.bits for f in cfg.reply) // 8
    motors = [
        FamilyMotor(i, n, cfg, np.zeros(out_bytes, np.uint8), np.zeros(in_bytes, np.uint8))
        for i, n in enumerate(nodes)
    ]
    return OdriveFamily(motors)


def _ids(frames: object) -> list[tuple[int, bool]]:
    return [(f.can_id, bool(getattr(f, "remote", False))) for f in frames]  # type: ignore[attr-defined]


def _request_field(fam: OdriveFamily, value: int) -> None:
    m = fam.motors[0]
    at, size = m.config.odrive.request_at
    m.outputs[at : at + size] = np.frombuffer(value.to_bytes(size, "little"), np.uint8)


def test_registered_under_its_name() -> None:
    assert families()["odrive"] is OdriveFamily


def test_a_cycle_sends_the_state_once_the_set_point_unless_idle_and_the_rtr() -> None:
    fam = _family()
    struct.pack_into("<f", fam.motors[0].outputs, 0, 0.5)  # position, turns
    _request_field(fam, 8)
    first = fam.cycle()
    assert _ids(first) == [(NODE << 5 | 0x07, False), (NODE << 5 | 0x0C, False), (NODE << 5 | 0x09, True)]
    assert struct.unpack("<I", bytes(first[0].data[:4]))[0] == 8
    assert struct.unpack_from("<f", bytes(first[1].data))[0] == 0.5
    assert _ids(fam.cycle()) == [(NODE << 5 | 0x0C, False), (NODE << 5 | 0x09, True)]  # state once
    _request_field(fam, 1)  # IDLE (the safe stop's value): the state, then no set-point
    assert _ids(fam.cycle()) == [(NODE << 5 | 0x07, False), (NODE << 5 | 0x09, True)]
    assert _ids(fam.cycle()) == [(NODE << 5 | 0x09, True)]


def test_the_encoder_answer_is_the_reply_and_a_heartbeat_a_status_taken_whenever_it_comes() -> None:
    fam = _family()
    answer = struct.pack("<ff", 1.25, -0.5)
    assert fam.carries(NODE << 5 | 0x09, True, answer) == []  # extended id: not ours
    assert fam.carries(NODE << 5 | 0x09, False, answer[:6]) == []  # short: malformed
    assert fam.route(NODE << 5 | 0x09, False, answer) == [0]
    assert struct.unpack_from("<ff", bytes(fam.motors[0].inputs)) == (1.25, -0.5)
    assert fam.take(NODE << 5 | 0x09, False, answer) == ()  # a reply is no status
    assert fam.take(NODE << 5 | 0x01, False, b"\x01\x00") == ()  # a short heartbeat is dropped
    assert fam.error(0) == (0, None)
    hb = struct.pack("<IBBBx", 0x2000, 1, 0, 1)
    assert fam.take(NODE << 5 | 0x01, False, hb) == (0,)
    assert fam.error(0) == (0x2000, "MOTOR_OVER_TEMP")
    # firmware 0.6: a new error asks Get_Error with the next cycle, once
    assert fam.take(NODE << 5 | 0x01, False, hb) == (0,)
    assert _ids(fam.cycle())[0] == (NODE << 5 | 0x03, True)
    assert (NODE << 5 | 0x03, True) not in _ids(fam.cycle())
    fam.take(NODE << 5 | 0x03, False, struct.pack("<II", 0x2000, 0x2000))
    assert fam.active_errors == {0: (0x2000, 0x2000)}
    assert fam.error(0)[0] == 0x2000 and fam.take(NODE << 5 | 0x01, False, struct.pack("<IBBBx", 0, 1, 0, 1))
    assert fam.error(0) == (0, None)


def test_enter_writes_closed_loop_and_awaits_a_heartbeat_saying_so_bounded() -> None:
    fam = _family()
    steps = list(fam.bring_up("enter"))
    assert [s.frame[0] for s in steps] == [NODE << 5 | 0x07, NODE << 5 | 0x01]
    state, wait = steps
    assert struct.unpack("<I", state.frame[2][:4])[0] == 8 and state.until is None
    assert isinstance(wait.frame[2], Remote) and wait.awaits == (0,)
    assert wait.until is not None and wait.timeout_s is not None and 0 < wait.timeout_s < 10
    at, size = fam.motors[0].config.odrive.request_at
    assert int.from_bytes(bytes(fam.motors[0].outputs[at : at + size]), "little") == 8  # in the image
    assert not wait.until()
    fam.take(NODE << 5 | 0x01, False, struct.pack("<IBBBx", 0, 1, 0, 1))  # still IDLE
    assert not wait.until()
    fam.take(NODE << 5 | 0x01, False, struct.pack("<IBBBx", 0, 8, 0, 1))
    assert wait.until()
    assert _ids(fam.cycle())[0] == (NODE << 5 | 0x0C, False)  # closed loop sent at enter: not again


def test_exit_and_the_stop_send_idle_and_recovery_clears_then_arms() -> None:
    fam = _family()
    assert [(f[0], struct.unpack("<I", f[2][:4])[0]) for f in fam.stop_frames()] == [(NODE << 5 | 0x07, 1)]
    steps = fam.recover(0)
    clear = next(steps)
    assert clear.frame[0] == NODE << 5 | 0x18 and clear.until is None
    assert [s.frame[0] for s in steps] == [NODE << 5 | 0x07, NODE << 5 | 0x01]


def test_endpoint_access_is_0_6_only_returns_the_answer_and_configure_refuses_a_read_back() -> None:
    with pytest.raises(ValueError, match=r"firmware 0\.6 only"):
        next(_family("odrive_3_6.yaml").access(0, 432))
    fam = _family()
    steps = fam.access(0, 432, struct.pack("<f", 0.25))
    write = next(steps)
    assert write.frame[2] == bytes([1]) + struct.pack("<H", 432) + b"\0" + struct.pack("<f", 0.25)
    read = steps.send(None)
    assert read.frame[2][:3] == bytes([0]) + struct.pack("<H", 432) and read.timeout_s is not None
    assert read.answer is not None
    txsdo = NODE << 5 | 0x05
    other = bytes([0]) + struct.pack("<H", 999) + b"\0" + bytes(4)
    mine = bytes([0]) + struct.pack("<H", 432) + b"\0" + struct.pack("<f", 0.25)
    assert not read.answer(txsdo, False, other)  # another endpoint's answer
    assert not read.answer(txsdo, True, mine) and not read.answer(txsdo + 32, False, mine)  # not this axis
    assert not read.answer(txsdo, False, mine[:6])  # short
    assert read.answer(txsdo, False, mine)
    with pytest.raises(StopIteration) as done:
        steps.send(mine)
    assert done.value.value == struct.pack("<f", 0.25)


def test_set_mode_switches_the_set_point_after_its_frame_and_refuses_an_unknown_mode() -> None:
    fam = _family()
    _request_field(fam, 8)
    steps = fam.set_mode(0, "velocity")
    step = next(steps)
    assert step.frame[0] == NODE << 5 | 0x0B and struct.unpack("<II", step.frame[2]) == (2, 1)
    assert fam.mode(0) == "position"  # not before the frame went out
    assert list(steps) == [] and fam.mode(0) == "velocity"
    assert (NODE << 5 | 0x0D, False) in _ids(fam.cycle())
    with pytest.raises(ValueError, match="no mode 'spin'"):
        next(fam.set_mode(0, "spin"))


def test_two_axes_with_one_node_id_are_refused() -> None:
    with pytest.raises(ValueError, match="node id 3"):
        _family(nodes=(3, 3))
    with pytest.raises(ValueError, match=r"0\.\.63"):
        _family(nodes=(64,))


def test_configure_refuses_an_endpoint_that_reads_back_otherwise() -> None:
    items = (ConfigItem("watchdog_timeout", 432, "float32", 0.25),)
    fam = _family(config=items)
    steps = fam.configure()
    hb = next(steps)
    fam.take(NODE << 5 | 0x01, False, struct.pack("<IBBBx", 0, 1, 0, 1))
    assert hb.until is not None and hb.until()
    assert next(steps).frame[0] == NODE << 5 | 0x0B
    next(steps)  # the write
    read = next(steps)
    wrong = bytes([0]) + struct.pack("<H", items[0].endpoint) + b"\0" + struct.pack("<I", 0xDEAD)
    assert read.answer is not None and read.answer(NODE << 5 | 0x05, False, wrong)
    with pytest.raises(StepRefused, match=f"endpoint {items[0].name}"):
        steps.send(wrong)


def test_register_key_names_an_endpoint_by_the_map_or_its_id_firmware_0_6_only() -> None:
    items = (ConfigItem("watchdog_timeout", 432, "float32", 0.25),)
    cfg = _family(config=items).motors[0].config
    assert OdriveFamily.register_key(cfg, "watchdog_timeout", None, True) == (
        432,
        "watchdog_timeout",
        "float32",
        False,
    )
    assert OdriveFamily.register_key(cfg, "0x1B1", None, False) == (0x1B1, "endpoint 433", "uint32", False)
    assert OdriveFamily.register_key(cfg, "433", "bool", True)[2] == "bool"
    for reg, typ, message in (
        ("433", None, "give --type"),
        ("70000", "uint32", "0..65535"),
        ("watchdog", None, "neither an endpoint id"),
    ):
        with pytest.raises(ValueError, match=message):
            OdriveFamily.register_key(cfg, reg, typ, True)
    old = _family("odrive_3_6.yaml").motors[0].config
    with pytest.raises(ValueError, match=r"firmware 0\.5 has no endpoint access"):
        OdriveFamily.register_key(old, "433", "uint32", False)
