"""Plain CDR (XCDR1, little-endian) for the messages the served cycle writes, without cyclonedds's
per-field serializer.

cyclonedds's Python serializer walks a sample field by field through its
type machinery: 45-60 us for a 3-joint ``JointState`` and 85-140 us for an
``AxisState`` on the reference VM, against about 2 us for handing the bytes
to the C writer. :func:`plan` compiles a final IDL struct (keyed or not) of
primitives, strings, nested structs, arrays of primitives and unbounded sequences of those into a
list of field operations once; :func:`encode` then writes a sample's bytes
with ``struct`` (a few us). :class:`PlainWriter` is a ``DataWriter`` that
uses it when it can and cyclonedds's own serializer otherwise (XCDR2
representation, any other type); :class:`PlainReader` decodes the same way.

The layout is OMG DDS-XTYPES 1.3, 7.4.1 (XCDR version 1): a 4-byte
encapsulation header (``00 01 00 00``: CDR, little-endian), each primitive
aligned to its size (at most 8) from the end of that header, a string as a
uint32 length counting its NUL then its UTF-8 bytes and the NUL, a sequence
as a uint32 count then its elements (a primitive sequence's first element
aligned to its size only when there is one). The writer pads the whole to a
multiple of 4, as ``DataWriter.write`` does. ``tests/unit/test_dds_cdr.py``
checks every message type against cyclonedds's own ``serialize`` (the
oracle) on random samples.
"""

from __future__ import annotations

import struct
import typing
from collections.abc import Callable
from typing import Any

import numpy as np
import numpy.typing as npt
from cyclonedds.core import DDSException, InstanceState, SampleState, ViewState
from cyclonedds.idl import IdlStruct
from cyclonedds.idl.types import array, sequence
from cyclonedds.internal import InvalidSample
from cyclonedds.pub import DataWriter
from cyclonedds.sub import DataReader

try:  # the C calls DataWriter.write and DataReader.take end with; absent in another binding: no fast path
    from cyclonedds._clayer import ddspy_take, ddspy_write  # type: ignore[import-not-found]
except ImportError:  # pragma: no cover - depends on the installed cyclonedds
    ddspy_take = ddspy_write = None

HEADER = b"\x00\x01\x00\x00"  # CDR_LE encapsulation, options 0
_PRIMITIVES = {  # IDL name: struct code (size = alignment in XCDR1)
    "int8": "b",
    "uint8": "B",
    "int16": "h",
    "uint16": "H",
    "int32": "i",
    "uint32": "I",
    "int64": "q",
    "uint64": "Q",
    "float32": "f",
    "float64": "d",
}
_PY = {bool: "?", str: "str"}  # plain annotations: a bool is one byte, a str a string
_U32 = struct.Struct("<I")

# one field: (kind, attribute, code or sub-plan); kinds: "p" primitive, "s" string, "t" nested struct,
# "ps" sequence of primitives, "ss" sequence of strings, "ts" sequence of structs, "pa" array of primitives
# (its length in the plan: (code, length)); a struct's plan: (its class, its ops)
Op = tuple[str, str, Any]
# where a primitive (count 0) or a primitive sequence's values (count n) sit: path -> (offset, code, count)
Slots = dict[str, tuple[int, str, int]]
_ANY_STATE = SampleState.Any | ViewState.Any | InstanceState.Any  # what DataReader.take takes by default


_PLANS: dict[type, list[Op] | None] = {}  # made once per type (1 ms the first time: type hints, cyclonedds)


def plan(cls: type) -> list[Op] | None:
    """The field operations that encode ``cls``, or None when this module cannot encode it exactly
    (not final, or a member type it does not know: a union, a bounded string...). Keys do not change
    a sample's bytes: the C writer derives the key from them, as it does for cyclonedds's own."""
    if cls not in _PLANS:
        _PLANS[cls] = _plan(cls)
    return _PLANS[cls]


