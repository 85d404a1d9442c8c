"""`fieldbus import eds` on two servo drive makers' files (tests/data/eds, see SOURCE.md).

- ``technosoft_ipos.eds``: Technosoft's EDS of the iPOS drives (CiA 402, CRLF line ends).
  Its TPDO3 and TPDO4 are disabled by default: their COB-IDs are written
  ``$NODEID+0x80000380`` and ``$NODEID+0x80000480`` (bit 31 set).
- ``elmo_gold.dcf``: a DCF of an Elmo Gold drive (CiA 402). Most of its mapping is
  given only as DCF ``ParameterValue`` (no ``DefaultValue``), and ParameterValue
  overrides the DefaultValue of the transmission types (255 -> 1).

Every expected value below was read from the files by hand (the line is named
where it matters); the mappings are also compared with canopen's own reading.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import canopen
import pytest

from fieldbus import load_drive_map
from fieldbus.cli import main
from fieldbus.interop.eds import import_eds

DATA = Path(__file__).resolve().parents[1] / "data" / "eds"
IPOS = DATA / "technosoft_ipos.eds"
ELMO = DATA / "elmo_gold.dcf"


def _val(var: Any) -> Any:
    """canopen's DCF ParameterValue, else the DefaultValue."""
    return var.value if getattr(var, "value", None) is not None else var.default


def _od_mapping(od: Any, index: int) -> list[tuple[int, int, int]]:
    count = _val(od[index][0])
    raws = [_val(od[index][s]) for s in range(1, count + 1)]
    return [(r >> 16, (r >> 8) & 0xFF, r & 0xFF) for r in raws]


def _mapped(pdo: Any) -> list[tuple[int, int, int]]:
    return [(c.index, c.sub_index, c.bits) for c in pdo.channels if not c.is_gap]


def _can(drive: Any) -> dict[int, tuple[Any, ...]]:
    return {
        p.index: (p.canopen.cob_id, p.canopen.cob_id_absolute, p.canopen.transmission_type)
        for p in (*drive.rpdo, *drive.tpdo)
        if p.canopen is not None
    }


def test_files_are_the_copies_described_in_source_md() -> None:
    # sizes as in SOURCE.md; both keep their CRLF line ends
    assert len(IPOS.read_bytes()) == 46497 and IPOS.read_bytes().count(b"\r\n") == 3035
    assert len(ELMO.read_bytes()) == 71916 and ELMO.read_bytes().count(b"\r\n") == 4503


@pytest.mark.parametrize("path", [IPOS, ELMO], ids=lambda p: p.name)
def test_each_file_imports_validates_and_round_trips_through_the_cli(path: Path, tmp_path: Path) -> None:
    r = import_eds(path)
    out = tmp_path / "map.yaml"
    out.write_text(r.text)
    d = load_drive_map(out)
    assert d.canopen is not None and d.profile == "cia402"
    assert main(["validate", str(out)]) == 0
    cli_out = tmp_path / "cli.yaml"
    assert main(["import", "eds", str(path), "--node-id", "5", "-o", str(cli_out)]) == 0
    assert load_drive_map(cli_out).vendor_id == d.vendor_id


def test_technosoft_ipos_identity_mapping_and_communication(tmp_path: Path) -> None:
    od = canopen.objectdictionary.import_od(str(IPOS))
    r = import_eds(IPOS, node_id=5)
    d = r.drive
    # [DeviceInfo] VendorNumber=0x000001A3 and [1018sub1] DefaultValue=0x000001A3;
    # [1018sub2]/[1018sub3] have no DefaultValue and [DeviceInfo] has no ProductNumber
    assert (d.vendor_id, d.product_id, d.revision) == (0x1A3, 0, 0)
    assert any("no product code" in w for w in r.warnings)
    assert d.profile == "cia402"
    # [1600sub1..] .. [1603sub2]: CiA 402 control word plus one command object each
    assert [(p.index, _mapped(p)) for p in d.rpdo] == [
        (0x1600, [(0x6040, 0, 16)]),
        (0x1601, [(0x6040, 0, 16), (0x6060, 0, 8)]),
        (0x1602, [(0x6040, 0, 16), (0x607A, 0, 32)]),
        (0x1603, [(0x6040, 0, 16), (0x60FF, 0, 32)]),
    ]
    for p in d.rpdo:
        assert _mapped(p) == _od_mapping(od, p.index)
    # DataType 0x0006 (UNSIGNED16), 0x0002 (INTEGER8), 0x0004 (INTEGER32)
    assert [c.type.name for c in d.rpdo[3].channels] == ["uint16", "int32"]
    assert d.rpdo[1].channels[1].type.name == "int8"
    # TPDO1/TPDO2 ([1A00], [1A01]); TPDO3/TPDO4 are disabled by their COB-IDs (lines 983, 1030)
    assert [(p.index, _mapped(p)) for p in d.tpdo] == [
        (0x1A00, [(0x6041, 0, 16)]),
        (0x1A01, [(0x6041, 0, 16), (0x6061, 0, 8)]),
    ]
    assert [s.split(":")[0] for s in r.skipped] == ["TPDO3 (0x1A02)", "TPDO4 (0x1A03)"]
    assert "0x80000385" in r.skipped[0] and "0x80000485" in r.skipped[1]  # $NODEID+0x80000380, node 5
    # $NODEID+0x200 .. +0x500 and +0x180/+0x280: relative; Transmission type DefaultValue=0x01
    assert _can(d) == {
        0x1600: (0x200, False, 1), 0x1601: (0x300, False, 1),
        0x1602: (0x400, False, 1), 0x1603: (0x500, False, 1),
        0x1A00: (0x180, False, 1), 0x1A01: (0x280, False, 1),
    }  # fmt: skip
    # [1800sub3] Inhibit Time DefaultValue=0x012C, [1800sub5] Event timer DefaultValue=0
    tp1 = d.tpdo[0].canopen
    assert tp1 is not None and (tp1.inhibit_time, tp1.event_timer) == (0x012C, 0)
    assert d.canopen is not None and d.canopen.heartbeat_ms == 0  # [1017] DefaultValue=0


