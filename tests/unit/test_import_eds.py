"""fieldbus import eds: EDS/DCF -> drive map, compared with canopen's own reading of the files."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import canopen
import pytest

from fieldbus import load_drive_map
from fieldbus.cli import main
from fieldbus.core.pdo.model import Direction
from fieldbus.errors import BackendUnavailableError, PdoMapError
from fieldbus.interop.eds import import_eds

DATA = Path(__file__).resolve().parents[1] / "data" / "eds"
SAMPLE = DATA / "canopen_sample.eds"  # canopen's test/sample.eds (a DCF-like EDS with NodeID=2)
SIMPLE = DATA / "ros2_canopen_simple.eds"


def _od_mapping(od: canopen.objectdictionary.ObjectDictionary, index: int) -> list[tuple[int, int, int]]:
    count = od[index][0].default
    raws = [od[index][s].default for s in range(1, count + 1)]
    return [(r >> 16, (r >> 8) & 0xFF, r & 0xFF) for r in raws]


@pytest.mark.parametrize("path", [SAMPLE, SIMPLE], ids=lambda p: p.name)
def test_each_file_imports_and_validates(path: Path, tmp_path: Path) -> None:
    r = import_eds(path)
    out = tmp_path / "map.yaml"
    out.write_text(r.text)
    d = load_drive_map(out)
    assert d.canopen is not None
    assert main(["validate", str(out)]) == 0


def test_sample_matches_canopen_reading() -> None:
    od = canopen.objectdictionary.import_od(str(SAMPLE))
    d = import_eds(SAMPLE).drive
    assert d.vendor_id == od[0x1018][1].value == 1  # ParameterValue of the DCF-style file
    assert d.profile == "cia402"
    for pdo in (*d.rpdo, *d.tpdo):
        mapped = [(c.index, c.sub_index, c.bits) for c in pdo.channels if c.index]
        assert mapped == _od_mapping(od, pdo.index)
        assert pdo.canopen is not None
    assert [p.index for p in d.rpdo] == [0x1600, 0x1601, 0x1602, 0x1603]
    assert [p.index for p in d.tpdo] == [0x1A00, 0x1A01, 0x1A02, 0x1A03]
    # names from the object dictionary where it has the object
    rp1 = d.rpdo[0].channels[0]
    assert rp1.name == "integer16_value" and od[0x2001].name == "INTEGER16 value"
    # 0x2001 (INTEGER16) mapped with 50 bits: kept as 50 bits, padded to whole bytes
    assert (rp1.type.name, d.rpdo[0].channels[1].type.name) == ("bit50", "bit6")
    # COB-IDs from $NODEID+512 etc., relative; transmission types as in 0x1400/0x1800 sub 2
    assert [(p.canopen.cob_id, p.canopen.cob_id_absolute) for p in d.rpdo if p.canopen] == [
        (0x200, False), (0x300, False), (0x400, False), (0x500, False),
    ]  # fmt: skip
    assert (
        [p.canopen.transmission_type for p in d.tpdo if p.canopen]
        == [od[0x1800 + i][2].default for i in range(4)]
        == [255, 255, 0, 0]
    )
    assert d.canopen.heartbeat_ms == od[0x1017].default == 0
    # objects missing from the EDS get their CiA 402 type
    assert d.find(Direction.OUTPUTS, 0x607A) is not None
    assert d.find(Direction.OUTPUTS, 0x607A).type.name == "int32"  # type: ignore[union-attr]


def test_simple_matches_canopen_reading() -> None:
    od = canopen.objectdictionary.import_od(str(SIMPLE))
    r = import_eds(SIMPLE)
    assert (r.drive.vendor_id, r.drive.product_id) == (0x360, 0)
    assert od[0x1600][0].default is None  # canopen does not read the [1600Value] compact mapping
    assert r.drive.rpdo == () and r.drive.tpdo == ()
    assert any("RPDO1 (0x1600): maps nothing" in s for s in r.skipped)


def test_node_id_and_absolute_cob_ids(tmp_path: Path) -> None:
    text = SAMPLE.read_text().replace("DefaultValue=$NODEID+768", "DefaultValue=0x311")
    d = import_eds(tmp_path / "x.eds", text=text, node_id=0x11).drive
    pdo = d.rpdo[1]
    assert pdo.canopen is not None and (pdo.canopen.cob_id, pdo.canopen.cob_id_absolute) == (0x300, False)
    d = import_eds(tmp_path / "x.eds", text=text, node_id=0x12).drive
    pdo = d.rpdo[1]
    assert pdo.canopen is not None and (pdo.canopen.cob_id, pdo.canopen.cob_id_absolute) == (0x311, True)
    invalid = SAMPLE.read_text().replace("DefaultValue=$NODEID+896", "DefaultValue=0x80000380")
    r = import_eds(tmp_path / "y.eds", text=invalid)
    assert [p.index for p in r.drive.tpdo] == [0x1A00, 0x1A01, 0x1A03]
    assert any("TPDO3 (0x1A02): COB-ID 0x80000380 is invalid" in s for s in r.skipped)


def test_errors_name_the_file(tmp_path: Path) -> None:
    with pytest.raises(PdoMapError, match=r"bad\.eds: canopen could not read this EDS/DCF"):
        import_eds(tmp_path / "bad.eds", text="[DeviceInfo\nVendorNumber=1\n")
    with pytest.raises(PdoMapError, match=r"map\.txt: expected an \.eds or \.dcf file"):
        import_eds(tmp_path / "map.txt", text="")
    with pytest.raises(PdoMapError, match=r"missing\.eds: cannot read"):
        import_eds(tmp_path / "missing.eds")


def test_without_canopen_the_error_names_the_extra(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setitem(sys.modules, "canopen", None)
    with pytest.raises(BackendUnavailableError, match=r"pip install 'fieldbus\[interop\]'"):
        import_eds(SAMPLE)
    assert main(["import", "eds", str(SAMPLE)]) == 1


def test_cli_import_eds(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "sample.yaml"
    assert main(["import", "eds", str(SAMPLE), "-o", str(out), "--node-id", "5"]) == 0
    assert load_drive_map(out).rpdo[0].canopen is not None
    capsys.readouterr()
    assert main(["import", "eds", str(SAMPLE), "--json"]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert doc["ok"] and doc["map"]["canopen"] is True and len(doc["map"]["outputs"]["pdo"]) == 4
