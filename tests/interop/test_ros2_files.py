"""The three real ethercat_driver_ros2 files load unchanged and lay out as their devices do."""

from __future__ import annotations

import math
from pathlib import Path

from fieldbus.core.pdo import Direction, load_drive_map
from fieldbus.core.pdo.layout import layout


def test_all_three_files_load(interop_dir: Path) -> None:
    files = sorted(interop_dir.glob("*.yaml"))
    assert [f.name for f in files] == [
        "beckhoff_ek1914.yaml",
        "beckhoff_el1918.yaml",
        "maxon_epos4_50_5.yaml",
    ]
    for f in files:
        drive = load_drive_map(f)
        assert drive.rpdo or drive.tpdo


def test_ek1914_txpdo_layout_is_bit_exact(interop_dir: Path) -> None:
    lay = layout(load_drive_map(interop_dir / "beckhoff_ek1914.yaml")).inputs
    a00 = [e for e in lay.entries if e.pdo_index == 0x1A00]
    assert [(e.channel.type.name, e.bit_offset, e.bits) for e in a00] == [
        ("int8", 0, 8),
        ("bool", 8, 1),
        ("bool", 9, 1),
        ("bit6", 10, 6),
        ("int16", 16, 16),
        ("int16", 32, 16),
    ]
    pdos = {p.index: (p.bit_offset, p.bits) for p in lay.pdos}
    assert pdos == {0x1A00: (0, 48), 0x1A01: (48, 16)}
    assert lay.size == 8
    assert [e.name for e in lay.channels if e.pdo_index == 0x1A01] == [
        "input_1",
        "input_2",
        "input_3",
        "input_4",
    ]


def test_el1918_sizes(interop_dir: Path) -> None:
    lay = layout(load_drive_map(interop_dir / "beckhoff_el1918.yaml"))
    assert lay.outputs.bits == 48 + 8 + 16
    assert lay.inputs.bits == 48 + 16
    assert lay.outputs.entry("safety_states").byte_offset == 6


def test_epos4_scaling_defaults_and_sdos(interop_dir: Path) -> None:
    drive = load_drive_map(interop_dir / "maxon_epos4_50_5.yaml")
    assert (drive.vendor_id, drive.product_id, drive.assign_activate) == (0xFB, 0x63500000, 0x0300)
    assert drive.auto_fault_reset is True
    pos = drive.find(Direction.OUTPUTS, 0x607A)
    assert pos is not None and pos.name == "position" and math.isclose(pos.factor, 8769.23076923077)
    assert pos.default is None  # .nan means "no default"
    mode = drive.find(Direction.OUTPUTS, 0x6060)
    assert mode is not None and mode.default == 9
    assert [(s.index, s.sub_index, s.data) for s in drive.sdo] == [(0x60C2, 1, b"\x0a"), (0x60C2, 2, b"\xfd")]
    assert layout(drive).outputs.size == 23 and layout(drive).inputs.size == 25
