"""The one output path's rules: what a command value must pass before any codec encodes it (no I/O).

Every command value a drive receives, whatever wrote it (the controller into the process image, a CAN
family's mode frame built from the image, ``ProfileMove``, ``Homing``, the safe stop), passes
:meth:`OutputRules.apply` in the cycle, before ``to_wire()`` and before any family codec reads the image:

- **NaN** keeps the value sent last (initially the channel's default), never a jump to 0 nor garbage;
- **±inf** saturates to the map's limit on that side; with no limit on that side it keeps the value sent
  last (it never becomes the wire type's maximum, e.g. INT32_MAX);
- **out of range** (outside the map's ``min..max`` window) saturates to the window;
- **too big a step** (``max_step`` per cycle, or ``max_rate`` x the bus cycle time) is clamped to the step,
  on axes that are engaged (CiA 402: operation enabled in a cyclic synchronous mode, 8-10, when the map
  has 0x6061); an axis that is not follows what is asked, so enabling it starts from where the controller
  is, and a profile mode's target (a destination: ``ProfileMove``) is not ramped;
- every refused value is counted per axis and reason (:attr:`OutputRules.counts`) and the first cycle
  of a refusal streak of one axis's channel is an :class:`OutputClamp` event (asked, sent).

The limits come from the map (:func:`channel_limits`): its ``limits:`` section, else the start-up
SDOs' software position limit (0x607D), maximum profile velocity (0x607F) and maximum torque (0x6072)
for the CiA 402 targets, and each scaled raw-CAN command field's ``min..max``. ``limits: off`` keeps only
NaN and inf rules. Vectorised over axes; :meth:`OutputRules.apply` allocates nothing on a clean cycle.
"""

from __future__ import annotations

import enum
import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt

from fieldbus.core import kernels
from fieldbus.core.canfamily import families
from fieldbus.core.command_guard import UnsafeOutputError as UnsafeOutputError
from fieldbus.core.command_guard import finite as finite
from fieldbus.core.pdo.image import DirectionImage
from fieldbus.core.pdo.layout import DirectionLayout, EntryLayout
from fieldbus.core.pdo.model import DriveMap, OutputLimit
from fieldbus.errors import FieldbusError

TARGET_POSITION, TARGET_VELOCITY, TARGET_TORQUE = 0x607A, 0x60FF, 0x6071
SOFTWARE_POSITION_LIMIT, MAX_PROFILE_VELOCITY, MAX_TORQUE = 0x607D, 0x607F, 0x6072
OPERATION_ENABLED_MASK, OPERATION_ENABLED = 0x6F, 0x27  # CiA 402 statusword: operation enabled
CYCLIC_MODES = (8, 10)  # CiA 402 modes of operation: cyclic synchronous position, velocity, torque


class Reason(enum.IntEnum):
    """Why a command value was refused (a column of :attr:`OutputRules.counts`)."""

    NAN = 0  # not a number: the value sent last was kept
    INF = 1  # infinite: saturated to the limit, or the value sent last kept where there is none
    RANGE = 2  # outside the map's window: saturated to it
    STEP = 3  # changed more than the map's step per cycle: clamped to the step


@dataclass(frozen=True)
class OutputClamp:
    """A command value refused in one cycle: ``asked`` by the controller, ``sent`` instead (channel units)."""

    cycle: int
    group: str
    axis: int  # row of the group's image
    channel: str
    reason: Reason
    asked: float
    sent: float

    @property
    def kind(self) -> str:
        return "output_clamp"

    def __str__(self) -> str:
        return (
            f"cycle {self.cycle} group '{self.group}' axis {self.axis}: {self.channel} {self.reason.name} "
            f"asked {self.asked:g}, sent {self.sent:g}"
        )


@dataclass(frozen=True)
class ChannelLimit:
    """The limits of one output channel, in the units the image shows (engineering units when scaled)."""

    channel: str
    min: float = -math.inf
    max: float = math.inf
    max_step: float = math.inf  # largest change per cycle (on engaged axes)
    source: str = "map"  # where the limit comes from: "map", "0x607D", "rawcan min..max", ...


