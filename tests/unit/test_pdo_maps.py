"""The drive maps in pdo_maps/ load, cite their sources, build their SDO plans and carry known facts.

Also keeps docs/yaml-reference.md honest: every key the loader accepts is in it,
its example error messages are the loader's real messages, and its Python block runs.

The expected sizes below are added up by hand from each manual's object types
(the comments show the sums), not taken from the layout code.
"""

from __future__ import annotations

import re
import textwrap
from pathlib import Path

import numpy as np
import pytest

from fieldbus.core.cia402 import Cia402Controller
from fieldbus.core.pdo import drive_map_from_text, load_drive_map
from fieldbus.core.pdo import load as loader
from fieldbus.core.pdo.image import ProcessImage
from fieldbus.core.pdo.layout import layout
from fieldbus.core.pdo.model import Direction, DriveMap
from fieldbus.core.pdo.names import default_name
from fieldbus.core.rawcan import FIELD_KEYS, RAWCAN_KEYS
from fieldbus.core.sdo import StepKind, canopen_plan, coe_plan
from fieldbus.errors import PdoMapError

REPO = Path(__file__).resolve().parents[2]
PDO_MAPS = REPO / "pdo_maps"
REFERENCE = REPO / "docs" / "yaml-reference.md"
MAPS = sorted(PDO_MAPS.glob("*.yaml"))
REQUIRED = (
    "maxon_epos4",
    "elmo_gold",
    "synapticon_somanet",
    "beckhoff_el7201",
    "generic_cia402",
    "maxon_epos4_canopen",
)
# a citation: a standard, a document id or version, or a chapter/section/table of a manual or ESI
CITATION = re.compile(
    r"CiA \d{3}|IEC \d|\brel\d{3,}|\bv\d+\.\d|version \d|chapter|section|table|\bESI\b|documentation|manual",
    re.IGNORECASE,
)


def _load(path: Path) -> DriveMap:
    return load_drive_map(path)


def _maps(*, canopen: bool = False, cia402: bool = False, coe: bool = False) -> list[Path]:
    """The maps with a ``canopen:`` section, the CiA 402 ones, or the ones with an object dictionary (not raw CAN)."""
    return [
        p
        for p in MAPS
        if (not canopen or _load(p).canopen is not None)
        and (not cia402 or _load(p).profile == "cia402")
        and (not coe or _load(p).rawcan is None)
    ]


@pytest.fixture(scope="module")
def maps() -> dict[str, DriveMap]:
    return {p.stem: _load(p) for p in MAPS}


def test_the_required_maps_exist() -> None:
    stems = {p.stem for p in MAPS}
    assert len(MAPS) >= 6
    assert set(REQUIRED) <= stems, sorted(set(REQUIRED) - stems)


@pytest.mark.parametrize("path", MAPS, ids=lambda p: p.stem)
def test_map_loads_and_is_named_after_its_file(path: Path) -> None:
    drive = _load(path)
    assert drive.source == str(path)
    assert path.stem.startswith(drive.name), (path.stem, drive.name)


@pytest.mark.parametrize("path", MAPS, ids=lambda p: p.stem)
def test_map_cites_its_manual(path: Path) -> None:
    drive = _load(path)
    assert drive.description.strip(), f"{path.name}: empty description"
    assert CITATION.search(drive.description), f"{path.name}: description cites no manual or standard"
    header = [line for line in path.read_text().splitlines() if line.startswith("#")]
    assert header and CITATION.search(" ".join(header)), f"{path.name}: no source in the header comment"


@pytest.mark.parametrize("path", _maps(cia402=True), ids=lambda p: p.stem)
def test_cia402_maps_have_controlword_and_statusword_under_default_names(path: Path) -> None:
    drive = _load(path)
    cw = drive.find(Direction.OUTPUTS, 0x6040)
    sw = drive.find(Direction.INPUTS, 0x6041)
    assert cw is not None and cw.name == "controlword" and cw.type.name == "uint16"
    assert sw is not None and sw.name == "statusword" and sw.type.name == "uint16"
    # the other CiA 402 objects a map carries keep their default names too (the controller finds them so)
    for direction in Direction:
        for ch in drive.channels(direction):
            if (ch.index, ch.sub_index) in (
                (0x6060, 0),
                (0x6061, 0),
                (0x607A, 0),
                (0x6064, 0),
                (0x606C, 0),
            ):
                assert ch.name == default_name(ch.index, ch.sub_index)


