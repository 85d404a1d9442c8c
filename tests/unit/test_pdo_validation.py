"""Each validation rule raises a PdoMapError naming the right file:line and field path."""

from __future__ import annotations

import textwrap
from pathlib import Path

import pytest

from fieldbus.core.network import load_network
from fieldbus.core.pdo import drive_map_from_text, load_drive_map
from fieldbus.errors import FieldbusError, PdoMapError

HEAD = "vendor_id: 0x2\nproduct_id: 0x10\n"


def err(text: str, file: str = "x.yaml") -> PdoMapError:
    with pytest.raises(PdoMapError) as info:
        drive_map_from_text(textwrap.dedent(text), file)
    return info.value


def line_of(text: str, needle: str) -> int:
    for n, line in enumerate(textwrap.dedent(text).splitlines(), start=1):
        if needle in line:
            return n
    raise AssertionError(needle)


def test_error_is_a_fieldbus_error_and_value_error() -> None:
    e = err("vendor_id: 1\n")
    assert isinstance(e, FieldbusError) and isinstance(e, ValueError)
    assert "product_id" in str(e)


def test_unknown_type_with_suggestion_names_line_column_and_path() -> None:
    text = HEAD + textwrap.dedent("""\
        rpdo:
          - index: 0x1600
            channels:
              - {index: 0x6040, sub_index: 0, type: uint16}
              - {index: 0x607a, sub_index: 0, type: int32}
              - {index: 0x60ff, sub_index: 0, type: int33}
        """)
    e = err(text)
    assert e.file == "x.yaml" and e.line == 8 and e.column == 45
    assert e.path == "rpdo[0].channels[2].type"
    assert str(e) == "x.yaml:8:45 rpdo[0].channels[2].type: unknown type 'int33' (did you mean int32?)"


