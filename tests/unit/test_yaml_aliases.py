"""YAML anchors, aliases and ``<<`` merge keys: right values, right locations, no blow-up.

An alias shares the object built for its anchor (as ``yaml.safe_load`` does), so
a "billion laughs" document loads in time proportional to its text.
"""

from __future__ import annotations

import subprocess
import sys
import textwrap
import time
import tracemalloc
from pathlib import Path

import pytest
import yaml

from fieldbus.commands.demo import DEMO_MAP
from fieldbus.core.network import load_network, network_from_text
from fieldbus.core.pdo import drive_map_from_text, load_drive_map
from fieldbus.core.yamlsrc import MAX_ALIAS_NODES, load_located
from fieldbus.errors import PdoMapError

ROOT = Path(__file__).resolve().parents[2]


def alias_bomb(levels: int, *, key: str = "description", width: int = 10, mapping: bool = False) -> str:
    """A drive map whose ``key`` holds ``width ** levels`` leaves through nested aliases.

    The anchors are written as items of ``key``'s list, so the bomb sits where a
    drive map allows it and validation fails on its shape, after loading.
    """
    lines = ["name: bomb", "vendor_id: 1", "product_id: 2", f"{key}:"]
    lines.append(f"  - &l0 [{', '.join(['lol'] * width)}]")
    for i in range(1, levels + 1):
        if mapping:
            items = ", ".join(f"k{j}: *l{i - 1}" for j in range(width))
            lines.append(f"  - &l{i} {{{items}}}")
        else:
            lines.append(f"  - &l{i} [{', '.join([f'*l{i - 1}'] * width)}]")
    return "\n".join(lines) + "\n"


BOMB_LINE = 4  # the line of ``key:`` in alias_bomb()


class _NoAliasDumper(yaml.SafeDumper):
    def ignore_aliases(self, data: object) -> bool:
        return True


def expand(text: str) -> str:
    """``text`` as PyYAML reads it, written back without any anchor, alias or merge key."""
    return yaml.dump(yaml.safe_load(text), Dumper=_NoAliasDumper, sort_keys=False)


# --- the alias bomb ----------------------------------------------------------------------------


@pytest.mark.timeout(60)
@pytest.mark.parametrize("levels", [3, 6, 9, 12])
@pytest.mark.parametrize(
    ("key", "mapping", "path", "words"),
    [
        ("description", False, "description", "expected a string, got a list"),
        ("rpdo", False, "rpdo[0]", "expected a mapping, got a list"),
        ("sdo", True, "sdo[0]", "expected a mapping, got a list"),
        ("sm", True, "sm[0]", "expected a mapping, got a list"),
    ],
)
def test_alias_bomb_is_cheap_and_located(levels: int, key: str, mapping: bool, path: str, words: str) -> None:
    text = alias_bomb(levels, key=key, mapping=mapping)
    tracemalloc.start()
    start = time.perf_counter()
    try:
        with pytest.raises(PdoMapError) as info:
            drive_map_from_text(text, "bomb.yaml")
        elapsed = time.perf_counter() - start
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert elapsed < 1.0, f"{levels}-level alias bomb took {elapsed:.2f} s"
    assert peak < 8 * 2**20, f"{levels}-level alias bomb peaked at {peak / 2**20:.1f} MiB"
    e = info.value
    assert e.file == "bomb.yaml" and e.path == path and words in e.message, str(e)
    assert e.line is not None and e.line >= BOMB_LINE and e.column is not None, str(e)


@pytest.mark.timeout(60)
def test_nine_level_bomb_through_load_drive_map(tmp_path: Path) -> None:
    path = tmp_path / "bomb.yaml"
    path.write_text(alias_bomb(9))
    start = time.perf_counter()
    with pytest.raises(PdoMapError) as info:
        load_drive_map(path)
    assert time.perf_counter() - start < 1.0
    assert info.value.file == str(path) and info.value.line == BOMB_LINE
    assert str(info.value).startswith(f"{path}:{BOMB_LINE}:")