@pytest.mark.parametrize("path", _maps(coe=True), ids=lambda p: p.stem)  # raw-CAN motors have no OD
def test_coe_plan_builds_and_assigns_every_pdo(path: Path) -> None:
    plan = coe_plan(_load(path))
    drive = _load(path).bus_map  # a multi-axis map: the whole device (every axis's PDOs and SDOs)
    writes = {(s.index, s.sub_index, s.data) for s in plan.writes}
    for assign, pdos in ((0x1C12, drive.rpdo), (0x1C13, drive.tpdo)):
        for i, pdo in enumerate(pdos, start=1):
            assert (assign, i, pdo.index.to_bytes(2, "little")) in writes
        assert (assign, 0, bytes([len(pdos)])) in writes
    for pdo in (*drive.rpdo, *drive.tpdo):
        kinds = {s.kind for s in plan.steps if s.index == pdo.index}
        assert kinds == ({StepKind.VERIFY} if pdo.fixed else {StepKind.WRITE})
    tail = plan.steps[len(plan.steps) - len(drive.sdo) :]
    assert [(s.index, s.sub_index, s.data) for s in tail] == [
        (w.index, w.sub_index, w.data) for w in drive.sdo
    ]


@pytest.mark.parametrize("path", _maps(canopen=True), ids=lambda p: p.stem)
@pytest.mark.parametrize("node", [1, 5, 127])
def test_canopen_plan_builds_with_predefined_cob_ids(path: Path, node: int) -> None:
    drive = _load(path)
    assert drive.canopen is not None and not drive.canopen.fd
    plan = canopen_plan(drive, node)
    writes = {(s.index, s.sub_index): s.data for s in plan.writes if s.readback is not None}
    for comm, pdos, base in ((0x1400, drive.rpdo, 0x200), (0x1800, drive.tpdo, 0x180)):
        for pdo in pdos:
            assert pdo.size <= 8, f"{pdo.index:#x} does not fit a classic CAN frame"
            n = pdo.number - 1
            cob = base + 0x100 * n + node  # CiA 301 pre-defined connection set
            assert writes[(comm + n, 1)] == cob.to_bytes(4, "little")
            assert writes[(comm + n, 2)] == b"\x01"  # synchronous, every SYNC
    assert writes[(0x1017, 0)] == drive.canopen.heartbeat_ms.to_bytes(2, "little")


@pytest.mark.parametrize("path", MAPS, ids=lambda p: p.stem)
def test_process_images_build(path: Path) -> None:
    drive = _load(path)
    aligns = (1, 8) if drive.canopen is not None else (1,)
    for align in aligns:
        img = ProcessImage(layout(drive, pdo_align=align), n_axes=3)
        img.outputs.to_wire()
        img.inputs.from_wire()


@pytest.mark.parametrize("name", ["generic_cia402", "maxon_epos4", "maxon_epos4_canopen", "elmo_gold"])
def test_cia402_controller_runs_on_the_image(name: str) -> None:
    drive = _load(PDO_MAPS / f"{name}.yaml")
    img = ProcessImage(layout(drive), n_axes=2)
    ctrl = Cia402Controller(2)
    img.inputs["statusword"][:] = 0x0040  # switch on disabled
    ctrl.step(
        img.inputs["statusword"],
        img.outputs["controlword"],
        img.inputs["modes_of_operation_display"],
        img.outputs["modes_of_operation"],
    )
    assert img.outputs["controlword"].dtype == np.uint16
    assert list(img.outputs["modes_of_operation"]) == [8, 8]  # CSP requested


# -- facts per map (sizes summed by hand from the manuals' object types) --


def _sizes(drive: DriveMap) -> tuple[int, int]:
    lay = layout(drive)
    return lay.outputs.size, lay.inputs.size


