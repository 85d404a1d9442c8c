"""CubeMars maps and codec (fieldbus.core.cubemars): validation errors name file, line and field; servo
packets and status frames against the manual's layout decoded with ``struct``; the multi-turn unwrapper."""

from __future__ import annotations

import math
import struct
from pathlib import Path

import pytest

from fieldbus import PDO_MAPS
from fieldbus.core import cubemars
from fieldbus.core.pdo import drive_map_from_text, load_drive_map
from fieldbus.errors import PdoMapError

SERVO = Path(PDO_MAPS) / "cubemars_ak80_9_servo.yaml"
MIT = Path(PDO_MAPS) / "cubemars_ak10_9_mit.yaml"


def test_servo_packets_and_status_frame_follow_the_manual() -> None:
    proto = load_drive_map(SERVO).rawcan.cubemars  # type: ignore[union-attr]
    assert proto is not None and proto.protocol == "servo"
    pos_spd = proto.mode_named("position_speed")
    assert cubemars.servo_id(pos_spd.packet, 0x68) == 0x668  # packet << 8 | id
    values = {"position": math.radians(90.0), "speed_limit": 2.0, "accel_limit": 10.0}
    erpm_per_rad_s = 21 * 9 * 60 / (2 * math.pi)
    assert struct.unpack(">ihh", cubemars.encode_servo(pos_spd.fields, values)) == (
        900_000,  # 90 deg x 10,000
        round(2.0 * erpm_per_rad_s / 10),
        round(10.0 * erpm_per_rad_s / 10),
    )
    current = proto.mode_named("current")
    assert cubemars.encode_servo(current.fields, {"current": -1.5}) == struct.pack(">i", -1500)
    assert cubemars.encode_servo(current.fields, {"current": 1e9}) == struct.pack(
        ">i", 2**31 - 1
    )  # saturates
    frame = struct.pack(">hhhbB", -1234, 250, -310, -5, 3)  # -123.4 deg, 2500 erpm, -3.1 A, -5 °C, error 3
    got = cubemars.decode_servo(proto.status, frame)
    assert got["position"] == pytest.approx(math.radians(-123.4), abs=1e-6)
    assert got["velocity"] == pytest.approx(2500 / erpm_per_rad_s, rel=1e-4)
    assert got["current"] == pytest.approx(-3.1) and got["temperature"] == -5 and got["error"] == 3
    assert cubemars.encode_status(proto.status, got) == frame
    assert proto.error_name(3) == "over-voltage" and proto.error_name(9) == "unknown error 9"


def test_unwrapper_follows_wraps_both_ways() -> None:
    unwrap = cubemars.Unwrapper(-12.5, 12.5)
    seen = [unwrap(x) for x in (12.0, 12.4, -12.4, -12.0, 12.3, 11.0, -12.2)]
    assert seen == pytest.approx([12.0, 12.4, 12.6, 13.0, 12.3, 11.0, 12.8])
    unwrap.reset()
    assert unwrap(-12.4) == -12.4


def _mit_text(**changes: str) -> str:
    text = MIT.read_text()
    for old, new in changes.items():
        assert old in text
        text = text.replace(old, new)
    return text


@pytest.mark.parametrize(
    ("old", "new", "message"),
    [
        ("protocol: mit", "protocol: servo\n    unwrap_typo: 1", "unwrap_typo"),
        ("into: position_total", "into: temperature", "not the last reply field, float32"),
        ("from: position,", "from: motor_id,", "not a scaled reply field"),
        ("error_field: error", "error_field: position", "not an unscaled reply field"),
        ("{name: error, bits: 8}", "{name: error, bits: 32, type: float32}", "unsigned fields"),
        ("  cubemars:\n", "  damiao_x: 1\n  cubemars:\n", "damiao_x"),
    ],
)
def test_bad_cubemars_sections_are_refused_naming_the_field(old: str, new: str, message: str) -> None:
    with pytest.raises(PdoMapError, match=message) as exc:
        drive_map_from_text(_mit_text(**{old: new}), file="ak.yaml")
    assert "ak.yaml:" in str(exc.value) and "rawcan" in str(exc.value)


def test_a_servo_map_needs_a_little_endian_image() -> None:
    text = SERVO.read_text().replace("  byte_order: little\n", "")
    with pytest.raises(PdoMapError, match="byte_order"):
        drive_map_from_text(text, file="servo.yaml")


def test_the_family_takes_packets_and_status_through_the_image_codec_only() -> None:
    """The servo image is the wire's numbers: a packet's bytes are the row's (``to_wire``), a status frame
    lands in the row and ``from_wire`` decodes it; both against ``struct`` per the manual's layout."""
    from fieldbus.core.canfamily import FamilyMotor
    from fieldbus.core.cubemarsfamily import CubemarsFamily
    from fieldbus.core.pdo.image import ProcessImage
    from fieldbus.core.pdo.layout import layout

    drive = load_drive_map(SERVO)
    img = ProcessImage(layout(drive), 1)
    fam = CubemarsFamily([FamilyMotor(0, 0x68, drive.rawcan, img.outputs.wire[0], img.inputs.wire[0], "j0")])
    out = img.outputs
    out["mode"][0], out["position"][0], out["speed_limit"][0] = 6, math.radians(90.0), 2.0
    out["accel_limit"][0] = math.nan  # the image keeps the raw value sent last (0): never INT16_MAX
    out.to_wire()
    (frame,) = fam.cycle()
    erpm_per_rad_s = 21 * 9 * 60 / (2 * math.pi)
    assert (frame.can_id, frame.extended) == (0x668, True)
    assert struct.unpack(">ihh", frame.data) == (900_000, round(2.0 * erpm_per_rad_s / 10), 0)
    out["mode"][0] = 9  # names no packet: nothing sent
    out.to_wire()
    assert fam.cycle() == []
    status = struct.pack(">hhhbB", -1234, 250, -310, -5, 3)
    assert fam.route(0x2968, True, status) == [0] and fam.route(0x2968, True, status[:6]) == []
    img.inputs.from_wire()
    inp = img.inputs
    assert inp["position"][0] == pytest.approx(math.radians(-123.4), abs=1e-6)
    assert inp["current"][0] == pytest.approx(-3.1) and int(inp["temperature"][0]) == -5
    assert fam.error(0) == (3, "over-voltage")
