"""A family's own part of a classic ``rawcan:`` section (``rawcan.<CanFamily.section>``) is parsed by the
family through :meth:`CanFamily.parse_section`, never by the classic parser: a third party's family owns a
key the same way the built-in ones do, and ``fieldbus/core/rawcan.py`` names no family of its own.

The refusals of the built-in families' sections are pinned word for word (users and tools match them).
The fake family is this test's own; there is no independent oracle for how our map loader reads a map.
"""

from __future__ import annotations

import sys
import types
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pytest
import yaml

from fieldbus.core import canfamily, rawcan
from fieldbus.core.canfamily import ClassicSection, families
from fieldbus.core.mitfamily import MitFamily
from fieldbus.core.pdo import load_drive_map
from fieldbus.errors import PdoMapError

ROOT = Path(__file__).resolve().parents[2]
MAPS = ROOT / "pdo_maps"


@dataclass(frozen=True)
class Gearbox:
    """The fake family's own section: a gear ratio and the command field it scales."""

    ratio: float
    field: str


class GearFamily(MitFamily):
    """MIT frames behind a gearbox: a third party's family owning ``rawcan.gearbox``."""

    name = "gearbox"
    section = "gearbox"

    @classmethod
    def parse_section(cls, r: Any, classic: ClassicSection) -> Gearbox:
        if "gearbox" not in classic.mapping:
            raise r.err(classic.path, "family gearbox needs its 'gearbox' section (ratio)")
        path = (*classic.path, "gearbox")
        m = r.mapping(classic.mapping["gearbox"], path, ("ratio", "field"), required=("ratio", "field"))
        ratio = r.number(m["ratio"], (*path, "ratio"))
        if not ratio > 0.0:
            raise r.err((*path, "ratio"), f"ratio {ratio:g} must be positive")
        field = r.string(m["field"], (*path, "field"))
        if field not in {f.name for f in classic.command}:
            raise r.err((*path, "field"), f"'{field}' is not a command field")
        return Gearbox(ratio, field)


CLASSIC = """\
name: geared
rawcan:
  family: {family}
  command:
    - {{name: position, bits: 16, min: -12.5, max: 12.5, unit: rad}}
    - {{name: velocity, bits: 12, min: -50.0, max: 50.0, unit: rad/s}}
    - {{name: kp, bits: 12, min: 0.0, max: 500.0}}
    - {{name: kd, bits: 12, min: 0.0, max: 5.0}}
    - {{name: torque, bits: 12, min: -18.0, max: 18.0, unit: N·m}}
  reply:
    - {{name: motor_id, bits: 8}}
    - {{name: position, bits: 16, min: -12.5, max: 12.5, unit: rad}}
    - {{name: velocity, bits: 12, min: -50.0, max: 50.0, unit: rad/s}}
    - {{name: torque, bits: 12, min: -18.0, max: 18.0, unit: N·m}}
{section}"""
GEARBOX = "  gearbox:\n    ratio: {ratio}\n    field: {field}\n"


@pytest.fixture
def gear_family(monkeypatch: pytest.MonkeyPatch) -> None:
    """GearFamily in the registry table, importable as ``gear_motors:GearFamily``."""
    module = types.ModuleType("gear_motors")
    module.GearFamily = GearFamily  # type: ignore[attr-defined]
    monkeypatch.setitem(sys.modules, "gear_motors", module)
    monkeypatch.setitem(canfamily.BUILTIN, "gearbox", "gear_motors:GearFamily")


def _write(tmp_path: Path, text: str) -> Path:
    path = tmp_path / "geared.yaml"
    path.write_text(text, encoding="utf-8")
    return path


def _geared(tmp_path: Path, family: str = "gearbox", ratio: str = "9", field: str = "velocity") -> Path:
    return _write(tmp_path, CLASSIC.format(family=family, section=GEARBOX.format(ratio=ratio, field=field)))


def test_a_registered_family_parses_its_own_section_of_a_map_file(gear_family: None, tmp_path: Path) -> None:
    dm = load_drive_map(_geared(tmp_path))
    cfg = dm.rawcan
    assert cfg is not None and cfg.family == "gearbox"
    assert cfg.section("gearbox") == Gearbox(9.0, "velocity")
    assert dict(cfg.sections) == {"gearbox": Gearbox(9.0, "velocity")}
    # the classic part is the MIT frame as ever: the family only added its own section
    assert [f.name for f in cfg.command] == ["position", "velocity", "kp", "kd", "torque"]
    assert cfg.damiao is None and cfg.odrive is None and cfg.cubemars is None