def test_generic_cia402(maps: dict[str, DriveMap]) -> None:
    d = maps["generic_cia402"]
    assert (d.vendor_id, d.product_id, d.profile) == (0x00000FB1, 0x00000402, "cia402")
    assert [p.index for p in d.rpdo] == [0x1600, 0x1601]
    assert [p.index for p in d.tpdo] == [0x1A00, 0x1A01]
    assert [p.size for p in d.rpdo] == [2 + 4, 4 + 2 + 1]
    assert [p.size for p in d.tpdo] == [2 + 4, 4 + 2 + 1]
    assert _sizes(d) == (13, 13)
    assert [(s.index, s.sub_index, s.value) for s in d.sdo] == [(0x6060, 0, 8)]
    assert {c.name for c in d.channels(Direction.OUTPUTS)} == {
        "controlword",
        "target_position",
        "target_velocity",
        "target_torque",
        "modes_of_operation",
    }
    assert {c.name for c in d.channels(Direction.INPUTS)} == {
        "statusword",
        "position_actual_value",
        "velocity_actual_value",
        "torque_actual_value",
        "modes_of_operation_display",
    }
    torque = d.find(Direction.OUTPUTS, 0x6071)
    assert torque is not None and torque.factor == 10.0  # % -> per mille of rated torque
    assert d.canopen is not None and d.canopen.heartbeat_ms == 100


def test_maxon_epos4(maps: dict[str, DriveMap]) -> None:
    d = maps["maxon_epos4"]
    assert (d.vendor_id, d.product_id) == (0xFB, 0x63500000)
    assert d.product_id >> 16 == 0x6350  # hardware version of the EPOS4 50/5
    assert [p.index for p in d.rpdo] == [0x1603] and [p.index for p in d.tpdo] == [0x1A03]
    assert not any(p.fixed for p in (*d.rpdo, *d.tpdo))
    assert _sizes(d) == (2 + 4 + 4 + 2 + 4 + 4 + 2 + 1, 2 + 4 + 4 + 2 + 1 + 4)  # (23, 17)
    assert d.assign_activate == 0x0300 and d.canopen is None


def test_maxon_epos4_canopen(maps: dict[str, DriveMap]) -> None:
    d = maps["maxon_epos4_canopen"]
    assert d.vendor_id == 0xFB and d.profile == "cia402"
    assert d.canopen is not None and d.canopen.disable_unused_pdos
    assert [p.size for p in d.rpdo] == [2 + 4, 4 + 2 + 1]
    assert [p.size for p in d.tpdo] == [2 + 4, 4 + 2 + 1]
    for pdo in (*d.rpdo, *d.tpdo):
        assert pdo.canopen is not None
        assert (pdo.canopen.transmission_type, pdo.canopen.cob_id_absolute) == (1, False)
    assert [p.canopen.cob_id for p in d.rpdo if p.canopen] == [0x200, 0x300]
    assert [p.canopen.cob_id for p in d.tpdo if p.canopen] == [0x180, 0x280]
    plan = canopen_plan(d, 3)
    disabled = [s.index for s in plan.writes if s.why.startswith("disable unused")]
    assert disabled == [0x1402, 0x1403, 0x1802, 0x1803]


def test_elmo_gold(maps: dict[str, DriveMap]) -> None:
    d = maps["elmo_gold"]
    assert (d.vendor_id, d.product_id, d.revision) == (0x9A, 0x00030924, 0x00010420)
    assert [p.index for p in d.rpdo] == [0x1605]
    assert [p.index for p in d.tpdo] == [0x1A02, 0x1A11]
    assert all(p.fixed for p in (*d.rpdo, *d.tpdo))
    assert _sizes(d) == (4 + 4 + 2 + 2 + 2 + 1 + 1, 4 + 2 + 2 + 1 + 1 + 4)  # (16, 14), with ESI padding bytes
    assert [hex(c.mapping_value) for c in d.rpdo[0].channels] == [
        "0x607a0020",
        "0x60ff0020",
        "0x60710010",
        "0x60720010",
        "0x60400010",
        "0x60600008",
        "0x8",
    ]
    max_torque = d.find(Direction.OUTPUTS, 0x6072)
    assert max_torque is not None and max_torque.default == 1000  # not torque-limited to 0 at start
    assert d.ethercat.mailbox_size == 140 and d.assign_activate == 0x0300
    plan = coe_plan(d)
    assert not [s for s in plan.writes if s.index in (0x1605, 0x1A02, 0x1A11)]  # fixed: only checked