def _raw_to_value(e: EntryLayout, raw: float) -> float:
    """An output channel's raw value in image units (outputs: ``raw = factor * value + offset``)."""
    ch = e.channel
    return (raw - ch.offset) / ch.factor if ch.scaled else raw


def _sdo_value(drive: DriveMap, index: int, sub_index: int) -> float | None:
    for s in drive.sdo:
        if s.index == index and s.sub_index == sub_index:
            return float(s.value)
    return None


def channel_limits(
    drive: DriveMap, lay: DirectionLayout, cycle_s: float, narrow: Sequence[OutputLimit] = ()
) -> tuple[ChannelLimit, ...]:
    """The limits of ``drive``'s output channels (``lay``: its outputs layout), ``cycle_s`` seconds a cycle.

    The map's ``limits:`` win; otherwise CiA 402 targets take the start-up SDOs' window 0x607D:01..02,
    +-0x607F (target velocity), +-0x6072 (target torque); scaled raw-CAN command fields their
    ``min..max``. ``limits: off`` gives none. ``narrow`` (a network file's per-slave ``limits:``) then
    only narrows: the window is the intersection, the step the smaller one.
    """
    found: dict[str, ChannelLimit] = {}
    if not drive.limits_off:
        found = _map_limits(drive, lay, cycle_s)
    for lim in narrow:
        old = found.get(lim.channel, ChannelLimit(lim.channel))
        lo = old.min if lim.min is None else max(old.min, lim.min)
        hi = old.max if lim.max is None else min(old.max, lim.max)
        found[lim.channel] = ChannelLimit(
            lim.channel, lo, hi, min(old.max_step, _step(lim, cycle_s)), "network"
        )
    return tuple(found.values())


def _step(lim: OutputLimit, cycle_s: float) -> float:
    """The largest change per cycle a ``limits:`` entry allows (``max_step``, ``max_rate`` x the cycle)."""
    step = lim.max_step if lim.max_step is not None else math.inf
    if lim.max_rate is not None:
        step = min(step, lim.max_rate * cycle_s)
    return step


def _map_limits(drive: DriveMap, lay: DirectionLayout, cycle_s: float) -> dict[str, ChannelLimit]:
    found: dict[str, ChannelLimit] = {}

    def window(index: int, lo_raw: float | None, hi_raw: float | None, source: str) -> None:
        e = lay.find(index)
        if e is None or lo_raw is None or hi_raw is None or lo_raw >= hi_raw:
            return
        a, b = sorted((_raw_to_value(e, lo_raw), _raw_to_value(e, hi_raw)))
        found[e.name] = ChannelLimit(e.name, a, b, source=source)

    window(
        TARGET_POSITION,
        _sdo_value(drive, SOFTWARE_POSITION_LIMIT, 1),
        _sdo_value(drive, SOFTWARE_POSITION_LIMIT, 2),
        "0x607D",
    )
    for index, obj in ((TARGET_VELOCITY, MAX_PROFILE_VELOCITY), (TARGET_TORQUE, MAX_TORQUE)):
        top = _sdo_value(drive, obj, 0)
        if top is not None and top > 0:
            window(index, -top, top, f"0x{obj:04X}")
    if drive.rawcan is not None:
        for f in drive.rawcan.command:
            if f.min is not None and f.max is not None:
                found[f.name] = ChannelLimit(f.name, f.min, f.max, source="rawcan min..max")
        family = families().get(drive.rawcan.family) if drive.rawcan.protocol is not None else None
        for name, lo, hi in family.command_limits(drive.rawcan.protocol) if family is not None else ():
            found[name] = ChannelLimit(name, lo, hi, source="rawcan min..max")
    for lim in drive.limits:
        old = found.get(lim.channel, ChannelLimit(lim.channel))
        found[lim.channel] = ChannelLimit(
            lim.channel,
            old.min if lim.min is None else lim.min,
            old.max if lim.max is None else lim.max,
            _step(lim, cycle_s),
            "map",
        )
    return found


