"""--write-maps from scan results: one map per distinct device, valid files or none at all."""

from __future__ import annotations

from pathlib import Path

import pytest

from fieldbus.core.network import load_network
from fieldbus.errors import FieldbusError
from fieldbus.scan.model import Device, Identity, PdoEntry, ScannedPdo, entry_name, entry_type
from fieldbus.scan.writemaps import BusSpec, Placed, write_maps

BUS = BusSpec("ethercat", "eth0")


def _drive(tpdo_entries: list[PdoEntry], name: str = "Servo X") -> Device:
    rpdo = [ScannedPdo(0x1600, [PdoEntry(0x6040, 0, 16, "uint16", "controlword")])]
    return Device(name, Identity(0x99, 0x10, 2, 1234), rpdo, [ScannedPdo(0x1A00, tpdo_entries)])


def test_same_identity_other_mapping_gets_its_own_map(tmp_path: Path) -> None:
    a = _drive([PdoEntry(0x6041, 0, 16, "uint16", "statusword")])
    b = _drive([PdoEntry(0x6041, 0, 16, "uint16", "statusword"), PdoEntry(0x6064, 0, 32, "int32", "pos")])
    placed = [Placed(a, 0), Placed(b, 1), Placed(a, 2)]
    written = write_maps(placed, tmp_path, BUS, "fieldbus scan ethercat eth0")
    assert [p.name for p in written.maps] == ["servo_x.yaml", "servo_x_2.yaml"]
    net = load_network(written.network)
    maps = [s.map for s in net.buses[0].slaves]
    assert [len(m.tpdo[0].channels) for m in maps] == [1, 2, 1]
    assert all(m.profile == "cia402" and m.revision == 2 for m in maps)
    assert [s.name for s in net.buses[0].slaves] == ["servo_x_p0", "servo_x_2_p1", "servo_x_p2"]


def test_duplicate_names_in_a_direction_are_made_unique(tmp_path: Path) -> None:
    d = _drive([PdoEntry(0x6041, 0, 16, "uint16", "x"), PdoEntry(0x6000, 1, 16, "uint16", "x")])
    written = write_maps([Placed(d, 0)], tmp_path, BUS, "scan")
    chans = load_network(written.network).buses[0].slaves[0].map.tpdo[0].channels
    assert [c.name for c in chans] == ["x", "x_2"]


def test_nothing_is_written_when_a_map_would_not_validate(tmp_path: Path) -> None:
    d = _drive([PdoEntry(0x6041, 0, 16, "uint16", "statusword")])
    d.rpdo[0].entries.append(PdoEntry(0x2000, 0, 0, entry_type(0x2000, 0, 0)[0], "odd"))  # a 0-bit entry
    with pytest.raises(FieldbusError, match="does not validate"):
        write_maps([Placed(d, 0)], tmp_path / "out", BUS, "scan")
    assert not (tmp_path / "out").exists()


def test_entry_types_and_names() -> None:
    assert entry_type(0x6064, 0, 32, 0x0004) == ("int32", "sdo-info")
    assert entry_type(0x6064, 0, 32) == ("int32", "cia402")  # no SDO Information: CiA 402 table
    assert entry_type(0x2000, 0, 16) == ("uint16", "guess")
    assert entry_type(0x2000, 0, 12) == ("bit12", "guess")
    assert entry_type(0x6064, 0, 32, 0x0007) == ("uint32", "sdo-info")  # the device's word wins
    assert entry_name(0x6041, 0, "Status Word") == "status_word"
    assert entry_name(0x6041, 0, None) == "statusword"
    assert entry_name(0x2000, 3, "  ") == "x2000_03"


def test_padding_entries_are_written_as_unnamed_gaps(tmp_path: Path) -> None:
    # an Elmo-style fixed PDO ends in 8 bits of padding (0x0000:00) and a dummy int16 (0x0003:00)
    d = _drive([PdoEntry(0x6041, 0, 16, "uint16", "statusword"), PdoEntry(0x0000, 0, 8, "uint8", "x0000_00")])
    d.rpdo[0].entries += [
        PdoEntry(0x0003, 0, 16, "uint16", "x0003_00"),
        PdoEntry(0x0000, 0, 8, "uint8", "pad"),
    ]
    written = write_maps([Placed(d, 0)], tmp_path, BUS, "scan")
    m = load_network(written.network).buses[0].slaves[0].map
    assert [(c.index, c.bits, c.is_gap) for c in m.rpdo[0].channels] == [
        (0x6040, 16, False),
        (0x0003, 16, True),
        (0x0000, 8, True),
    ]
    assert [(c.index, c.bits, c.is_gap) for c in m.tpdo[0].channels] == [(0x6041, 16, False), (0, 8, True)]
