"""Vectorised process images: N axes of one drive map, as numpy structured arrays.

A :class:`DirectionImage` holds two views of the same process data:

- ``values``: what the controller uses, shape ``(N,)``, one named field per
  channel. Channels with ``factor``/``offset``/``unit`` are float64 in
  engineering units; others keep their raw type (``bool`` for single bits).
- ``wire``: the bytes as they travel, shape ``(N, size)`` uint8, one row per
  axis, rows contiguous (so it can be a view into a master's IO map).

``to_wire()`` encodes ``values`` into ``wire``; ``from_wire()`` decodes.
A master calls ``outputs.to_wire()`` and ``inputs.from_wire()`` each cycle; an
emulated drive calls the opposite pair. Both use precomputed views and ``out=``
ufuncs only: a cycle allocates nothing.

Scaling follows ethercat_driver_ros2: inputs ``value = factor * raw + offset``,
outputs ``raw = factor * value + offset``. Raw results are rounded (integer
types) and saturated to the type's range. A NaN output value keeps the raw value
sent last (initially the channel's ``default``), so a controller glitch never
puts garbage on the wire.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt

from fieldbus.core.pdo.layout import DirectionLayout, EntryLayout, MapLayout
from fieldbus.core.pdo.model import Direction
from fieldbus.errors import FieldbusError

U8 = npt.NDArray[np.uint8]


def user_dtype(dl: DirectionLayout) -> np.dtype[Any]:
    """The ``values`` dtype: scaled channels first (float64, contiguous), then the rest."""
    scaled = [(e.name, "f8") for e in dl.channels if e.channel.scaled]
    plain = [(e.name, _plain_format(e)) for e in dl.channels if not e.channel.scaled]
    return np.dtype(scaled + plain)


def _plain_format(e: EntryLayout) -> str:
    dt = e.channel.type
    if dt.name == "bool":
        return "?"
    return "=" + dt.numpy[1:] if dt.numpy[0] == "<" else dt.numpy


def wire_dtype(dl: DirectionLayout, names: list[str]) -> np.dtype[Any]:
    """Structured dtype over one wire row for the byte-aligned entries ``names``."""
    entries = [dl.entry(n) for n in names]
    return np.dtype(
        {
            "names": names,
            "formats": [e.channel.type.numpy for e in entries],
            "offsets": [e.byte_offset for e in entries],
            "itemsize": max(dl.size, 1),
        }
    )


@dataclass(frozen=True)
class _Affine:
    """raw = a * value + b (to wire); value = c * raw + d (from wire); per scaled column."""

    a: npt.NDArray[np.float64]
    b: npt.NDArray[np.float64]
    c: npt.NDArray[np.float64]
    d: npt.NDArray[np.float64]
    lo: npt.NDArray[np.float64]
    hi: npt.NDArray[np.float64]


class _BitField:
    """Precomputed views and scratch for one entry that is not byte-aligned."""

    def __init__(self, e: EntryLayout, wire: U8, src: npt.NDArray[Any], n: int) -> None:
        dt = e.channel.type
        self.bool = dt.name == "bool"
        self.width_mask = np.uint64((1 << dt.bits) - 1)
        self.src = src  # (N,) view: the user field, or a scaled column of raw values
        # (byte view, shift of the entry's bit 0 relative to this byte's bit 0)
        self.bytes = [(wire[:, e.byte_offset + j], 8 * j - e.shift) for j in range(e.span_bytes)]
        # bits of byte j the entry covers: [shift - 8j, shift + bits - 8j) clipped to [0, 8)
        self.masks = []
        for j in range(e.span_bytes):
            lo_bit = max(0, e.shift - 8 * j)
            hi_bit = min(8, e.shift + dt.bits - 8 * j)
            m = ((1 << hi_bit) - 1) & ~((1 << lo_bit) - 1)
            self.masks.append((np.uint8(m), np.uint8(~m & 0xFF)))
        self.signed = dt.signed
        self.stage = np.zeros(n, dtype=np.uint64)
        self.stage_i = np.zeros(n, dtype=np.int64)
        self.part = np.zeros(n, dtype=np.uint64)
        self.part8 = np.zeros(n, dtype=np.uint8)
        self.sign_bit = np.uint64(1 << (dt.bits - 1)) if dt.signed else np.uint64(0)
        self.sign_ext = np.uint64(((1 << 64) - 1) ^ ((1 << dt.bits) - 1)) if dt.signed else np.uint64(0)
        self.flags = np.zeros(n, dtype=bool)

    def to_wire(self) -> None:
        if self.bool:
            src = self.src.view(np.uint8)  # numpy bools are bytes 0/1
            (col, _), (m, keep) = self.bytes[0], self.masks[0]
            np.multiply(src, m, out=self.part8)
            np.bitwise_and(col, keep, out=col)
            np.bitwise_or(col, self.part8, out=col)
            return
        if self.signed or self.src.dtype.kind == "f":
            np.copyto(self.stage_i, self.src, casting="unsafe")
            np.copyto(self.stage, self.stage_i, casting="unsafe")
        else:
            np.copyto(self.stage, self.src, casting="unsafe")
        np.bitwise_and(self.stage, self.width_mask, out=self.stage)
        for (col, rel), (m, keep) in zip(self.bytes, self.masks, strict=True):
            if rel >= 0:
                np.right_shift(self.stage, np.uint64(rel), out=self.part)
            else:
                np.left_shift(self.stage, np.uint64(-rel), out=self.part)
            np.copyto(self.part8, self.part, casting="unsafe")
            np.bitwise_and(self.part8, m, out=self.part8)
            np.bitwise_and(col, keep, out=col)
            np.bitwise_or(col, self.part8, out=col)

    def from_wire(self) -> None:
        if self.bool:
            col, _ = self.bytes[0]
            np.bitwise_and(col, self.masks[0][0], out=self.part8)
            np.not_equal(self.part8, 0, out=self.src)
            return
        self.stage.fill(0)
        for (col, rel), (m, _) in zip(self.bytes, self.masks, strict=True):
            np.bitwise_and(col, m, out=self.part8)
            np.copyto(self.part, self.part8)
            if rel >= 0:
                np.left_shift(self.part, np.uint64(rel), out=self.part)
            else:
                np.right_shift(self.part, np.uint64(-rel), out=self.part)
            np.bitwise_or(self.stage, self.part, out=self.stage)
        if self.signed:
            np.bitwise_and(self.stage, self.sign_bit, out=self.part)
            np.not_equal(self.part, 0, out=self.flags)
            np.bitwise_or(self.stage, self.sign_ext, out=self.stage, where=self.flags)
            np.copyto(self.stage_i, self.stage, casting="unsafe")
            np.copyto(self.src, self.stage_i, casting="unsafe")
        else:
            np.copyto(self.src, self.stage, casting="unsafe")


class DirectionImage:
    """One direction (outputs = RxPDOs or inputs = TxPDOs) of N axes sharing a map.

    ``wire`` may be given as an ``(N, size)`` uint8 view into a larger buffer
    (for example a master's IO map); otherwise it is allocated.
    """

    def __init__(self, dl: DirectionLayout, n_axes: int, wire: U8 | None = None) -> None:
        if n_axes < 1:
            raise ValueError("n_axes must be >= 1")
        self.layout = dl
        self.n_axes = n_axes
        size = dl.size
        if wire is None:
            wire = np.zeros((n_axes, size), dtype=np.uint8)
        elif wire.shape != (n_axes, size) or wire.dtype != np.uint8:
            raise ValueError(f"wire must be uint8 of shape {(n_axes, size)}, got {wire.dtype} {wire.shape}")
        self.wire: U8 = wire
        self.values: npt.NDArray[Any] = np.zeros(n_axes, dtype=user_dtype(dl))

        channels = dl.channels
        for e in channels:
            if e.channel.type.is_float and not e.aligned:
                raise FieldbusError(
                    f"{e.name}: {e.channel.type.name} entry at bit {e.bit_offset} is not byte aligned"
                )
        scaled = [e for e in channels if e.channel.scaled]
        # scaled columns: aligned ones first (one structured cast), then bit-level ones
        scaled.sort(key=lambda e: not e.aligned)
        self._scaled_names = [e.name for e in scaled]
        k = len(scaled)
        self._k = k
        n_aligned_scaled = sum(1 for e in scaled if e.aligned)
        if k:
            itemsize = self.values.dtype.itemsize
            # (N, k) float64 view over the scaled block of `values` (in user-dtype order)
            self._scaled_view = np.ndarray(
                (n_axes, k), dtype=np.float64, buffer=self.values, offset=0, strides=(itemsize, 8)
            )
            order = [self.values.dtype.names.index(nm) for nm in self._scaled_names]  # type: ignore[union-attr]
            self._col_order = np.array(order, dtype=np.intp)
            self._identity_order = order == list(range(k))
        self._work = np.zeros((n_axes, k), dtype=np.float64)  # raw values, float64
        self._last = np.zeros((n_axes, k), dtype=np.float64)  # raw values sent last
        self._nan = np.zeros((n_axes, k), dtype=bool)
        self._gather = np.zeros((n_axes, k), dtype=np.float64)
        f = np.array([e.channel.factor for e in scaled], dtype=np.float64)
        o = np.array([e.channel.offset for e in scaled], dtype=np.float64)
        if dl.direction is Direction.OUTPUTS:  # raw = f*value + o
            a, b, c, d = f, o, 1.0 / f, -o / f
        else:  # value = f*raw + o
            a, b, c, d = 1.0 / f, -o / f, f, o
        self._affine = _Affine(
            a, b, c, d,
            np.array([e.channel.type.min for e in scaled], dtype=np.float64),
            np.array([e.channel.type.max for e in scaled], dtype=np.float64),
        )  # fmt: skip
        self._int_cols = np.array([not e.channel.type.is_float for e in scaled], dtype=bool)
        self._all_int = bool(self._int_cols.all())
        for i, e in enumerate(scaled):
            if e.channel.default is not None:
                self._last[:, i] = e.channel.default
                self._work[:, i] = e.channel.default

        # Byte-aligned entries move as structured copies, one call per group:
        # (wire view, values-side view). Scaled ones go through `_work` (raw as float64).
        self._scaled_pair: tuple[npt.NDArray[Any], npt.NDArray[Any]] | None = None
        if n_aligned_scaled:
            names = self._scaled_names[:n_aligned_scaled]
            work_dtype = np.dtype([(nm, "f8") for nm in names])
            work_view = np.ndarray((n_axes,), dtype=work_dtype, buffer=self._work, strides=(8 * k,))
            self._scaled_pair = (self._wire_struct(names), work_view)
        plain = [e.name for e in channels if not e.channel.scaled and e.aligned]
        self._plain_pair = (self._wire_struct(plain), self.values[plain]) if plain else None
        # bit-level entries
        self._bits: list[_BitField] = []
        for e in channels:
            if e.aligned:
                continue
            src = self._work[:, self._scaled_names.index(e.name)] if e.channel.scaled else self.values[e.name]
            self._bits.append(_BitField(e, self.wire, src, n_axes))
        # plain defaults
        for e in channels:
            if not e.channel.scaled and e.channel.default is not None:
                self.values[e.name] = e.channel.default
        if k and dl.direction is Direction.OUTPUTS:
            self._raw_to_values()  # scaled outputs start at their default, in units

    def _wire_struct(self, names: list[str]) -> npt.NDArray[Any]:
        dt = wire_dtype(self.layout, names)
        return np.ndarray((self.n_axes,), dtype=dt, buffer=self.wire, strides=(self.wire.strides[0],))

    @property
    def names(self) -> tuple[str, ...]:
        """Channel names in wire order."""
        return self.layout.names

    def __getitem__(self, name: str) -> npt.NDArray[Any]:
        """``image["target_position"]``: the (N,) view of one channel in ``values``."""
        return self.values[name]

    def __setitem__(self, name: str, value: Any) -> None:
        self.values[name] = value

    # -- encode ---------------------------------------------------------------
    def to_wire(self) -> None:
        """Encode ``values`` into ``wire`` (all axes)."""
        if self._k:
            self._values_to_raw()
            if self._scaled_pair is not None:
                np.copyto(self._scaled_pair[0], self._scaled_pair[1], casting="unsafe")
        if self._plain_pair is not None:
            np.copyto(self._plain_pair[0], self._plain_pair[1], casting="unsafe")
        for bf in self._bits:
            bf.to_wire()

    def from_wire(self) -> None:
        """Decode ``wire`` into ``values`` (all axes)."""
        if self._plain_pair is not None:
            np.copyto(self._plain_pair[1], self._plain_pair[0], casting="unsafe")
        for bf in self._bits:
            bf.from_wire()
        if self._k:
            if self._scaled_pair is not None:
                np.copyto(self._scaled_pair[1], self._scaled_pair[0], casting="unsafe")
            np.copyto(self._last, self._work)
            self._raw_to_values()

    def _values_to_raw(self) -> None:
        aff, w = self._affine, self._work
        src = self._scaled_view if self._identity_order else self._gathered()
        np.multiply(src, aff.a, out=w)
        np.add(w, aff.b, out=w)
        np.isnan(w, out=self._nan)
        np.copyto(w, self._last, where=self._nan)
        if self._all_int:
            np.rint(w, out=w)
        else:
            np.rint(w, out=w, where=self._int_cols)
        np.minimum(w, aff.hi, out=w)  # saturate (np.clip's wrapper allocates)
        np.maximum(w, aff.lo, out=w)
        np.copyto(self._last, w)

    def _gathered(self) -> npt.NDArray[np.float64]:
        np.take(self._scaled_view, self._col_order, axis=1, out=self._gather)
        return self._gather

    def _raw_to_values(self) -> None:
        aff = self._affine
        if self._identity_order:
            np.multiply(self._work, aff.c, out=self._scaled_view)
            np.add(self._scaled_view, aff.d, out=self._scaled_view)
        else:
            np.multiply(self._work, aff.c, out=self._gather)
            np.add(self._gather, aff.d, out=self._gather)
            self._scaled_view[:, self._col_order] = self._gather

    def raw(self, name: str) -> npt.NDArray[Any]:
        """A fresh (allocating) array of the raw wire values of ``name`` (diagnostics, tests)."""
        from fieldbus.core.pdo.layout import get_value

        e = self.layout.entry(name)
        return np.array([get_value(self.wire[i].data, e) for i in range(self.n_axes)])


class ProcessImage:
    """Outputs and inputs of N axes sharing one drive map.

    ``outputs`` are the RxPDOs (master -> drive), ``inputs`` the TxPDOs
    (drive -> master), both named from the master's side.
    """

    def __init__(
        self,
        map_layout: MapLayout,
        n_axes: int = 1,
        *,
        out_wire: U8 | None = None,
        in_wire: U8 | None = None,
    ) -> None:
        self.layout = map_layout
        self.n_axes = n_axes
        self.outputs = DirectionImage(map_layout.outputs, n_axes, out_wire)
        self.inputs = DirectionImage(map_layout.inputs, n_axes, in_wire)

    def pack(self) -> None:
        """Master side: encode outputs for sending."""
        self.outputs.to_wire()

    def unpack(self) -> None:
        """Master side: decode received inputs."""
        self.inputs.from_wire()