def widenings(
    drive: DriveMap, lay: DirectionLayout, cycle_s: float, narrow: Sequence[OutputLimit]
) -> list[tuple[str, str, str]]:
    """What in ``narrow`` (a network file's per-slave ``limits:``) would widen ``drive``'s own limits:
    (channel, key, why) for each ``min`` below, ``max`` above the map's window or a step above its step."""
    base = {lim.channel: lim for lim in channel_limits(drive, lay, cycle_s)}
    out: list[tuple[str, str, str]] = []
    for lim in narrow:
        b = base.get(lim.channel, ChannelLimit(lim.channel, source="none"))
        src = f"the map's window {b.min:g}..{b.max:g} ({b.source})"
        if lim.min is not None and lim.min < b.min:
            out.append((lim.channel, "min", f"min {lim.min:g} is below {src}: a network file only narrows"))
        if lim.max is not None and lim.max > b.max:
            out.append((lim.channel, "max", f"max {lim.max:g} is above {src}: a network file only narrows"))
        step = _step(lim, cycle_s)
        if step > b.max_step:
            key = "max_step" if lim.max_step is not None else "max_rate"
            out.append(
                (
                    lim.channel,
                    key,
                    f"a step of {step:g} per cycle is above the map's {b.max_step:g}: a network file only narrows",
                )
            )
    return out


def _float_runs(values: npt.NDArray[Any], names: Sequence[str]) -> list[list[str]]:
    """The float columns among ``names`` (wire order) in runs of one dtype lying side by side in the
    row (each starts where the one before ends): one block each, one ufunc per rule for the run."""
    fields = values.dtype.fields
    assert fields is not None
    runs: list[list[str]] = []
    end = -1
    for name in names:
        dt, at = fields[name][:2]
        if dt.kind != "f":
            continue
        if runs and at == end and fields[runs[-1][0]][0] == dt:
            runs[-1].append(name)
        else:
            runs.append([name])
        end = at + dt.itemsize
    return runs


def _run_view(values: npt.NDArray[Any], names: list[str]) -> npt.NDArray[Any]:
    """(N, len(names)) writable view of a run of :func:`_float_runs` in the image's rows."""
    first = values[names[0]]
    return np.lib.stride_tricks.as_strided(
        first, shape=(len(values), len(names)), strides=(values.strides[0], first.dtype.itemsize)
    )


def slave_limits(
    slaves: Sequence[Any], lay: DirectionLayout, cycle_s: float
) -> dict[int, tuple[ChannelLimit, ...]]:
    """Per row of a group's image, the limits of the slaves whose network entry narrows them (``limits``)."""
    rows: dict[int, tuple[ChannelLimit, ...]] = {}
    row = 0
    for s in slaves:
        narrow = getattr(s, "limits", ())
        if narrow:
            lims = channel_limits(s.map, lay, cycle_s, narrow)
            for k in range(s.map.axes):
                rows[row + k] = lims
        row += s.map.axes
    return rows


