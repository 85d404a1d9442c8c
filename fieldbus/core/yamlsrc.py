"""YAML loading that remembers where every value came from.

``load_located`` returns plain Python data plus the 1-based line/column of every
mapping key and value, so validation errors can name ``file:line:column`` and a
field path such as ``rpdo[0].channels[2].type``.

Anchors, aliases and ``<<`` merge keys are supported. Each node is built once and
an alias shares the built object (as ``yaml.safe_load`` does), so a document of
nested aliases ("billion laughs") loads in time proportional to its text; the
data is read-only by convention, nothing may mutate it. Work done for aliases and
merges is still bounded by :data:`MAX_ALIAS_NODES`.

Numbers in exponent form without a dot (``5e-6``, ``1E3``, ``1.5e3``) are floats,
as in YAML 1.2 and JSON; PyYAML's YAML 1.1 rule alone would read them as strings.

``load_file`` reads only a regular file of at most :data:`MAX_FILE_BYTES`,
refuses binary and non-UTF-8 content without quoting it, and drops a UTF-8 BOM.
"""

from __future__ import annotations

import re
import stat
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
_FLOAT_TAG = "tag:yaml.org,2002:float"
MAX_FILE_BYTES = 8 * 1024 * 1024
"""Largest YAML file read (the shipped maps are a few kB; an ESI-derived map some 100 kB)."""
TOKEN_CHARS = 32
"""Most characters of a file's text that a message quotes (a key, a value, a YAML token)."""

# YAML 1.2 core schema floats that YAML 1.1 reads as strings: an exponent without a dot before it,
# or without a sign (5e-6, 1E3, 1.5e3, .5e3). Dotted forms with a signed exponent are 1.1 floats already.
_EXP_FLOAT = re.compile(r"^[-+]?(?:[0-9][0-9_]*(?:\.[0-9_]*)?|\.[0-9][0-9_]*)[eE][-+]?[0-9]+$")


class _Loader(yaml.SafeLoader):
    """PyYAML's safe loader plus the exponent floats of :data:`_EXP_FLOAT`."""


_Loader.add_implicit_resolver(_FLOAT_TAG, _EXP_FLOAT, list("-+0123456789."))

_FastLoader: type[Any] | None = None
if getattr(yaml, "__with_libyaml__", False):

    class _CLoader(yaml.CSafeLoader):
        """libyaml's parser with the same resolvers: the same nodes and marks, several times faster."""

    _CLoader.add_implicit_resolver(_FLOAT_TAG, _EXP_FLOAT, list("-+0123456789."))
    _FastLoader = _CLoader


def token(value: object, limit: int = TOKEN_CHARS) -> str:
    """``value`` as a short, printable token for a message (at most ``limit`` characters)."""
    text = value if isinstance(value, str) else str(value)
    clean = "".join(ch if ch.isprintable() else "?" for ch in text[: limit + 1])
    return clean if len(clean) <= limit else clean[: limit - 3] + "..."


_KEY_CHARS = re.compile(r"[A-Za-z0-9_.\-]{0,32}")


def key_token(key: object) -> str:
    """A mapping key for a message: its leading name characters (at most 32: the longest key of our own files is 27), ``...`` if it has more.

    Keys of drive maps and network files are short names; a key that is not (a line of some other
    file read as YAML) is not quoted beyond its first name characters.
    """
    text = key if isinstance(key, str) else str(key)
    head = _KEY_CHARS.match(text)
    shown = head.group() if head else ""
    return shown if shown == text else shown + "..."


_QUOTED = re.compile(r"'([^']*)'|\"([^\"]*)\"")


def _clip_quoted(message: str) -> str:
    """A PyYAML message without the file's text: it quotes aliases, anchors and tags in full.

    Kept: a quoted character (``'\\t'``) and PyYAML's token names (``'<stream end>'``); anything
    else quoted becomes ``'...'`` (the file may be no YAML of ours; line and column say where).
    """

    def keep(m: re.Match[str]) -> str:
        inner = m.group(1) if m.group(1) is not None else m.group(2)
        if len(inner) <= 2 or (inner.startswith("<") and inner.endswith(">") and len(inner) <= 20):
            return f"'{inner}'"
        return "'...'"

    return _QUOTED.sub(keep, message)