def test_nine_level_bomb_loads_shared_like_pyyaml() -> None:
    # no bomb data in an assert: on failure pytest would print its 10**9-item repr
    doc = load_located(alias_bomb(9), "bomb.yaml")
    items = doc.data["description"]
    shared = items[9][0] is items[9][9] is items[8]
    assert shared, "an alias must reuse the anchored object, not copy it"
    entries = len(doc.values)
    assert entries < 100, "one location per written node, not 10**9"
    deep = doc.where(("description", 9, 3, 2, 1))  # l9[3] is l8, l8[2] is l7, l7[1] is l6
    assert deep == doc.where(("description", 6)) == (BOMB_LINE + 7, 5)  # the node '&l6 [...]'


@pytest.mark.timeout(120)
def test_nine_level_bomb_through_fieldbus_validate(tmp_path: Path) -> None:
    path = tmp_path / "bomb.yaml"
    path.write_text(alias_bomb(9))
    out = subprocess.run(
        [sys.executable, "-m", "fieldbus", "validate", str(path)],
        capture_output=True,
        text=True,
        timeout=60,
        check=False,
        cwd=ROOT,
    )
    assert out.returncode == 1, out.stdout + out.stderr
    assert f"{path}:{BOMB_LINE}:" in out.stderr and "description" in out.stderr, out.stderr


@pytest.mark.timeout(60)
def test_nine_level_bomb_in_a_network_file() -> None:
    text = "buses:\n" + alias_bomb(9).split("description:\n", 1)[1]
    start = time.perf_counter()
    with pytest.raises(PdoMapError) as info:
        network_from_text(text, "net.yaml")
    assert time.perf_counter() - start < 1.0
    assert info.value.path == "buses[0]" and info.value.line == 2


def test_recursive_alias_is_refused_with_its_location() -> None:
    with pytest.raises(PdoMapError) as info:
        drive_map_from_text("vendor_id: 1\nproduct_id: 2\ndescription: &a [x, *a]\n", "r.yaml")
    assert "recursive" in info.value.message
    assert (info.value.file, info.value.line, info.value.column) == ("r.yaml", 3, 14)
    with pytest.raises(PdoMapError, match="recursive"):
        load_located("a: &a {<<: *a}\n")


def test_quadratic_merge_chain_is_bounded() -> None:
    n = 1000  # each mapping merges the previous one: n * n / 2 copied keys
    lines = ["chain:", "  - &m0 {k0: 0}"]
    lines += [f"  - &m{i} {{<<: *m{i - 1}, k{i}: {i}}}" for i in range(1, n)]
    with pytest.raises(PdoMapError) as info:
        load_located("\n".join(lines) + "\n", "chain.yaml")
    assert f"more than {MAX_ALIAS_NODES} nodes" in info.value.message
    # bounded work, counted rather than timed: the load stopped at the mapping where the copied keys passed
    # the limit (about sqrt(2 * limit) mappings in), not after copying all n * n / 2 of them
    assert info.value.file == "chain.yaml" and info.value.line is not None
    assert 2 < info.value.line < 2 + 2 * int((2 * MAX_ALIAS_NODES) ** 0.5) < n
    assert info.value.column is not None


def test_deep_alias_chain_keeps_the_depth_limit() -> None:
    lines = ["a:", "  - &n0 [x]"] + [f"  - &n{i} [*n{i - 1}]" for i in range(1, 80)]
    with pytest.raises(PdoMapError, match="nested deeper than 64 levels"):
        load_located("\n".join(lines) + "\n")


# --- anchors as drive maps really use them --------------------------------------------------------