class _Block:
    """Columns of one dtype the rules work on in place: ``x`` (N, m), or a float64 copy of an integer column.

    The clean cycle costs a clamp and one comparison (plus the step's): a side without a limit is
    clamped at the dtype's largest finite number, so NaN (NaN != NaN) and infinities show up as a
    change and take the slow path, which tells the reasons apart.
    """

    def __init__(
        self, x: npt.NDArray[Any], names: list[str], limits: list[list[ChannelLimit]], src: Any = None
    ) -> None:
        """``limits[row][column]``: each row's limits (a network file may narrow one slave's)."""
        n, m = x.shape
        self.view = x  # the image's columns (strided): gathered into ``x`` once, written back when changed
        self.x = np.ascontiguousarray(x)
        self.names, self.src = names, src  # src: the integer column (N,) copied in and out
        dt = x.dtype
        big = float(np.finfo(dt).max)

        def per_axis(value: Callable[[ChannelLimit], float]) -> npt.NDArray[Any]:
            return np.array([[value(lim) for lim in row] for row in limits], dtype=dt).reshape(n, m)

        self.last = np.array(x, dtype=dt, copy=True)  # what was sent last
        self.lo = per_axis(lambda lim: max(lim.min, -big))
        self.hi = per_axis(lambda lim: min(lim.max, big))
        self.open_lo = per_axis(lambda lim: lim.min == -math.inf).astype(bool)
        self.open_hi = per_axis(lambda lim: lim.max == math.inf).astype(bool)
        self.stepped = any(math.isfinite(lim.max_step) for row in limits for lim in row)
        self.step = per_axis(lambda lim: min(lim.max_step, big))
        self.nstep = np.negative(self.step)
        self.asked = np.zeros((n, m), dtype=dt)
        self.work = np.zeros((n, m), dtype=dt)
        self.delta = np.zeros((n, m), dtype=dt)
        self.ok = np.zeros((n, m), dtype=bool)
        self.flag = [np.zeros((n, m), dtype=bool) for _ in Reason]  # per reason: refused this cycle
        self.was = np.zeros((n, m), dtype=bool)  # refused the cycle before (streaks: one event each)
        self.was_any = False  # an element of ``was`` is set
        self.any = np.zeros((n, m), dtype=bool)
        self.keep, self.side, self.new = (np.zeros((n, m), dtype=bool) for _ in range(3))
        self.per_axis = np.zeros(n, dtype=bool)
        # the newest refusal per value (OutputRules.last_clamp): cycle (-1: none), reason, asked, sent
        self.last_cycle = np.full((n, m), -1, dtype=np.int64)
        self.last_reason = np.zeros((n, m), dtype=np.int64)
        self.last_asked = np.zeros((n, m), dtype=dt)
        self.last_sent = np.zeros((n, m), dtype=dt)
        self.hit = False
        self.started = False  # the first cycle sets the reference of the step rule
        self.col = self.x[:, 0]
        # the clean cycle's test, on the image's columns as they are (no gather): without a step rule and
        # without an integer source; with no finite window anywhere it is one "all finite" test. It reads
        # lo/hi/step as built here: limits are fixed for the block's life (a change means a new OutputRules)
        self.quick = src is None and not self.stepped
        self.windowed = bool(np.any(self.lo > -big) or np.any(self.hi < big))
        # the clean cycle's test and its copy into ``last`` as one call (core.kernels)
        self.clean = kernels.window(self.view, self.last, *((self.lo, self.hi) if self.windowed else ()))

    def apply(self, engaged: Callable[[], npt.NDArray[np.bool_]] | None) -> bool:
        """The rules on this block; True when a value was refused (the flags then say which).

        ``engaged()``: (N, 1) per axis, the step rule applies (None: every axis, after the first cycle).
        """
        x, last, w, ok = self.x, self.last, self.work, self.ok
        # the clean cycle (every value in its window, or finite without one): none is refused nor changed
        if self.quick and not self.hit and self.clean():
            self.started = True
            return False
        if self.src is not None:
            np.copyto(self.col, self.src, casting="unsafe")
        else:
            np.copyto(x, self.view)
        if self.hit:
            for f in self.flag:
                f.fill(False)
        hit = False
        np.minimum(x, self.hi, out=w)
        np.maximum(w, self.lo, out=w)
        np.not_equal(w, x, out=ok)  # NaN, an infinity or out of the window
        if np.count_nonzero(ok):
            hit = True
            self._refuse()
        if self.stepped and self.started:
            d, big = self.delta, self.flag[Reason.STEP]
            np.subtract(x, last, out=d)
            np.minimum(d, self.step, out=w)
            np.maximum(w, self.nstep, out=w)
            np.not_equal(w, d, out=big)
            if np.count_nonzero(big) and engaged is not None:  # only then: which axes are engaged
                np.logical_and(big, engaged(), out=big)
            if np.count_nonzero(big):
                if not hit:
                    np.copyto(self.asked, x)
                    hit = True
                np.add(last, w, out=x, where=big)
        self.started = True
        np.copyto(last, x)
        if hit:  # what is sent instead, back into the image (the controller reads what went out)
            if self.src is not None:
                np.rint(self.col, out=self.src, casting="unsafe")
            else:
                np.copyto(self.view, x)
        self.hit = hit
        return hit

    def _refuse(self) -> None:
        """The slow path (a value changed by the clamp in ``work``): reasons, and NaN / open-side inf -> last."""
        x, asked, ok, flag = self.x, self.asked, self.ok, self.flag
        np.copyto(asked, x)
        np.isnan(asked, out=flag[Reason.NAN])
        np.isinf(asked, out=flag[Reason.INF])
        rng = flag[Reason.RANGE]
        np.isfinite(asked, out=rng)
        np.logical_and(rng, ok, out=rng)
        np.copyto(x, self.work)
        np.copyto(x, self.last, where=flag[Reason.NAN])
        # an infinity towards a side without a limit keeps the value sent last (never the dtype's maximum)
        keep, side = self.keep, self.side
        np.greater(asked, 0, out=keep)
        np.logical_and(keep, self.open_hi, out=keep)
        np.less(asked, 0, out=side)
        np.logical_and(side, self.open_lo, out=side)
        np.logical_or(keep, side, out=keep)
        np.logical_and(keep, flag[Reason.INF], out=keep)
        np.copyto(x, self.last, where=keep)


