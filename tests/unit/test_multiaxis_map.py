"""Drive maps with ``axes:`` (multi-axis CiA 402 slaves): the whole device as the bus sees it, and errors."""

from __future__ import annotations

from pathlib import Path

import pytest

from fieldbus.core.pdo.load import drive_map_from_text, load_drive_map
from fieldbus.core.sdo.plan import coe_plan
from fieldbus.errors import PdoMapError

TWO_AXIS = Path(__file__).resolve().parents[2] / "pdo_maps" / "generic_cia402_2axis.yaml"

BASE = """\
name: two
vendor_id: 1
product_id: 2
profile: cia402
{axes}
sdo:
  - {{index: 0x6060, sub_index: 0, type: int8, value: 8}}
  - {{index: 0x2000, sub_index: 0, type: uint8, value: 1}}
rpdo:
  - index: 0x1600
    channels:
      - {{index: 0x6040, sub_index: 0, type: uint16}}
      - {{index: 0x607A, sub_index: 0, type: int32}}
tpdo:
  - index: 0x1A00
    channels:
      - {{index: 0x6041, sub_index: 0, type: uint16}}
{extra}"""


def _map(axes: str, extra: str = "") -> str:
    return BASE.format(axes=axes, extra=extra)


def test_the_bus_sees_every_axis_at_its_offsets() -> None:
    drive = load_drive_map(TWO_AXIS)
    assert drive.axes == 2 and drive.object_offsets == (0, 0x800) and drive.pdo_offsets == (0, 0x10)
    bus = drive.bus_map
    assert [p.index for p in bus.rpdo] == [0x1600, 0x1601, 0x1610, 0x1611]
    assert [c.index for p in bus.rpdo[2:] for c in p.channels] == [0x6840, 0x687A, 0x68FF, 0x6871, 0x6860]
    assert drive.axis_index(0x603F, 1) == 0x683F and drive.axis_index(0x1018, 1) == 0x1018
    # the CoE plan maps and assigns both axes' PDOs and writes the mode to both axes
    writes = {(s.index, s.sub_index): s.data for s in coe_plan(drive).steps}
    assert writes[(0x1C12, 3)] == (0x1610).to_bytes(2, "little")
    assert writes[(0x1610, 1)] == (0x68400010).to_bytes(4, "little")
    assert writes[(0x6060, 0)] == writes[(0x6860, 0)] == b"\x08"


def test_explicit_offsets_per_axis() -> None:
    drive = drive_map_from_text(
        _map("axes: {count: 3, object_offsets: [0, 0x1000, 0x800], pdo_offsets: [0, 0x20, 0x40]}")
    )
    assert [p.index for p in drive.bus_map.rpdo] == [0x1600, 0x1620, 0x1640]
    assert [p.channels[0].index for p in drive.bus_map.rpdo] == [0x6040, 0x7040, 0x6840]
    # a start-up SDO to an axis object goes to each axis; a device object (0x2000) once
    assert [s.index for s in drive.bus_map.sdo] == [0x6060, 0x2000, 0x7060, 0x6860]


@pytest.mark.parametrize(
    ("axes", "extra", "line", "field", "words"),
    [
        ("axes: 9", "", 5, "axes", "9"),
        (
            "axes: {count: 2, object_offsets: [0, 0x400]}",
            "",
            5,
            "axes.object_offsets[1]",
            "multiple of 0x800",
        ),
        ("axes: {count: 2, object_offsets: [0]}", "", 5, "axes.object_offsets", "1 offsets for 2 axes"),
        ("axes: {count: 3, pdo_offsets: [0, 0x10, 0x10]}", "", 5, "axes.pdo_offsets[2]", "given twice"),
        ("axes: {cuont: 2}", "", 5, "axes.cuont", "did you mean count"),
        (
            "axes: 2",
            "      - {index: 0x2001, sub_index: 0, type: uint16}\n",
            18,
            "tpdo[0].channels[1].index",
            "not a CiA 402 axis object",
        ),
        ("axes: 2", "      - {index: 0, sub_index: 0, type: bit4}\n", 14, "tpdo", "whole bytes"),
    ],
)
def test_a_wrong_axes_section_names_file_line_and_field(
    axes: str, extra: str, line: int, field: str, words: str
) -> None:
    with pytest.raises(PdoMapError) as err:
        drive_map_from_text(_map(axes, extra), file="two.yaml")
    text = str(err.value)
    assert text.startswith(f"two.yaml:{line}:"), text
    assert field in text and words in text, text


def test_bandwidth_and_validate_count_every_axis(tmp_path: Path) -> None:
    from fieldbus.commands.validate import map_summary, network_summary
    from fieldbus.core.bandwidth import bus_bandwidth
    from fieldbus.core.network import network_from_text

    net = network_from_text(
        f"buses:\n  - {{name: arm, type: ethercat, interface: eth0, slaves: [{{name: s, map: {TWO_AXIS}}}]}}\n"
    )
    slave = network_summary(net)["buses"][0]["slaves"][0]
    assert (slave["output_bytes"], slave["input_bytes"]) == (2 * 13, 2 * 15)
    assert bus_bandwidth(net.buses[0]).bytes_per_cycle == 2 * 13 + 2 * 15
    assert map_summary(net.buses[0].slaves[0].map)["axes"] == 2
