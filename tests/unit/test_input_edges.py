"""Input edges of issue 28: what the loaders refuse, warn about or now accept.

Each test names the rule it checks; the CLI side (every command against the
hostile corpus, the secret never quoted) is in ``test_fuzz_hostile_files.py``.
"""

from __future__ import annotations

import ast
import json
import re
from pathlib import Path

import pytest

from fieldbus.cli import main
from fieldbus.core.network import check_backend_options, load_network, network_from_text
from fieldbus.core.pdo import drive_map_from_text, load_drive_map
from fieldbus.core.pdo.image import ProcessImage
from fieldbus.core.pdo.layout import layout
from fieldbus.core.yamlsrc import MAX_FILE_BYTES, load_located
from fieldbus.errors import ChannelNameError, FieldbusError, PdoMapError
from fieldbus.registry import BACKEND_OPTIONS

REPO = Path(__file__).resolve().parents[2]
GENERIC = REPO / "pdo_maps" / "generic_cia402.yaml"
HEAD = "vendor_id: 0x2\nproduct_id: 0x10\n"
RPDO = "rpdo:\n  - index: 0x1600\n    channels:\n"


def _net(tmp_path: Path, text: str, name: str = "net.yaml") -> Path:
    path = tmp_path / name
    path.write_text(text)
    return path


def _one_bus(extra: str = "", kind: str = "ethercat", top: str = "", slave: str = "") -> str:
    node = ", node_id: 1" if kind in ("canopen", "rawcan") else ""
    return (
        f"{top}buses:\n  - {{name: b, type: {kind}{extra}, "
        f"slaves: [{{name: 'a{{i}}', map: {json.dumps(str(GENERIC))}{node}{slave}}}]}}\n"
    )


# ------------------------------------------------------------------ exponent floats (item 2)


@pytest.mark.parametrize(
    ("written", "value"),
    [("5e-6", 5e-6), ("1E3", 1000.0), ("1.5e3", 1500.0), ("+2e2", 200.0), ("-3E-1", -0.3)],
)
def test_exponent_floats_are_numbers(written: str, value: float) -> None:
    drive = drive_map_from_text(
        HEAD + RPDO + f"      - {{index: 0x607A, sub_index: 0, type: int32, factor: {written}, unit: rad}}\n"
    )
    assert drive.rpdo[0].channels[0].factor == value
    # the YAML 1.1 forms still read as before; hex and words that look like exponents stay what they were
    data = load_located("a: -2.5e+3\nb: .5E-2\nc: 0x1e3\nd: e3\ne: 5e\nf: 1e3x\n").data
    assert data == {"a": -2500.0, "b": 0.005, "c": 0x1E3, "d": "e3", "e": "5e", "f": "1e3x"}


def test_exponent_form_of_a_whole_number_is_an_integer() -> None:
    net = network_from_text(
        _one_bus(", interface: eth0", top="cycle_time_us: 2e3\nreceive_timeout_us: 5E2\n"), "n.yaml", base="/"
    )
    assert net.cycle_time_us == 2000 and net.buses[0].receive_timeout_us == 500
    with pytest.raises(PdoMapError, match="expected an integer, got float"):
        network_from_text(_one_bus(", interface: eth0", top="cycle_time_us: 1.2345e3\n"), "n.yaml", base="/")


# ------------------------------------------------------------------ not a map (item 1, loader side)


@pytest.mark.parametrize(
    "text",
    ["root:$6$abcdefgh:1:0:99999:7:::\n", "- 1\n- 2\n", "just words\n", "", "password: hunter2hunter2\n"],
)
def test_a_file_that_is_not_a_drive_map_is_refused_without_its_content(text: str) -> None:
    with pytest.raises(PdoMapError, match="not a drive map") as info:
        drive_map_from_text(text, "x.yaml")
    message = str(info.value)
    for word in ("abcdefgh", "hunter2", "just words", "root"):
        assert word not in message


def test_an_unknown_key_is_quoted_only_up_to_its_first_name_characters() -> None:
    with pytest.raises(PdoMapError) as info:
        drive_map_from_text(HEAD + "root:$6$0123456789abcdef0123456789: x\n", "x.yaml")
    assert "unknown key 'root...'" in str(info.value) and "0123" not in str(info.value)
    with pytest.raises(PdoMapError) as info:  # a typo is shown whole, with the suggestion
        drive_map_from_text(HEAD + "descripton: x\n", "x.yaml")
    assert "unknown key 'descripton' (did you mean description?)" in str(info.value)