def test_the_hook_refuses_with_file_line_and_field(gear_family: None, tmp_path: Path) -> None:
    with pytest.raises(PdoMapError) as info:
        load_drive_map(_geared(tmp_path, ratio="-2"))
    e = info.value
    assert (e.path, e.message) == ("rawcan.gearbox.ratio", "ratio -2 must be positive")
    assert e.file is not None and e.file.endswith("geared.yaml") and e.line == 16
    with pytest.raises(PdoMapError, match="'speed' is not a command field"):
        load_drive_map(_geared(tmp_path, field="speed"))
    with pytest.raises(PdoMapError) as info:
        load_drive_map(_write(tmp_path, CLASSIC.format(family="gearbox", section="")))
    assert (info.value.path, info.value.message) == (
        "rawcan",
        "family gearbox needs its 'gearbox' section (ratio)",
    )


def test_another_familys_map_refuses_the_section(gear_family: None, tmp_path: Path) -> None:
    with pytest.raises(PdoMapError) as info:
        load_drive_map(_geared(tmp_path, family="mit"))
    assert (info.value.path, info.value.message) == (
        "rawcan.gearbox",
        "a 'gearbox' section needs family: gearbox",
    )


def test_without_the_family_the_section_is_an_unknown_key(tmp_path: Path) -> None:
    with pytest.raises(PdoMapError, match="unknown key 'gearbox'"):
        load_drive_map(_geared(tmp_path, family="mit"))


def test_a_family_claiming_a_classic_key_is_refused(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    monkeypatch.setattr(GearFamily, "section", "reply")
    with pytest.raises(TypeError, match="family gearbox's section 'reply'"):
        rawcan.section_owners({"gearbox": GearFamily})


def test_rawcan_py_names_no_family_of_its_own() -> None:
    """The classic parser reaches the families only through the registry and the hooks."""
    text = (ROOT / "fieldbus" / "core" / "rawcan.py").read_text(encoding="utf-8").lower()
    others = [name for name in families() if name not in rawcan.FAMILIES]
    assert {"damiao", "odrive", "cubemars"} <= set(others)
    assert [name for name in others if name in text] == []


def _edit(src: str, change: Any) -> Any:
    doc = yaml.safe_load((MAPS / src).read_text(encoding="utf-8"))
    change(doc["rawcan"])
    return doc


def _set(key: str, value: Any) -> Any:
    return lambda raw: raw.__setitem__(key, value)


def _drop(key: str) -> Any:
    return lambda raw: raw.pop(key)


def _cubemars_on_mit(raw: dict[str, Any]) -> None:
    raw["cubemars"] = yaml.safe_load((MAPS / "cubemars_ak10_9_mit.yaml").read_text())["rawcan"]["cubemars"]


def _wide_command(raw: dict[str, Any]) -> None:
    raw["command"].append({"name": "extra", "bits": 8})


# the built-in families' refusals, word for word as the classic parser gave them before the hooks
REFUSALS = [
    ("damiao_dm_j4310.yaml", _drop("damiao"), "rawcan",
     "family damiao needs its 'damiao' section (modes, registers, errors)"),
    ("damiao_dm_j4310.yaml", _set("family", "mit"), "rawcan.damiao", "a 'damiao' section needs family: damiao"),
    ("damiao_dm_j4310.yaml", _set("odrive", {}), "rawcan.odrive", "an 'odrive' section needs family: odrive"),
    ("odrive_s1.yaml", _drop("odrive"), "rawcan",
     "family odrive needs byte_order: little and its 'odrive' section (CANSimple)"),
    ("cubemars_ak10_9_mit.yaml", _drop("cubemars"), "rawcan",
     "family cubemars needs its 'cubemars' section (protocol servo or mit)"),
    ("cubemars_ak80_9_mit.yaml", _cubemars_on_mit, "rawcan.cubemars",
     "a 'cubemars' section needs family: cubemars"),
    ("cubemars_ak10_9_mit.yaml", _wide_command, "rawcan.command",
     "fields add up to 72 bits; a classic CAN frame is 8..64 bits"),
]  # fmt: skip


@pytest.mark.parametrize(("src", "change", "path", "message"), REFUSALS)
def test_built_in_sections_refuse_as_before(
    src: str, change: Any, path: str, message: str, tmp_path: Path
) -> None:
    target = tmp_path / src
    target.write_text(yaml.safe_dump(_edit(src, change), allow_unicode=True), encoding="utf-8")
    with pytest.raises(PdoMapError) as info:
        load_drive_map(target)
    assert (info.value.path, info.value.message) == (path, message)


def test_the_reference_documents_every_built_in_familys_section_key() -> None:
    """RAWCAN_KEYS holds the classic keys only now: the families' keys are checked here instead."""
    doc = (ROOT / "docs" / "yaml-reference.md").read_text(encoding="utf-8")
    keys = list(rawcan.section_owners(families()))
    assert sorted(keys) == ["cubemars", "damiao", "odrive"]
    assert [k for k in keys if f"`{k}`" not in doc] == []
