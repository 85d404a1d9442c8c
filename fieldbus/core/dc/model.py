"""Protocol data, timing assumptions and the ESC time-control loop (pure).

Units: every time is in nanoseconds (ns), every drift or rate in parts per
million (ppm) unless a name says ``_frac`` (a plain fraction, 1 ppm = 1e-6).
A positive drift means the clock runs fast. Sources: docs/dc.md.
"""

from __future__ import annotations

import enum
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

#: 5 ns per metre of copper cable (signal speed about 2/3 c), the usual figure
#: for Cat-5 twisted pair (IEEE 802.3 allows up to 5.7 ns/m).
CABLE_NS_PER_M = 5.0
#: EtherCAT system time counts from 2000-01-01 00:00 UTC (ETG.1000.4; SOEM subtracts
#: 946684800 s from the Unix time in ecx_configdc).
EPOCH_2000_UNIX_S = 946_684_800
#: SOEM starts cyclic operation 100 ms after reading the system time (ethercatdc.c ``SyncDelay``).
SOEM_SYNC_DELAY_NS = 100_000_000
#: The ESC's local clock ticks at 100 MHz: 10 ns per tick (ESC datasheet Section I, DC chapter).
TICK_NS = 10
#: Largest rate correction of the modelled time-control loop: one 1 ns step every 0x80
#: ticks of 10 ns, about 781 ppm (speed counter minimum 0x0080, datasheet Section II).
MAX_CORRECTION_FRAC = 1.0 / (0x80 * TICK_NS)
#: Loop time constant per unit of Speed Counter Start (0x1000 gives 65.5 ms).
TAU_NS_PER_SPEED_COUNT = 16_000
#: The difference filter weighs a sample 2^-depth per this much time since the previous one.
FILTER_REF_INTERVAL_NS = 1_000_000


class DcRegister(enum.IntEnum):
    """ESC distributed-clock registers (ETG.1000.4, ESC datasheet Section II, 0x0900-0x09FF)."""

    RECEIVE_TIME_PORT0 = 0x0900  # u32 local time of the frame at port 0; a write latches all ports
    RECEIVE_TIME_PORT1 = 0x0904  # u32 local time of the frame coming back at port 1
    RECEIVE_TIME_PORT2 = 0x0908
    RECEIVE_TIME_PORT3 = 0x090C
    SYSTEM_TIME = 0x0910  # u64 local copy of system time; a write feeds the time-control loop
    RECEIVE_TIME_EPU = 0x0918  # u64 local time of the frame at the processing unit
    SYSTEM_TIME_OFFSET = 0x0920  # u64 system time - local time
    SYSTEM_TIME_DELAY = 0x0928  # u32 propagation delay reference clock -> this ESC
    SYSTEM_TIME_DIFF = 0x092C  # u32 filtered difference, bit 31 = local copy smaller than received
    SPEED_COUNTER_START = 0x0930  # u16 loop bandwidth; a write resets the loop filters
    SPEED_COUNTER_DIFF = 0x0932  # i16 clock period deviation
    SYSTEM_TIME_DIFF_FILTER_DEPTH = 0x0934  # u8
    SPEED_COUNTER_FILTER_DEPTH = 0x0935  # u8
    CYCLIC_UNIT_CONTROL = 0x0980  # u8 (0 = ECAT controls cyclic unit and latch)
    ACTIVATION = 0x0981  # u8 SyncActivation bits
    START_TIME_CYCLIC = 0x0990  # u64 system time of the first SYNC0 pulse
    SYNC0_CYCLE_TIME = 0x09A0  # u32
    SYNC1_CYCLE_TIME = 0x09A4  # u32


class SyncActivation(enum.IntFlag):
    """Bits of register 0x0981 (SOEM writes 3 for SYNC0, 7 for SYNC0 + SYNC1)."""

    CYCLIC_OPERATION = 0x01
    SYNC0 = 0x02
    SYNC1 = 0x04


@dataclass(frozen=True)
class EscTiming:
    """Frame delays inside one ESC, in ns (ESC datasheet Section I, "propagation delay").

    ``processing_ns``: port 0 in -> processing unit -> port 1 out (t_P); also the
    turn-around of a slave whose port 1 is closed (the frame loops back through
    the processing unit). ``forwarding_ns``: port 1 in -> port 0 out through the
    auto-forwarder only (t_F). t_Diff = t_P - t_F. Defaults are the order of an
    ET1100 with MII ports, PHY delays not included; see docs/dc.md.
    """

    processing_ns: float = 320.0
    forwarding_ns: float = 280.0

    @property
    def t_diff_ns(self) -> float:
        """t_Diff = processing - forwarding delay (ns)."""
        return self.processing_ns - self.forwarding_ns


