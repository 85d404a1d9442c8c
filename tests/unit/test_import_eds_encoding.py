"""EDS files that are not UTF-8: read as Windows-1252, else Latin-1, and say so.

``cp1252_comment.eds`` (tests/data/eds, written for these tests) is a small CiA 402 servo
EDS whose third line, a comment, holds one Windows-1252 byte (0x94, a closing quotation
mark), as real vendor files edited on Windows do. canopen's own parser reading the same
file as cp1252 is the oracle for what the import must give.
"""

from __future__ import annotations

import codecs
import io
from pathlib import Path

import canopen
import pytest

from fieldbus.cli import main
from fieldbus.interop.device import load_device
from fieldbus.interop.eds import import_eds

DATA = Path(__file__).resolve().parents[1] / "data" / "eds"
CP1252 = DATA / "cp1252_comment.eds"


def _mapping(od: canopen.objectdictionary.ObjectDictionary, index: int) -> list[tuple[int, int, int]]:
    raws = [od[index][s].default for s in range(1, od[index][0].default + 1)]
    return [(r >> 16, (r >> 8) & 0xFF, r & 0xFF) for r in raws]


def test_a_cp1252_eds_imports_and_says_how_it_was_read() -> None:
    raw = CP1252.read_bytes()
    assert [b for b in raw if b > 0x7F] == [0x94]  # the one byte that is not UTF-8
    r = import_eds(CP1252)
    assert r.warnings == ("not UTF-8 (byte 0x94 on line 3): read as Windows-1252 (cp1252)",)
    assert "# warning: not UTF-8 (byte 0x94 on line 3): read as Windows-1252 (cp1252)" in r.text
    fp = io.StringIO(CP1252.read_bytes().decode("cp1252"))
    fp.name = CP1252.name
    od = canopen.objectdictionary.import_od(fp)
    d = r.drive
    assert (d.vendor_id, d.product_id, d.revision) == (0x0F00, 0x1252, 0x00010000)
    assert d.profile == "cia402"
    for pdo in (*d.rpdo, *d.tpdo):
        assert [(c.index, c.sub_index, c.bits) for c in pdo.channels] == _mapping(od, pdo.index)
    assert [p.index for p in d.rpdo] == [0x1600] and [p.index for p in d.tpdo] == [0x1A00]


def test_a_byte_cp1252_leaves_undefined_falls_back_to_latin1(tmp_path: Path) -> None:
    odd = tmp_path / "latin1.eds"
    odd.write_bytes(CP1252.read_bytes().replace(b"\x94", b"\x81"))  # 0x81: no character in cp1252
    r = import_eds(odd)
    assert r.warnings == ("not UTF-8 (byte 0x81 on line 3): read as Latin-1 (ISO 8859-1)",)
    assert [p.index for p in r.drive.rpdo] == [0x1600]


def test_utf8_with_or_without_a_bom_reads_without_a_note(tmp_path: Path) -> None:
    text = CP1252.read_bytes().decode("cp1252")
    plain, bom = tmp_path / "plain.eds", tmp_path / "bom.eds"
    plain.write_bytes(text.encode("utf-8"))
    bom.write_bytes(codecs.BOM_UTF8 + text.encode("utf-8"))
    for path in (plain, bom):
        r = import_eds(path)
        assert r.warnings == ()
        assert r.drive.vendor_id == 0x0F00
    from fieldbus.interop.eds import decode_vendor_text

    assert decode_vendor_text("Ä".encode()) == ("Ä", None)


def test_the_emulators_and_the_cli_read_it_too(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert load_device(CP1252).product_id == 0x1252  # what python -m sim_slaves.* --map uses
    out = tmp_path / "servo.yaml"
    assert main(["import", "eds", str(CP1252), "-o", str(out)]) == 0
    err = capsys.readouterr().err
    assert "warning: not UTF-8 (byte 0x94 on line 3): read as Windows-1252 (cp1252)" in err
    assert "flange" not in err  # the file's text is never quoted
    assert main(["validate", str(out)]) == 0