def test_technosoft_ipos_disabled_tpdos_are_left_out_without_a_node_id() -> None:
    # bit 31 of a $NODEID-relative COB-ID (lines 983, 1030) counts before the node id is known
    r = import_eds(IPOS)
    assert [p.index for p in r.drive.tpdo] == [0x1A00, 0x1A01]
    assert list(r.skipped) == [
        "TPDO3 (0x1A02): COB-ID $NODEID+0x80000380 is invalid (bit 31) by default",
        "TPDO4 (0x1A03): COB-ID $NODEID+0x80000480 is invalid (bit 31) by default",
    ]


def test_elmo_gold_dcf_parameter_values_are_used() -> None:
    od = canopen.objectdictionary.import_od(str(ELMO))
    r = import_eds(ELMO)
    d = r.drive
    # [1018sub1] DefaultValue=0x0000009A; [1018sub2]/[1018sub3] empty, so [DeviceInfo]
    # ProductNumber=0x00030923 and RevisionNumber=0x000103F6
    assert (d.vendor_id, d.product_id, d.revision) == (0x9A, 0x00030923, 0x000103F6)
    assert d.profile == "cia402"
    # mappings written only as ParameterValue ([1600sub2], [1602sub1], [1603sub1], [1A00sub3] ...)
    assert [(p.index, _mapped(p)) for p in d.rpdo] == [
        (0x1600, [(0x6040, 0, 16), (0x6060, 0, 8)]),
        (0x1602, [(0x607A, 0, 32), (0x60FF, 0, 32)]),
        (0x1603, [(0x60C1, 1, 32)]),
    ]
    assert [(p.index, _mapped(p)) for p in d.tpdo] == [
        (0x1A00, [(0x6041, 0, 16), (0x6061, 0, 8), (0x2041, 0, 32)]),
        (0x1A02, [(0x6064, 0, 32), (0x606C, 0, 32)]),
    ]
    for p in (*d.rpdo, *d.tpdo):
        assert _mapped(p) == _od_mapping(od, p.index)
    # [1601sub0], [1A01sub0], [1A03sub0] have neither DefaultValue nor ParameterValue
    assert sorted(s.split(":")[0] for s in r.skipped) == [
        "RPDO2 (0x1601)",
        "TPDO2 (0x1A01)",
        "TPDO4 (0x1A03)",
    ]
    # [2041] Timestamp DataType=0x0007; [60C1sub1] DataType=0x0004
    ts = d.tpdo[0].channels[2]
    assert (ts.type.name, ts.name) == ("uint32", "timestamp")
    assert d.rpdo[2].channels[0].type.name == "int32"
    # COB-IDs $NODEID+0x200/0x400/0x500, $NODEID+0x180/0x380; Transmission Type
    # DefaultValue=255 but ParameterValue=0x1: the DCF value wins
    assert _can(d) == {
        0x1600: (0x200, False, 1), 0x1602: (0x400, False, 1), 0x1603: (0x500, False, 1),
        0x1A00: (0x180, False, 1), 0x1A02: (0x380, False, 1),
    }  # fmt: skip
    assert od[0x1400][2].default == 255 and od[0x1400][2].value == 1
    assert d.canopen is not None and d.canopen.heartbeat_ms == 0  # [1017] DefaultValue=0
