"""fieldbus import esi: ESI XML -> drive map (fieldbus.interop.esi, fieldbus.commands.import_)."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from fieldbus import load_drive_map
from fieldbus.cli import main
from fieldbus.core.pdo.load import drive_map_from_text
from fieldbus.core.pdo.model import Direction
from fieldbus.core.sdo.plan import StepKind, coe_plan
from fieldbus.errors import PdoMapError
from fieldbus.interop.esi import EsiDeviceChoiceError, import_esi, list_devices, parse_int

# A small ESI written for these tests (not a vendor file): a CiA 402 drive with CoE, DC,
# an alternative RxPDO, a bit entry, a gap, and values in hex (#x) and decimal.
SERVO = """<?xml version="1.0" encoding="ISO-8859-1"?>
<EtherCATInfo Version="1.6">
  <Vendor><Id>#x000000AB</Id><Name>Test vendor</Name></Vendor>
  <Descriptions><Devices>
    <Device Physics="YY">
      <Type ProductCode="#x00001234" RevisionNo="65536">DRV1</Type>
      <Name LcId="1031">Servoregler</Name>
      <Name LcId="1033">Servo drive</Name>
      <Sm DefaultSize="256" StartAddress="#x1000" ControlByte="#x26" Enable="1">MBoxOut</Sm>
      <Sm DefaultSize="256" StartAddress="#x1100" ControlByte="#x22" Enable="1">MBoxIn</Sm>
      <Sm StartAddress="#x1200" ControlByte="#x64" Enable="1">Outputs</Sm>
      <Sm StartAddress="#x1300" ControlByte="#x20" Enable="1">Inputs</Sm>
      <RxPdo Sm="2" Mandatory="0"><Index>#x1600</Index><Name>RxPDO CSP</Name><Exclude>#x1601</Exclude>
        <Entry><Index>#x6040</Index><SubIndex>0</SubIndex><BitLen>16</BitLen><Name>Controlword</Name><DataType>UINT</DataType></Entry>
        <Entry><Index>#x607A</Index><SubIndex>0</SubIndex><BitLen>32</BitLen><Name>Target position</Name><DataType>DINT</DataType></Entry>
      </RxPdo>
      <RxPdo Fixed="1"><Index>#x1601</Index><Name>RxPDO CSV</Name><Exclude>#x1600</Exclude>
        <Entry><Index>#x6040</Index><SubIndex>0</SubIndex><BitLen>16</BitLen><Name>Controlword</Name><DataType>UINT</DataType></Entry>
        <Entry><Index>#x60FF</Index><SubIndex>0</SubIndex><BitLen>32</BitLen><Name>Target velocity</Name><DataType>DINT</DataType></Entry>
      </RxPdo>
      <TxPdo Sm="3" Fixed="1" Mandatory="1"><Index>6656</Index><Name>TxPDO</Name>
        <Entry><Index>#x6041</Index><SubIndex>0</SubIndex><BitLen>16</BitLen><Name>Statusword</Name><DataType>UINT</DataType></Entry>
        <Entry><Index>#x60FD</Index><SubIndex>0</SubIndex><BitLen>1</BitLen><Name>Limit switch</Name><DataType>BOOL</DataType></Entry>
        <Entry><Index>#x2001</Index><SubIndex>3</SubIndex><BitLen>3</BitLen><Name>Mode bits</Name><DataType>BIT3</DataType></Entry>
        <Entry><Index>#x0</Index><BitLen>4</BitLen></Entry>
        <Entry><Index>#x6064</Index><SubIndex>0</SubIndex><BitLen>32</BitLen><Name>Position actual value</Name><DataType>DINT</DataType></Entry>
        <Entry><Index>#x2002</Index><SubIndex>1</SubIndex><BitLen>32</BitLen><Name>Motor temperature</Name><DataType>REAL</DataType></Entry>
      </TxPdo>
      <Mailbox DataLinkLayer="true"><CoE SdoInfo="true" PdoAssign="true" PdoConfig="true"/></Mailbox>
      <Dc>
        <OpMode><Name>Synchron</Name><Desc>SM-Synchron</Desc><AssignActivate>#x0</AssignActivate></OpMode>
        <OpMode><Name>DC</Name><Desc>DC-Synchron</Desc><AssignActivate>#x300</AssignActivate>
          <CycleTimeSync0 Factor="1">0</CycleTimeSync0><ShiftTimeSync0>-2000</ShiftTimeSync0>
          <CycleTimeSync1 Factor="0">250000</CycleTimeSync1><ShiftTimeSync1>1000</ShiftTimeSync1></OpMode>
      </Dc>
    </Device>
  </Devices></Descriptions>