def test_synapticon_somanet(maps: dict[str, DriveMap]) -> None:
    d = maps["synapticon_somanet"]
    assert (d.vendor_id, d.product_id, d.revision) == (0x22D2, 0x201, 0x0A000002)
    assert [p.index for p in d.rpdo] == [0x1600, 0x1601, 0x1602]
    assert [p.index for p in d.tpdo] == [0x1A00, 0x1A01, 0x1A02, 0x1A03]
    assert [p.size for p in d.rpdo] == [2 + 1 + 2 + 4 + 4 + 2 + 4, 4 + 4, 4 + 4]
    assert [p.size for p in d.tpdo] == [2 + 1 + 4 + 4 + 2 + 4, 2 * 4 + 4, 4, 4 + 4 + 4 + 4 + 2]
    assert _sizes(d) == (35, 51)
    assert [c.address for c in d.rpdo[0].channels] == [
        "0x6040:00",
        "0x6060:00",
        "0x6071:00",
        "0x607A:00",
        "0x60FF:00",
        "0x60B2:00",
        "0x2701:00",
    ]


def test_beckhoff_el7201(maps: dict[str, DriveMap]) -> None:
    d = maps["beckhoff_el7201"]
    assert (d.vendor_id, d.product_id) == (2, 0x1C213052)
    assert (d.product_id >> 16, d.product_id & 0xFFFF) == (7201, 0x3052)  # EL7201, "EL" terminal
    assert d.profile is None  # MDP 742: controlword/statusword are not 0x6040/0x6041
    assert [p.index for p in d.rpdo] == [0x1600, 0x1606]
    assert [p.index for p in d.tpdo] == [0x1A00, 0x1A01, 0x1A02, 0x1A03, 0x1A06]
    assert all(p.fixed and len(p.channels) == 1 for p in (*d.rpdo, *d.tpdo))
    assert _sizes(d) == (2 + 4, 4 + 2 + 4 + 2 + 4)  # (6, 16)
    cw = d.find(Direction.OUTPUTS, 0x7010, 1)
    sw = d.find(Direction.INPUTS, 0x6010, 1)
    assert cw is not None and cw.name == "controlword"
    assert sw is not None and sw.name == "statusword"
    assert [(s.index, s.sub_index, s.value) for s in d.sdo] == [(0x7010, 3, 8)]  # CSP


def test_maps_have_distinct_names_and_identities(maps: dict[str, DriveMap]) -> None:
    assert len({d.name for d in maps.values()}) == len(maps)
    ids = [(d.vendor_id, d.product_id) for d in maps.values() if d.rawcan is None]
    assert len(set(ids)) == len(ids)


# -- docs/yaml-reference.md --


def _doc() -> str:
    return REFERENCE.read_text()


@pytest.mark.parametrize(
    "keys",
    [
        loader._TOP_KEYS,
        loader._PDO_KEYS,
        loader._CHANNEL_KEYS,
        loader._SDO_KEYS,
        loader._SM_KEYS,
        loader._ETHERCAT_KEYS,
        loader._CANOPEN_KEYS,
        loader._CANOPEN_PDO_KEYS,
        RAWCAN_KEYS,
        FIELD_KEYS,
        loader._PROFILES,
    ],
    ids=[
        "top",
        "pdo",
        "channel",
        "sdo",
        "sm",
        "ethercat",
        "canopen",
        "canopen.pdo",
        "rawcan",
        "field",
        "profile",
    ],
)
def test_reference_documents_every_key(keys: tuple[str, ...]) -> None:
    doc = _doc()
    missing = [k for k in keys if f"`{k}`" not in doc]
    assert not missing, f"docs/yaml-reference.md does not document {missing}"


