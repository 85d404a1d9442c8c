"""YAML loading that remembers where every value came from.

``load_located`` returns plain Python data plus the 1-based line/column of every
mapping key and value, so validation errors can name ``file:line:column`` and a
field path such as ``rpdo[0].channels[2].type``.
"""

from __future__ import annotations

from collections.abc import Hashable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml

from fieldbus.errors import PdoMapError

PathT = tuple[str | int, ...]
_MAX_DEPTH = 64


def format_path(path: PathT) -> str:
    """``("rpdo", 0, "type")`` -> ``"rpdo[0].type"``."""
    out = ""
    for part in path:
        if isinstance(part, int):
            out += f"[{part}]"
        else:
            out += f".{part}" if out else str(part)
    return out


@dataclass
class Located:
    """A loaded YAML document with the source position of each node."""

    data: Any
    file: str
    values: dict[PathT, tuple[int, int]] = field(default_factory=dict)
    keys: dict[PathT, tuple[int, int]] = field(default_factory=dict)
    collections: set[PathT] = field(default_factory=set)

    def where(self, path: PathT, *, key: bool = False) -> tuple[int | None, int | None]:
        """Line and column of ``path`` (its key if ``key``), else of its nearest parent."""
        probe = tuple(path)
        if (key or probe in self.collections) and probe in self.keys:
            return self.keys[probe]  # a whole list/mapping is reported at its key
        while True:
            if probe in self.values:
                return self.values[probe]
            if not probe:
                return (None, None)
            probe = probe[:-1]

    def error(self, path: PathT, message: str, *, key: bool = False) -> PdoMapError:
        """A :class:`PdoMapError` located at ``path``."""
        line, column = self.where(path, key=key)
        return PdoMapError(message, file=self.file, line=line, column=column, path=format_path(path))


def load_located(text: str, file: str = "<string>") -> Located:
    """Parse one YAML document; any syntax problem is a located :class:`PdoMapError`."""
    loader: yaml.SafeLoader | None = None
    try:
        loader = yaml.SafeLoader(text)
        node = loader.get_single_node()
        doc = Located(data=None, file=file)
        if node is not None:
            doc.data = _build(loader, node, (), doc, 0)
        return doc
    except yaml.MarkedYAMLError as exc:
        mark = exc.problem_mark or exc.context_mark
        msg = " ".join(p for p in (exc.context, exc.problem) if p) or "invalid YAML"
        raise PdoMapError(
            f"YAML syntax: {msg}",
            file=file,
            line=mark.line + 1 if mark else None,
            column=mark.column + 1 if mark else None,
        ) from None
    except yaml.reader.ReaderError as exc:
        raise PdoMapError(f"YAML: {exc.reason} (character 0x{exc.character:02X})", file=file) from None
    except yaml.YAMLError as exc:
        raise PdoMapError(f"YAML: {exc}", file=file) from None
    except RecursionError:
        raise PdoMapError("YAML nested too deeply", file=file) from None
    finally:
        if loader is not None:
            loader.dispose()


def load_file(path: str | Path) -> Located:
    """Read and parse ``path``; an unreadable file is a :class:`PdoMapError`."""
    p = Path(path)
    try:
        text = p.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise PdoMapError("file not found", file=str(p)) from None
    except UnicodeDecodeError as exc:
        raise PdoMapError(f"not UTF-8 text ({exc.reason} at byte {exc.start})", file=str(p)) from None
    except OSError as exc:
        raise PdoMapError(f"cannot read: {exc.strerror}", file=str(p)) from None
    return load_located(text, str(p))


def _mark(node: yaml.Node) -> tuple[int, int]:
    return (node.start_mark.line + 1, node.start_mark.column + 1)


def _build(loader: yaml.SafeLoader, node: yaml.Node, path: PathT, doc: Located, depth: int) -> Any:
    if depth > _MAX_DEPTH:
        raise doc.error(path, f"nested deeper than {_MAX_DEPTH} levels")
    doc.values[path] = _mark(node)
    if isinstance(node, (yaml.MappingNode, yaml.SequenceNode)):
        doc.collections.add(path)
    if isinstance(node, yaml.MappingNode):
        loader.flatten_mapping(node)  # resolves '<<' merge keys
        out: dict[Any, Any] = {}
        for key_node, value_node in node.value:
            if not isinstance(key_node, yaml.ScalarNode):
                raise PdoMapError(
                    "mapping keys must be plain scalars",
                    file=doc.file,
                    line=_mark(key_node)[0],
                    column=_mark(key_node)[1],
                    path=format_path(path),
                )
            key = loader.construct_object(key_node, deep=True)
            if not isinstance(key, Hashable):
                key = str(key)
            if isinstance(key, (bool, float)) or key is None:
                key = str(key_node.value)
            if key in out:
                raise PdoMapError(
                    f"duplicate key '{key}'",
                    file=doc.file,
                    line=_mark(key_node)[0],
                    column=_mark(key_node)[1],
                    path=format_path(path),
                )
            child: PathT = (*path, key)
            doc.keys[child] = _mark(key_node)
            out[key] = _build(loader, value_node, child, doc, depth + 1)
        return out
    if isinstance(node, yaml.SequenceNode):
        return [_build(loader, item, (*path, i), doc, depth + 1) for i, item in enumerate(node.value)]
    return loader.construct_object(node, deep=True)
