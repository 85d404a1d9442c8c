"""A drive map's ``motion_profile:`` section: start-up SDOs 0x6081/0x6083/0x6084, located errors."""

from __future__ import annotations

from pathlib import Path

import pytest

import fieldbus
from fieldbus import PdoMapError

BASE = (Path(fieldbus.__file__).resolve().parent / "data" / "demo_joint.yaml").read_text()
LINES = BASE.count("\n")  # the section starts on line LINES + 1


def _load(section: str) -> fieldbus.DriveMap:
    return fieldbus.drive_map_from_text(BASE + section, "joint.yaml")


def test_motion_profile_section_becomes_startup_sdos_after_the_maps_own() -> None:
    d = _load("motion_profile:\n  velocity: 100000\n  deceleration: 4294967295\n  timeout_ms: 2500\n")
    assert d.motion_profile is not None and d.motion_profile.timeout_ms == 2500
    assert d.motion_profile.acceleration is None  # not set: not written, the drive keeps its own
    got = [(s.index, s.sub_index, s.type.name, s.data) for s in d.sdo]
    assert got == [
        (0x6060, 0, "int8", b"\x08"),  # the map's own start-up write first
        (0x6081, 0, "uint32", (100000).to_bytes(4, "little")),
        (0x6084, 0, "uint32", b"\xff\xff\xff\xff"),
    ]


@pytest.mark.parametrize(
    ("section", "line", "field", "words"),
    [
        ("motion_profile:\n  velocity: 0\n", 2, "motion_profile.velocity", "out of range"),
        ("motion_profile:\n  acceleration: -5\n", 2, "motion_profile.acceleration", "out of range"),
        ("motion_profile:\n  deceleration: slow\n", 2, "motion_profile.deceleration", "integer"),
        ("motion_profile:\n  timeout_ms: 0\n", 2, "motion_profile.timeout_ms", "out of range"),
        ("motion_profile:\n  velocty: 3\n", 2, "motion_profile.velocty", "did you mean velocity"),
        ("motion_profile: 35\n", 1, "motion_profile", "mapping"),
    ],
)
def test_bad_motion_profile_values_are_located(section: str, line: int, field: str, words: str) -> None:
    with pytest.raises(PdoMapError) as e:
        _load(section)
    msg = str(e.value)
    assert msg.startswith(f"joint.yaml:{LINES + line}:") and f" {field}: " in msg and words in msg, msg


def test_a_profile_object_set_twice_is_refused_where_the_sdo_list_sets_it() -> None:
    text = BASE.replace(
        "sdo:\n",
        "sdo:\n  - {index: 0x6083, sub_index: 0, type: uint32, value: 5}\n",
    )
    with pytest.raises(PdoMapError) as e:
        fieldbus.drive_map_from_text(text + "motion_profile: {acceleration: 10}\n", "joint.yaml")
    assert " sdo[0].index: " in str(e.value) and "motion_profile.acceleration" in str(e.value)