def test_reference_lists_every_data_type() -> None:
    doc = _doc()
    from fieldbus.core.datatypes import TYPE_NAMES

    assert not [t for t in TYPE_NAMES if f"`{t}`" not in doc]


HEAD = "vendor_id: 0x2\nproduct_id: 0x10\n"
RPDO = "rpdo:\n  - index: 0x1600\n    channels:\n"
TPDO = "tpdo:\n  - index: 0x1A00\n    channels:\n"
CW = "      - {index: 0x6040, sub_index: 0, type: uint16}\n"
BAD = {
    "unknown key": HEAD + "vendr: 3\n",
    "missing id": "vendor_id: 0x2\n",
    "duplicate key": HEAD + "vendor_id: 3\n",
    "int range": "vendor_id: 0x100000000\nproduct_id: 1\n",
    "not int": "vendor_id: abc\nproduct_id: 1\n",
    "name": HEAD + "name: my drive\n",
    "profile": HEAD + "profile: cia401\n",
    "rpdo index": HEAD + "rpdo:\n  - index: 0x1A00\n    channels: []\n",
    "tpdo index": HEAD + "tpdo:\n  - index: 0x1600\n    channels: []\n",
    "pdo twice": HEAD + RPDO + CW + "  - index: 0x1600\n    channels: []\n",
    "duplicate name": HEAD + RPDO + CW + CW,
    "type": HEAD + RPDO + "      - {index: 0x60ff, sub_index: 0, type: int33}\n",
    "interface": HEAD + RPDO + "      - {index: 0x6040, sub_index: 0, type: uint16, state_interface: cw}\n",
    "gap sub": HEAD + RPDO + "      - {index: 0, sub_index: 1, type: bit8}\n",
    "gap name": HEAD + RPDO + "      - {index: 0, sub_index: 0, type: bit8, name: pad}\n",
    "mask type": HEAD + TPDO + "      - {index: 0x6000, sub_index: 1, type: uint8, mask: 1}\n",
    "mask bits": HEAD + TPDO + "      - {index: 0x6000, sub_index: 1, type: bool, mask: 3}\n",
    "mask position": HEAD + TPDO + "      - {index: 0x6000, sub_index: 1, type: bool, mask: 2}\n",
    "mask overlap": HEAD
    + TPDO
    + "      - {index: 0x6000, sub_index: 1, type: bool, mask: 1}\n"
    + "      - {index: 0x6000, sub_index: 2, type: bool, mask: 1}\n",
    "default input": HEAD + TPDO + "      - {index: 0x6041, sub_index: 0, type: uint16, default: 0}\n",
    "default fit": HEAD + RPDO + "      - {index: 0x6060, sub_index: 0, type: int8, default: 300}\n",
    "factor 0": HEAD + RPDO + "      - {index: 0x607A, sub_index: 0, type: int32, factor: 0}\n",
    "factor tiny": HEAD + RPDO + "      - {index: 0x607A, sub_index: 0, type: int32, factor: 1.0e-320}\n",
    "offset over factor": HEAD
    + RPDO
    + "      - {index: 0x607A, sub_index: 0, type: int32, factor: 1.0e-300, offset: 1.0e+300}\n",
    "scaled bits": HEAD + TPDO + "      - {index: 0x6000, sub_index: 1, type: bool, mask: 1, unit: V}\n",
    "float align": HEAD
    + TPDO
    + "      - {index: 0x6000, sub_index: 1, type: bool, mask: 1}\n"
    + "      - {index: 0x6000, sub_index: 2, type: float}\n",
    "cia402 controlword": HEAD
    + "profile: cia402\n"
    + TPDO
    + "      - {index: 0x6041, sub_index: 0, type: uint16}\n",
    "cia402 statusword": HEAD + "profile: cia402\n" + RPDO + CW,
    "can size": HEAD
    + "canopen: {}\n"
    + RPDO
    + "      - {index: 0x607A, sub_index: 0, type: int32}\n"
    + "      - {index: 0x60FF, sub_index: 0, type: int32}\n"
    + CW,
    "can bits": HEAD
    + "canopen: {}\n"
    + TPDO
    + "      - {index: 0x6000, sub_index: 1, type: bool, mask: 1}\n",
    "can number": HEAD + "canopen: {}\n" + "rpdo:\n  - index: 0x1604\n    channels:\n" + CW,
    "can orphan": HEAD + "canopen: {pdo: [{index: 0x1601, transmission_type: 1}]}\n" + RPDO + CW,
    "can twice": HEAD + "canopen: {pdo: [{index: 0x1600}, {index: 0x1600}]}\n" + RPDO + CW,
    "can cob": HEAD + "canopen: {pdo: [{index: 0x1600, cob_id: 0x7FF}]}\n" + RPDO + CW,
    "sdo fit": HEAD + "sdo:\n  - {index: 0x6060, sub_index: 0, type: int8, value: 200}\n",
    "sdo index": HEAD + "sdo:\n  - {index: 0x0FFF, sub_index: 0, type: int8, value: 1}\n",
    "sm twice": HEAD + "sm:\n  - {index: 2, type: output}\n  - {index: 2, type: output}\n",
    "sm direction": HEAD + "sm:\n  - {index: 3, type: output, pdo: tpdo}\n",
    "mailbox": HEAD + "ethercat: {mailbox_size: 16}\n",
    "rawcan mix": "rawcan:\n  command: [{name: p, bits: 8}]\n  reply: [{name: q, bits: 8}]\nrpdo: []\n",
    "rawcan bits": "rawcan:\n  command: [{name: p, bits: 12}]\n  reply: [{name: q, bits: 8}]\n",
    "rawcan min max": "rawcan:\n  command: [{name: p, bits: 8, min: 1}]\n  reply: [{name: q, bits: 8}]\n",
    "rawcan node field": "rawcan:\n  node_field: id\n  command: [{name: p, bits: 8}]\n  reply: [{name: q, bits: 8}]\n",
    "rawcan safe stop": "rawcan:\n  command: [{name: p, bits: 8}]\n  reply: [{name: q, bits: 8}]\n",
}


