"""`fieldbus import esi` on real ESI files from public projects (tests/data/esi, see SOURCE.md).

Three shapes: a file with several devices and two revisions of one product and no
CoE (AB&T EasyCAT), a digital I/O board whose PDOs are single bits (rt-labs'
EVB-LAN9252 demo), and a robot actuator with CoE and DC whose TxPDOs break the
ETG index ranges (Pollen Robotics' Orbita2d): its assignment is fixed, so they are kept, with a warning.
Expected values below were read from the files by hand.
"""

from __future__ import annotations

from pathlib import Path

import pytest

from fieldbus import load_drive_map
from fieldbus.cli import main
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


def test_a_fixed_assignment_servo_imports_as_the_device_names_its_pdos(tmp_path: Path) -> None:
    """Orbita2d: CoE without PdoAssign/PdoConfig (line 250), so its own assignment and mapping are used;
    its TxPDOs are 0x1700 and 0x1800 (ETG.1000.6: 0x1A00-0x1BFF), kept with a warning naming the line."""
    r = import_esi_file(str(ORBITA))
    d = r.drive
    assert (d.vendor_id, d.product_id, d.revision) == (0xF3F, 0x1, 0x1)
    assert d.ethercat.pdo_assign is False and d.ethercat.coe
    assert [p.index for p in d.rpdo] == [0x1600] and [p.index for p in d.tpdo] == [0x1700, 0x1800]
    assert all(p.fixed for p in (*d.rpdo, *d.tpdo))
    assert [w.split(":")[0] for w in r.warnings if "outside" in w] == ["line 119", "line 194"]
    # out: UINT16 + UINT8 + 10 REAL = 344 bits; in: 0x1700 UINT16 + UINT8 + 8 REAL = 280,
    # 0x1800 3 UINT16 + UINT8 + 6 REAL = 248 (REAL is float; UINT16/UINT8 are taken as uint16/uint8)
    assert [c.type.name for c in d.rpdo[0].channels][:3] == ["uint16", "uint8", "float"]
    assert [p.bits for p in (*d.rpdo, *d.tpdo)] == [344, 280, 248]
    assert d.profile is None  # the file maps 0x6041 in its RxPDO and 0x6040 in its TxPDO
    assert d.assign_activate == 0x0300  # DC mode DC_Sync
    out = tmp_path / "orbita2d.yaml"
    out.write_text(r.text)
    assert load_drive_map(out).tpdo == d.tpdo  # what was written loads back as the same map
