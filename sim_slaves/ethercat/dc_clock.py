"""Register-level model of one ESC's distributed clock, and a line of them (pure, integer ns).

``now_ns`` everywhere is the caller's true time line (the emulator's clock),
never the slave's: each ESC turns it into its own local time with its drift.
An emulator drives one ``DcSlaveClock`` per slave:

* a write to 0x0900 (the master's BWR) latches port 0 and the processing unit
  at ``now_ns`` = the moment the frame reached this slave; call
  ``latch_port(1, t)`` when the same frame comes back at port 1;
* a write to 0x0910 is the ARMW/FRMW time-control input (received system time);
* reads return little-endian bytes of the registers at ``now_ns``;
* ``sync0_edges``/``sync1_edges`` give the pulses in a window of true time.

``DcSegment`` places clocks on a line with cables and does the same for a frame
sent by the master at ``t_master_ns``.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt

from fieldbus.core.dc.master import LineTiming, line_timing, sync1_period_ns
from fieldbus.core.dc.model import (
    CABLE_NS_PER_M,
    FILTER_REF_INTERVAL_NS,
    DcRegister,
    EscTiming,
    LoopConfig,
    LoopState,
    SyncActivation,
    wrap_signed,
)

DC_FIRST = 0x0900
DC_END = 0x09B0  # exclusive: 0x0900-0x09AF are modelled as memory (0x09A0/0x09A4 cycle times included)
U64 = (1 << 64) - 1
U32 = (1 << 32) - 1


class DcSlaveClock:
    """One ESC's local clock, time-control loop and SYNC unit, behind its registers.

    ``drift_ppm``: how fast the crystal runs against true time (positive =
    fast). ``initial_local_ns``: local time at true time 0 (power-up state).
    Local time = initial + (1 + drift) x (1 + loop correction) x elapsed.
    """

    def __init__(
        self,
        *,
        drift_ppm: float = 0.0,
        initial_local_ns: int = 0,
        timing: EscTiming | None = None,
        loop: LoopConfig | None = None,
    ) -> None:
        self._drift_ppm = float(drift_ppm)
        self.timing = timing or EscTiming()
        self._loop_cfg = loop or LoopConfig()
        self._mem = bytearray(DC_END - DC_FIRST)
        self._anchor_true = 0  # true time of the last rate change (ns)
        self._anchor_local = int(initial_local_ns) & U64
        self._anchor_frac = 0.0  # sub-ns part of local time at the anchor
        # time-control loop state (scalar form of model.LoopState; see time_control_input)
        self._diff = 0.0
        self._integral = 0.0
        self._correction = 0.0
        self._primed = False
        self._drift_factor = 1.0 + self._drift_ppm * 1e-6
        self._rate = self._drift_factor
        self._last_sample_local: int | None = None
        self.offset_ns = 0
        self.delay_ns = 0
        self.activation = SyncActivation(0)
        self.start_time_ns = 0
        self.sync0_cycle_ns = 0
        self.sync1_cycle_ns = 0
        self.port_rx_local = [0, 0, 0, 0]  # full local times latched per port
        self.epu_rx_local = 0
        self._put(DcRegister.SPEED_COUNTER_START, self._loop_cfg.speed_counter_start, 2)
        self._put(DcRegister.SYSTEM_TIME_DIFF_FILTER_DEPTH, self._loop_cfg.diff_filter_depth, 1)
        self._put(DcRegister.SPEED_COUNTER_FILTER_DEPTH, self._loop_cfg.speed_filter_depth, 1)

    # ----- time
    @property
    def drift_ppm(self) -> float:
        """Crystal drift against true time (ppm, positive = fast); change it with :meth:`set_drift`."""
        return self._drift_ppm

    def set_drift(self, drift_ppm: float, now_ns: int) -> None:
        """From true time ``now_ns`` on the crystal runs ``drift_ppm`` off (local time stays continuous)."""
        self._rebase(now_ns)
        self._drift_ppm = float(drift_ppm)
        self._update_rate()

    def _update_rate(self) -> None:
        self._drift_factor = 1.0 + self._drift_ppm * 1e-6
        self._rate = self._drift_factor * (1.0 + self._correction)

    @property
    def rate(self) -> float:
        """Local ns per true ns: (1 + drift) x (1 + loop correction)."""
        return self._rate

    @property
    def loop_state(self) -> LoopState:
        """The time-control loop's filter and integrator (a copy, as one-slave arrays)."""
        return LoopState(
            np.array([self._diff]),
            np.array([self._integral]),
            np.array([self._correction]),
            np.array([self._primed]),
        )

    @property
    def loop_config(self) -> LoopConfig:
        """The loop's current knobs (0x0930/0x0934/0x0935 as last written)."""
        return self._loop_cfg

    @property
    def _loop_cfg(self) -> LoopConfig:
        return self._cfg

    @_loop_cfg.setter
    def _loop_cfg(self, cfg: LoopConfig) -> None:
        self._cfg = cfg
        self._loop_consts = (2.0**-cfg.diff_filter_depth, cfg.tau_ns, cfg.max_correction_frac)

    def _local_exact(self, now_ns: int) -> float:
        return self._anchor_frac + (now_ns - self._anchor_true) * self._rate

    def local_time(self, now_ns: int) -> int:
        """Local time (ns, 64-bit) at true time ``now_ns``."""
        return (self._anchor_local + math.floor(self._local_exact(now_ns))) & U64

    def system_time(self, now_ns: int) -> int:
        """Local copy of the system time (0x0910): local time + offset (ns, 64-bit)."""
        return (self.local_time(now_ns) + self.offset_ns) & U64

    def true_time_of_system(self, system_ns: int, after_ns: int) -> int:
        """True time (ns) at which the system time reaches ``system_ns``, at the current rate.

        Exact while the loop correction does not change in between (use it
        for windows shorter than one time-control sample).
        """
        ahead = wrap_signed(system_ns - self.system_time(after_ns), 64)
        return after_ns + round(ahead / self.rate)

    def _rebase(self, now_ns: int) -> None:
        exact = self._local_exact(now_ns)
        whole = math.floor(exact)
        self._anchor_local = (self._anchor_local + whole) & U64
        self._anchor_frac = exact - whole
        self._anchor_true = now_ns

    # ----- receive-time latching
    def latch_port(self, port: int, now_ns: int) -> None:
        """The latch frame reaches ``port`` (0-3) at true time ``now_ns``; port 0 also latches the EPU."""
        if not 0 <= port <= 3:
            raise ValueError(f"port must be 0..3, not {port}")
        t = self.local_time(now_ns)
        self.port_rx_local[port] = t
        if port == 0:
            self.epu_rx_local = t

    def latch_receive_times(self, port0_ns: int, port1_ns: int | None = None) -> None:
        """Latch a BWR to 0x0900 arriving at port 0 at ``port0_ns`` and back at port 1 at ``port1_ns``."""
        self.latch_port(0, port0_ns)
        if port1_ns is not None:
            self.latch_port(1, port1_ns)

    # ----- time-control loop
    def time_control_input(self, received_ns: int, now_ns: int, bits: int = 32) -> None:
        """A received system time (ARMW/FRMW write to 0x0910) at true time ``now_ns``.

        delta = (system time - delay) - received, compared on the lower ``bits``
        bits (the ESC uses 32); the loop then adjusts the clock speed from
        ``now_ns`` on. The loop is :func:`fieldbus.core.dc.model.loop_step` for
        one slave, written out as scalar arithmetic with the same operations in
        the same order (an emulator runs this once per slave and cycle: about
        1 us instead of 20; a test checks that both give the same numbers).
        """
        # rebase at now_ns: the rate changes from here on
        exact = self._anchor_frac + (now_ns - self._anchor_true) * self._rate
        whole = math.floor(exact)
        local = (self._anchor_local + whole) & U64
        self._anchor_local = local
        self._anchor_frac = exact - whole
        self._anchor_true = now_ns
        m = 1 << bits
        d = (local + self.offset_ns - self.delay_ns - received_ns) % m
        delta = float(d - m if d >= m >> 1 else d)
        last = self._last_sample_local
        self._last_sample_local = local
        dt = 0.0 if last is None else float((local - last) & U64)
        # model.loop_step (``a if a < b else b`` is min/np.minimum for numbers that are not NaN)
        weight, tau, cmax = self._loop_consts
        alpha = weight * dt / FILTER_REF_INTERVAL_NS
        if alpha > 1.0:
            alpha = 1.0
        primed = self._primed
        diff = self._diff + alpha * (delta - self._diff) if primed else delta
        x = (dt if dt < tau else tau) / tau
        prop = -2.0 * diff / tau
        integral = self._integral
        if primed and not abs(integral + prop) >= cmax:  # anti-windup: hold while saturated
            integral = integral - diff * x / tau
        if integral > cmax:
            integral = cmax
        elif integral < -cmax:
            integral = -cmax
        corr = integral + prop
        if corr > cmax:
            corr = cmax
        elif corr < -cmax:
            corr = -cmax
        self._diff = diff
        self._integral = integral
        self._correction = corr
        self._primed = True
        self._rate = self._drift_factor * (1.0 + corr)

    def reset_loop(self, now_ns: int) -> None:
        """What a write to Speed Counter Start (0x0930) does: clear the loop's filters."""
        self._rebase(now_ns)
        self._diff = self._integral = self._correction = 0.0
        self._primed = False
        self._update_rate()
        self._last_sample_local = None

    # ----- SYNC unit
    def _edges(self, first_sys: int, period: int, from_ns: int, to_ns: int) -> list[int]:
        if period <= 0:
            t = self.true_time_of_system(first_sys, from_ns)
            return [t] if from_ns <= t < to_ns else []
        sys_from = self.system_time(from_ns)
        k = max(0, -(-wrap_signed(sys_from - first_sys, 64) // period))
        out: list[int] = []
        while True:
            t = self.true_time_of_system(first_sys + k * period, from_ns)
            if t >= to_ns:
                return out
            if t >= from_ns:
                out.append(t)
            k += 1

    def sync0_edges(self, from_ns: int, to_ns: int) -> list[int]:
        """True times in [from_ns, to_ns) where SYNC0 fires: system time = start + k x cycle0 (k >= 0).

        Empty unless 0x0981 has cyclic operation and SYNC0 on. A cycle time of 0
        gives a single pulse at the start time.
        """
        need = SyncActivation.CYCLIC_OPERATION | SyncActivation.SYNC0
        if self.activation & need != need:
            return []
        return self._edges(self.start_time_ns, self.sync0_cycle_ns, from_ns, to_ns)

    def sync1_edges(self, from_ns: int, to_ns: int) -> list[int]:
        """True times of SYNC1 pulses: cycle1 after a SYNC0 pulse, every (cycle1 // cycle0 + 1) SYNC0 cycles."""
        need = SyncActivation.CYCLIC_OPERATION | SyncActivation.SYNC1
        if self.activation & need != need or self.sync0_cycle_ns <= 0:
            return []
        period = sync1_period_ns(self.sync0_cycle_ns, self.sync1_cycle_ns)
        return self._edges(self.start_time_ns + self.sync1_cycle_ns, period, from_ns, to_ns)

    # ----- registers
    def _put(self, addr: int, value: int, size: int) -> None:
        self._mem[addr - DC_FIRST : addr - DC_FIRST + size] = (value & ((1 << (8 * size)) - 1)).to_bytes(
            size, "little"
        )

    def _refresh(self, now_ns: int) -> None:
        for port in range(4):
            self._put(DcRegister.RECEIVE_TIME_PORT0 + 4 * port, self.port_rx_local[port], 4)
        self._put(DcRegister.SYSTEM_TIME, self.system_time(now_ns), 8)
        self._put(DcRegister.RECEIVE_TIME_EPU, self.epu_rx_local, 8)
        self._put(DcRegister.SYSTEM_TIME_OFFSET, self.offset_ns, 8)
        self._put(DcRegister.SYSTEM_TIME_DELAY, self.delay_ns, 4)
        self._put(DcRegister.ACTIVATION, int(self.activation), 1)
        self._put(DcRegister.START_TIME_CYCLIC, self.start_time_ns, 8)
        self._put(DcRegister.SYNC0_CYCLE_TIME, self.sync0_cycle_ns, 4)
        self._put(DcRegister.SYNC1_CYCLE_TIME, self.sync1_cycle_ns, 4)
        mag = min(round(abs(self._diff)), 0x7FFF_FFFF)
        self._put(DcRegister.SYSTEM_TIME_DIFF, mag | (0x8000_0000 if self._diff < 0 else 0), 4)
        speed_diff = round(self._correction / 1e-8)  # 0.01 ppm units (model's)
        self._put(DcRegister.SPEED_COUNTER_DIFF, max(-0x7FFF, min(0x7FFF, speed_diff)), 2)

    @staticmethod
    def _check(addr: int, size: int) -> None:
        if size <= 0 or addr < DC_FIRST or addr + size > DC_END:
            raise ValueError(
                f"DC registers span 0x{DC_FIRST:04X}-0x{DC_END - 1:04X}; got 0x{addr:04X}+{size}"
            )

    def read_register(self, addr: int, size: int, now_ns: int) -> bytes:
        """Little-endian bytes of ``size`` bytes from ``addr`` (0x0900-0x09AF) at true time ``now_ns``."""
        self._check(addr, size)
        self._refresh(now_ns)
        return bytes(self._mem[addr - DC_FIRST : addr - DC_FIRST + size])

    def write_register(self, addr: int, data: bytes, now_ns: int) -> None:
        """Apply a write of ``data`` at ``addr`` at true time ``now_ns`` (what the ESC does with it).

        0x0900: latch port 0 and the EPU receive time. 0x0910: time-control
        input (4 or 8 bytes of received system time). 0x0920 offset, 0x0928
        delay, 0x0930 speed counter start (resets the loop), 0x0934/0x0935
        filter depths, 0x0981 activation, 0x0990 start time, 0x09A0/0x09A4
        cycle times. Other bytes are stored as plain memory.
        """
        self._check(addr, len(data))
        if addr <= DcRegister.SYSTEM_TIME < addr + len(data) and addr != DcRegister.SYSTEM_TIME:
            raise ValueError("a write touching System Time (0x0910) must start at 0x0910")
        self._refresh(now_ns)
        start = addr - DC_FIRST
        self._mem[start : start + len(data)] = data
        touched = range(addr, addr + len(data))

        def u(reg: int, size: int) -> int:
            return int.from_bytes(self._mem[reg - DC_FIRST : reg - DC_FIRST + size], "little")

        if DcRegister.RECEIVE_TIME_PORT0 in touched:
            self.latch_port(0, now_ns)
        if DcRegister.SYSTEM_TIME in touched:
            # the ESC compares the lower 32 bits whatever the write size (datasheet Section I)
            self.time_control_input(int.from_bytes(data[:4], "little"), now_ns, bits=32)
        if any(r in touched for r in range(DcRegister.SYSTEM_TIME_OFFSET, DcRegister.SYSTEM_TIME_OFFSET + 8)):
            self._rebase(now_ns)
            self.offset_ns = u(DcRegister.SYSTEM_TIME_OFFSET, 8)
        if any(r in touched for r in range(DcRegister.SYSTEM_TIME_DELAY, DcRegister.SYSTEM_TIME_DELAY + 4)):
            self.delay_ns = u(DcRegister.SYSTEM_TIME_DELAY, 4)
        if (
            DcRegister.SYSTEM_TIME_DIFF_FILTER_DEPTH in touched
            or DcRegister.SPEED_COUNTER_FILTER_DEPTH in touched
        ):
            self._loop_cfg = LoopConfig(
                speed_counter_start=self._loop_cfg.speed_counter_start,
                diff_filter_depth=u(DcRegister.SYSTEM_TIME_DIFF_FILTER_DEPTH, 1) & 0x0F,
                speed_filter_depth=u(DcRegister.SPEED_COUNTER_FILTER_DEPTH, 1) & 0x0F,
                max_correction_frac=self._loop_cfg.max_correction_frac,
            )
        if DcRegister.SPEED_COUNTER_START in touched or DcRegister.SPEED_COUNTER_START + 1 in touched:
            scs = max(0x80, u(DcRegister.SPEED_COUNTER_START, 2) & 0x7FFF)
            self._loop_cfg = LoopConfig(
                speed_counter_start=scs,
                diff_filter_depth=self._loop_cfg.diff_filter_depth,
                speed_filter_depth=self._loop_cfg.speed_filter_depth,
                max_correction_frac=self._loop_cfg.max_correction_frac,
            )
            self.reset_loop(now_ns)
        if DcRegister.ACTIVATION in touched:
            self.activation = SyncActivation(u(DcRegister.ACTIVATION, 1) & 0x07)
        if any(r in touched for r in range(DcRegister.START_TIME_CYCLIC, DcRegister.START_TIME_CYCLIC + 8)):
            self.start_time_ns = u(DcRegister.START_TIME_CYCLIC, 8)
        if any(r in touched for r in range(DcRegister.SYNC0_CYCLE_TIME, DcRegister.SYNC0_CYCLE_TIME + 4)):
            self.sync0_cycle_ns = u(DcRegister.SYNC0_CYCLE_TIME, 4)
        if any(r in touched for r in range(DcRegister.SYNC1_CYCLE_TIME, DcRegister.SYNC1_CYCLE_TIME + 4)):
            self.sync1_cycle_ns = u(DcRegister.SYNC1_CYCLE_TIME, 4)


#: one clock of a line, as :class:`ClockArrays` holds it (the C loop's ``Clock`` record)
CLOCK_RECORD = np.dtype(
    [
        ("anchor_local", np.uint64),  # local ns at the anchor (64-bit, wraps)
        ("anchor_frac", np.float64),  # sub-ns part of it
        ("anchor_true", np.int64),  # true ns of the anchor
        ("rate", np.float64),  # local ns per true ns
        ("drift_factor", np.float64),  # 1 + drift
        ("offset", np.uint64),  # 0x0920
        ("delay", np.uint64),  # 0x0928
        ("last_sample", np.uint64),  # local ns of the last loop sample
        ("diff", np.float64),  # filtered system time difference (ns)
        ("integral", np.float64),  # integral rate correction (fraction)
        ("correction", np.float64),  # rate correction (fraction)
        ("weight", np.float64),  # 2^-depth of the difference filter
        ("tau", np.float64),  # loop time constant (ns)
        ("cmax", np.float64),  # bound of the correction (fraction)
        ("has_last", np.bool_),
        ("primed", np.bool_),
    ],
    align=True,
)

#: ``time_control(rec, received, now, a, b, ref_ns)``: the loop samples of clocks a..b-1 in C
LoopFunction = Callable[[npt.NDArray[np.void], int, npt.NDArray[np.int64], int, int, float], None]


def _c_loop() -> LoopFunction | None:
    """``sim_slaves._dcloop.time_control`` if it is built for :data:`CLOCK_RECORD`'s layout, else None."""
    try:
        from sim_slaves import _dcloop  # type: ignore[attr-defined]
    except ImportError:
        return None
    fields = CLOCK_RECORD.fields
    assert fields is not None
    ours = tuple((name, fields[name][1]) for name in CLOCK_RECORD.names or ())
    if tuple(_dcloop.layout) != ours or _dcloop.record_size != CLOCK_RECORD.itemsize:
        return None
    loop: LoopFunction = _dcloop.time_control
    return loop


class ClockArrays:
    """The time-control state of a line of clocks: one :data:`CLOCK_RECORD` per clock.

    :class:`LineClock` objects keep their anchor and loop state here
    (:attr:`field`: a view of the records per field), so a line can run the
    loops of all its clocks in one call of :attr:`loop`: about 3 us for 64
    clocks, against about 1.5 us per clock one by one, with the same bits.
    """

    #: the C loop, or None where ``sim_slaves._dcloop`` is not built (then clock by clock)
    loop: LoopFunction | None = _c_loop()

    def __init__(self, n: int) -> None:
        self.rec = np.zeros(n, dtype=CLOCK_RECORD)
        for name in ("rate", "drift_factor", "weight", "tau", "cmax"):
            self.rec[name] = 1.0
        self.field: dict[str, npt.NDArray[Any]] = {name: self.rec[name] for name in CLOCK_RECORD.names or ()}


class LineClock(DcSlaveClock):
    """A :class:`DcSlaveClock` whose time-control state is element ``index`` of a line's :class:`ClockArrays`.

    It behaves as the clock it was made from (``source``, whose state it
    takes over); the line steps the loops of all its clocks together.
    """

    def __init__(self, arrays: ClockArrays, index: int, source: DcSlaveClock) -> None:
        self.arrays = arrays
        self.index = index
        for name, value in vars(source).items():
            if name not in ("arrays", "index"):
                setattr(self, name, value)
        for name in _IN_ARRAYS:  # (a LineClock source keeps these in its arrays, not in vars())
            setattr(self, name, getattr(source, name))


def _element(array: str, cast: Callable[[Any], Any]) -> property:
    def get(self: LineClock) -> Any:
        return cast(self.arrays.field[array][self.index])

    def put(self: LineClock, value: Any) -> None:
        self.arrays.field[array][self.index] = value

    return property(get, put)


def _last_sample_get(self: LineClock) -> int | None:
    f, i = self.arrays.field, self.index
    return int(f["last_sample"][i]) if f["has_last"][i] else None


def _last_sample_put(self: LineClock, value: int | None) -> None:
    f, i = self.arrays.field, self.index
    f["has_last"][i] = value is not None
    f["last_sample"][i] = 0 if value is None else value


def _loop_consts_get(self: LineClock) -> tuple[float, float, float]:
    f, i = self.arrays.field, self.index
    return float(f["weight"][i]), float(f["tau"][i]), float(f["cmax"][i])


def _loop_consts_put(self: LineClock, value: tuple[float, float, float]) -> None:
    f, i = self.arrays.field, self.index
    f["weight"][i], f["tau"][i], f["cmax"][i] = value


_ELEMENTS = (
    ("_anchor_local", "anchor_local", int),
    ("_anchor_frac", "anchor_frac", float),
    ("_anchor_true", "anchor_true", int),
    ("_rate", "rate", float),
    ("_drift_factor", "drift_factor", float),
    ("offset_ns", "offset", int),
    ("delay_ns", "delay", int),
    ("_diff", "diff", float),
    ("_integral", "integral", float),
    ("_correction", "correction", float),
    ("_primed", "primed", bool),
)
for _name, _array, _cast in _ELEMENTS:
    setattr(LineClock, _name, _element(_array, _cast))
LineClock._last_sample_local = property(_last_sample_get, _last_sample_put)  # type: ignore[assignment]
LineClock._loop_consts = property(_loop_consts_get, _loop_consts_put)  # type: ignore[assignment]
#: the attributes of a :class:`LineClock` that live in its line's :class:`ClockArrays`
_IN_ARRAYS = (*(name for name, _, _ in _ELEMENTS), "_last_sample_local", "_loop_consts")


@dataclass
class DcSegment:
    """A line of DC slaves (slave 0 next to the master, and the reference clock).

    ``cable_m[0]``: master -> slave 0, ``cable_m[i]``: slave i-1 -> slave i (m).
    """

    clocks: Sequence[DcSlaveClock]
    cable_m: Sequence[float]
    ns_per_m: float = CABLE_NS_PER_M

    def timing(self, t_master_ns: int) -> LineTiming:
        """True times of a frame sent at ``t_master_ns`` at every slave's ports."""
        return line_timing(t_master_ns, [c.timing for c in self.clocks], self.cable_m, self.ns_per_m)

    def latch_receive_times(self, t_master_ns: int) -> LineTiming:
        """A BWR to 0x0900 sent at ``t_master_ns``: every slave latches its port 0, EPU and port 1 times."""
        lt = self.timing(t_master_ns)
        for i, clock in enumerate(self.clocks):
            p1 = lt.port1_ns[i]
            clock.latch_receive_times(round(lt.port0_ns[i]), None if np.isnan(p1) else round(p1))
        return lt

    def distribute_system_time(self, t_master_ns: int, reference: int = 0) -> int:
        """An FRMW on 0x0910 of ``reference`` sent at ``t_master_ns``: returns the time read.

        The reference's system time is read as the frame passes its processing
        unit and written into every later slave as the frame passes theirs.
        """
        lt = self.timing(t_master_ns)
        ref_time = self.clocks[reference].system_time(round(lt.epu_ns[reference]))
        data = ref_time.to_bytes(8, "little")
        for i in range(reference + 1, len(self.clocks)):
            self.clocks[i].write_register(DcRegister.SYSTEM_TIME, data, round(lt.epu_ns[i]))
        return ref_time