@pytest.mark.parametrize("text", BAD.values(), ids=list(BAD))
def test_reference_error_examples_are_the_real_messages(text: str) -> None:
    with pytest.raises(PdoMapError) as info:
        drive_map_from_text(text, "bad.yaml")
    message = str(info.value)
    assert f"`{message}`" in _doc(), f"docs/yaml-reference.md lacks the example: {message}"


def test_reference_python_block_runs(monkeypatch: pytest.MonkeyPatch) -> None:
    blocks = re.findall(r"```python\n(.*?)```", _doc(), re.S)
    assert len(blocks) == 1
    monkeypatch.chdir(REPO)
    exec(compile(textwrap.dedent(blocks[0]), "docs/yaml-reference.md", "exec"), {})


def test_reference_yaml_blocks_load() -> None:
    """The complete YAML examples in the reference are valid maps (abridged excerpts are skipped)."""
    blocks = re.findall(r"```yaml\n(.*?)```", _doc(), re.S)
    full = [b for b in blocks if "vendor_id:" in b]
    assert full
    for block in full:
        drive_map_from_text(block, "example.yaml")
    bit_packing = next(b for b in blocks if "type: bit6" in b)
    drive = drive_map_from_text(HEAD + bit_packing, "bits.yaml")
    assert layout(drive).inputs.size == 3


def test_reference_validate_output_is_current() -> None:
    """The `fieldbus validate` listing in the worked example matches the map's real layout."""
    drive = _load(PDO_MAPS / "generic_cia402.yaml")
    doc = _doc()
    for direction in (layout(drive).outputs, layout(drive).inputs):
        for e in direction.channels:
            unit = f" [{e.channel.unit}]" if e.channel.unit else ""
            row = f"bit {e.bit_offset:4d} +{e.bits:<2d} {e.channel.address} {e.channel.type.name:<7} {e.name}{unit}"
            assert row in doc, row
