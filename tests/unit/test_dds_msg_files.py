"""The ``fieldbus_msgs`` ROS 2 package shipped in ``fieldbus/dds/fieldbus_msgs`` says what the wire says.

Each ``.msg`` / ``.srv`` file is parsed (ROS 2 interface syntax: ``type name``
per line, ``#`` comments, ``---`` between request and response) and compared
field by field, in order, with the cyclonedds IDL definitions the server
publishes (:mod:`fieldbus.dds.messages`, :mod:`fieldbus.dds.services`), so a
ROS 2 package built from these files reads and writes the same bytes.
"""

from __future__ import annotations

import re
import typing
from pathlib import Path
from typing import Any

import pytest

pytest.importorskip("cyclonedds")

import fieldbus.dds
from fieldbus.dds import messages as m
from fieldbus.dds import services as s

PKG = Path(fieldbus.dds.__file__).resolve().parent / "fieldbus_msgs"
FIELD = re.compile(r"^([A-Za-z0-9_/]+(?:\[\])?)\s+([a-z][a-z0-9_]*)$")
REQUEST_HEADER = ("client_guid", "sequence_number")  # rmw_cyclonedds' request header, not in the .srv


def _parse(path: Path, text: str | None = None) -> list[list[tuple[str, str]]]:
    """The parts of an interface file (one for .msg, request and response for .srv): (type, name)."""
    parts: list[list[tuple[str, str]]] = [[]]
    for no, raw in enumerate((path.read_text() if text is None else text).splitlines(), 1):
        line = raw.split("#", 1)[0].strip()
        if not line:
            continue
        if line == "---":
            parts.append([])
            continue
        hit = FIELD.match(line)
        assert hit, f"{path.name}:{no}: not a 'type name' line: {raw!r}"
        parts[-1].append((hit.group(1), hit.group(2)))
    return parts


def _ros_type(hint: Any) -> str:
    """The ROS 2 interface type of a cyclonedds field annotation."""
    if hint is bool:
        return "bool"
    if hint is str:
        return "string"
    name = getattr(hint, "__idl_typename__", None)
    if name is not None:  # a nested struct: pkg::msg::dds_::Type_ -> pkg/Type
        pkg, _, _, typ = name.split("::")
        return f"{pkg}/{typ.rstrip('_')}"
    if typing.get_origin(hint) is typing.Annotated:
        base, *meta = typing.get_args(hint)
        if isinstance(meta[0], str):
            return meta[0]  # uint8 ... float64
        (item,) = typing.get_args(base)
        return _ros_type(item) + "[]"
    raise AssertionError(f"no ROS 2 type for {hint!r}")


def _idl_fields(cls: type, skip: tuple[str, ...] = ()) -> list[tuple[str, str]]:
    hints = typing.get_type_hints(cls, include_extras=True)
    return [(_ros_type(h), n) for n, h in hints.items() if n not in skip]


@pytest.mark.parametrize("cls", [m.AxisState, m.JointCommand, m.Request, m.Reply], ids=lambda c: c.__name__)
def test_each_msg_file_has_the_idl_fields_in_order(cls: type) -> None:
    (fields,) = _parse(PKG / "msg" / f"{cls.__name__}.msg")
    assert fields == _idl_fields(cls)
    assert cls.__idl_typename__ == f"fieldbus_msgs::msg::dds_::{cls.__name__}_"  # type: ignore[attr-defined]


@pytest.mark.parametrize("name", ["SetMode", "SdoRead", "SdoWrite"])
def test_each_srv_file_has_the_request_and_response_fields_in_order(name: str) -> None:
    request, response = _parse(PKG / "srv" / f"{name}.srv")
    req_cls, rep_cls = getattr(s, f"{name}Request"), getattr(s, f"{name}Response")
    assert request == _idl_fields(req_cls, REQUEST_HEADER)
    assert response == _idl_fields(rep_cls, REQUEST_HEADER)
    assert req_cls.__idl_typename__ == f"fieldbus_msgs::srv::dds_::{name}_Request_"


def test_the_package_lists_every_interface_file_and_nothing_else() -> None:
    files = sorted(str(p.relative_to(PKG)) for p in PKG.glob("*/*.*"))
    cmake = (PKG / "CMakeLists.txt").read_text()
    assert sorted(re.findall(r'"((?:msg|srv)/\w+\.(?:msg|srv))"', cmake)) == files
    fieldbus_types = {
        t.split("::")[-1].rstrip("_").removesuffix("_Request").removesuffix("_Response")
        for t in (
            c.__idl_typename__
            for c in (*vars(m).values(), *vars(s).values())
            if isinstance(c, type) and hasattr(c, "__idl_typename__")
        )
        if t.startswith("fieldbus_msgs::")
    }
    assert {Path(f).stem for f in files} == fieldbus_types
    assert "<name>fieldbus_msgs</name>" in (PKG / "package.xml").read_text()


def test_a_field_the_file_lacks_is_caught() -> None:
    """The comparison can fail: a .msg without one field does not match its IDL type."""
    path = PKG / "msg" / "Reply.msg"
    (fields,) = _parse(path, path.read_text().replace("bool ok ", "", 1))
    assert [f for f in _idl_fields(m.Reply) if f not in fields] == [("bool", "ok")]