ANCHORED_MAP = textwrap.dedent("""\
    # A CiA 402 servo plus a few digital inputs, written with anchors and merge keys.
    name: anchored_servo
    vendor_id: 0x000000fb
    product_id: 0x65520000
    profile: cia402
    sdo:
      - &sdo_mode {index: 0x6060, sub_index: 0, type: int8, value: 8}
      - {<<: *sdo_mode, index: 0x60c2, sub_index: 1, type: uint8, value: 1}
    rpdo:
      - index: 0x1600
        channels:
          - {index: 0x6040, sub_index: 0, type: uint16, command_interface: controlword}
          - &rad_out
            index: 0x607a
            sub_index: 0
            type: int32
            factor: 10430.378
            unit: rad
            command_interface: position
          - {<<: *rad_out, index: 0x60ff, command_interface: velocity}
          - {<<: *rad_out, index: 0x60b1, command_interface: velocity_offset, factor: 1000.0}
          - {index: 0x6071, sub_index: 0, type: int16, command_interface: effort}
          - &pad {index: 0, sub_index: 0, type: bit8}
          - *pad
    tpdo:
      - index: 0x1a00
        channels:
          - {index: 0x6041, sub_index: 0, type: uint16, state_interface: statusword}
          - &rad_in {index: 0x6064, sub_index: 0, type: int32, factor: 0.0000958738, unit: rad, state_interface: position}
          - {<<: *rad_in, index: 0x606c, state_interface: velocity}
          - {<<: [*rad_in, *pad], index: 0x6077, type: int16, state_interface: effort, unit: Nm}
      - index: 0x1a01
        channels:
          - &din {index: 0x60fd, sub_index: 0, type: bool, mask: 1, name: limit_negative}
          - {<<: *din, mask: 2, name: limit_positive}
          - {<<: *din, mask: 4, name: home_switch}
          - {index: 0, sub_index: 0, type: bit5}
    sm:
      - &sm_out {index: 2, type: output, pdo: rpdo, watchdog: enable}
      - {<<: *sm_out, index: 3, type: input, pdo: tpdo}
    """)


def test_anchored_map_loads_like_its_expansion() -> None:
    drive = drive_map_from_text(ANCHORED_MAP, "anchored_servo.yaml")
    expanded = expand(ANCHORED_MAP)
    assert "<<" not in expanded and "*" not in expanded and "&" not in expanded
    assert drive == drive_map_from_text(expanded, "anchored_servo.yaml")
    rx = {c.name: c for c in drive.rpdo[0].channels}
    assert rx["velocity"].address == "0x60FF:00" and rx["velocity"].unit == "rad"
    assert rx["velocity"].factor == 10430.378
    assert rx["velocity_offset"].factor == 1000.0  # written here, overrides the merged one
    assert [c.is_gap for c in drive.rpdo[0].channels[-2:]] == [True, True]
    tx = {c.name: c for c in drive.tpdo[0].channels}
    assert tx["effort"].type.name == "int16" and tx["effort"].unit == "Nm"
    assert tx["effort"].factor == 0.0000958738  # the first merged mapping wins over *pad
    assert [c.mask for c in drive.tpdo[1].channels[:3]] == [1, 2, 4]
    assert [s.index for s in drive.sdo] == [0x6060, 0x60C2]
    assert [(s.index, s.type, s.pdo) for s in drive.sm] == [(2, "output", "rpdo"), (3, "input", "tpdo")]


def _line_col(text: str, needle: str) -> tuple[int, int]:
    """1-based line and column of the only occurrence of ``needle``."""
    hits = [
        (n, line.index(needle) + 1) for n, line in enumerate(text.splitlines(), start=1) if needle in line
    ]
    assert len(hits) == 1, hits
    return hits[0]


def test_error_in_a_written_override_points_at_the_override() -> None:
    text = ANCHORED_MAP.replace("command_interface: velocity}", "command_interface: velocity, unit: 5}")
    with pytest.raises(PdoMapError) as info:
        drive_map_from_text(text, "m.yaml")
    e = info.value
    assert e.path == "rpdo[0].channels[2].unit" and "expected a string" in e.message
    line, col = _line_col(text, "unit: 5")
    assert (e.line, e.column) == (line, col + len("unit: "))


def test_merged_key_wrong_only_where_merged_is_located_at_the_anchor() -> None:
    # the rpdo channel's anchor brings command_interface into a tpdo channel
    text = ANCHORED_MAP.replace("- {<<: *rad_in, index: 0x606c", "- {<<: *rad_out, index: 0x606c")
    with pytest.raises(PdoMapError) as info:
        drive_map_from_text(text, "m.yaml")
    e = info.value
    assert e.path == "tpdo[0].channels[2].command_interface", str(e)
    assert "belongs in the other direction" in e.message
    assert (e.line, e.column) == _line_col(text, "command_interface: position"), str(e)