</EtherCATInfo>
"""

# Two products, one of them in two revisions; digital I/O without a mailbox, inputs on SM0.
MULTI = """<?xml version="1.0"?>
<EtherCATInfo>
  <Vendor><Id>2</Id><Name>Test vendor</Name></Vendor>
  <Descriptions><Devices>
    <Device><Type ProductCode="#x03f03052" RevisionNo="#x00100000">DI8</Type><Name LcId="1033">8 inputs</Name>
      <Sm DefaultSize="1" StartAddress="#x1000" ControlByte="#x00" Enable="1">Inputs</Sm>
      <TxPdo Fixed="1" Mandatory="1" Sm="0"><Index>#x1a00</Index><Name>Channel 1</Name>
        <Entry><Index>#x6000</Index><SubIndex>1</SubIndex><BitLen>1</BitLen><Name>Input</Name><DataType>BOOL</DataType></Entry></TxPdo>
      <TxPdo Fixed="1" Mandatory="1" Sm="0"><Index>#x1a01</Index><Name>Channel 2</Name>
        <Entry><Index>#x6010</Index><SubIndex>1</SubIndex><BitLen>1</BitLen><Name>Input</Name><DataType>BOOL</DataType></Entry></TxPdo>
    </Device>
    <Device><Type ProductCode="#x03f03052" RevisionNo="#x00110000">DI8</Type><Name LcId="1033">8 inputs</Name>
      <Sm DefaultSize="1" StartAddress="#x1000" ControlByte="#x00" Enable="1">Inputs</Sm>
      <TxPdo Fixed="1" Mandatory="1" Sm="0"><Index>#x1a00</Index><Name>Channel 1</Name>
        <Entry><Index>#x6000</Index><SubIndex>1</SubIndex><BitLen>1</BitLen><Name>Input</Name><DataType>BOOL</DataType></Entry></TxPdo>
      <TxPdo Fixed="1" Mandatory="1" Sm="0"><Index>#x1a01</Index><Name>Channel 2</Name>
        <Entry><Index>#x6010</Index><SubIndex>1</SubIndex><BitLen>1</BitLen><Name>Input</Name><DataType>BOOL</DataType></Entry></TxPdo>
      <TxPdo Fixed="1" Mandatory="1" Sm="0"><Index>#x1a02</Index><Name>Pad</Name>
        <Entry><Index>#x0</Index><BitLen>70</BitLen></Entry></TxPdo>
    </Device>
    <Device><Type ProductCode="#x07d83052" RevisionNo="#x00100000">DO8</Type><Name LcId="1033">8 outputs</Name>
      <Sm StartAddress="#xf00" ControlByte="#x44" Enable="1">Outputs</Sm>
      <RxPdo Fixed="1" Mandatory="1" Sm="0"><Index>#x1600</Index><Name>Channel 1</Name>
        <Entry><Index>#x7000</Index><SubIndex>1</SubIndex><BitLen>1</BitLen><Name>Output</Name><DataType>BOOL</DataType></Entry></RxPdo>
    </Device>
  </Devices></Descriptions>