def test_map_paths_that_are_not_map_files_are_refused_before_reading(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    secret = tmp_path / "shadow"
    secret.write_text("root:$6$SECRETSECRET:1::\n")
    (tmp_path / "folder.yaml").mkdir()
    loop = tmp_path / "loop.yaml"
    loop.symlink_to(loop)
    cases = {
        str(secret): "ends in .yaml or .yml",
        "folder.yaml": "is a directory",
        "loop.yaml": "symbolic link loop",
        "''": "empty",
        "/dev/null": "ends in .yaml or .yml",
    }
    for target, words in cases.items():
        net = _net(
            tmp_path,
            f"buses:\n  - {{name: b, type: ethercat, interface: eth0, slaves: [{{name: a, map: {target}}}]}}\n",
        )
        with pytest.raises(PdoMapError, match=words) as info:
            load_network(net)
        assert info.value.file == str(net) and info.value.path == "buses[0].slaves[0].map", target
        assert "SECRET" not in str(info.value)
    # what does load, as docs/network-reference.md says: relative to the network file (not the current
    # folder), or absolute
    (tmp_path / "maps").mkdir()
    (tmp_path / "maps" / "j.yml").write_text(GENERIC.read_text())
    rel = _net(
        tmp_path,
        "buses:\n  - {name: b, type: ethercat, interface: eth0, slaves: [{name: a, map: maps/j.yml}]}\n",
    )
    monkeypatch.chdir("/")
    assert load_network(rel).buses[0].slaves[0].map.name == "generic_cia402"
    absolute = _net(tmp_path, _one_bus(", interface: eth0"), "abs.yaml")
    assert load_network(absolute).buses[0].slaves[0].map.source == str(GENERIC.resolve())


def test_files_that_are_not_text_are_refused_by_what_they_are(tmp_path: Path) -> None:
    (tmp_path / "big.yaml").write_bytes(b"")
    with (tmp_path / "big.yaml").open("r+b") as f:
        f.truncate(MAX_FILE_BYTES + 1)  # sparse: no disk used
    (tmp_path / "nul.yaml").write_bytes(HEAD.encode() + b"name: a\x00b\n")
    (tmp_path / "utf16.yaml").write_bytes(HEAD.encode("utf-16"))
    (tmp_path / "latin1.yaml").write_bytes(HEAD.encode() + "description: caf\xe9\n".encode("latin-1"))
    (tmp_path / "bom.yaml").write_bytes(b"\xef\xbb\xbf" + HEAD.encode())
    expected = {
        "big.yaml": "a YAML file here is at most",
        "nul.yaml": "a binary file",
        "utf16.yaml": "UTF-16",
        "latin1.yaml": r"not UTF-8 text \(byte 0xE9 on line 3\)",
    }
    for name, words in expected.items():
        with pytest.raises(PdoMapError, match=words):
            load_drive_map(tmp_path / name)
    assert load_drive_map(tmp_path / "bom.yaml").vendor_id == 2
    with pytest.raises(PdoMapError, match="not a regular file"):
        load_drive_map("/dev/zero")
    with pytest.raises(PdoMapError, match="is a directory"):
        load_drive_map(tmp_path)


def test_yaml_syntax_messages_quote_no_text_of_the_file() -> None:
    for text in (
        "vendor_id: *SECRETSECRET\n",
        "!<tag:SECRETSECRET> 1\nx: 1\n",
        "a: !!python/name:SECRETSECRET 1\n",
    ):
        with pytest.raises(PdoMapError) as info:
            drive_map_from_text(text, "x.yaml")
        assert "SECRET" not in str(info.value) and info.value.line is not None
    with pytest.raises(PdoMapError, match="found character '\\\\t'"):  # a single character is still shown
        drive_map_from_text(HEAD + "rpdo:\n\t- 1\n")


# ------------------------------------------------------------------ refuse or warn (item 3)


def _validate(capsys: pytest.CaptureFixture[str], path: Path) -> tuple[int, str, str]:
    code = main(["validate", str(path)])
    out = capsys.readouterr()
    return code, out.out, out.err


def test_an_overloaded_can_bus_is_refused_by_validate_with_its_figure(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    net = _net(
        tmp_path, _one_bus(", interface: can0, can_interface: virtual", "canopen", slave=", count: 12")
    )
    code, out, err = _validate(capsys, net)
    assert code == 1 and "OK" not in out
    assert re.fullmatch(
        r"error: \S+net\.yaml:2:5 buses\[0\]: bus 'b' needs \d+\.\d % of the canopen bus at 1000 Hz .*\n", err
    ), err
    assert main(["bandwidth", str(net)]) == 3  # documented: a bus over 100 % load
    assert "error:" in capsys.readouterr().err
    slow = _net(
        tmp_path,
        _one_bus(
            ", interface: can0, can_interface: virtual",
            "canopen",
            top="cycle_time_us: 10000\n",
            slave=", count: 12",
        ),
        "slow.yaml",
    )
    assert _validate(capsys, slow)[0] == 0 and main(["bandwidth", str(slow)]) == 0


def test_a_receive_timeout_longer_than_the_cycle_is_a_warning(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    net = _net(tmp_path, _one_bus(", interface: eth0", top="cycle_time_us: 1000\nreceive_timeout_us: 3000\n"))
    assert load_network(net).warnings == (
        f"{net}:2:21 receive_timeout_us: bus 'b': receive_timeout_us 3000 is longer than its cycle (1000 us): "
        "a lost reply makes that cycle late by up to 2000 us",
    )
    code, out, err = _validate(capsys, net)
    assert code == 0 and "OK" in out and err.startswith("warning: ") and err.count("\n") == 1
    assert json.loads(_json_validate(capsys, net))["files"][0]["warnings"] == list(load_network(net).warnings)
    fine = _net(tmp_path, _one_bus(", interface: eth0", top="receive_timeout_us: 1000\n"), "fine.yaml")
    assert load_network(fine).warnings == ()
    # run says it too, before it runs (here on the emulator, for one cycle)
    main(["run", str(net), "--backend", "sim", "--cycles", "1"])
    assert "warning: " in capsys.readouterr().err


def _json_validate(capsys: pytest.CaptureFixture[str], path: Path) -> str:
    assert main(["validate", "--json", str(path)]) == 0
    return capsys.readouterr().out


@pytest.mark.parametrize(
    ("extra", "kind", "words"),
    [
        (", interface: ''", "ethercat", "buses[0].interface: empty: name the network card"),
        (", interface: '   '", "canopen", "buses[0].interface: empty: name the CAN channel"),
        (", interface: ' eth0'", "ethercat", "has spaces at an end"),
        (", interface: eth0, redundant_interface: ''", "ethercat", "buses[0].redundant_interface: empty"),
    ],
)
def test_an_empty_interface_is_refused(extra: str, kind: str, words: str) -> None:
    with pytest.raises(PdoMapError, match=re.escape(words)):
        network_from_text(_one_bus(extra, kind), "n.yaml", base="/")


def test_an_unknown_can_interface_is_refused_with_the_nearest_known_one() -> None:
    can = pytest.importorskip("can.interfaces", reason="python-can is not installed: the names are its own")
    with pytest.raises(
        PdoMapError,
        match=r"can_interface: python-can has no interface 'socketcann' \(did you mean socketcan\?\)",
    ):
        network_from_text(
            _one_bus(", interface: can0, can_interface: socketcann", "canopen"), "n.yaml", base="/"
        )
    for name in ("virtual", "socketcan", "udp_multicast"):
        assert name in can.VALID_INTERFACES
        network_from_text(
            _one_bus(f", interface: can0, can_interface: {name}", "canopen"), "n.yaml", base="/"
        )


def test_a_pdo_longer_than_a_classic_can_frame_is_refused_on_a_classic_bus(tmp_path: Path) -> None:
    fd_map = tmp_path / "fd.yaml"
    fd_map.write_text(
        HEAD + "canopen: {fd: true}\n" + RPDO + "      - {index: 0x607A, sub_index: 0, type: int32}\n"
        "      - {index: 0x60FF, sub_index: 0, type: int32}\n      - {index: 0x6071, sub_index: 0, type: int16}\n"
    )
    classic = "buses:\n  - {name: b, type: canopen, interface: can0, can_interface: virtual%s, slaves: [{name: a, map: fd.yaml, node_id: 1}]}\n"
    with pytest.raises(PdoMapError, match="rpdo 0x1600 of map fd is 10 bytes and this bus is classic CAN"):
        load_network(_net(tmp_path, classic % ""))
    assert (
        load_network(_net(tmp_path, classic % ", data_bitrate: 5000000")).buses[0].data_bitrate == 5_000_000
    )
    assert load_network(_net(tmp_path, classic % ", can_options: {fd: true}")).buses[0].can_options == (
        ("fd", True),
    )


def test_unknown_open_network_options_are_refused_with_a_suggestion(tmp_path: Path) -> None:
    import fieldbus

    net = _net(tmp_path, _one_bus(", interface: eth0"))
    with pytest.raises(
        FieldbusError, match=r"unknown option 'chain_map' for the sim backend; did you mean chain_maps\?"
    ):
        fieldbus.open_network(net, backend="sim", chain_map=[])
    with pytest.raises(FieldbusError, match=r"'pcap' is for the ethercat backend"):
        fieldbus.open_network(net, backend="sim", pcap="x.pcap")
    with pytest.raises(FieldbusError, match=r"unknown option 'can_logg'"):
        check_backend_options(["canopen"], ["can_logg"])
    check_backend_options(["canopen", "ethercat"], ["can_log", "pcap"])  # shared: one bus reads each
    check_backend_options(["some_plugin"], ["anything"])  # a backend from an entry point: not ours to judge


def test_the_option_table_lists_what_each_backend_reads() -> None:
    """Every ``options.get("name")`` in a built-in backend's source is in BACKEND_OPTIONS, and no more."""
    from fieldbus.backends import BACKENDS

    for kind, (module, _cls, _extra) in BACKENDS.items():
        source = (REPO / (module.replace(".", "/") + ".py")).read_text()
        read = set()
        for node in ast.walk(ast.parse(source)):
            if (
                isinstance(node, ast.Call)
                and isinstance(node.func, ast.Attribute)
                and node.func.attr == "get"
                and isinstance(node.func.value, ast.Name)
                and node.func.value.id == "options"
                and node.args
                and isinstance(node.args[0], ast.Constant)
            ):
                read.add(node.args[0].value)
        assert read == set(BACKEND_OPTIONS[kind]), kind


# ------------------------------------------------------------------ channel names (item 4)


def test_a_wrong_channel_name_names_the_channels_and_the_nearest() -> None:
    img = ProcessImage(layout(load_drive_map(GENERIC)), 2)
    with pytest.raises(ChannelNameError) as info:
        img.outputs["target_pos"]
    e = info.value
    assert isinstance(e, FieldbusError) and isinstance(e, KeyError) and isinstance(e, ValueError)
    assert str(e) == (
        "no outputs (RxPDO) channel 'target_pos'; did you mean 'target_position'? (channels: controlword, "
        "target_position, target_velocity, target_torque, modes_of_operation)"
    )
    with pytest.raises(
        ChannelNameError, match="no inputs \\(TxPDO\\) channel 'statusward'; did you mean 'statusword'"
    ):
        img.inputs["statusward"] = 1
    img.outputs["target_position"] = [1.0, 2.0]
    assert list(img.outputs["target_position"]) == [1.0, 2.0]
    with pytest.raises(ValueError, match="broadcast"):  # a bad value is still numpy's own error
        img.outputs["target_position"] = [1.0, 2.0, 3.0]


# ------------------------------------------------------------------ docs (item 5)


def test_the_network_reference_names_only_maps_that_exist() -> None:
    doc = (REPO / "docs" / "network-reference.md").read_text()
    paths = re.findall(r"map: ([^\s,}]+\.ya?ml)", doc)
    assert paths
    for p in paths:
        if p.startswith(".."):
            assert (REPO / "docs" / p).resolve().is_file(), p


def test_the_yaml_reference_and_the_loader_agree_on_a_pdo_name() -> None:
    doc = (REPO / "docs" / "yaml-reference.md").read_text()
    row = next(line for line in doc.splitlines() if line.startswith("| `name`, `description` |"))
    assert "| string |" in row
    drive_map_from_text(HEAD + "rpdo:\n  - {index: 0x1600, name: RxPDO 1, channels: []}\n")
    with pytest.raises(PdoMapError, match=r"rpdo\[0\]\.name: expected a string, got a list"):
        drive_map_from_text(HEAD + "rpdo:\n  - {index: 0x1600, name: [a], channels: []}\n")


def test_the_network_reference_example_loads_as_written() -> None:
    doc = (REPO / "docs" / "network-reference.md").read_text()
    block = re.findall(r"```yaml\n(.*?)```", doc, re.S)[0]
    net = network_from_text(block, "docs/network-reference.md", base=REPO / "docs")
    assert [b.name for b in net.buses] == ["legs", "arm"]
    assert net.bus("arm").slaves[0].map.canopen is not None