@pytest.mark.parametrize(
    ("text", "needle", "path", "words"),
    [
        (HEAD + "vendr: 3\n", "vendr", "vendr", "did you mean vendor"),
        (
            HEAD
            + "rpdo:\n  - index: 0x1600\n    channels:\n      - {index: 0x6040, sub_index: 0, type: uint16, factr: 2}\n",
            "factr",
            "rpdo[0].channels[0].factr",
            "did you mean factor",
        ),
        (
            HEAD + "rpdo:\n  - index: 0x1a00\n    channels: []\n",
            "0x1a00",
            "rpdo[0].index",
            "0x1600-0x17FF",
        ),
        (
            HEAD + "tpdo:\n  - index: 0x1600\n    channels: []\n",
            "0x1600",
            "tpdo[0].index",
            "0x1A00-0x1BFF",
        ),
        (
            HEAD
            + "tpdo:\n  - index: 0x1a00\n    channels:\n      - {index: 0x10000, sub_index: 0, type: uint8}\n",
            "0x10000",
            "tpdo[0].channels[0].index",
            "out of range",
        ),
        (
            HEAD
            + "tpdo:\n  - index: 0x1a00\n    channels:\n      - {index: 0x6041, sub_index: 256, type: uint8}\n",
            "256",
            "tpdo[0].channels[0].sub_index",
            "out of range",
        ),
        (
            HEAD
            + "rpdo:\n  - index: 0x1600\n    channels:\n"
            + "      - {index: 0x6040, sub_index: 0, type: uint16, name: cw}\n"
            + "      - {index: 0x6041, sub_index: 0, type: uint16, name: cw}\n",
            "0x6041",
            "rpdo[0].channels[1].name",
            "duplicate outputs channel name 'cw'",
        ),
        (
            HEAD
            + "tpdo:\n  - index: 0x1a00\n    channels:\n"
            + "      - {index: 0x6001, sub_index: 1, type: bool, mask: 1}\n"
            + "      - {index: 0x6001, sub_index: 2, type: bool, mask: 1}\n",
            "sub_index: 2",
            "tpdo[0].channels[1].mask",
            "overlaps bit 0 of byte 0",
        ),
        (
            HEAD
            + "tpdo:\n  - index: 0x1a00\n    channels:\n"
            + "      - {index: 0x6001, sub_index: 1, type: bool, mask: 4}\n",
            "mask: 4",
            "tpdo[0].channels[0].mask",
            "does not match",
        ),
        (
            HEAD
            + "rpdo:\n  - index: 0x1600\n    channels:\n"
            + "      - {index: 0x6060, sub_index: 0, type: int8, default: 200}\n",
            "default: 200",
            "rpdo[0].channels[0].default",
            "does not fit int8",
        ),
        (
            HEAD + "sdo:\n  - {index: 0x6060, sub_index: 0, type: uint8, value: -1}\n",
            "value: -1",
            "sdo[0].value",
            "does not fit uint8",
        ),
        (
            HEAD + "sdo:\n  - {index: 0x6060, sub_index: 0, type: int16, value: 1.5}\n",
            "value: 1.5",
            "sdo[0].value",
            "does not fit int16",
        ),
        (
            HEAD
            + "canopen: {}\nrpdo:\n  - index: 0x1600\n    channels:\n"
            + "      - {index: 0x607a, sub_index: 0, type: int32}\n"
            + "      - {index: 0x60ff, sub_index: 0, type: int32}\n"
            + "      - {index: 0x6040, sub_index: 0, type: uint16}\n",
            "channels:",
            "rpdo[0].channels",
            "10 bytes; classic CAN carries at most 8",
        ),
        (
            HEAD
            + "rpdo:\n  - index: 0x1600\n    channels:\n"
            + "      - {index: 0x6040, sub_index: 0, type: uint16, state_interface: cw}\n",
            "state_interface",
            "rpdo[0].channels[0].state_interface",
            "belongs in the other direction",
        ),
        (
            HEAD
            + "tpdo:\n  - index: 0x1a00\n    channels:\n"
            + "      - {index: 0x0000, sub_index: 0, type: bit3}\n"
            + "      - {index: 0x6064, sub_index: 0, type: double}\n",
            "double",
            "tpdo[0].channels[1].type",
            "must start on a byte boundary",
        ),
        (
            HEAD + "rpdo:\n  - index: 0x1600\n    channels: []\n  - index: 0x1600\n    channels: []\n",
            "- index: 0x1600\n    channels: []\n  - index",  # not used: second occurrence below
            "rpdo[1].index",
            "listed twice",
        ),
        (
            HEAD
            + "profile: cia402\ntpdo:\n  - index: 0x1a00\n    channels:\n      - {index: 0x6041, sub_index: 0, type: uint16}\n",
            "rpdo",
            "rpdo",
            "controlword",
        ),
        (
            HEAD + "sm:\n  - {index: 2, type: input, pdo: rpdo}\n",
            "index: 2",
            "sm[0].pdo",
            "needs an output SyncManager",
        ),
        (
            HEAD + "vendor_id: 3\n",
            "vendor_id: 3",
            "",
            "duplicate key 'vendor_id'",
        ),
    ],
)
def test_rule_names_line_and_field(text: str, needle: str, path: str, words: str) -> None:
    e = err(text)
    assert e.path == path, str(e)
    assert words in str(e), str(e)
    lines = text.splitlines()
    if path == "rpdo[1].index":
        expected_line = [i for i, ln in enumerate(lines, 1) if "0x1600" in ln][1]
    elif path == "rpdo":
        expected_line = None  # the key is missing: no line of its own
    elif needle in text:
        expected_line = line_of(text, needle.splitlines()[0])
    else:
        expected_line = None
    if expected_line is not None:
        assert e.line == expected_line, str(e)
        assert str(e).startswith(f"x.yaml:{expected_line}:"), str(e)


def test_yaml_syntax_error_is_located() -> None:
    e = err(HEAD + "rpdo: [\n  {index: 1\n")
    assert e.line is not None and "YAML syntax" in e.message