def test_aliased_node_error_is_located_at_the_anchor() -> None:
    # an sdo entry reused as a channel: 'value' is unknown there; sdo is checked after rpdo
    text = ANCHORED_MAP.replace("- *pad\n", "- *sdo_mode\n")
    with pytest.raises(PdoMapError) as info:
        drive_map_from_text(text, "m.yaml")
    e = info.value
    assert e.path == "rpdo[0].channels[6].value" and "unknown key 'value'" in e.message, str(e)
    assert (e.line, e.column) == _line_col(text, "value: 8"), str(e)


NETWORK = """\
name: biped
cycle_time_us: 1000
buses:
  - &left
    name: left_leg
    type: ethercat
    interface: eth0
    slaves: &joints
      - {name: "hip_{i}", map: anchored_servo.yaml, count: 3}
      - {name: knee, map: anchored_servo.yaml}
  - {<<: *left, name: right_leg, interface: eth1}
  - {name: arms, type: sim, slaves: *joints}
"""


def test_anchored_network_loads_like_its_expansion(tmp_path: Path) -> None:
    (tmp_path / "anchored_servo.yaml").write_text(ANCHORED_MAP)
    (tmp_path / "net.yaml").write_text(NETWORK)
    (tmp_path / "expanded.yaml").write_text(expand(NETWORK))
    net = load_network(tmp_path / "net.yaml")
    assert [(b.name, b.type, b.interface, len(b.slaves)) for b in net.buses] == [
        ("left_leg", "ethercat", "eth0", 4),
        ("right_leg", "ethercat", "eth1", 4),
        ("arms", "sim", None, 4),
    ]
    assert [s.name for s in net.buses[1].slaves] == ["hip_0", "hip_1", "hip_2", "knee"]
    expanded = load_network(tmp_path / "expanded.yaml")
    assert expanded.buses == net.buses


def test_error_under_an_aliased_list_is_located_at_the_anchor(tmp_path: Path) -> None:
    (tmp_path / "anchored_servo.yaml").write_text(ANCHORED_MAP)
    text = NETWORK.replace("type: sim", "type: canopen")
    with pytest.raises(PdoMapError) as info:
        network_from_text(text, "net.yaml", base=tmp_path)
    e = info.value
    assert e.path == "buses[2].slaves[0]" and "needs 'node_id'" in e.message, str(e)
    assert (e.line, e.column) == _line_col(text, '{name: "hip_{i}"'), str(e)


def test_merge_key_is_overridden_by_a_written_key() -> None:
    doc = load_located("d: &d {type: int32, unit: rad}\nx: {<<: *d, type: uint16}\n", "m.yaml")
    assert doc.data["x"] == {"type": "uint16", "unit": "rad"}
    assert doc.where(("x", "type")) == (2, 19)  # written here
    assert doc.where(("x", "unit")) == (1, 27)  # merged: where it is written, in the anchor
    assert doc.where(("x", "unit"), key=True) == (1, 21)
    with pytest.raises(PdoMapError, match="duplicate key 'type'"):
        load_located("x: {type: a, type: b}\n")
    with pytest.raises(PdoMapError, match="merges a mapping"):
        load_located("x: {<<: [1]}\n")


def test_bomb_where_a_choice_is_expected_is_named_by_kind() -> None:
    """An error message never renders the value: a choice given a nine-level bomb says 'a list'."""
    text = alias_bomb(9, key="profile")
    start = time.perf_counter()
    with pytest.raises(PdoMapError, match="expected one of cia402, got a list"):
        drive_map_from_text(text, "bomb.yaml")
    assert time.perf_counter() - start < 1.0


def test_a_count_out_of_range_is_said_in_decimal_an_index_in_hex(tmp_path: Path) -> None:
    """Range errors write a value the way such a field is written: a count in decimal, an index in hex."""
    f = tmp_path / "net.yaml"
    f.write_text("cycle_time_us: 1000\nsafe_stop_after: 1000000\nbuses: []\n")
    with pytest.raises(PdoMapError, match=r"safe_stop_after: 1000000 out of range 1\.\.100000$"):
        load_network(f)
    m = tmp_path / "m.yaml"
    text = DEMO_MAP.read_text()
    assert "{index: 0x6040," in text
    m.write_text(text.replace("{index: 0x6040,", "{index: 0x10000,", 1))
    with pytest.raises(PdoMapError, match=r"0x10000 out of range 0\.\.0xFFFF"):
        load_drive_map(m)
