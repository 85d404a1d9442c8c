"""Fuzzing: malformed drive maps and network files raise nothing but PdoMapError.

CI runs 2,000 cases per test; the long run is documented in docs/reliability.md:
``FIELDBUS_FUZZ_EXAMPLES=10000 pytest tests/unit/test_fuzz_maps.py``.
"""

from __future__ import annotations

import copy
import os
from pathlib import Path
from typing import Any

import pytest
import yaml
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from fieldbus.core.network import network_from_text
from fieldbus.core.pdo import drive_map_from_text
from fieldbus.core.pdo.image import ProcessImage
from fieldbus.core.pdo.layout import layout
from fieldbus.core.sdo import canopen_plan, coe_plan
from fieldbus.errors import FieldbusError, PdoMapError

EXAMPLES = int(os.environ.get("FIELDBUS_FUZZ_EXAMPLES", "2000"))
_DUMPER: Any = getattr(yaml, "CSafeDumper", yaml.SafeDumper)
INTEROP = Path(__file__).resolve().parents[1] / "data" / "ethercat_driver_ros2"
SEEDS = [
    (INTEROP / f).read_text()
    for f in ("beckhoff_ek1914.yaml", "beckhoff_el1918.yaml", "maxon_epos4_50_5.yaml")
] + [
    """
name: can_servo
vendor_id: 0x9
product_id: 0x10
profile: cia402
canopen: {heartbeat_ms: 100, pdo: [{index: 0x1a00, transmission_type: 1}]}
rpdo:
  - index: 0x1600
    channels:
      - {index: 0x6040, sub_index: 0, type: uint16}
      - {index: 0x607a, sub_index: 0, type: int32, factor: 1000, unit: rad}
      - {index: 0x6060, sub_index: 0, type: int8, default: 8}
      - {index: 0, sub_index: 0, type: bit8}
tpdo:
  - index: 0x1a00
    channels:
      - {index: 0x6041, sub_index: 0, type: uint16}
      - {index: 0x6064, sub_index: 0, type: int32, factor: 0.001}
      - {index: 0x2000, sub_index: 1, type: bool, mask: 1}
      - {index: 0, sub_index: 0, type: bit15}
sm:
  - {index: 2, type: output, pdo: rpdo, watchdog: enable}
"""
]
SEEDS.append((Path(__file__).resolve().parents[2] / "pdo_maps" / "cubemars_ak80_9_mit.yaml").read_text())
SEED_DOCS = [yaml.safe_load(s) for s in SEEDS]


def alias_bomb(levels: int, key: str = "description", *, mapping: bool = False, head: str = "") -> str:
    """``width ** levels`` leaves under ``key`` through nested anchors ("billion laughs")."""
    head = head or "name: bomb\nvendor_id: 1\nproduct_id: 2\n"
    lines = [f"{key}:", f"  - &l0 [{', '.join(['lol'] * 10)}]"]
    for i in range(1, levels + 1):
        if mapping:
            lines.append(f"  - &l{i} {{{', '.join(f'k{j}: *l{i - 1}' for j in range(10))}}}")
        else:
            lines.append(f"  - &l{i} [{', '.join([f'*l{i - 1}'] * 10)}]")
    return head + "\n".join(lines) + "\n"


# Text-only seeds: yaml.safe_dump of a loaded bomb would write out every one of its 10**9 leaves.
ALIAS_BOMBS = [
    alias_bomb(levels, key, mapping=mapping)
    for levels in (3, 6, 9)
    for key, mapping in (("description", False), ("rpdo", False), ("sdo", True), ("ethercat", True))
] + [alias_bomb(9, head=SEEDS[3]), alias_bomb(9, "buses", head="name: net\n")]
# The hostile corpus's small text files (tests/data/hostile, every command against it in
# test_fuzz_hostile_files.py) as seeds too: their mutations must raise nothing but PdoMapError either.
HOSTILE = Path(__file__).resolve().parents[1] / "data" / "hostile"
HOSTILE_SEEDS = []
for _p in sorted(HOSTILE.iterdir()):
    if _p.is_file() and _p.suffix in (".yaml", ".yml", "") and _p.stat().st_size < 8000:
        try:
            HOSTILE_SEEDS.append(_p.read_bytes().decode("utf-8"))
        except UnicodeDecodeError:
            continue
TEXT_SEEDS = SEEDS + ALIAS_BOMBS + HOSTILE_SEEDS

garbage = st.one_of(
    st.none(),
    st.booleans(),
    st.integers(-(2**70), 2**70),
    st.floats(allow_nan=True, allow_infinity=True),
    st.text(max_size=12),
    st.sampled_from(
        ["bool", "int33", "bit0", "bit65", "bit7", "uint64", "double", "0x6040", "rpdo", "enable"]
    ),
    st.lists(st.integers(-5, 70000), max_size=3),
    st.dictionaries(
        st.sampled_from(["index", "type", "x", "channels"]), st.integers(-1, 0x20000), max_size=3
    ),
)


def _paths(node: Any, prefix: tuple[Any, ...] = ()) -> list[tuple[Any, ...]]:
    out = [prefix]
    if isinstance(node, dict):
        for k, v in node.items():
            out += _paths(v, (*prefix, k))
    elif isinstance(node, list):
        for i, v in enumerate(node):
            out += _paths(v, (*prefix, i))
    return out


def _set(doc: Any, path: tuple[Any, ...], value: Any) -> Any:
    if not path:
        return value
    parent = doc
    for p in path[:-1]:
        parent = parent[p]
    parent[path[-1]] = value
    return doc