def _plan(cls: type) -> list[Op] | None:
    if not (isinstance(cls, type) and issubclass(cls, IdlStruct)):
        return None
    idl = cls.__idl__
    try:
        idl.populate()  # type: ignore[no-untyped-call]
        hints = typing.get_type_hints(cls, include_extras=True)
    except (TypeError, NameError):  # a type cyclonedds cannot resolve either: its own write will say so
        return None
    if getattr(cls, "__idl_annotations__", {}).get("extensibility", "final") != "final":
        return None
    for notes in getattr(cls, "__idl_field_annotations__", {}).values():  # optional, external, ids...
        if any(k != "key" for k in notes):
            return None
    ops: list[Op] = []
    for name, hint in hints.items():
        op = _member(name, hint)
        if op is None:
            return None
        ops.append(op)
    return ops


def _member(name: str, hint: Any) -> Op | None:
    kind = _scalar(hint)
    if kind is not None:
        return (kind[0], name, kind[1])
    meta: tuple[Any, ...] = getattr(hint, "__metadata__", ())
    if len(meta) == 1 and isinstance(meta[0], sequence) and meta[0].max_length is None:
        inner = _scalar(meta[0].subtype)
        if inner is not None:
            return (inner[0] + "s", name, inner[1])
    if len(meta) == 1 and isinstance(meta[0], array):
        inner = _scalar(meta[0].subtype)
        if inner is not None and inner[0] == "p":
            return ("pa", name, (inner[1], meta[0].length))
    return None


def _scalar(hint: Any) -> tuple[str, Any] | None:
    """("p", code) for a primitive, ("s", None) for an unbounded string, ("t", (class, plan)) for a
    struct."""
    if hint in _PY:
        code = _PY[hint]
        return ("s", None) if code == "str" else ("p", code)
    meta: tuple[Any, ...] = getattr(hint, "__metadata__", ())
    if len(meta) == 1 and isinstance(meta[0], str) and meta[0] in _PRIMITIVES:
        return ("p", _PRIMITIVES[meta[0]])
    sub = plan(hint) if isinstance(hint, type) else None
    return ("t", (hint, sub)) if sub is not None else None


def encode(ops: list[Op], sample: Any) -> bytes:
    """``sample``'s XCDR1 bytes, encapsulation header included, padded to a multiple of 4."""
    buf = bytearray(HEADER)
    _struct(buf, ops, sample)
    pad = -len(buf) % 4
    return bytes(buf + b"\x00" * pad) if pad else bytes(buf)


def _aligned(pos: int, size: int) -> int:
    """``pos`` moved up to the next multiple of ``size`` counted from the end of the 4-byte header."""
    return pos + -(pos - 4) % size


def _align(buf: bytearray, size: int) -> None:
    pad = _aligned(len(buf), size) - len(buf)
    if pad:
        buf += b"\x00" * pad


def _struct(buf: bytearray, ops: list[Op], sample: Any, slots: Slots | None = None, path: str = "") -> None:
    """Append ``sample``'s fields; with ``slots``, note where each primitive and primitive sequence went."""
    for kind, name, arg in ops:
        value = getattr(sample, name)
        if kind == "p":
            size = struct.calcsize(arg)
            if size > 1:
                _align(buf, size)
            if slots is not None:
                slots[path + name] = (len(buf), arg, 0)
            buf += struct.pack("<" + arg, value)
        elif kind == "s":
            _string(buf, value)
        elif kind == "t":
            _struct(buf, arg[1], value, slots, f"{path}{name}.")
        elif kind == "ps":
            _align(buf, 4)
            buf += _U32.pack(len(value))
            if len(value):
                _align(buf, struct.calcsize(arg))
                if slots is not None:
                    slots[path + name] = (len(buf), arg, len(value))
                buf += struct.pack(f"<{len(value)}{arg}", *value)
        elif kind == "pa":  # no count: exactly the array's length
            code, length = arg
            if len(value) != length:
                raise ValueError(f"{name}: {len(value)} values for an array of {length}")
            _align(buf, struct.calcsize(code))
            if slots is not None:
                slots[path + name] = (len(buf), code, length)
            buf += struct.pack(f"<{length}{code}", *value)
        else:  # "ss", "ts": a count, then each element (not addressed by a slot)
            _align(buf, 4)
            buf += _U32.pack(len(value))
            for v in value:
                if kind == "ss":
                    _string(buf, v)
                else:
                    _struct(buf, arg[1], v)


