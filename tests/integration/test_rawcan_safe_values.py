"""A raw-CAN safe_value merges with the MIT default kp = kd = torque = 0 (issue 23, defect 11).

The frames the motors get after the safe stop latches are read off the virtual
bus by a listener and decoded here from the published MIT layout (bgkatz
motorcontrol / CubeMars manual: p16 v12 kp12 kd12 t12, big-endian, MSB first,
``uint = (x - min) * 4095 / (max - min)``), not by fieldbus's codec.
"""

from __future__ import annotations

import os
from pathlib import Path

import pytest

can = pytest.importorskip("can")

from fieldbus import PDO_MAPS  # noqa: E402
from fieldbus.core.pdo import drive_map_from_text, load_drive_map  # noqa: E402
from fieldbus.errors import PdoMapError  # noqa: E402
from fieldbus.network import open_network  # noqa: E402
from sim_slaves.mit_motor import MitMotorSimulator  # noqa: E402

pytestmark = pytest.mark.timeout(120)
MIT_MAP = Path(PDO_MAPS) / "cubemars_ak80_9_mit.yaml"
SAFE_POSITION = 0.25  # rad
RANGES = {
    "position": (-12.5, 12.5, 16),
    "kp": (0.0, 500.0, 12),
    "kd": (0.0, 5.0, 12),
    "torque": (-18.0, 18.0, 12),
}


def decode_command(data: bytes) -> dict[str, float]:
    """The published MIT command frame, field by field."""
    x = int.from_bytes(data, "big")
    raw = {
        "position": x >> 48,
        "velocity": (x >> 36) & 0xFFF,
        "kp": (x >> 24) & 0xFFF,
        "kd": (x >> 12) & 0xFFF,
        "torque": x & 0xFFF,
    }
    out = {}
    for name, (lo, hi, bits) in RANGES.items():
        out[name] = raw[name] * (hi - lo) / ((1 << bits) - 1) + lo
    return out


def lsb(name: str) -> float:
    lo, hi, bits = RANGES[name]
    return (hi - lo) / ((1 << bits) - 1)


def _with_safe_position(tmp_path: Path) -> Path:
    text = MIT_MAP.read_text()
    old = "{name: position, bits: 16, min: -12.5, max: 12.5, unit: rad}\n    - {name: velocity"
    assert old in text
    f = tmp_path / "ak80_safe_position.yaml"
    safe = old.replace("unit: rad}", f"unit: rad, safe_value: {SAFE_POSITION}}}")
    f.write_text(text.replace(old, safe, 1))  # the command's position (the reply's comes after)
    return f


def test_a_safe_value_on_position_keeps_kp_kd_and_torque_at_zero(tmp_path: Path) -> None:
    map_file = _with_safe_position(tmp_path)
    channel = f"fb-mitsafe-{os.getpid()}"
    net_file = tmp_path / "net.yaml"
    net_file.write_text(
        "cycle_time_us: 2000\nreceive_timeout_us: 20000\nsafe_stop_after: 4\nbuses:\n"
        f"  - {{name: legs, type: rawcan, interface: {channel}, can_interface: virtual,\n"
        f"     slaves: [{{name: 'm{{i}}', map: {map_file}, node_id: 1, count: 2}}]}}\n"
    )
    drive = load_drive_map(map_file)
    with (
        can.Bus(interface="virtual", channel=channel) as listener,
        can.Bus(interface="virtual", channel=channel) as sim_bus,
        MitMotorSimulator(sim_bus, [(drive, n) for n in (1, 2)], dt_s=0.002) as sim,
        open_network(net_file) as net,
    ):
        op = net.bring_up()
        out = op["legs"].outputs
        for _ in range(5):
            out["kp"][:], out["kd"][:], out["torque"][:], out["position"][:] = 40.0, 1.5, 2.0, 0.4
            assert op.exchange().fresh
        for n in (1, 2):
            sim.drop_replies(n, 4)
        stops = []
        for _ in range(4):
            out["kp"][:], out["kd"][:], out["torque"][:], out["position"][:] = 40.0, 1.5, 2.0, 0.4
            stops.append(op.exchange().safe_stop)
        assert stops == [False, False, False, True]
        while listener.recv(timeout=0) is not None:
            pass
        out["kp"][:], out["kd"][:], out["torque"][:], out["position"][:] = 40.0, 1.5, 2.0, 0.4
        op.exchange()  # the controller keeps pushing; the cycle after the latch sends the safe command
        commands = {}
        while (msg := listener.recv(timeout=0)) is not None:
            if len(msg.data) == 8 and msg.arbitration_id in (1, 2):  # commands (replies have 6 bytes)
                commands[msg.arbitration_id] = decode_command(bytes(msg.data))
        assert set(commands) == {1, 2}
        for n, cmd in commands.items():
            assert abs(cmd["position"] - SAFE_POSITION) <= lsb("position"), (n, cmd)
            assert cmd["kp"] == 0.0 and cmd["kd"] == 0.0, (n, cmd)
            assert abs(cmd["torque"]) <= lsb("torque"), (n, cmd)
        values = dict(op.safe_stops["legs"].plan.values)
        assert values == {"position": SAFE_POSITION, "kp": 0.0, "kd": 0.0, "torque": 0.0}
        assert not sim.errors


def test_a_default_that_cannot_be_sent_asks_for_a_safe_value() -> None:
    """kp of 1..500 cannot be 0: refused, naming the field, instead of silently left out."""
    text = MIT_MAP.read_text().replace("{name: kp, bits: 12, min: 0.0,", "{name: kp, bits: 12, min: 1.0,")
    with pytest.raises(PdoMapError, match=r"rawcan.command\[2\]: the safe stop sends kp = 0 \(MIT default\)"):
        drive_map_from_text(text, "m.yaml")
    fixed = text.replace("{name: kp, bits: 12, min: 1.0,", "{name: kp, safe_value: 1.0, bits: 12, min: 1.0,")
    drive = drive_map_from_text(fixed, "m.yaml")
    assert drive.rawcan is not None
    assert [(f.name, f.safe_value) for f in drive.rawcan.command if f.safe_value is not None] == [
        ("kp", 1.0),
        ("kd", 0.0),
        ("torque", 0.0),
    ]
