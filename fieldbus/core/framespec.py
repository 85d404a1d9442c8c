"""The declarative raw-CAN family's frames as data: fields, frames, the protocol (the parser: canframes).

A field's ``offset_bits`` count from its slot's start; engineering value =
(raw - offset) / scale. Pure: bytes in, bytes out.
"""

from __future__ import annotations

import math
import struct
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any


@dataclass(frozen=True)
class FrameField:
    """One field of a frame slot: ``offset_bits`` from the slot's start (LSB-first bit numbering for
    bit fields; whole-byte fields start on a byte)."""

    name: str
    type: str
    bits: int
    offset_bits: int
    byte_order: str = "little"
    scale: float | None = None  # raw per engineering unit
    offset: float = 0.0  # raw at 0
    unit: str | None = None
    safe_value: float | None = None
    description: str = ""

    @property
    def scaled(self) -> bool:
        return self.scale is not None or self.offset != 0.0

    def pack(self, value: float) -> int:
        """The raw wire integer of ``value`` (engineering units), NaN-safe: NaN sends 0, out of range
        saturates (for frames built outside the image: safe stops, emulators)."""
        raw = value * (self.scale if self.scale is not None else 1.0) + self.offset
        if self.type == "float32":
            f = 0.0 if math.isnan(raw) else max(-3.4028234663852886e38, min(3.4028234663852886e38, raw))
            return int.from_bytes(struct.pack("<f", f), "little")
        lo, hi = (
            (-(1 << (self.bits - 1)), (1 << (self.bits - 1)) - 1)
            if self.type == "int"
            else (0, (1 << self.bits) - 1)
        )
        r = (
            0
            if math.isnan(raw)
            else max(lo, min(hi, round(raw) if math.isfinite(raw) else (hi if raw > 0 else lo)))
        )
        return r & ((1 << self.bits) - 1)

    def unpack(self, raw: int) -> float:
        """Engineering value of the wire integer ``raw``."""
        if self.type == "float32":
            x = float(struct.unpack("<f", raw.to_bytes(4, "little"))[0])
        elif self.type == "int" and raw >= 1 << (self.bits - 1):
            x = float(raw - (1 << self.bits))
        else:
            x = float(raw)
        return (x - self.offset) / (self.scale if self.scale is not None else 1.0)


@dataclass(frozen=True)
class FrameSpec:
    """A command or feedback frame: CAN id, motors per frame (1: per motor, id + node_id), slot size."""

    can_id: int
    motors: int  # 1: one frame per motor on id + node_id; > 1: one shared frame, slot k = node k
    extended: bool
    stride: int  # bytes per motor slot
    length: int  # data bytes of the frame
    fields: tuple[FrameField, ...]
    swap: tuple[int, ...]  # slot byte j travels as row byte swap[j] (big-endian fields reversed)
    deadline_us: float | None = None  # feedback: later than this after the cycle's commands is stale

    @property
    def shared(self) -> bool:
        return self.motors > 1

    def frame_id(self, node: int) -> int:
        return self.can_id if self.shared else self.can_id + node

    def slot(self, node: int) -> int:
        """Byte offset of motor ``node``'s slot in its frame."""
        return (node - 1) * self.stride if self.shared else 0

    def encode(self, values: Mapping[str, float]) -> bytes:
        """One slot from engineering values with Python integers (independent of the image codec)."""
        out = bytearray(self.stride)
        for f in self.fields:
            raw = f.pack(float(values.get(f.name, 0.0)))
            if f.bits % 8 == 0 and f.offset_bits % 8 == 0:
                o, n = f.offset_bits // 8, f.bits // 8
                out[o : o + n] = raw.to_bytes(n, "big" if f.byte_order == "big" else "little")
            else:
                x = int.from_bytes(out, "little") | raw << f.offset_bits
                out[:] = x.to_bytes(self.stride, "little")
        return bytes(out)

    def decode(self, slot: bytes) -> dict[str, float]:
        """Engineering values of one slot (Python integers, independent of the image codec)."""
        values: dict[str, float] = {}
        for f in self.fields:
            if f.bits % 8 == 0 and f.offset_bits % 8 == 0:
                o, n = f.offset_bits // 8, f.bits // 8
                raw = int.from_bytes(slot[o : o + n], "big" if f.byte_order == "big" else "little")
            else:
                raw = (int.from_bytes(slot, "little") >> f.offset_bits) & ((1 << f.bits) - 1)
            values[f.name] = f.unpack(raw)
        return values


@dataclass(frozen=True)
class FramesProtocol:
    """A declarative family's protocol: its two frames, special frames and fault table."""

    command: FrameSpec
    feedback: FrameSpec
    enable: bytes | None = None
    disable: bytes | None = None
    zero: bytes | None = None
    clear: bytes | None = None
    fault_field: str | None = None
    fault_codes: tuple[tuple[int, str], ...] = ()
    ok_codes: tuple[int, ...] = (0,)

    def fault_code(self, row: Any) -> int | None:
        """The fault field's code in a feedback image row (its fields little-endian in place), or None
        when the map has no fault field."""
        if self.fault_field is None:
            return None
        f = next(g for g in self.feedback.fields if g.name == self.fault_field)
        x = int.from_bytes(bytes(row[: self.feedback.stride]), "little")
        return (x >> f.offset_bits) & ((1 << f.bits) - 1)

    def fault_name(self, code: int) -> str:
        return dict(self.fault_codes).get(code, f"code {code}")

    def safe_slot(self) -> bytes:
        """The command slot of the safe stop: every field's ``safe_value`` (0 where it has none)."""
        return self.command.encode({f.name: f.safe_value or 0.0 for f in self.command.fields})