def _string(buf: bytearray, value: str) -> None:
    raw = value.encode("utf-8")
    _align(buf, 4)
    buf += _U32.pack(len(raw) + 1)
    buf += raw
    buf += b"\x00"


def decode(cls: type, ops: list[Op], data: bytes) -> Any:
    """The ``cls`` sample in ``data`` (XCDR1 little-endian, encapsulation header first); a
    ``ValueError`` for any other encoding or a message that ends early or has bytes to spare
    beyond the padding."""
    if data[:2] != HEADER[:2]:
        raise ValueError(f"not little-endian plain CDR: encapsulation {data[:2].hex()}")
    sample, end = _read(cls, ops, data, 4)
    if len(data) - end > 3:
        raise ValueError(f"{len(data) - end} bytes after the sample")
    return sample


def _read(cls: type, ops: list[Op], data: bytes, pos: int) -> tuple[Any, int]:
    unpack = struct.unpack_from
    values: dict[str, Any] = {}
    try:
        for kind, name, arg in ops:
            if kind == "p":
                size = struct.calcsize(arg)
                pos = _aligned(pos, size)
                values[name] = unpack("<" + arg, data, pos)[0]
                pos += size
            elif kind == "s":
                values[name], pos = _read_string(data, pos)
            elif kind == "t":
                values[name], pos = _read(arg[0], arg[1], data, pos)
            elif kind == "pa":
                code, count = arg
                pos = _aligned(pos, struct.calcsize(code))
                values[name] = list(unpack(f"<{count}{code}", data, pos))
                pos += count * struct.calcsize(code)
            else:
                pos = _aligned(pos, 4)
                count = unpack("<I", data, pos)[0]
                pos += 4
                if count > len(data):  # every element takes a byte at least
                    raise ValueError(f"{name}: {count} elements in {len(data)} bytes")
                if kind == "ps":
                    if count:
                        size = struct.calcsize(arg)
                        pos = _aligned(pos, size)
                        values[name] = list(unpack(f"<{count}{arg}", data, pos))
                        pos += count * size
                    else:
                        values[name] = []
                elif kind == "ss":
                    items = []
                    for _ in range(count):
                        item, pos = _read_string(data, pos)
                        items.append(item)
                    values[name] = items
                else:
                    structs = []
                    for _ in range(count):
                        item, pos = _read(arg[0], arg[1], data, pos)
                        structs.append(item)
                    values[name] = structs
    except (struct.error, UnicodeDecodeError) as exc:
        raise ValueError(f"{cls.__name__}.{name}: {exc}") from None
    if pos > len(data):
        raise ValueError(f"{cls.__name__}: ends {pos - len(data)} bytes early")
    return cls(**values), pos


def _read_string(data: bytes, pos: int) -> tuple[str, int]:
    pos = _aligned(pos, 4)
    n = struct.unpack_from("<I", data, pos)[0]
    pos += 4
    if n < 1 or pos + n > len(data) or data[pos + n - 1] != 0:
        raise ValueError(f"a string of {n} bytes at {pos} is not NUL-terminated inside the message")
    return data[pos : pos + n - 1].decode("utf-8"), pos + n


