"""Bus types are declared by the backends and found through the registry (fieldbus.registry).

A backend registered in the ``fieldbus.backends`` entry-point group brings its
own bus type: a network file may name it, its declared options are checked
like a built-in backend's, and an unknown type is refused at its place in the
file with the list of known ones (the registered one among them).
"""

from __future__ import annotations

import sys
import types
from importlib.metadata import EntryPoint
from pathlib import Path
from typing import Any, ClassVar

import pytest

from fieldbus import registry
from fieldbus.backends import backend_class
from fieldbus.core.network import backend_options, check_open_options, is_can_type, load_network
from fieldbus.errors import FieldbusError, PdoMapError

NETWORK = """\
name: plugin_bus
buses:
  - name: arm
    type: {kind}
    slaves:
      - {{name: j1, map: "shipped:generic_cia402"}}
"""


class AcmeBackend:
    """Stands in for a third-party backend: only what the registry reads is declared."""

    bus_options: ClassVar[tuple[str, ...]] = ("acme_port",)
    can_bus: ClassVar[bool] = False


@pytest.fixture
def acme(monkeypatch: pytest.MonkeyPatch) -> type[AcmeBackend]:
    module = types.ModuleType("acme_fieldbus")
    module.AcmeBackend = AcmeBackend  # type: ignore[attr-defined]
    monkeypatch.setitem(sys.modules, "acme_fieldbus", module)
    eps = [EntryPoint("acme", "acme_fieldbus:AcmeBackend", registry.GROUP)]

    def entry_points(**kw: Any) -> list[EntryPoint]:
        return eps if kw.get("group") == registry.GROUP else []

    monkeypatch.setattr(registry, "entry_points", entry_points)
    return AcmeBackend


def _write(tmp_path: Path, kind: str) -> Path:
    path = tmp_path / "net.yaml"
    path.write_text(NETWORK.format(kind=kind))
    return path


def test_a_network_file_names_a_bus_type_registered_by_entry_point(
    acme: type[AcmeBackend], tmp_path: Path
) -> None:
    net = load_network(_write(tmp_path, "acme"))
    assert [b.type for b in net.buses] == ["acme"]
    assert net.buses[0].slaves[0].name == "j1"
    assert not net.buses[0].is_can
    assert backend_class("acme") is acme  # type: ignore[comparison-overlap]
    assert backend_options("acme") == ("acme_port",)
    check_open_options(net, None, {"acme_port": 1})
    with pytest.raises(FieldbusError, match=r"unknown option 'acme_prot'.*did you mean acme_port"):
        check_open_options(net, None, {"acme_prot": 1})


def test_without_the_entry_point_the_type_is_refused_at_its_line_with_the_known_ones(tmp_path: Path) -> None:
    path = _write(tmp_path, "acme")
    with pytest.raises(PdoMapError) as err:
        load_network(path)
    assert str(err.value) == f"{path}:4:11 buses[0].type: 'acme' is not one of sim, ethercat, canopen, rawcan"


def test_an_unknown_type_lists_the_registered_ones_too(acme: type[AcmeBackend], tmp_path: Path) -> None:
    with pytest.raises(PdoMapError, match=r"'acme2' is not one of .*acme.*did you mean acme"):
        load_network(_write(tmp_path, "acme2"))


def test_built_in_types_keep_their_declarations() -> None:
    assert registry.bus_type_names()[:4] == ("sim", "ethercat", "canopen", "rawcan")
    assert is_can_type("canopen") and is_can_type("rawcan")
    assert not is_can_type("ethercat") and not is_can_type("sim") and not is_can_type("nope")
    assert backend_options("nope") is None  # no backend: nothing to check against


class AcmeCanBackend:
    """A registered CAN backend: its buses take node ids and a bit rate."""

    can_bus: ClassVar[bool] = True  # no bus_options: it takes any option


def test_a_registered_can_type_takes_node_ids_and_a_bitrate(
    monkeypatch: pytest.MonkeyPatch, tmp_path: Path
) -> None:
    module = types.ModuleType("acme_can")
    module.AcmeCanBackend = AcmeCanBackend  # type: ignore[attr-defined]
    monkeypatch.setitem(sys.modules, "acme_can", module)
    ep = EntryPoint("acmecan", "acme_can:AcmeCanBackend", registry.GROUP)
    monkeypatch.setattr(
        registry, "entry_points", lambda **kw: [ep] if kw.get("group") == registry.GROUP else []
    )
    path = tmp_path / "can.yaml"
    path.write_text(
        NETWORK.format(kind="acmecan")
        .replace("    slaves:", "    bitrate: 500000\n    slaves:")
        .replace('"shipped:generic_cia402"}', '"shipped:generic_cia402", node_id: 5}')
    )
    bus = load_network(path).buses[0]
    assert bus.is_can and bus.bitrate == 500_000
    assert [s.node_id for s in bus.slaves] == [5]
    assert backend_options("acmecan") is None
    check_open_options(load_network(path), None, {"whatever": 1})  # declares none: any option passes
    path.write_text(NETWORK.format(kind="acmecan"))
    with pytest.raises(PdoMapError, match="a CAN slave needs 'node_id'"):
        load_network(path)
