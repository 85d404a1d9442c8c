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
outputs ``raw = factor * value + offset``, computed in float64 (a product, then
a sum; an offset of 0 adds nothing, so ``-0.0`` stays ``-0.0``). The one rule for
a scaled output's raw value, in every type and both engines:

- rounded half to even (``numpy.rint``) for integer types;
- saturated to the type's range: anything at or above the maximum, ``+1e30``
  and ``+inf`` included, gives the maximum (``INT64_MAX`` and ``UINT64_MAX``
  exactly, although float64 cannot hold them), anything at or below the
  minimum gives the minimum; float types saturate to their largest finite value;
- a NaN (the value, or ``factor * value + offset``) keeps the raw value sent last
  (initially the channel's ``default``, else 0), so a controller glitch never
  puts garbage on the wire nor makes the drive jump to raw 0 (a position of 0
  can be far away); the raw value sent last is what the drive already follows.

Two engines do this work: the C codec (``fieldbus._codec``, for the scaled
channels, byte-aligned or bit-level integers) and numpy (everything else, and
everywhere when the C codec is not built). They give the same wire bytes and the same decoded values, bit for
bit (``tests/unit/test_codec_differential.py``). ``engine=`` chooses: ``"auto"``
(C where it applies), ``"c"`` (C or an error) or ``"numpy"``.
"""

from __future__ import annotations

import difflib
from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt

from fieldbus.core.datatypes import DataType
from fieldbus.core.pdo.layout import DirectionLayout, EntryLayout, MapLayout
from fieldbus.core.pdo.model import Direction
from fieldbus.errors import ChannelNameError, FieldbusError

U8 = npt.NDArray[np.uint8]


ENGINES = ("auto", "c", "numpy")


def _int_max(dt: DataType) -> int:
    return (1 << (dt.bits - 1)) - 1 if dt.signed else (1 << dt.bits) - 1


class _Top:
    """Float -> integer conversion for a type whose maximum float64 cannot hold (64-bit).

    ``float(2**63 - 1)`` is ``2**63``: the saturated value sits one past the range,
    where a plain cast is undefined (numpy gives ``INT64_MIN``, or 0 for uint64).
    Sources are already clamped to ``[min, float(max)]``; values below ``limit``
    (``2**63`` or ``2**64``) convert as usual, the others give exactly ``max``.
    Preallocated masks: a cycle allocates nothing.
    """

    def __init__(self, dt: DataType, shape: tuple[int, ...]) -> None:
        top = _int_max(dt)
        self.limit = np.float64(top + 1)
        self.top = np.array(top, dtype=np.int64 if dt.signed else np.uint64)
        self.fits = np.zeros(shape, dtype=bool)
        self.over = np.zeros(shape, dtype=bool)

    @staticmethod
    def needed(dt: DataType) -> bool:
        return not dt.is_float and float(_int_max(dt)) != _int_max(dt)

    def cast(self, src: npt.NDArray[np.float64], out: npt.NDArray[Any]) -> None:
        """``out = rint(src)`` saturated to the type; ``out`` is the type or a wider one of its sign."""
        np.less(src, self.limit, out=self.fits)
        np.rint(src, out=out, casting="unsafe", where=self.fits)
        np.logical_not(self.fits, out=self.over)
        np.copyto(out, self.top, where=self.over)


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
        self.top = _Top(dt, (n,)) if src.dtype.kind == "f" and _Top.needed(dt) else None

    def stage_raw(self) -> None:
        """``stage`` = the entry's raw bits (width-masked uint64) from ``src``."""
        if self.bool:
            np.copyto(self.stage, self.src.view(np.uint8), casting="unsafe")
            return
        if self.src.dtype.kind == "f":  # a scaled entry: rounded raw values within [min, float(max)]
            dst = self.stage_i if self.signed else self.stage
            if self.top is not None:
                self.top.cast(self.src, dst)
            else:
                np.copyto(dst, self.src, casting="unsafe")
            if self.signed:
                np.copyto(self.stage, self.stage_i, casting="unsafe")
        elif self.signed:
            np.copyto(self.stage_i, self.src, casting="unsafe")
            np.copyto(self.stage, self.stage_i, casting="unsafe")
        else:
            np.copyto(self.stage, self.src, casting="unsafe")
        np.bitwise_and(self.stage, self.width_mask, out=self.stage)

    def store(self, raw: npt.NDArray[np.uint64]) -> None:
        """``src`` = the entry's value from its raw bits ``raw`` (width-masked; clobbered when signed)."""
        if self.bool:
            np.not_equal(raw, 0, out=self.src)
            return
        if self.signed:
            np.bitwise_and(raw, self.sign_bit, out=self.part)
            np.not_equal(self.part, 0, out=self.flags)
            np.bitwise_or(raw, self.sign_ext, out=raw, where=self.flags)
            np.copyto(self.stage_i, raw, casting="unsafe")
            np.copyto(self.src, self.stage_i, casting="unsafe")
        else:
            np.copyto(self.src, raw, casting="unsafe")

    def to_wire(self) -> None:
        if self.bool:
            src = self.src.view(np.uint8)  # numpy bools are bytes 0/1
            (col, _), (m, keep) = self.bytes[0], self.masks[0]
            np.multiply(src, m, out=self.part8)
            np.bitwise_and(col, keep, out=col)
            np.bitwise_or(col, self.part8, out=col)
            return
        self.stage_raw()
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


class _BitWord:
    """The bit-level entries that lie in one 8-byte word of the row, coded together as one uint64.

    The wire row is little-endian bit order (an entry's bit 0 at ``8 * byte_offset + shift``), so
    bytes ``[8k, 8k + 8)`` read as a little-endian uint64 hold each of its entries at a fixed shift:
    per entry a cast, a mask, a shift and an or (a shift and a mask to decode), instead of a handful
    of ufuncs per byte the entry touches. The row may end inside the word (a 6-byte CAN reply).
    """

    def __init__(self, wire: U8, word: int, fields: list[tuple[_BitField, int]], n: int) -> None:
        lo = 8 * word
        self.cols = wire[:, lo : min(lo + 8, wire.shape[1])]
        self.w = self.cols.shape[1]
        self.buf = np.zeros((n, 8), dtype=np.uint8)
        self.word: npt.NDArray[np.uint64] = self.buf.view("<u8").reshape(n)
        self.fields = [(bf, np.uint64(pos - 64 * word)) for bf, pos in fields]
        covered = 0
        for bf, pos in self.fields:
            covered |= int(bf.width_mask) << int(pos)
        self.keep = np.uint64(~covered & ((1 << 64) - 1))  # bits of other entries in the word
        self.part = np.zeros(n, dtype=np.uint64)

    def to_wire(self) -> None:
        word, part = self.word, self.part
        np.copyto(self.buf[:, : self.w], self.cols)
        np.bitwise_and(word, self.keep, out=word)
        for bf, pos in self.fields:
            bf.stage_raw()
            np.left_shift(bf.stage, pos, out=part)
            np.bitwise_or(word, part, out=word)
        np.copyto(self.cols, self.buf[:, : self.w])

    def from_wire(self) -> None:
        np.copyto(self.buf[:, : self.w], self.cols)
        for bf, pos in self.fields:
            np.right_shift(self.word, pos, out=bf.stage)
            np.bitwise_and(bf.stage, bf.width_mask, out=bf.stage)
            bf.store(bf.stage)


class _ByteBits:
    """An unsigned, unscaled bit-level entry inside one byte of the row (a CAN reply's error nibble),
    decoded from that byte alone: a shift and / or a mask, no gather of its 8-byte word."""

    def __init__(self, e: EntryLayout, wire: U8, dst: npt.NDArray[np.uint8]) -> None:
        self.col = wire[:, e.byte_offset]
        self.dst = dst
        self.shift = np.uint8(e.shift)
        self.mask = np.uint8((1 << e.bits) - 1)
        self.masked = e.shift + e.bits < 8  # bits above the entry to clear after the shift

    @staticmethod
    def fits(e: EntryLayout, dst: npt.NDArray[Any]) -> bool:
        """Whether ``e`` (its values column ``dst``) decodes this way."""
        dt = e.channel.type
        return (
            not e.channel.scaled
            and dt.name != "bool"
            and not dt.signed
            and e.shift + e.bits <= 8
            and dst.dtype == np.uint8
        )

    def from_wire(self) -> None:
        if not self.shift:
            np.bitwise_and(self.col, self.mask, out=self.dst)
            return
        np.right_shift(self.col, self.shift, out=self.dst)
        if self.masked:
            np.bitwise_and(self.dst, self.mask, out=self.dst)


def _bit_words(
    entries: list[tuple[EntryLayout, _BitField]], wire: U8, n: int
) -> tuple[list[_BitWord], list[_BitField]]:
    """Entries grouped by the 8-byte word of the row they lie in; those that cross a word stay alone."""
    words: dict[int, list[tuple[_BitField, int]]] = {}
    alone: list[_BitField] = []
    for e, bf in entries:
        pos = 8 * e.byte_offset + e.shift
        if pos // 64 == (pos + e.bits - 1) // 64:
            words.setdefault(pos // 64, []).append((bf, pos))
        else:
            alone.append(bf)
    return [_BitWord(wire, k, fields, n) for k, fields in sorted(words.items())], alone


def _round8(n: int) -> int:
    return -(-n // 8) * 8


def _bit_format(e: EntryLayout) -> str:
    dt = e.channel.type
    if dt.name == "bool":
        return "?"
    return dt.numpy


@dataclass(frozen=True)
class ImageLayout:
    """Where each channel lives in one row of ``values`` (bytes).

    The row starts with the wire bytes themselves (``size`` bytes): byte-aligned
    unscaled channels are fields at their wire offsets, so they cost nothing to
    encode or decode. Then, 8-byte aligned, one float64 per scaled channel (the
    engineering value), then one field per remaining bit-level channel.
    """

    dtype: np.dtype[Any]
    size: int  # wire bytes per row
    float_offset: int  # byte offset of the float64 block
    scaled: tuple[EntryLayout, ...]  # float-block column order: aligned (by wire offset), then bit-level
    groups: tuple[tuple[int, int, str, int], ...]  # (first column, columns, wire dtype, wire offset)
    bits: tuple[EntryLayout, ...]  # unscaled bit-level channels


def image_layout(dl: DirectionLayout) -> ImageLayout:
    size = dl.size
    names: list[str] = []
    formats: list[str] = []
    offsets: list[int] = []
    for e in dl.channels:
        if e.aligned and not e.channel.scaled:
            names.append(e.name)
            formats.append(e.channel.type.numpy)
            offsets.append(e.byte_offset)
    aligned = sorted((e for e in dl.channels if e.channel.scaled and e.aligned), key=lambda e: e.bit_offset)
    unaligned = [e for e in dl.channels if e.channel.scaled and not e.aligned]
    scaled = (*aligned, *unaligned)
    float_offset = _round8(size)
    for j, e in enumerate(scaled):
        names.append(e.name)
        formats.append("<f8")
        offsets.append(float_offset + 8 * j)
    groups: list[tuple[int, int, str, int]] = []
    for j, e in enumerate(aligned):
        fmt = e.channel.type.numpy
        if groups:
            first, count, gfmt, goff = groups[-1]
            if gfmt == fmt and goff + count * (e.bits // 8) == e.byte_offset:
                groups[-1] = (first, count + 1, gfmt, goff)
                continue
        groups.append((j, 1, fmt, e.byte_offset))
    cursor = float_offset + 8 * len(scaled)
    bits = tuple(e for e in dl.channels if not e.channel.scaled and not e.aligned)
    for e in bits:
        fmt = _bit_format(e)
        width = np.dtype(fmt).itemsize
        cursor = -(-cursor // width) * width
        names.append(e.name)
        formats.append(fmt)
        offsets.append(cursor)
        cursor += width
    # keep the user-visible field order = wire order
    order = {e.name: i for i, e in enumerate(dl.channels)}
    fields = sorted(zip(names, formats, offsets, strict=True), key=lambda f: order[f[0]])
    dtype = np.dtype(
        {
            "names": [f[0] for f in fields],
            "formats": [f[1] for f in fields],
            "offsets": [f[2] for f in fields],
            "itemsize": _round8(max(cursor, 8)),
        }
    )
    return ImageLayout(dtype, size, float_offset, scaled, tuple(groups), bits)


def user_dtype(dl: DirectionLayout) -> np.dtype[Any]:
    """The dtype of ``values`` rows for direction layout ``dl``."""
    return image_layout(dl).dtype


class DirectionImage:
    """One direction (outputs = RxPDOs or inputs = TxPDOs) of N axes sharing a map.

    ``values`` (N,) structured and ``wire`` (N, size) uint8 share one buffer:
    each ``wire`` row is contiguous, rows are ``values.dtype.itemsize`` apart.
    """

    def __init__(self, dl: DirectionLayout, n_axes: int, *, engine: str = "auto") -> None:
        if n_axes < 1:
            raise ValueError("n_axes must be >= 1")
        if engine not in ENGINES:
            raise ValueError(f"engine must be one of {', '.join(ENGINES)}, not {engine!r}")
        for e in dl.channels:
            if e.channel.type.is_float and not e.aligned:
                raise FieldbusError(
                    f"{e.name}: {e.channel.type.name} entry at bit {e.bit_offset} is not byte aligned"
                )
        self.layout = dl
        self.n_axes = n_axes
        il = image_layout(dl)
        self.image_layout = il
        stride = il.dtype.itemsize
        self._buf = np.zeros(n_axes * stride, dtype=np.uint8)
        self.values: npt.NDArray[Any] = np.ndarray((n_axes,), dtype=il.dtype, buffer=self._buf)
        self.wire: U8 = np.ndarray((n_axes, dl.size), dtype=np.uint8, buffer=self._buf, strides=(stride, 1))
        k = len(il.scaled)
        self._k = k
        self._scaled = np.ndarray(
            (n_axes, k), dtype=np.float64, buffer=self._buf, offset=il.float_offset, strides=(stride, 8)
        )
        self._last = np.zeros((n_axes, k), dtype=np.float64)  # raw values (float64) encoded last
        self._work = np.zeros((n_axes, k), dtype=np.float64)
        self._ok = np.zeros((n_axes, k), dtype=bool)
        c, d = self._bind_scaling(il, dl.direction, n_axes)
        self._bind_groups(il, n_axes, stride)
        self._bit_scaled = [(il.scaled.index(e), e) for e in il.scaled if not e.aligned]
        self._apply_defaults(dl, il, c, d)
        self._choose_engine(engine, k)
        self._bind_bits(dl, il, n_axes)

    def _bind_scaling(
        self, il: ImageLayout, direction: Direction, n_axes: int
    ) -> tuple[npt.NDArray[np.float64], npt.NDArray[np.float64]]:
        """The scaled channels' coefficients: ``a*x + b`` from value to raw, ``c*x + d`` from raw to value
        (per channel and, as contiguous copies, per axis), and each type's raw range; returns (c, d)."""
        f = np.array([e.channel.factor for e in il.scaled], dtype=np.float64)
        o = np.array([e.channel.offset for e in il.scaled], dtype=np.float64)
        if direction is Direction.OUTPUTS:  # raw = f*value + o
            a, b, c, d = f, o, 1.0 / f, -o / f
        else:  # value = f*raw + o
            a, b, c, d = 1.0 / f, -o / f, f, o
        # An offset of 0 is stored as -0.0, the identity of IEEE addition (x + -0.0 == x for every x;
        # x + 0.0 turns -0.0 into +0.0). The C codec always adds it, numpy skips the sum when no channel
        # has an offset: the same bits either way.
        b, d = (np.where(v == 0.0, -0.0, v) for v in (b, d))
        lo = np.array([e.channel.type.min for e in il.scaled], dtype=np.float64)
        hi = np.array([e.channel.type.max for e in il.scaled], dtype=np.float64)
        self._coef = (a, b, c, d, lo, hi)
        # per-axis copies of the coefficients: contiguous (N, k) operands are ~2x faster than broadcasting
        self._a, self._b, self._c, self._d, self._lo, self._hi = (
            np.ascontiguousarray(np.broadcast_to(v, (n_axes, self._k))) for v in self._coef
        )
        self._use_b = bool(np.any(b != 0.0))
        self._use_d = bool(np.any(d != 0.0))
        self._is_int = [not e.channel.type.is_float for e in il.scaled]
        return c, d

    def _bind_groups(self, il: ImageLayout, n_axes: int, stride: int) -> None:
        """Wire views of each run of same-typed, adjacent scaled entries: one ufunc each."""
        self._groups: list[
            tuple[npt.NDArray[Any], npt.NDArray[Any], npt.NDArray[Any], npt.NDArray[Any], bool, _Top | None]
        ] = []
        for first, count, fmt, off in il.groups:
            width = np.dtype(fmt).itemsize
            wv = np.ndarray((n_axes, count), dtype=fmt, buffer=self._buf, offset=off, strides=(stride, width))
            cols = slice(first, first + count)
            dt = il.scaled[first].channel.type
            top = _Top(dt, (n_axes, count)) if _Top.needed(dt) else None
            self._groups.append(
                (wv, self._last[:, cols], self._scaled[:, cols], self._c[:, cols], not dt.is_float, top)
            )

    def _apply_defaults(
        self, dl: DirectionLayout, il: ImageLayout, c: npt.NDArray[np.float64], d: npt.NDArray[np.float64]
    ) -> None:
        """Defaults: plain ones straight into values; scaled ones as the initial raw value."""
        for e in dl.channels:
            if e.channel.default is None:
                continue
            if e.channel.scaled:
                j = il.scaled.index(e)
                self._last[:, j] = e.channel.default
                self._scaled[:, j] = c[j] * e.channel.default + d[j]
            else:
                self.values[e.name] = e.channel.default

    def _choose_engine(self, engine: str, k: int) -> None:
        """The C codec when asked for or on "auto" and it can code these channels; else numpy."""
        self.engine = "numpy"
        self._fast: Any = None
        bit_floats = any(e.channel.type.is_float for _, e in self._bit_scaled)  # no bit-level floats in C
        if engine in ("auto", "c") and k and not bit_floats:
            self._fast = _make_fast(self)
            if self._fast is not None:
                self.engine = "c"
        if engine == "c" and self.engine != "c" and k:
            why = (
                "it does not handle floats that are not byte-aligned"
                if bit_floats
                else "fieldbus._codec did not build or import"
            )
            raise FieldbusError(f"the C codec is not available: {why}")

    def _bind_bits(self, dl: DirectionLayout, il: ImageLayout, n_axes: int) -> None:
        """Bit-level entries on the numpy bit path: all of them, or only the unscaled ones when the C
        codec codes the scaled ones; one uint64 per 8-byte word of the row for the entries inside it."""
        bit_entries: list[tuple[EntryLayout, _BitField]] = []
        for e in dl.channels:
            if e.aligned or (self._fast is not None and e.channel.scaled):
                continue
            src = self._work[:, il.scaled.index(e)] if e.channel.scaled else self.values[e.name]
            bit_entries.append((e, _BitField(e, self.wire, src, n_axes)))
        words, alone = _bit_words(bit_entries, self.wire, n_axes)
        self._bits: list[_BitWord | _BitField] = [*words, *alone]
        # decoding: an unsigned entry inside one byte straight from that byte, the others by word
        small = [_ByteBits(e, self.wire, bf.src) for e, bf in bit_entries if _ByteBits.fits(e, bf.src)]
        rest = [(e, bf) for e, bf in bit_entries if not _ByteBits.fits(e, bf.src)]
        words, alone = _bit_words(rest, self.wire, n_axes)
        self._decode: list[_BitWord | _BitField | _ByteBits] = [*words, *alone, *small]

    @property
    def names(self) -> tuple[str, ...]:
        """Channel names in wire order."""
        return self.layout.names

    def __getitem__(self, name: str) -> npt.NDArray[Any]:
        """``image["target_position"]``: the (N,) view of one channel in ``values``.

        An unknown name is a :class:`~fieldbus.errors.ChannelNameError` naming the channels.
        """
        try:
            return self.values[name]
        except (ValueError, KeyError):
            if isinstance(name, str) and name not in (self.values.dtype.fields or {}):
                raise self._no_channel(name) from None
            raise

    def __setitem__(self, name: str, value: Any) -> None:
        try:
            self.values[name] = value
        except (ValueError, KeyError):
            if isinstance(name, str) and name not in (self.values.dtype.fields or {}):
                raise self._no_channel(name) from None
            raise  # a value that does not fit the channel: numpy's own message

    def _no_channel(self, name: object) -> ChannelNameError:
        """The error for a name this image does not have: its channels, and the nearest one."""
        text = str(name)
        near = difflib.get_close_matches(text, self.names, n=1, cutoff=0.5)
        hint = f"; did you mean '{near[0]}'?" if near else ""
        kind = "outputs (RxPDO)" if self.layout.direction is Direction.OUTPUTS else "inputs (TxPDO)"
        return ChannelNameError(
            f"no {kind} channel {text!r}{hint} (channels: {', '.join(self.names) or 'none'})"
        )

    # -- encode ---------------------------------------------------------------
    def to_wire(self) -> None:
        """Encode ``values`` into ``wire`` (all axes). Unscaled byte-aligned channels are already there."""
        if self._k:
            if self._fast is not None:
                self._fast.encode()
            else:
                self._encode_numpy()
        for bf in self._bits:
            bf.to_wire()

    def _encode_numpy(self) -> None:
        w, last, ok = self._work, self._last, self._ok
        np.multiply(self._scaled, self._a, out=w)
        if self._use_b:
            np.add(w, self._b, out=w)
        np.minimum(w, self._hi, out=w)  # saturate; NaN stays NaN
        np.maximum(w, self._lo, out=w)
        np.equal(w, w, out=ok)  # False where NaN
        np.copyto(last, w, where=ok)  # NaN keeps the raw value sent last
        for wv, lg, _, _, is_int, top in self._groups:
            if top is not None:  # 64-bit: float(max) is one past the range
                top.cast(lg, wv)
            elif is_int:
                np.rint(lg, out=wv, casting="unsafe")
            else:
                np.copyto(wv, lg, casting="unsafe")
        for j, _ in self._bit_scaled:
            np.rint(last[:, j], out=w[:, j])

    def from_wire(self) -> None:
        """Decode ``wire`` into ``values`` (all axes)."""
        for bf in self._decode:
            bf.from_wire()
        if not self._k:
            return
        if self._fast is not None:
            self._fast.decode()
            return
        for wv, _, sg, cg, _, _ in self._groups:
            np.multiply(wv, cg, out=sg)
        for j, _ in self._bit_scaled:
            np.multiply(self._work[:, j], self._c[:, j], out=self._scaled[:, j])
        if self._use_d:
            np.add(self._scaled, self._d, out=self._scaled)

    def raw(self, name: str) -> npt.NDArray[Any]:
        """A fresh (allocating) array of the raw wire values of ``name`` (diagnostics, tests)."""
        from fieldbus.core.pdo.layout import get_value

        e = self.layout.entry(name)
        return np.array([get_value(bytes(self.wire[i]), e) for i in range(self.n_axes)])


def _make_fast(img: DirectionImage) -> Any:
    """The C codec for ``img``'s scaled channels, or None where it is not built."""
    try:
        from fieldbus import _codec  # type: ignore[attr-defined]
    except ImportError:
        return None
    import struct
    import sys

    if sys.byteorder != "little":
        return None
    il = img.image_layout
    a, b, c, d, lo, hi = img._coef

    def kind(e: EntryLayout) -> tuple[bytes, int, int]:
        """Type code, bit shift and width of a column (bit-level: x unsigned, y signed)."""
        if e.aligned:
            return np.dtype(e.channel.type.numpy).char.encode(), 0, 0
        return (b"y" if e.channel.type.signed else b"x"), e.shift, e.bits

    spec = b"".join(
        struct.pack(
            "<icBBxdddddd",
            e.byte_offset,
            *kind(e),
            a[j],
            b[j],
            c[j],
            d[j],
            lo[j],
            hi[j],
        )
        for j, e in enumerate(il.scaled)
    )
    return _codec.ScaledCodec(img._buf, img.n_axes, il.dtype.itemsize, il.float_offset, img._last, spec)


class ProcessImage:
    """Outputs and inputs of N axes sharing one drive map.

    ``outputs`` are the RxPDOs (master -> drive), ``inputs`` the TxPDOs
    (drive -> master), both named from the master's side. The master calls
    ``outputs.to_wire()`` before sending and ``inputs.from_wire()`` after
    receiving; an emulated drive calls the opposite pair.
    """

    def __init__(self, map_layout: MapLayout, n_axes: int = 1, *, engine: str = "auto") -> None:
        self.layout = map_layout
        self.n_axes = n_axes
        self.outputs = DirectionImage(map_layout.outputs, n_axes, engine=engine)
        self.inputs = DirectionImage(map_layout.inputs, n_axes, engine=engine)
