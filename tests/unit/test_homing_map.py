"""A drive map's ``homing:`` section: start-up SDOs in CiA 402 types, located errors, per-axis time-outs."""

from __future__ import annotations

from pathlib import Path

import pytest

import fieldbus
from fieldbus import Cia402Controller, Homing, PdoMapError

BASE = (Path(fieldbus.__file__).resolve().parent / "data" / "demo_joint.yaml").read_text()
LINES = BASE.count("\n")  # the homing section starts on line LINES + 1


def _load(section: str) -> fieldbus.DriveMap:
    return fieldbus.drive_map_from_text(BASE + section, "joint.yaml")


def test_homing_section_becomes_startup_sdos_in_their_cia402_types() -> None:
    d = _load(
        "homing:\n  method: -3\n  offset: -100\n  speeds: {switch: 4294967295, zero: 1000}\n"
        "  acceleration: 500000\n  timeout_ms: 2500\n"
    )
    assert d.homing is not None and d.homing.timeout_ms == 2500
    got = [(s.index, s.sub_index, s.type.name, s.data) for s in d.sdo if s.description.startswith("homing")]
    assert got == [
        (0x6098, 0, "int8", b"\xfd"),  # -3: a manufacturer's method
        (0x607C, 0, "int32", (-100).to_bytes(4, "little", signed=True)),
        (0x6099, 1, "uint32", b"\xff\xff\xff\xff"),
        (0x6099, 2, "uint32", (1000).to_bytes(4, "little")),
        (0x609A, 0, "uint32", (500000).to_bytes(4, "little")),
    ]
    # the map's own SDOs come first, the homing ones after, so bring-up writes them in this order
    assert d.sdo[0].index == 0x6060 and len(d.sdo) == 6


@pytest.mark.parametrize(
    ("section", "line", "field", "words"),
    [
        ("homing:\n  method: 16\n", 2, "homing.method", "not a CiA 402 homing method"),
        ("homing:\n  method: 0\n", 2, "homing.method", "not a CiA 402 homing method"),
        ("homing:\n  method: 200\n", 2, "homing.method", "out of range"),
        ("homing:\n  method: 17\n  speeds: {switch: -1}\n", 3, "homing.speeds.switch", "out of range"),
        ("homing:\n  method: 17\n  offset: 2147483648\n", 3, "homing.offset", "out of range"),
        ("homing:\n  method: 17\n  acceleration: fast\n", 3, "homing.acceleration", "integer"),
        ("homing:\n  method: 35\n  timeout_ms: 0\n", 3, "homing.timeout_ms", "out of range"),
        ("homing:\n  method: 35\n  spead: 3\n", 3, "homing.spead", "did you mean speeds"),
        ("homing:\n  offset: 3\n", 1, "homing", "missing required key 'method'"),
        ("homing: 35\n", 1, "homing", "mapping"),
    ],
)
def test_bad_homing_values_are_located(section: str, line: int, field: str, words: str) -> None:
    with pytest.raises(PdoMapError) as e:
        _load(section)
    msg = str(e.value)
    assert msg.startswith(f"joint.yaml:{LINES + line}:") and f" {field}: " in msg and words in msg, msg


def test_a_homing_object_set_twice_is_refused_where_the_sdo_list_sets_it() -> None:
    text = BASE.replace(
        'description: "modes of operation: CSP"}\n',
        'description: "modes of operation: CSP"}\n  - {index: 0x6098, sub_index: 0, type: int8, value: 1}\n',
    )
    with pytest.raises(PdoMapError, match=r"sdo\[1\]\.index: 0x6098:00 is homing\.method"):
        fieldbus.drive_map_from_text(text + "homing: {method: 35}\n", "joint.yaml")


def test_homing_time_outs_per_axis_from_the_maps() -> None:
    slow, plain = _load("homing: {method: 17, timeout_ms: 2500}\n"), _load("")
    h = Homing.from_maps(Cia402Controller(3), [slow, plain, slow], cycle_time_us=2000)
    assert list(h.timeout_cycles) == [1250, 15_000, 1250]  # 30 s without a section
    with pytest.raises(ValueError, match="2 drive maps for 3 axes"):
        Homing.from_maps(Cia402Controller(3), [slow, plain], cycle_time_us=1000)
