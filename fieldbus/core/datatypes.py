"""PDO / SDO data types: YAML names, bit lengths, numpy dtypes and value ranges.

Names follow ethercat_driver_ros2 (``bool``, ``int8`` .. ``uint64``, ``float``,
``double``, ``bitN``). The CoE data type codes are those of ETG.1000.6 /
CiA 301 (0x0001 BOOLEAN .. 0x001B UNSIGNED64).
"""

from __future__ import annotations

import difflib
import re
from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class DataType:
    """One PDO/SDO data type.

    ``bits`` is the bit length on the wire; ``numpy`` the little-endian dtype
    string used in process images (``None`` for ``bitN`` entries, which have no
    byte-aligned representation); ``coe_code`` the CiA 301 data type index.
    """

    name: str
    bits: int
    kind: str  # "bool" | "int" | "uint" | "float" | "bits"
    coe_code: int

    @property
    def signed(self) -> bool:
        return self.kind == "int"

    @property
    def is_float(self) -> bool:
        return self.kind == "float"

    @property
    def is_bits(self) -> bool:
        """True for sub-byte entries (``bool`` and ``bitN``) packed at bit level."""
        return self.kind in ("bool", "bits")

    @property
    def numpy(self) -> str:
        """Little-endian numpy dtype of a byte-aligned value (bit types: smallest uint)."""
        if self.kind == "float":
            return "<f4" if self.bits == 32 else "<f8"
        if self.kind in ("int", "uint"):
            return f"<{'i' if self.kind == 'int' else 'u'}{self.bits // 8}"
        if self.kind == "bool":
            return "?"
        return _uint_for_bits(self.bits)

    @property
    def min(self) -> float:
        """Smallest representable raw value."""
        if self.kind == "int":
            return float(-(1 << (self.bits - 1)))
        if self.kind == "float":
            return float(np.finfo(self.numpy).min)
        return 0.0

    @property
    def max(self) -> float:
        """Largest representable raw value."""
        if self.kind == "int":
            return float((1 << (self.bits - 1)) - 1)
        if self.kind == "float":
            return float(np.finfo(self.numpy).max)
        return float((1 << self.bits) - 1)

    def fits(self, value: float) -> bool:
        """Whether ``value`` is representable as a raw value of this type."""
        if self.kind == "float":
            return (
                bool(value != value)
                or abs(value) <= self.max
                or value
                in (
                    float("inf"),
                    float("-inf"),
                )
            )
        if value != value or value in (float("inf"), float("-inf")):
            return False
        if float(value) != int(value):
            return False
        return self.min <= value <= self.max

    def encode(self, value: float) -> bytes:
        """Little-endian bytes of ``value`` as an SDO payload (``bitN``: ceil(N/8) bytes)."""
        nbytes = max(1, (self.bits + 7) // 8)
        if self.kind == "float":
            return np.array([value], dtype=self.numpy).tobytes()
        return int(value).to_bytes(nbytes, "little", signed=self.signed)

    def decode(self, data: bytes) -> float | int:
        """Inverse of :meth:`encode`."""
        if self.kind == "float":
            return float(np.frombuffer(data, dtype=self.numpy)[0])
        return int.from_bytes(data, "little", signed=self.signed)


def _uint_for_bits(bits: int) -> str:
    for size in (8, 16, 32, 64):
        if bits <= size:
            return f"<u{size // 8}" if size > 8 else "u1"
    raise ValueError(f"no unsigned integer holds {bits} bits")


_FIXED: dict[str, DataType] = {
    t.name: t
    for t in (
        DataType("bool", 1, "bool", 0x0001),
        DataType("int8", 8, "int", 0x0002),
        DataType("int16", 16, "int", 0x0003),
        DataType("int32", 32, "int", 0x0004),
        DataType("uint8", 8, "uint", 0x0005),
        DataType("uint16", 16, "uint", 0x0006),
        DataType("uint32", 32, "uint", 0x0007),
        DataType("float", 32, "float", 0x0008),
        DataType("double", 64, "float", 0x0011),
        DataType("int64", 64, "int", 0x0015),
        DataType("uint64", 64, "uint", 0x001B),
    )
}
_BITS_RE = re.compile(r"^bit([1-9][0-9]*)$")
MAX_BITN = 64  # widest bitN entry (gaps wider than this are written as several entries)

TYPE_NAMES: tuple[str, ...] = (*_FIXED, "bitN")


def lookup(name: str) -> DataType | None:
    """The data type called ``name`` (``bitN`` for 1 <= N <= 64), or None."""
    if name in _FIXED:
        return _FIXED[name]
    m = _BITS_RE.match(name)
    if m:
        n = int(m.group(1))
        if 1 <= n <= MAX_BITN:
            return DataType(name, n, "bits", 0x0000)
    return None


def suggest(name: str) -> str | None:
    """The closest known type name to ``name`` (for 'did you mean' hints)."""
    m = re.match(r"^bits?([0-9]+)$", name)
    if m and 1 <= int(m.group(1)) <= MAX_BITN:
        return f"bit{int(m.group(1))}"
    close = difflib.get_close_matches(name, list(_FIXED), n=1, cutoff=0.6)
    return close[0] if close else None