class Layout:
    """One message's bytes with every string and sequence length fixed, its numbers written in place.

    Made from a prototype sample (its strings and sequence lengths are the
    layout's); :meth:`array` is a writable numpy view of a primitive
    sequence's values, :meth:`set` writes one primitive (a dotted path:
    ``"header.stamp.sec"``), :meth:`bytes` is the encoded message. For the
    messages a served group writes every cycle: the same bytes as
    :func:`encode` of the equivalent sample, without building it."""

    def __init__(self, cls: type, prototype: Any) -> None:
        ops = plan(cls)
        if ops is None:
            raise TypeError(f"{cls.__name__} cannot be laid out here (see fieldbus.dds.cdr.plan)")
        self.slots: Slots = {}
        buf = bytearray(HEADER)
        _struct(buf, ops, prototype, self.slots)
        buf += b"\x00" * (-len(buf) % 4)
        self.buf = buf
        self._scalars = {p: struct.Struct("<" + c) for p, (_, c, n) in self.slots.items() if n == 0}

    def array(self, path: str) -> npt.NDArray[Any]:
        """The values of the primitive sequence ``path``, a view into the message (writes go in place)."""
        offset, code, count = self.slots[path]
        return np.frombuffer(self.buf, dtype=np.dtype("<" + code), count=count, offset=offset)

    def set(self, path: str, value: float | int | bool) -> None:
        """Write the primitive ``path`` (an out-of-range integer is a ``struct.error``)."""
        self._scalars[path].pack_into(self.buf, self.slots[path][0], value)

    def packer(self, *paths: str) -> Callable[..., None]:
        """A function that writes the primitives ``paths``, in that order, from its arguments."""
        buf = self.buf
        ops = [(self._scalars[p].pack_into, self.slots[p][0]) for p in paths]

        def pack(*values: float | int | bool) -> None:
            for (pack_into, offset), v in zip(ops, values, strict=True):
                pack_into(buf, offset, v)

        return pack

    def bytes(self) -> bytes:
        """The message as it stands."""
        return bytes(self.buf)


class PlainReader(DataReader[Any]):
    """A ``DataReader`` whose ``take`` decodes with :func:`decode` when the type allows it (keys do not
    matter to a reader) and with cyclonedds's deserializer otherwise, or when a sample does not
    decode here (another encoding: cyclonedds says what is wrong with it)."""

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        cls = self._topic.data_type
        self._cls = cls
        self._ops = plan(cls) if ddspy_take is not None else None

    def take(self, N: int = 1, condition: Any = None, instance_handle: Any = None) -> list[Any]:
        ops = self._ops
        if ops is None or condition is not None or instance_handle is not None:
            return super().take(N=N, condition=condition, instance_handle=instance_handle)
        ret = ddspy_take(self._ref, _ANY_STATE, N)
        if isinstance(ret, int):
            raise DDSException(ret, f"Occurred while taking data in {self!r}")
        samples: list[Any] = []
        cls = self._cls
        for data, info in ret:
            if info.valid_data:
                try:
                    sample = decode(cls, ops, data)
                except ValueError:
                    sample = cls.deserialize(data)
                sample.sample_info = info
                samples.append(sample)
            else:
                samples.append(InvalidSample(cls.deserialize_key(data), info))
        return samples


class PlainWriter(DataWriter[Any]):
    """A ``DataWriter`` whose ``write`` encodes with :func:`encode` when the type and the writer's data
    representation allow it (checked once: the type's default sample must encode to exactly the bytes
    cyclonedds makes) and falls back to cyclonedds's serializer otherwise."""

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self._ops = plan(self.data_type) if ddspy_write is not None else None
        if self._ops is not None:
            probe = self.data_type()
            ours = encode(self._ops, probe)
            theirs = probe.serialize(use_version_2=self._use_version_2)
            if ours != theirs.ljust(len(ours), b"\x00"):
                self._ops = None

    @property
    def fast(self) -> bool:
        """Whether samples are encoded here (True) or by cyclonedds."""
        return self._ops is not None

    def write_encoded(self, data: bytes) -> None:
        """Write bytes made by :func:`encode` or a :class:`Layout` of this writer's type (a fast writer only)."""
        if ddspy_write is None or self._ops is None:
            raise TypeError(f"{self!r} does not take pre-encoded samples")
        ret = ddspy_write(self._ref, data)
        if ret < 0:
            raise DDSException(ret, f"Occurred while writing sample in {self!r}")

    def write(self, sample: Any, timestamp: int | None = None) -> None:
        ops = self._ops
        if ops is None or timestamp is not None or type(sample) is not self.data_type:
            super().write(sample, timestamp)
            return
        self.write_encoded(encode(ops, sample))
