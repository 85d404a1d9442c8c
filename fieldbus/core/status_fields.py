"""What the observers carry of a bus's status, derived from the dataclass itself.

The recording, the testing kit's trace, the ``--monitor`` view and the DDS
diagnostics each show :class:`~fieldbus.network.BusStatus`. None of them lists
its fields by hand: they read :func:`status_fields` of the status class they
are given, so a field added to ``BusStatus`` appears in all four. Each field is
carried one of four ways, decided by its type once here:

- :attr:`Carry.NUMBER`: ``bool``, ``int`` or an ``IntEnum`` (``Verdict``), maybe
  ``| None``: one int64 per cycle (``None`` as :data:`NO_VALUE`);
- :attr:`Carry.TEXT`: ``str | None`` and anything else (a nested dataclass is
  shown by its ``str()``): kept when it changes (compared by identity);
- :attr:`Carry.PER_SLAVE`: a numpy array, one entry per slave (``fresh``);
- :attr:`Carry.CONSTANT`: fixed at bring-up (:data:`DECLARED`: the bus's name
  and expected working counter); carried once, beside the per-cycle data.

An observer that leaves a field out says so in its own ``EXCLUDED`` map (field
-> where else it is carried, or why not); :func:`check_covered` is the test's
check that every field is carried or excluded.
"""

from __future__ import annotations

import dataclasses
import enum
import sys
import types
import typing
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np

NO_VALUE = -(2**63)  # an int64 field with no value in that cycle (a ``None``)


class Carry(enum.Enum):
    """How an observer carries one status field (see the module)."""

    NUMBER = "number"
    TEXT = "text"
    PER_SLAVE = "per_slave"
    CONSTANT = "constant"


# the one declared mapping: fields whose type alone does not say how they are carried
DECLARED: dict[str, Carry] = {"name": Carry.CONSTANT, "expected_wkc": Carry.CONSTANT}


@dataclass(frozen=True)
class StatusField:
    """One field of a status dataclass and how it is carried."""

    name: str
    carry: Carry
    optional: bool = False  # ``None`` is a value of it (a NUMBER stores it as NO_VALUE)
    flag: bool = False  # a NUMBER that is a ``bool``


def _hints(cls: type) -> dict[str, Any]:
    """The resolved annotations of ``cls`` and its bases; one that cannot be resolved (it names a type
    imported for type checking only) is left out, the others still resolve."""
    try:
        return typing.get_type_hints(cls)
    except Exception:
        pass
    out: dict[str, Any] = {}
    for klass in reversed(cls.__mro__):
        module = sys.modules.get(klass.__module__)
        globalns = vars(module) if module is not None else {}
        for name, ann in vars(klass).get("__annotations__", {}).items():
            try:
                out.update(
                    typing.get_type_hints(types.SimpleNamespace(__annotations__={name: ann}), globalns)
                )
            except Exception:
                out.pop(name, None)
    return out


def _field(name: str, hint: Any) -> StatusField:
    """How the field ``name`` of type ``hint`` is carried (TEXT when the type says nothing else)."""
    args = typing.get_args(hint) if typing.get_origin(hint) in (typing.Union, types.UnionType) else (hint,)
    optional = type(None) in args
    rest = [a for a in args if a is not type(None)]
    base = (typing.get_origin(rest[0]) or rest[0]) if len(rest) == 1 else object
    carry = Carry.TEXT
    if isinstance(base, type) and issubclass(base, np.ndarray):
        carry = Carry.PER_SLAVE
    elif isinstance(base, type) and issubclass(base, int):  # bool, int, IntEnum
        carry = Carry.NUMBER
    return StatusField(name, DECLARED.get(name, carry), optional, base is bool)


def status_fields(cls: type) -> tuple[StatusField, ...]:
    """Every field of the dataclass ``cls`` (a :class:`~fieldbus.network.BusStatus` or subclass), in order.

    A field whose annotation cannot be resolved is carried as TEXT (its ``str()``): shown, never lost.
    """
    hints = _hints(cls)
    return tuple(_field(f.name, hints.get(f.name, object)) for f in dataclasses.fields(cls))


def of(cls: type, *carries: Carry, exclude: Iterable[str] = ()) -> tuple[StatusField, ...]:
    """The fields of ``cls`` carried one of the ways ``carries``, but those in ``exclude``."""
    skip = set(exclude)
    return tuple(f for f in status_fields(cls) if f.carry in carries and f.name not in skip)


def plain(value: object) -> object:
    """A status value as plain data (JSON): an enum by name, an array or a tuple as a list, a number or
    text as itself, ``None`` as ``None``, anything else (a nested dataclass) by its ``str()``."""
    if value is None or isinstance(value, bool | str | float):
        return value
    if isinstance(value, enum.Enum):
        return value.name
    if isinstance(value, int):
        return int(value)
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, tuple | list):
        return [plain(v) for v in value]
    return str(value)


def text(value: object) -> str | None:
    """A TEXT field's value as kept: ``None`` or its ``str()``."""
    return None if value is None else str(value)


def as_plain(status: object, exclude: Iterable[str] = ()) -> dict[str, object]:
    """Every field of the dataclass instance ``status`` but ``exclude``, as :func:`plain` data, in order."""
    skip = set(exclude)
    return {
        f.name: plain(getattr(status, f.name))
        for f in dataclasses.fields(status)  # type: ignore[arg-type]
        if f.name not in skip
    }


def event_fields(event: object, renamed: Mapping[str, str], exclude: Iterable[str] = ()) -> dict[str, object]:
    """Every field of the event dataclass ``event`` (``BusEvent``, ``DriveFault``, ``OutputClamp``, a
    subclass) but ``exclude``, as :func:`plain` data, a field named in ``renamed`` under its new name."""
    skip = set(exclude)
    return {
        renamed.get(f.name, f.name): plain(getattr(event, f.name))
        for f in dataclasses.fields(event)  # type: ignore[arg-type]
        if f.name not in skip
    }


def check_covered(cls: type, carried: Iterable[str], excluded: Mapping[str, str], observer: str) -> list[str]:
    """What ``observer`` neither carries nor excludes of ``cls`` (each with where to declare it); ``[]``: all."""
    have = set(carried)
    return [
        f"{cls.__name__}.{f.name} is neither carried by {observer} nor named in its EXCLUDED"
        for f in status_fields(cls)
        if f.name not in have and f.name not in excluded
    ]