def _delete(doc: Any, path: tuple[Any, ...]) -> Any:
    if not path:
        return None
    parent = doc
    for p in path[:-1]:
        parent = parent[p]
    del parent[path[-1]]
    return doc


@st.composite
def mutated_docs(draw: Any) -> str:
    doc = copy.deepcopy(draw(st.sampled_from(SEED_DOCS)))
    for _ in range(draw(st.integers(1, 4))):
        paths = _paths(doc)
        path = draw(st.sampled_from(paths))
        op = draw(st.sampled_from(["set", "set", "delete", "add_key", "dup_list_item"]))
        try:
            if op == "set":
                doc = _set(doc, path, draw(garbage))
            elif op == "delete":
                doc = _delete(doc, path)
            elif op == "add_key":
                target = doc
                for p in path:
                    target = target[p]
                if isinstance(target, dict):
                    target[
                        draw(st.sampled_from(["mask", "factor", "unit", "bogus", "default", "fixed", "pdo"]))
                    ] = draw(garbage)
            elif op == "dup_list_item":
                target = doc
                for p in path:
                    target = target[p]
                if isinstance(target, list) and target:
                    target.append(copy.deepcopy(target[draw(st.integers(0, len(target) - 1))]))
        except (KeyError, IndexError, TypeError):
            pass
    # libyaml's emitter where installed: the same YAML, in a tenth of the time (the suite's time, issue 38)
    return yaml.dump(doc, Dumper=_DUMPER, sort_keys=False, allow_unicode=True)


@st.composite
def corrupted_text(draw: Any) -> str:
    text = draw(st.sampled_from(TEXT_SEEDS))
    for _ in range(draw(st.integers(1, 5))):
        pos = draw(st.integers(0, max(0, len(text) - 1)))
        op = draw(st.sampled_from(["insert", "delete", "replace"]))
        chunk = draw(
            st.sampled_from(
                [
                    "{",
                    "}",
                    "[",
                    ":",
                    "- ",
                    "\n",
                    "  ",
                    "&a",
                    "*a",
                    "!!python/object ",
                    "<<: *a",
                    "\t",
                    "'",
                    '"',
                    "%",
                    "0x",
                    "~",
                    "\x00",
                ]
            )
        )
        if op == "insert":
            text = text[:pos] + chunk + text[pos:]
        elif op == "delete":
            text = text[:pos] + text[pos + draw(st.integers(1, 20)) :]
        else:
            text = text[:pos] + chunk + text[pos + len(chunk) :]
    return text


def _exercise(text: str) -> None:
    """Everything a valid map feeds must work; anything else must be a PdoMapError."""
    try:
        drive = drive_map_from_text(text, "fuzz.yaml")
    except PdoMapError as exc:
        assert exc.file == "fuzz.yaml"
        str(exc)
        return
    for align in (1, 8):
        lay = layout(drive, pdo_align=align)
        img = ProcessImage(lay, 2)
        img.outputs.to_wire()
        img.inputs.from_wire()
    try:
        coe_plan(drive)
    except FieldbusError as exc:  # e.g. start-up SDOs with ethercat.coe false: a typed, named error
        assert "CoE" in str(exc)
    if drive.canopen is not None:
        canopen_plan(drive, 1)


SETTINGS = settings(max_examples=EXAMPLES, deadline=None, suppress_health_check=list(HealthCheck))


@SETTINGS
@given(mutated_docs())
def test_mutated_maps_raise_only_pdo_map_error(text: str) -> None:
    _exercise(text)


@SETTINGS
@given(corrupted_text())
def test_corrupted_yaml_raises_only_pdo_map_error(text: str) -> None:
    _exercise(text)


@pytest.mark.timeout(120)
def test_alias_bombs_are_refused_with_work_in_proportion_to_their_text(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """Work counted in node builds and Reader calls, not seconds: a bomb costs what its text costs.

    Expanded, the largest bombs hold 10**9 leaves; a loader or reader that walked them would also
    overrun the test's timeout.
    """
    from fieldbus.core import yamlsrc
    from fieldbus.core.yamlread import Reader

    calls = [0]

    def counted(cls: Any, name: str) -> None:
        original = getattr(cls, name)

        def wrapper(*args: Any, **kwargs: Any) -> Any:
            calls[0] += 1
            return original(*args, **kwargs)

        monkeypatch.setattr(cls, name, wrapper)

    counted(yamlsrc._Builder, "build")
    for name in ("mapping", "sequence", "integer", "number", "string", "name", "choice", "boolean"):
        counted(Reader, name)
    for text in ALIAS_BOMBS:
        bound = (
            20 * text.count(",") + 20 * text.count("\n") + 100
        )  # nodes written in the text, times a constant
        calls[0] = 0
        _exercise(text)
        assert calls[0] <= bound, (calls[0], bound, text[:200])
        calls[0] = 0
        with pytest.raises(PdoMapError):
            network_from_text(text, "net.yaml", base=INTEROP)
        assert calls[0] <= bound, (calls[0], bound, text[:200])


@settings(max_examples=EXAMPLES // 4, deadline=None, suppress_health_check=list(HealthCheck))
@given(
    st.recursive(
        garbage,
        lambda inner: st.one_of(
            st.lists(inner, max_size=3),
            st.dictionaries(
                st.sampled_from(["buses", "name", "type", "slaves", "map", "node_id", "count", "interface"]),
                inner,
                max_size=4,
            ),
        ),
        max_leaves=12,
    )
)
def test_random_network_documents_raise_only_pdo_map_error(doc: Any) -> None:
    try:
        text = yaml.safe_dump(doc)
    except yaml.YAMLError:
        return
    try:
        network_from_text(text, "net.yaml", base=INTEROP)
    except PdoMapError as exc:
        assert exc.file is not None