def format_path(path: PathT) -> str:
    """``("rpdo", 0, "type")`` -> ``"rpdo[0].type"``; keys shown as :func:`key_token`."""
    out = ""
    for part in path:
        if isinstance(part, int) and not isinstance(part, bool):
            out += f"[{part}]"
        else:
            out += f".{key_token(part)}" if out else key_token(part)
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
    """Parse one YAML document; any syntax problem is a located :class:`PdoMapError`.

    With libyaml installed its parser reads the document; whatever it refuses (or any problem at all)
    is read again by PyYAML's own, so the errors, their wording and positions are PyYAML's.
    """
    if _FastLoader is not None:
        fast: Any = None
        try:
            fast = _FastLoader(text)
            node = fast.get_single_node()
            doc = Located(data=None, file=file)
            if node is not None:
                doc.data = _Builder(fast, doc).build(node, (), 0)[0]
            return doc
        except Exception:  # the pure-Python reader below says what is wrong
            pass
        finally:
            if fast is not None:
                fast.dispose()
    loader: yaml.SafeLoader | None = None
    try:
        loader = _Loader(text)
        node = loader.get_single_node()
        doc = Located(data=None, file=file)
        if node is not None:
            doc.data = _Builder(loader, doc).build(node, (), 0)[0]
        return doc
    except yaml.MarkedYAMLError as exc:
        mark = exc.problem_mark or exc.context_mark
        msg = " ".join(p for p in (exc.context, exc.problem) if p) or "invalid YAML"
        raise PdoMapError(
            f"YAML syntax: {_clip_quoted(msg)}",
            file=file,
            line=mark.line + 1 if mark else None,
            column=mark.column + 1 if mark else None,
        ) from None
    except yaml.reader.ReaderError as exc:
        raise PdoMapError(f"YAML: {exc.reason} (character 0x{exc.character:02X})", file=file) from None
    except yaml.YAMLError as exc:
        raise PdoMapError(f"YAML: {_clip_quoted(str(exc))[:200]}", file=file) from None
    except RecursionError:
        raise PdoMapError("YAML nested too deeply", file=file) from None
    finally:
        if loader is not None:
            loader.dispose()


def load_file(path: str | Path) -> Located:
    """Read and parse ``path``; a file that cannot be YAML text is a :class:`PdoMapError`.

    Refused without quoting any of the content: a directory, a device, a FIFO or
    anything else that is not a regular file; a file larger than
    :data:`MAX_FILE_BYTES`; binary content (a NUL byte); UTF-16/32 or other
    non-UTF-8 text. A UTF-8 byte-order mark is dropped.
    """
    p = Path(path)
    data = read_text_bytes(p)
    if data.startswith(b"\xef\xbb\xbf"):
        data = data[3:]
    elif data.startswith((b"\xff\xfe", b"\xfe\xff", b"\x00\x00\xfe\xff")):
        raise PdoMapError("UTF-16/UTF-32 text; save it as UTF-8", file=str(p))
    if b"\x00" in data:
        raise PdoMapError("a binary file, not YAML text", file=str(p))
    try:
        text = data.decode("utf-8")
    except UnicodeDecodeError as exc:
        line = data.count(b"\n", 0, exc.start) + 1
        raise PdoMapError(
            f"not UTF-8 text (byte 0x{data[exc.start]:02X} on line {line}); save it as UTF-8", file=str(p)
        ) from None
    return load_located(text, str(p))


def read_text_bytes(p: Path, limit: int = MAX_FILE_BYTES) -> bytes:
    """The bytes of the regular file ``p`` (at most ``limit``), or a :class:`PdoMapError` saying why not."""
    try:
        st = p.stat()
    except FileNotFoundError:
        raise PdoMapError("file not found", file=str(p)) from None
    except RuntimeError:  # Python < 3.13 on a symlink loop in a parent
        raise PdoMapError("cannot read: symbolic link loop", file=str(p)) from None
    except OSError as exc:
        raise PdoMapError(f"cannot read: {exc.strerror or exc}", file=str(p)) from None
    if stat.S_ISDIR(st.st_mode):
        raise PdoMapError("is a directory, not a YAML file", file=str(p))
    if not stat.S_ISREG(st.st_mode):
        raise PdoMapError("not a regular file (a device, FIFO or socket)", file=str(p))
    if st.st_size > limit:
        raise PdoMapError(f"{st.st_size} bytes; a YAML file here is at most {limit}", file=str(p))
    try:
        with p.open("rb") as f:
            data = f.read(limit + 1)
    except OSError as exc:
        raise PdoMapError(f"cannot read: {exc.strerror or exc}", file=str(p)) from None
    if len(data) > limit:  # grew since stat, or a /proc-like file that reports size 0
        raise PdoMapError(f"more than {limit} bytes; a YAML file here is at most {limit}", file=str(p))
    return data


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
                raise self._at(key_node, path, f"duplicate key '{key_token(key)}'")
            explicit.add(key)
            merged.pop(key, None)  # a key written here overrides a merged one
            child: PathT = (*path, key)
            self.doc.keys[child] = _mark(key_node)
            out[key], child_height = self.build(value_node, child, depth + 1)
            height = max(height, child_height + 1)
        for key, first in merged.items():
            self.doc.aliases[(*path, key)] = first
        return out, height