</EtherCATInfo>
"""

BILLION_LAUGHS = """<?xml version="1.0"?>
<!DOCTYPE lolz [
 <!ENTITY lol "lol">
 <!ENTITY lol2 "&lol;&lol;&lol;&lol;&lol;&lol;&lol;&lol;&lol;&lol;">
 <!ENTITY lol3 "&lol2;&lol2;&lol2;&lol2;&lol2;&lol2;&lol2;&lol2;&lol2;&lol2;">
]>
<EtherCATInfo><Vendor><Id>&lol3;</Id></Vendor></EtherCATInfo>
"""

EXTERNAL = """<?xml version="1.0"?>
<!DOCTYPE x [
 <!ENTITY xxe SYSTEM "file:///etc/hostname">
]>
<EtherCATInfo><Vendor><Id>1</Id><Name>&xxe;</Name></Vendor></EtherCATInfo>
"""


def _line(text: str, needle: str) -> int:
    """1-based line of the first line of ``text`` containing ``needle``."""
    return next(i for i, line in enumerate(text.splitlines(), 1) if needle in line)


def test_servo_identity_pdos_and_dc() -> None:
    r = import_esi(SERVO, "servo.xml")
    d = r.drive
    assert (d.vendor_id, d.product_id, d.revision) == (0xAB, 0x1234, 65536)
    assert d.name == "drv1" and d.profile == "cia402"
    assert [p.index for p in d.rpdo] == [0x1600] and [p.index for p in d.tpdo] == [0x1A00]
    assert d.tpdo[0].fixed and not d.rpdo[0].fixed
    got = [
        (c.index, c.sub_index, c.bits, c.type.name, None if c.is_gap else c.name) for c in d.tpdo[0].channels
    ]
    assert got == [
        (0x6041, 0, 16, "uint16", "statusword"),
        (0x60FD, 0, 1, "bool", "digital_inputs"),
        (0x2001, 3, 3, "bit3", "mode_bits"),
        (0x0000, 0, 4, "bit4", None),
        (0x6064, 0, 32, "int32", "position_actual_value"),
        (0x2002, 1, 32, "float", "motor_temperature"),
    ]
    assert d.assign_activate == 0x0300
    assert d.ethercat.coe and d.ethercat.mailbox_size == 256
    assert d.ethercat.sync0_shift_ns == -2000 and d.ethercat.sync1_cycle_ns == 250000
    modes = {m.name: m for m in d.ethercat.dc_modes}
    assert set(modes) == {"Synchron", "DC"}
    assert modes["DC"].sync0_cycle_factor == 1 and modes["DC"].sync1_shift_ns == 1000
    assert [(s.index, s.type, s.pdo, s.watchdog) for s in d.sm] == [
        (0, "output", None, False), (1, "input", None, False), (2, "output", "rpdo", True), (3, "input", "tpdo", False),
    ]  # fmt: skip
    assert r.alternatives == ("0x1601 RxPDO CSV",)
    assert "Servo drive" in d.description  # the English name, not the German one


def test_without_pdo_assign_and_pdo_config_the_device_keeps_its_own() -> None:
    # ETG.2000: CoE@PdoAssign and @PdoConfig default to false - the master then neither assigns nor maps
    plain = SERVO.replace(' PdoAssign="true" PdoConfig="true"', "")
    r = import_esi(plain, "servo.xml")
    d = r.drive
    assert d.ethercat.pdo_assign is False and all(p.fixed for p in (*d.rpdo, *d.tpdo))
    assert "pdo_assign: false" in r.text
    plan = coe_plan(d)
    assert not {s.index for s in plan.steps} & {0x1C12, 0x1C13}  # the assignment is never written
    assert {s.index for s in plan.steps if s.kind is StepKind.VERIFY} == {0x1600, 0x1A00}  # mappings checked
    with pytest.raises(PdoMapError, match=r"the device's PDO assignment is fixed") as ei:
        import_esi(plain, "servo.xml", alternatives=["0x1601"])
    assert ei.value.line == _line(plain, "<CoE")
    # assignable, mapping fixed (a terminal with selectable predefined PDOs): assignment written, mapping verified
    d2 = import_esi(SERVO.replace(' PdoConfig="true"', ""), "servo.xml").drive
    assert d2.ethercat.pdo_assign and all(p.fixed for p in (*d2.rpdo, *d2.tpdo))
    assert {0x1C12, 0x1C13} <= {s.index for s in coe_plan(d2).steps}


def test_alternative_replaces_the_pdo_it_excludes() -> None:
    d = import_esi(SERVO, "servo.xml", alternatives=["0x1601"]).drive
    assert [p.index for p in d.rpdo] == [0x1601] and d.rpdo[0].fixed
    assert [c.name for c in d.rpdo[0].channels] == ["controlword", "target_velocity"]
    d2 = import_esi(SERVO, "servo.xml", alternatives=["RxPDO CSV"]).drive
    assert d2.rpdo == d.rpdo


def test_alternative_errors_name_the_choices() -> None:
    with pytest.raises(PdoMapError, match=r"--alternative 0x1605: no such PDO .*0x1601 RxPDO CSV"):
        import_esi(SERVO, "servo.xml", alternatives=["0x1605"])
    mandatory = SERVO.replace('<RxPdo Sm="2" Mandatory="0">', '<RxPdo Sm="2" Mandatory="1">')
    with pytest.raises(PdoMapError, match=r"excludes 0x1600 \(RxPDO CSP\), which is mandatory") as ei:
        import_esi(mandatory, "servo.xml", alternatives=["0x1601"])
    assert ei.value.file == "servo.xml" and ei.value.line == _line(SERVO, "<Index>#x1601</Index>")
    assert ei.value.path == "Descriptions/Devices/Device/RxPdo[2]"


def test_dc_mode_choice() -> None:
    assert import_esi(SERVO, "s.xml", dc_mode="none").drive.assign_activate == 0
    assert import_esi(SERVO, "s.xml", dc_mode="dc").drive.assign_activate == 0x300
    with pytest.raises(PdoMapError, match="no such DC mode; the device has Synchron, DC"):
        import_esi(SERVO, "s.xml", dc_mode="sync1")


def test_written_yaml_loads_and_validates(tmp_path: Path) -> None:
    out = tmp_path / "drv1.yaml"
    out.write_text(import_esi(SERVO, "servo.xml").text)
    d = load_drive_map(out)
    assert [c.name for c in d.channels(Direction.OUTPUTS)] == ["controlword", "target_position"]
    assert d.tpdo == import_esi(SERVO, "servo.xml").drive.tpdo
    assert main(["validate", str(out)]) == 0


def test_multi_device_lists_devices_and_picks() -> None:
    devs = list_devices(MULTI, "multi.xml")
    assert [(d.type, d.product_code, d.revision) for d in devs] == [
        ("DI8", 0x03F03052, 0x00100000), ("DI8", 0x03F03052, 0x00110000), ("DO8", 0x07D83052, 0x00100000),
    ]  # fmt: skip
    with pytest.raises(EsiDeviceChoiceError, match="describes 3 devices") as ei:
        import_esi(MULTI, "multi.xml")
    assert len(ei.value.devices) == 3
    with pytest.raises(EsiDeviceChoiceError, match=r"matches 2 revisions; add :REVISION"):
        import_esi(MULTI, "multi.xml", device="DI8")
    d = import_esi(MULTI, "multi.xml", device="di8:#x00100000").drive
    assert (d.product_id, d.revision, d.profile, d.ethercat.coe) == (0x03F03052, 0x00100000, None, False)
    assert [c.name for p in d.tpdo for c in p.channels] == ["channel_1_input", "channel_2_input"]
    assert [(s.index, s.type, s.pdo) for s in d.sm] == [(0, "input", "tpdo")]
    d = import_esi(MULTI, "multi.xml", device="0x07d83052").drive
    assert [(c.index, c.sub_index, c.type.name, c.name) for c in d.rpdo[0].channels] == [
        (0x7000, 1, "bool", "output")
    ]
    # a 70-bit gap is split into bitN entries of at most 64 bits
    d = import_esi(MULTI, "multi.xml", device="DI8:0x00110000").drive
    assert [c.type.name for c in d.tpdo[2].channels] == ["bit64", "bit6"]


def test_bad_device_names_the_choices() -> None:
    with pytest.raises(EsiDeviceChoiceError, match=r"--device EL9999 matches no device") as ei:
        import_esi(MULTI, "multi.xml", device="EL9999")
    text = str(ei.value)
    assert "DI8:0x00100000" in text and "DI8:0x00110000" in text and "DO8:0x00100000" in text


@pytest.mark.parametrize(
    ("doc", "what"),
    [
        (BILLION_LAUGHS, "entity declaration 'lol'"),
        (EXTERNAL, r"external entity 'xxe' \(file:///etc/hostname\)"),
    ],
)
def test_malicious_xml_is_refused(doc: str, what: str) -> None:
    with pytest.raises(
        PdoMapError, match=rf"refused: {what}; entity expansion and external entities are not allowed"
    ) as ei:
        import_esi(doc, "evil.xml")
    assert ei.value.file == "evil.xml" and ei.value.line == 3


def test_broken_xml_and_wrong_values_are_located() -> None:
    with pytest.raises(PdoMapError, match="not well-formed XML") as ei:
        import_esi("<EtherCATInfo>\n<Vendor>\n</EtherCATInfo>", "bad.xml")
    assert (ei.value.file, ei.value.line) == ("bad.xml", 3)
    bad = SERVO.replace(
        "<BitLen>32</BitLen><Name>Target position", "<BitLen>#xZZ</BitLen><Name>Target position"
    )
    with pytest.raises(PdoMapError, match=r"expected a number \(decimal or #x hex\), got '#xZZ'") as ei:
        import_esi(bad, "bad.xml")
    assert (
        ei.value.line == _line(bad, "#xZZ")
        and ei.value.path == "Descriptions/Devices/Device/RxPdo/Entry[2]/BitLen"
    )
    with pytest.raises(PdoMapError, match="not <EtherCATInfo>: not an ESI file"):
        import_esi("<EtherCATConfig/>", "eni.xml")


def test_types_and_numbers() -> None:
    assert parse_int("#x1A00") == 0x1A00 and parse_int("0x10") == 16 and parse_int(" 42 ") == 42
    assert parse_int("#xG") is None and parse_int(None) is None
    odd = SERVO.replace("<DataType>REAL</DataType>", "<DataType>UDINT24</DataType>")
    r = import_esi(odd, "s.xml")
    assert r.drive.tpdo[0].channels[-1].type.name == "bit32"
    assert any("UDINT24" in w for w in r.warnings)


def test_cli_import_esi(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    src = tmp_path / "servo.xml"
    src.write_text(SERVO, encoding="latin-1")
    out = tmp_path / "out.yaml"
    assert main(["import", "esi", str(src), "-o", str(out)]) == 0
    assert "drive map 'drv1'" in capsys.readouterr().out
    d = load_drive_map(out)
    assert d.product_id == 0x1234 and d.assign_activate == 0x300
    assert main(["import", "esi", str(src), "--alternative", "0x1601", "--json"]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert doc["ok"] and doc["map"]["outputs"]["pdo"][0]["index"] == "0x1601"
    assert drive_map_from_text(doc["yaml"], "x.yaml").rpdo[0].index == 0x1601
    multi = tmp_path / "multi.xml"
    multi.write_text(MULTI)
    assert main(["import", "esi", str(multi)]) == 2
    err = capsys.readouterr().err
    assert "describes 3 devices" in err and "DO8:0x00100000" in err
    assert main(["import", "esi", str(multi), "--device", "nope", "--json"]) == 2
    doc = json.loads(capsys.readouterr().out)
    assert not doc["ok"] and [d["type"] for d in doc["devices"]] == ["DI8", "DI8", "DO8"]
    assert main(["import", "esi", str(tmp_path / "missing.xml")]) == 1
    assert "cannot read" in capsys.readouterr().err
