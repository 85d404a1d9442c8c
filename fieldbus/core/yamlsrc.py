"""YAML loading that remembers where every value came from.

``load_located`` returns plain Python data plus the 1-based line/column of every
mapping key and value, so validation errors can name ``file:line:column`` and a
field path such as ``rpdo[0].channels[2].type``.

Anchors, aliases and ``<<`` merge keys are supported. Each node is built once and
an alias shares the built object (as ``yaml.safe_load`` does), so a document of
nested aliases ("billion laughs") loads in time proportional to its text; the
data is read-only by convention, nothing may mutate it. Work done for aliases and
merges is still bounded by :data:`MAX_ALIAS_NODES`.
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
MAX_ALIAS_NODES = 100_000
"""Most alias uses plus keys copied by ``<<`` merges in one document (guards quadratic merge chains)."""
_MERGE_TAG = "tag:yaml.org,2002:merge"
_VALUE_TAG = "tag:yaml.org,2002:value"


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

    data: Any = field(repr=False)  # may share objects: its repr can be exponentially long
    file: str
    values: dict[PathT, tuple[int, int]] = field(default_factory=dict)
    keys: dict[PathT, tuple[int, int]] = field(default_factory=dict)
    collections: set[PathT] = field(default_factory=set)
    aliases: dict[PathT, PathT] = field(default_factory=dict)
    """Path of a reused (aliased or merged) node -> path where that node was built."""

    def resolve(self, path: PathT) -> PathT:
        """``path`` with any aliased prefix replaced by the path where its node was built."""
        probe = tuple(path)
        if not self.aliases:
            return probe
        for _ in range(len(probe) + len(self.aliases) + 1):  # every step consumes part of the path
            for n in range(len(probe), 0, -1):
                target = self.aliases.get(probe[:n])
                if target is not None:
                    probe = (*target, *probe[n:])
                    break
            else:
                break
        return probe

    def where(self, path: PathT, *, key: bool = False) -> tuple[int | None, int | None]:
        """Line and column of ``path`` (its key if ``key``), else of its nearest parent.

        A value reached through an alias or merge is reported where it is written,
        at its anchor; the key of an aliased value is reported where the alias is used.
        """
        probe = tuple(path)
        real = self.resolve(probe)
        if probe and (key or real in self.collections):  # a whole list/mapping is reported at its key
            at = self.keys.get((*self.resolve(probe[:-1]), probe[-1])) or self.keys.get(real)
            if at is not None:
                return at
        while True:
            if real in self.values:
                return self.values[real]
            if not probe:
                return (None, None)
            probe = probe[:-1]
            real = self.resolve(probe)

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
            doc.data = _Builder(loader, doc).build(node, (), 0)[0]
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


class _Builder:
    """Node graph -> plain data, building every node once.

    An alias (``*name``) or a ``<<`` merge reuses the object built for its anchor,
    as PyYAML does, so a "billion laughs" document costs what its text costs.
    Reuse is recorded as a path alias in :attr:`Located.aliases`: an error found
    under the reusing path is reported at the anchored node's source position.
    """

    def __init__(self, loader: yaml.SafeLoader, doc: Located) -> None:
        self.loader = loader
        self.doc = doc
        self.built: dict[int, tuple[Any, PathT, int]] = {}  # id(node) -> (object, first path, height)
        self.active: set[int] = set()  # collections being built: an alias to one of them is a cycle
        self.reused = 0

    def _reuse(self, path: PathT, count: int = 1) -> None:
        self.reused += count
        if self.reused > MAX_ALIAS_NODES:
            raise self.doc.error(
                path, f"YAML aliases and merge keys expand to more than {MAX_ALIAS_NODES} nodes"
            )

    def build(self, node: yaml.Node, path: PathT, depth: int) -> tuple[Any, int]:
        """``node`` as Python data and its height (0 for a scalar)."""
        if depth > _MAX_DEPTH:
            raise self.doc.error(path, f"nested deeper than {_MAX_DEPTH} levels")
        ident = id(node)
        seen = self.built.get(ident)
        if seen is not None:
            shared, first, shared_height = seen
            self._reuse(path)
            if depth + shared_height > _MAX_DEPTH:
                raise self.doc.error(path, f"nested deeper than {_MAX_DEPTH} levels")
            self.doc.aliases[path] = first
            return shared, shared_height
        if ident in self.active:
            line, column = _mark(node)
            raise PdoMapError(
                "YAML alias refers to a node that contains it (a recursive structure)",
                file=self.doc.file,
                line=line,
                column=column,
                path=format_path(path),
            )
        self.doc.values[path] = _mark(node)
        value: Any
        height = 0
        if isinstance(node, (yaml.MappingNode, yaml.SequenceNode)):
            self.doc.collections.add(path)
            self.active.add(ident)
            if isinstance(node, yaml.MappingNode):
                value, height = self._mapping(node, path, depth)
            else:
                value = []
                for i, item in enumerate(node.value):
                    child, child_height = self.build(item, (*path, i), depth + 1)
                    value.append(child)
                    height = max(height, child_height + 1)
            self.active.discard(ident)
        else:
            value = self.loader.construct_object(node, deep=True)
        self.built[ident] = (value, path, height)
        return value, height

    def _key(self, key_node: yaml.Node, path: PathT) -> Any:
        if not isinstance(key_node, yaml.ScalarNode):
            raise self._at(key_node, path, "mapping keys must be plain scalars")
        if key_node.tag == _VALUE_TAG:  # '=' as a key, as PyYAML's flatten_mapping reads it
            key_node.tag = "tag:yaml.org,2002:str"
        key = self.loader.construct_object(key_node, deep=True)
        if not isinstance(key, Hashable):
            key = str(key)
        if isinstance(key, (bool, float)) or key is None:
            key = str(key_node.value)
        return key

    def _at(self, node: yaml.Node, path: PathT, message: str) -> PdoMapError:
        line, column = _mark(node)
        return PdoMapError(message, file=self.doc.file, line=line, column=column, path=format_path(path))

    def _mapping(self, node: yaml.MappingNode, path: PathT, depth: int) -> tuple[dict[Any, Any], int]:
        out: dict[Any, Any] = {}
        height = 0
        merged: dict[Any, PathT] = {}  # key taken from a '<<' merge -> where its value was built
        merge_key: yaml.Node | None = None
        for key_node, value_node in node.value:
            if key_node.tag != _MERGE_TAG:
                continue
            if merge_key is not None:
                raise self._at(key_node, path, "duplicate key '<<'")
            merge_key = key_node
            sources = value_node.value if isinstance(value_node, yaml.SequenceNode) else [value_node]
            for i, source in enumerate(sources):  # an earlier mapping wins over a later one
                if not isinstance(source, yaml.MappingNode):
                    raise self._at(source, (*path, "<<"), "'<<' merges a mapping or a list of mappings")
                seen = self.built.get(id(source))
                if seen is None:  # an inline mapping, or a cycle that build() reports
                    self.build(source, (*path, "<<", i), depth + 1)
                    seen = self.built[id(source)]
                elif depth + 1 + seen[2] > _MAX_DEPTH:
                    raise self.doc.error(path, f"nested deeper than {_MAX_DEPTH} levels")
                data, first, source_height = seen
                height = max(height, source_height)
                self._reuse(path, len(data))
                for key, item in data.items():
                    if key not in out:
                        out[key] = item
                        merged[key] = self.doc.resolve((*first, key))
        explicit: set[Any] = set()
        for key_node, value_node in node.value:
            if key_node.tag == _MERGE_TAG:
                continue
            key = self._key(key_node, path)
            if key in explicit:
                raise self._at(key_node, path, f"duplicate key '{key}'")
            explicit.add(key)
            merged.pop(key, None)  # a key written here overrides a merged one
            child: PathT = (*path, key)
            self.doc.keys[child] = _mark(key_node)
            out[key], child_height = self.build(value_node, child, depth + 1)
            height = max(height, child_height + 1)
        for key, first in merged.items():
            self.doc.aliases[(*path, key)] = first
        return out, height
