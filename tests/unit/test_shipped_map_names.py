"""A network file names a shipped drive map as ``map: shipped:NAME``, wherever the file is."""

from __future__ import annotations

from pathlib import Path

import pytest

import fieldbus
from fieldbus import PdoMapError


def _net(tmp_path: Path, map_entry: str, bus: str = "type: sim\n    interface: sim") -> Path:
    f = tmp_path / "net.yaml"
    node = ", node_id: 1" if "rawcan" in bus else ""
    f.write_text(
        "cycle_time_us: 1000\nbuses:\n"
        f"  - name: arm\n    {bus}\n"
        f"    slaves:\n      - {{name: 'j{{i}}', map: {map_entry}, count: 2{node}}}\n"
    )
    return f


@pytest.mark.parametrize(
    "entry", ["shipped:generic_cia402", "shipped:generic_cia402.yaml", "'shipped: elmo_gold'"]
)
def test_a_network_file_names_a_shipped_map_without_a_path(tmp_path: Path, entry: str) -> None:
    net = fieldbus.load_network(_net(tmp_path, entry))
    stem = entry.strip("'").split(":")[1].strip().removesuffix(".yaml")
    shipped = fieldbus.load_drive_map(fieldbus.PDO_MAPS / f"{stem}.yaml")
    drives = [s.map for s in net.buses[0].slaves]
    assert len(drives) == 2 and all(d == shipped for d in drives)


def test_every_shipped_map_has_a_name_a_network_file_can_use(tmp_path: Path) -> None:
    names = sorted(f.stem for f in fieldbus.PDO_MAPS.glob("*.yaml"))
    assert len(names) >= 10
    for name in names:
        shipped = fieldbus.load_drive_map(fieldbus.PDO_MAPS / f"{name}.yaml")
        bus = "type: rawcan\n    interface: vcan0" if shipped.rawcan else "type: sim\n    interface: sim"
        assert fieldbus.load_network(_net(tmp_path, f"shipped:{name}", bus)).buses[0].slaves[0].map == shipped


def test_a_bare_shipped_file_name_not_found_says_how_to_name_the_shipped_map(tmp_path: Path) -> None:
    with pytest.raises(PdoMapError) as info:
        fieldbus.load_network(_net(tmp_path, "generic_cia402.yaml"))
    assert "map file not found: generic_cia402.yaml" in str(info.value)
    assert "map: shipped:generic_cia402" in str(info.value)
    assert info.value.line == 7 and info.value.path == "buses[0].slaves[0].map"


def test_any_other_missing_map_says_shipped_maps_have_names(tmp_path: Path) -> None:
    with pytest.raises(PdoMapError, match=r"map: shipped:NAME' \(fieldbus.PDO_MAPS\)"):
        fieldbus.load_network(_net(tmp_path, "my_joint.yaml"))


@pytest.mark.parametrize(
    ("entry", "says"),
    [
        ("shipped:generic_cia40", "did you mean 'shipped:generic_cia402'"),
        ("shipped:../../pyproject.toml", "no shipped drive map '../../pyproject.toml'"),
        ("shipped:/etc/passwd.yaml", "no shipped drive map '/etc/passwd.yaml'"),
        (
            "'shipped:'",
            "the shipped maps are " + ", ".join(sorted(p.stem for p in fieldbus.PDO_MAPS.glob("*.yaml"))),
        ),
    ],
)
def test_an_unknown_shipped_name_is_refused_with_the_names(tmp_path: Path, entry: str, says: str) -> None:
    with pytest.raises(PdoMapError) as info:
        fieldbus.load_network(_net(tmp_path, entry))
    assert says in str(info.value)
    assert info.value.path == "buses[0].slaves[0].map"
