"""`fieldbus import esi` on real ESI files from public projects (tests/data/esi, see SOURCE.md).

Three shapes: a file with several devices and two revisions of one product and no
CoE (AB&T EasyCAT), a digital I/O board whose PDOs are single bits (rt-labs'
EVB-LAN9252 demo), and a robot actuator with CoE and DC whose TxPDOs break the
ETG index ranges (Pollen Robotics' Orbita2d): refused, with the line and the rule.
Expected values below were read from the files by hand.
"""

from __future__ import annotations

from pathlib import Path

import pytest

from fieldbus import load_drive_map
from fieldbus.cli import main
from fieldbus.errors import PdoMapError
from fieldbus.interop.esi import EsiDeviceChoiceError, import_esi_file, list_devices

DATA = Path(__file__).resolve().parents[1] / "data" / "esi"
EASYCAT = DATA / "abt_easycat_v2_0.xml"
EVB9252 = DATA / "rtlabs_evb9252_dig.xml"
ORBITA = DATA / "pollen_orbita2d.xml"


def test_several_devices_and_revisions_are_listed_and_one_is_chosen(tmp_path: Path) -> None:
    devices = list_devices(EASYCAT.read_bytes(), str(EASYCAT))
    assert [(d.type, d.product_code, d.revision) for d in devices] == [
        ("EasyCAT 32+32", 0x00DEFEDE, 0x5A00),
        ("EasyCAT 16+16 rev 1", 0xDEFEDE16, 0x5A01),
        ("EasyCAT 32+32 rev 1", 0x00DEFEDE, 0x5A01),
        ("EasyCAT 64+64 rev 1", 0xDEFEDE64, 0x5A01),
        ("EasyCAT 128+128 rev 1", 0xDEFED128, 0x5A01),
        ("EasyCAT configurable rev 1", 0xDEFEDECF, 0x5A01),
    ]
    with pytest.raises(EsiDeviceChoiceError):
        import_esi_file(str(EASYCAT))
    # one product code, two revisions: the revision picks one
    old = import_esi_file(str(EASYCAT), device="0x00DEFEDE:0x5A00")
    new = import_esi_file(str(EASYCAT), device="0x00DEFEDE:0x5A01")
    assert (old.drive.revision, new.drive.revision) == (0x5A00, 0x5A01)
    assert old.drive.vendor_id == 0x079A and old.drive.product_id == 0x00DEFEDE
    assert old.drive.ethercat is not None and not old.drive.ethercat.coe  # no mailbox at all
    # 32 output and 32 input bytes, each mapped at the CiA 301 dummy object 0x0005 (UNSIGNED8)
    assert [sum(c.bits for c in p.channels) for p in old.drive.rpdo] == [32 * 8]
    assert [sum(c.bits for c in p.channels) for p in old.drive.tpdo] == [32 * 8]
    assert any("0x0005" in w and "dummy" in w for w in old.warnings)
    out = tmp_path / "easycat.yaml"
    assert main(["import", "esi", str(EASYCAT), "--device", "EasyCAT 64+64 rev 1", "-o", str(out)]) == 0
    assert load_drive_map(out).product_id == 0xDEFEDE64


def test_bit_entries_of_a_digital_io_board(tmp_path: Path) -> None:
    got = import_esi_file(str(EVB9252))
    d = got.drive
    assert (d.vendor_id, d.product_id, d.revision) == (0x1337, 1234, 0)
    assert [(c.index, c.sub_index, c.type.name) for c in d.rpdo[0].channels] == [
        *[(0x7000, i, "bool") for i in range(1, 7)],
        (0, 0, "bit2"),  # padding to the byte
    ]
    assert [c.name for c in d.rpdo[0].channels if not c.is_gap] == [f"led{i}" for i in range(6)]
    assert [(c.index, c.sub_index, c.type.name) for c in d.tpdo[0].channels][:6] == [
        (0x6000, i, "bool") for i in range(1, 7)
    ]
    out = tmp_path / "evb.yaml"
    out.write_text(got.text)
    assert main(["validate", str(out)]) == 0


def test_a_txpdo_outside_the_etg_range_is_refused_where_it_is_written() -> None:
    """Orbita2d's TxPDOs are 0x1700 and 0x1800 (ETG.1000.6: 0x1A00-0x1BFF); nothing is guessed."""
    with pytest.raises(PdoMapError, match=r"TxPdo index 0x1700 is outside 0x1A00-0x1BFF") as info:
        import_esi_file(str(ORBITA))
    assert info.value.line == 119  # the <Index> of the first TxPdo
    assert "Descriptions/Devices/Device/TxPdo" in str(info.value)