class OutputRules:
    """The rules for one axis group's outputs (:mod:`fieldbus.core.output_rules`); call :meth:`apply` once a cycle.

    ``counts[axis, reason]``: refused values since bring-up, per row of the image and :class:`Reason`.
    """

    def __init__(
        self,
        group: str,
        image: DirectionImage,
        limits: Sequence[ChannelLimit] = (),
        statusword: npt.NDArray[np.uint16] | None = None,
        mode_display: npt.NDArray[np.int8] | None = None,
        rows: Mapping[int, Sequence[ChannelLimit]] | None = None,
    ) -> None:
        """``limits``: the group's (its map's); ``rows``: a row's own instead (:func:`slave_limits`)."""
        self.group = group
        self.image = image
        n = image.n_axes
        by_name = {lim.channel: lim for lim in limits}
        by_row = {r: {lim.channel: lim for lim in lims} for r, lims in (rows or {}).items()}
        for name in {*by_name, *(c for d in by_row.values() for c in d)}:
            if name not in image.names:
                raise FieldbusError(
                    f"group '{group}': limits name no output channel '{name}' ({', '.join(image.names)})"
                )
        self.limits = tuple(limits)
        self.row_limits = {r: tuple(lims) for r, lims in (rows or {}).items()}

        def per_row(names: list[str]) -> list[list[ChannelLimit]]:
            return [
                [by_row.get(r, by_name).get(c) or by_name.get(c) or ChannelLimit(c) for c in names]
                for r in range(n)
            ]

        self.blocks: list[_Block] = []
        il = image.image_layout
        scaled = [e.name for e in il.scaled]
        if scaled:  # the image's float64 block of engineering values, in place
            self.blocks.append(_Block(image._scaled, scaled, per_row(scaled)))
        values = image.values
        limited = {*by_name, *(c for d in by_row.values() for c in d)}
        raw = [e.name for e in image.layout.channels if not e.channel.scaled]
        for names in _float_runs(values, raw):  # unscaled floats on the wire (raw-CAN float32 fields)
            self.blocks.append(_Block(_run_view(values, names), names, per_row(names)))
        for e in image.layout.channels:
            if e.channel.scaled:
                continue
            col = values[e.name]
            if e.name in limited and col.dtype.kind in "iu":  # an integer channel with limits
                work = np.array(col, dtype=np.float64).reshape(n, 1)
                self.blocks.append(_Block(work, [e.name], per_row([e.name]), src=col))
        self.counts = np.zeros((n, len(Reason)), dtype=np.int64)
        self._statusword = statusword
        self._mode = mode_display  # 0x6061: the step rule holds in the cyclic synchronous modes only
        self._in_mode = np.zeros(n, dtype=bool)
        self._csp, self._cst = np.int8(CYCLIC_MODES[0]), np.int8(CYCLIC_MODES[1])
        self._engaged = np.ones(n, dtype=bool) if statusword is not None else None
        self._engaged2d = self._engaged[:, None] if self._engaged is not None else None
        self._sw = np.zeros(n, dtype=np.uint16)
        self._mask, self._enabled = np.uint16(OPERATION_ENABLED_MASK), np.uint16(OPERATION_ENABLED)
        self._stepped = any(b.stepped for b in self.blocks)
        # bound once: apply() makes no method object per cycle
        self._engaged_fn: Callable[[], npt.NDArray[np.bool_]] | None = (
            self._engaged_now if self._engaged is not None else None
        )
        self.refused_now = False  # a value was refused in the last apply()

    def apply(self) -> bool:
        """The rules on every output value of the group, in place; True when one was refused this cycle."""
        hit = False
        engaged = self._engaged_fn
        for b in self.blocks:
            if b.apply(engaged):
                hit = True
                for r in Reason:
                    np.logical_or.reduce(b.flag[r], axis=1, out=b.per_axis)
                    col = self.counts[:, r]
                    np.add(col, b.per_axis, out=col)
        self.refused_now = hit
        return hit

    def _engaged_now(self) -> npt.NDArray[np.bool_]:
        """(N, 1): the axes whose statusword says operation enabled (read when a step is too big only)."""
        assert self._statusword is not None and self._engaged is not None
        np.bitwise_and(self._statusword, self._mask, out=self._sw)
        np.equal(self._sw, self._enabled, out=self._engaged)
        if self._mode is not None:  # a profile mode's target is a destination, not a step (ProfileMove)
            np.greater_equal(self._mode, self._csp, out=self._in_mode)
            np.logical_and(self._engaged, self._in_mode, out=self._engaged)
            np.less_equal(self._mode, self._cst, out=self._in_mode)
            np.logical_and(self._engaged, self._in_mode, out=self._engaged)
        assert self._engaged2d is not None
        return self._engaged2d

    def events(self, cycle: int) -> list[OutputClamp]:
        """This cycle's new refusals (the first cycle of each streak per axis and channel), as events."""
        out: list[OutputClamp] = []
        for b in self.blocks:
            np.logical_or(b.flag[Reason.NAN], b.flag[Reason.INF], out=b.any)
            np.logical_or(b.any, b.flag[Reason.RANGE], out=b.any)
            np.logical_or(b.any, b.flag[Reason.STEP], out=b.any)
            np.greater(b.any, b.was, out=b.new)  # refused now, not in the cycle before: a streak starts
            if b.hit and np.count_nonzero(b.new):
                for axis, j in zip(*np.nonzero(b.new), strict=True):
                    reason = next(r for r in Reason if b.flag[r][axis, j])
                    out.append(
                        OutputClamp(
                            cycle,
                            self.group,
                            int(axis),
                            b.names[j],
                            reason,
                            float(b.asked[axis, j]),
                            float(b.x[axis, j]),
                        )
                    )
            if b.hit:  # every refusal of this cycle, streak or not, for last_clamp (no allocation)
                np.copyto(b.last_asked, b.asked, where=b.any)
                np.copyto(b.last_sent, b.x, where=b.any)
                np.copyto(b.last_cycle, cycle, where=b.any)
                for r in reversed(Reason):  # the first reason wins, as in the events
                    np.copyto(b.last_reason, int(r), where=b.flag[r])
            np.copyto(b.was, b.any)
            b.was_any = bool(np.count_nonzero(b.any))
        return out

    def last_clamp(self, row: int) -> OutputClamp | None:
        """The newest command value refused on ``row`` (any cycle of a streak, not only its first), as an
        :class:`OutputClamp`; None when none was. For monitors: read from any thread, without a lock (a
        value written by the cycle meanwhile may mix two cycles)."""
        best: OutputClamp | None = None
        for b in self.blocks:
            for j, name in enumerate(b.names):
                c = int(b.last_cycle[row, j])
                if c >= 0 and (best is None or c > best.cycle):
                    reason = Reason(int(b.last_reason[row, j]))
                    asked, sent = float(b.last_asked[row, j]), float(b.last_sent[row, j])
                    best = OutputClamp(c, self.group, row, name, reason, asked, sent)
        return best

    def rebase(self, rows: npt.NDArray[np.bool_]) -> None:
        """The NaN and step rules of ``rows`` restart from the image's values now (a transition's seed,
        :mod:`fieldbus.core.hold`): what counts as "sent last" is the seed, not what went out before. A
        value that is not finite is not taken (the reference keeps what was sent). Allocates: transitions
        only, never on a clean cycle."""
        sel = np.asarray(rows, dtype=bool)[:, None]
        for b in self.blocks:
            now = np.array(b.src if b.src is not None else b.view, dtype=b.last.dtype).reshape(b.last.shape)
            np.copyto(b.last, now, where=sel & np.isfinite(now))

    def settle(self) -> None:
        """No refusal this cycle: streaks end (call instead of :meth:`events` on a clean cycle)."""
        for b in self.blocks:
            if b.was_any:
                b.was.fill(False)
                b.was_any = False