def test_missing_file_is_a_pdo_map_error(tmp_path: Path) -> None:
    with pytest.raises(PdoMapError, match="file not found"):
        load_drive_map(tmp_path / "nope.yaml")


def test_network_missing_map_file_names_line(tmp_path: Path) -> None:
    net = tmp_path / "net.yaml"
    net.write_text(
        "buses:\n  - name: legs\n    type: ethercat\n    interface: eth0\n    slaves:\n"
        "      - {name: hip, map: maps/missing.yaml}\n"
    )
    with pytest.raises(PdoMapError) as info:
        load_network(net)
    assert info.value.line == 6 and info.value.path == "buses[0].slaves[0].map"
    assert "map file not found: maps/missing.yaml" in str(info.value)


def test_error_inside_a_referenced_map_names_that_map(tmp_path: Path) -> None:
    (tmp_path / "bad.yaml").write_text("vendor_id: 1\nproduct_id: 1\nrpdo: 3\n")
    net = tmp_path / "net.yaml"
    net.write_text("buses:\n  - {name: a, type: sim, slaves: [{name: s, map: bad.yaml}]}\n")
    with pytest.raises(PdoMapError) as info:
        load_network(net)
    assert info.value.file is not None and info.value.file.endswith("bad.yaml")
    assert info.value.line == 3 and info.value.path == "rpdo"


def test_pdo_name_must_be_text_and_yaml_booleans_are_explained(tmp_path: Path) -> None:
    from fieldbus.core.pdo import drive_map_from_text
    from fieldbus.errors import PdoMapError

    base = (
        "name: d\nvendor_id: 1\nproduct_id: 2\nrpdo:\n  - index: 0x1600\n    name: {bad: 1}\n"
        "    channels: [{index: 0x6040, sub_index: 0, type: uint16}]\n"
    )
    with pytest.raises(PdoMapError) as exc:
        drive_map_from_text(base, "d.yaml")
    assert (
        "d.yaml:6:" in str(exc.value)
        and "rpdo[0].name" in str(exc.value)
        and "expected a string" in str(exc.value)
    )
    sm = (
        "name: d\nvendor_id: 1\nproduct_id: 2\nrpdo:\n  - index: 0x1600\n"
        "    channels: [{index: 0x6040, sub_index: 0, type: uint16}]\n"
        "sm:\n  - {index: 2, type: output, pdo: rpdo, watchdog: on}\n"
    )
    with pytest.raises(PdoMapError) as exc:
        drive_map_from_text(sm, "d.yaml")
    assert (
        "sm[0].watchdog" in str(exc.value)
        and "YAML boolean" in str(exc.value)
        and "'on'" not in str(exc.value)
    )


@pytest.mark.parametrize(
    ("bus", "message", "line"),
    [
        ("{name: a, type: ethercat, interface: eth0,\n    redundant_interface: eth1, slaves: []}", None, 0),
        (
            "{name: a, type: ethercat, interface: eth0,\n    redundant_interface: eth0, slaves: []}",
            "another card",
            3,
        ),
        (
            "{name: a, type: canopen, interface: can0,\n    redundant_interface: can1, slaves: []}",
            "for ethercat",
            3,
        ),
    ],
)
def test_redundant_interface_is_an_ethercat_second_card(
    tmp_path: Path, bus: str, message: str | None, line: int
) -> None:
    net = tmp_path / "net.yaml"
    (tmp_path / "io.yaml").write_text("vendor_id: 1\nproduct_id: 2\n")
    net.write_text(f"buses:\n  - {bus.replace('slaves: []', 'slaves: [{name: s, map: io.yaml}]')}\n")
    if message is None:
        assert load_network(net).buses[0].redundant_interface == "eth1"
        return
    with pytest.raises(PdoMapError, match=message) as info:
        load_network(net)
    assert info.value.line == line and info.value.path == "buses[0].redundant_interface"