@dataclass(frozen=True)
class LoopConfig:
    """Knobs of the ESC time-control loop (registers 0x0930, 0x0934, 0x0935).

    The model is behavioural: a filtered phase error drives a PI controller on the
    clock rate with time constant ``tau_ns`` = speed_counter_start x 16 µs
    (0x1000 -> 65.5 ms; larger = smoother and slower, as the datasheet says), a
    critically damped pair of poles, and a rate correction bounded by
    ``max_correction_frac`` (about ±781 ppm). The difference filter (0x0934)
    averages the received errors with time constant 2^depth ms (weight 2^-depth
    per sample at 1 ms). 0x0935 is stored but not modelled.
    """

    speed_counter_start: int = 0x1000
    diff_filter_depth: int = 4
    speed_filter_depth: int = 0x0C
    max_correction_frac: float = MAX_CORRECTION_FRAC

    def __post_init__(self) -> None:
        if not 0x80 <= self.speed_counter_start <= 0x3FFF:
            raise ValueError(f"speed_counter_start must be 0x0080..0x3FFF, not {self.speed_counter_start:#x}")
        if not 0 <= self.diff_filter_depth <= 15:
            raise ValueError(f"diff_filter_depth must be 0..15, not {self.diff_filter_depth}")

    @property
    def tau_ns(self) -> float:
        """Loop time constant (ns)."""
        return float(self.speed_counter_start * TAU_NS_PER_SPEED_COUNT)


@dataclass(frozen=True)
class LoopState:
    """Filter and integrator of the time-control loop (one slave, or one per slave as arrays).

    ``diff_ns``: filtered (local copy - received) system time; ``integral_frac``
    and ``correction_frac``: rate corrections (fraction; negative slows the
    clock down); ``primed``: a sample has been seen since the last reset.
    """

    diff_ns: npt.NDArray[np.float64]
    integral_frac: npt.NDArray[np.float64]
    correction_frac: npt.NDArray[np.float64]
    primed: npt.NDArray[np.bool_]

    @classmethod
    def reset(cls, n: int) -> LoopState:
        """State after a write to Speed Counter Start (0x0930): filters cleared."""
        z = np.zeros(n)
        return cls(z, z.copy(), z.copy(), np.zeros(n, dtype=bool))


def loop_step(
    state: LoopState,
    delta_ns: npt.NDArray[np.float64],
    interval_ns: npt.NDArray[np.float64] | float,
    cfg: LoopConfig,
    mask: npt.NDArray[np.bool_] | None = None,
) -> LoopState:
    """One received system time: returns the new loop state.

    ``delta_ns`` = (local copy of system time - delay) - received system time,
    positive when this clock is ahead (ESC datasheet Section I, drift
    compensation). ``interval_ns``: local time since the previous sample
    (ignored for the first sample after a reset). Only slaves in ``mask`` are
    updated (all if None). Vectorised over slaves.
    """
    dt = np.asarray(interval_ns, dtype=np.float64)
    # difference filter: weight 2^-depth per 1 ms of interval (time constant 2^depth ms)
    alpha = np.minimum(1.0, 2.0**-cfg.diff_filter_depth * dt / FILTER_REF_INTERVAL_NS)
    diff = np.where(state.primed, state.diff_ns + alpha * (delta_ns - state.diff_ns), delta_ns)
    x = np.minimum(dt, cfg.tau_ns) / cfg.tau_ns
    cmax = cfg.max_correction_frac
    # critically damped PI: proportional 2/tau, integral 1/tau^2 (per unit of time)
    prop = -2.0 * diff / cfg.tau_ns
    saturated = np.abs(state.integral_frac + prop) >= cmax
    integ = np.where(
        state.primed & ~saturated,  # anti-windup: hold the integral while the output is saturated
        state.integral_frac - diff * x / cfg.tau_ns,
        state.integral_frac,
    )
    integ = np.clip(integ, -cmax, cmax)
    corr = np.clip(integ + prop, -cmax, cmax)
    primed = np.ones_like(state.primed)
    if mask is not None:
        diff = np.where(mask, diff, state.diff_ns)
        integ = np.where(mask, integ, state.integral_frac)
        corr = np.where(mask, corr, state.correction_frac)
        primed = np.where(mask, primed, state.primed)
    return LoopState(diff, integ, corr, primed)


def wrap_signed(value: int, bits: int) -> int:
    """``value`` modulo 2**bits as a signed integer (two's complement)."""
    m = 1 << bits
    v = value % m
    return v - m if v >= m >> 1 else v


def cable_delay_ns(length_m: float, ns_per_m: float = CABLE_NS_PER_M) -> float:
    """One-way delay of a cable of ``length_m`` metres (ns)."""
    if length_m < 0:
        raise ValueError(f"cable length must be >= 0 m, not {length_m}")
    return length_m * ns_per_m
