"""Typed, located reading of a loaded YAML document.

:class:`Reader` checks the shape and type of each value of a
:class:`~fieldbus.core.yamlsrc.Located` document; every problem is a
:class:`~fieldbus.errors.PdoMapError` naming ``file:line:column`` and the field
path. Used by drive maps (``fieldbus.core.pdo.load``), their ``rawcan:`` section
and network files (``fieldbus.core.network``).
"""

from __future__ import annotations

import difflib
import math
from collections.abc import Iterable, Mapping
from typing import Any

from fieldbus.core.yamlsrc import Located, PathT, key_token, token
from fieldbus.errors import PdoMapError


class Reader:
    """Typed, located access to a loaded YAML document (drive maps, rawcan sections, network files)."""

    def __init__(self, doc: Located) -> None:
        self.doc = doc

    def err(self, path: PathT, message: str, *, key: bool = False) -> PdoMapError:
        return self.doc.error(path, message, key=key)

    def mapping(
        self, value: Any, path: PathT, allowed: Iterable[str], required: Iterable[str] = ()
    ) -> Mapping[Any, Any]:
        """``value`` as a mapping with only ``allowed`` keys and every ``required`` key."""
        if not isinstance(value, Mapping):
            raise self.err(path, f"expected a mapping, got {_kind(value)}")
        allowed = tuple(allowed)
        for key in value:
            if key not in allowed:
                shown = key_token(key)
                near = difflib.get_close_matches(shown, allowed, n=1, cutoff=0.6)
                hint = f" (did you mean {near[0]}?)" if near else f" (allowed: {', '.join(allowed)})"
                raise self.err((*path, key), f"unknown key '{shown}'{hint}", key=True)
        for key in required:
            if key not in value:
                raise self.err(path, f"missing required key '{key}'")
        return value

    def sequence(self, value: Any, path: PathT) -> list[Any]:
        if value is None:
            return []
        if not isinstance(value, list):
            raise self.err(path, f"expected a list, got {_kind(value)}")
        return value

    def integer(self, value: Any, path: PathT, lo: int, hi: int) -> int:
        """An int in ``[lo, hi]``; hex strings such as ``"0x6040"`` and whole floats (``1e3``) are accepted."""
        if isinstance(value, float) and value.is_integer() and abs(value) <= 2**53:
            value = int(value)  # 1e3, 2.5e+3: exponent notation of a whole number
        if isinstance(value, str):
            try:
                value = int(value.strip(), 0)
            except ValueError:
                raise self.err(path, f"expected an integer, got '{token(value)}'") from None
        if isinstance(value, bool) or not isinstance(value, int):
            raise self.err(path, f"expected an integer, got {_kind(value)}")
        if not lo <= value <= hi:
            # hex for what is written in hex: an identifier, an index, a field as wide as its bits
            name = str(path[-1]) if path else ""
            hexa = name.endswith(("id", "index")) or (hi > 255 and hi & (hi + 1) == 0)
            raise self.err(path, f"{_num(value, hexa)} out of range {_num(lo, hexa)}..{_num(hi, hexa)}")
        return value

    def number(self, value: Any, path: PathT, *, allow_nan: bool = False) -> float:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise self.err(path, f"expected a number, got {_kind(value)}")
        if isinstance(value, float) and not math.isfinite(value) and not (allow_nan and math.isnan(value)):
            raise self.err(path, f"expected a finite number, got {value}")
        return float(value)

    def boolean(self, value: Any, path: PathT) -> bool:
        if not isinstance(value, bool):
            raise self.err(path, f"expected true or false, got {_kind(value)}")
        return value

    def string(self, value: Any, path: PathT) -> str:
        if not isinstance(value, str):
            raise self.err(path, f"expected a string, got {_kind(value)}")
        return value

    def name(self, value: Any, path: PathT) -> str:
        text = self.string(value, path)
        if not text or not text.isprintable() or any(ch in text for ch in " \t,:[]{}'\""):
            raise self.err(path, f"'{token(text)}' is not a usable name (no spaces, quotes or ,:[]{{}})")
        return text

    def choice(self, value: Any, path: PathT, options: Iterable[str]) -> str:
        options = tuple(options)
        if isinstance(value, bool):  # YAML 1.1 reads on/off/yes/no as booleans
            raise self.err(
                path,
                f"'{str(value).lower()}' is a YAML boolean here; write one of {', '.join(options)} in quotes",
            )
        if not isinstance(value, str):  # never str() it: an aliased list can hold 10**9 leaves
            raise self.err(path, f"expected one of {', '.join(options)}, got {_kind(value)}")
        if value not in options:
            near = difflib.get_close_matches(token(value), options, n=1, cutoff=0.5)
            hint = f" (did you mean {near[0]}?)" if near else ""
            raise self.err(path, f"'{token(value)}' is not one of {', '.join(options)}{hint}")
        return value


def _kind(value: Any) -> str:
    if value is None:
        return "nothing"
    if isinstance(value, bool):
        return f"a boolean ({value})"
    if isinstance(value, Mapping):
        return "a mapping"
    if isinstance(value, list):
        return "a list"
    if isinstance(value, str):
        return f"a string ('{token(value)}')"
    return f"{type(value).__name__} ({token(repr(value))})"


def _num(v: int, hexa: bool) -> str:
    return f"0x{v:X}" if hexa and v > 255 else str(v)
