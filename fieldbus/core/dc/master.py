"""What the master computes: frame timing on a line, propagation delays, offsets, SYNC start, host sync.

All times in ns. Receive times are the 32-bit latched values of registers
0x0900/0x0904 (ports 0 and 1) as the master reads them; the arithmetic wraps
like SOEM's ``int32``.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
import numpy.typing as npt

from fieldbus.core.dc.model import CABLE_NS_PER_M, SOEM_SYNC_DELAY_NS, EscTiming, wrap_signed


@dataclass(frozen=True)
class LineTiming:
    """True times (ns, on the master's time line) of one frame travelling a line of slaves.

    ``port0_ns[i]``: the frame reaches slave i's port 0 (downstream);
    ``port1_ns[i]``: it comes back at slave i's port 1 (NaN for the last slave,
    whose port 1 is closed); ``epu_ns[i]``: it reaches the processing unit
    (taken equal to the port 0 time: any constant latch offset is the same on
    every ESC and cancels); ``back_ns``: it is back at the master.
    """

    port0_ns: npt.NDArray[np.float64]
    port1_ns: npt.NDArray[np.float64]
    epu_ns: npt.NDArray[np.float64]
    back_ns: float


def line_timing(
    t_master_ns: float,
    escs: Sequence[EscTiming],
    cable_m: Sequence[float],
    ns_per_m: float = CABLE_NS_PER_M,
) -> LineTiming:
    """Where a frame sent by the master at ``t_master_ns`` is, slave by slave, on a line.

    ``cable_m[0]`` is the cable master -> slave 0, ``cable_m[i]`` slave i-1 ->
    slave i (metres, one-way delay ``ns_per_m`` per metre). Downstream a slave
    adds its processing delay, upstream its forwarding delay; the last slave
    turns the frame round through its processing unit (processing delay).
    """
    n = len(escs)
    if n == 0:
        raise ValueError("a line needs at least one slave")
    if len(cable_m) != n:
        raise ValueError(f"need {n} cable lengths (master->0, 0->1, ...), got {len(cable_m)}")
    wire = np.asarray(cable_m, dtype=np.float64) * ns_per_m
    if np.any(wire < 0):
        raise ValueError("cable lengths must be >= 0 m")
    tp = np.array([e.processing_ns for e in escs])
    tf = np.array([e.forwarding_ns for e in escs])
    p0 = np.empty(n)
    p0[0] = t_master_ns + wire[0]
    for i in range(1, n):
        p0[i] = p0[i - 1] + tp[i - 1] + wire[i]
    p1 = np.full(n, np.nan)
    out0 = p0[-1] + tp[-1]
    for i in range(n - 2, -1, -1):
        p1[i] = out0 + wire[i + 1]
        out0 = p1[i] + tf[i]
    return LineTiming(p0, p1, p0.copy(), float(out0 + wire[0]))


def _trunc_half(x: int) -> int:
    """x / 2 rounded toward zero, like C integer division."""
    return -((-x) // 2) if x < 0 else x // 2


def line_propagation_delays(
    port0_rx: Sequence[int],
    port1_rx: Sequence[int | None],
    t_diff_ns: int = 0,
) -> list[int]:
    """Propagation delay of each slave of a line from the reference clock (slave 0), in ns.

    SOEM's ecx_configdc for a line (every slave has DC, entry port 0, child on
    port 1): delay[i] = delay[i-1] + (dt3 - dt1) / 2 with dt3 = parent's
    port1 - port0 receive time (round trip of everything below the parent) and
    dt1 = the slave's own port1 - port0 (0 if port 1 is closed). SOEM assumes
    processing delay = forwarding delay; ``t_diff_ns`` (t_P - t_F) adds the
    ESC datasheet's correction for slaves that forward the frame back through
    their auto-forwarder (0 = SOEM exactly). ``port1_rx[i]`` is None where port 1
    is closed. Times are 32-bit register values; differences wrap.
    """
    n = len(port0_rx)
    if len(port1_rx) != n:
        raise ValueError("port0_rx and port1_rx must have the same length")
    delays = [0] * n
    for i in range(1, n):
        parent_p1 = port1_rx[i - 1]
        if parent_p1 is None:
            raise ValueError(f"slave {i - 1} has a child but its port 1 receive time is missing")
        dt3 = wrap_signed(parent_p1 - port0_rx[i - 1], 32)
        own_p1 = port1_rx[i]
        dt1 = 0 if own_p1 is None else wrap_signed(own_p1 - port0_rx[i], 32)
        if dt1 > dt3:  # SOEM keeps only a positive difference
            dt1 = -dt1
        corr = t_diff_ns if own_p1 is not None else 0
        delays[i] = delays[i - 1] + _trunc_half(dt3 - dt1 + corr)
    return delays


def soem_offsets(master_time_ns: int, epu_rx_local_ns: Sequence[int]) -> list[int]:
    """System time offsets (0x0920) as SOEM writes them: master time - local EPU receive time.

    Every slave gets the same master time although the frame reached it later,
    so right after this each slave's system time lags by its propagation delay;
    the time-control loop (which knows the delay) removes that lag.
    """
    return [wrap_signed(master_time_ns - t, 64) for t in epu_rx_local_ns]


def sync0_start_time(
    system_time_ns: int, cycle_ns: int, shift_ns: int = 0, sync_delay_ns: int = SOEM_SYNC_DELAY_NS
) -> int:
    """First SYNC0 pulse (0x0990) the way SOEM's ecx_dcsync0 picks it (system time, ns).

    The next whole multiple of ``cycle_ns`` after ``system_time_ns`` +
    ``sync_delay_ns``, plus one cycle, plus ``shift_ns`` (may be negative): slaves
    with the same cycle fire together.
    """
    if cycle_ns > 0:
        return ((system_time_ns + sync_delay_ns) // cycle_ns) * cycle_ns + cycle_ns + shift_ns
    return system_time_ns + sync_delay_ns + shift_ns


def sync1_period_ns(cycle0_ns: int, cycle1_ns: int) -> int:
    """Period of SYNC1 pulses: (cycle1 // cycle0 + 1) x cycle0 (SOEM ecx_dcsync01's true cycle time)."""
    if cycle0_ns <= 0:
        raise ValueError("SYNC1 needs a SYNC0 cycle time > 0")
    return (cycle1_ns // cycle0_ns + 1) * cycle0_ns


@dataclass(frozen=True)
class HostSyncConfig:
    """Host-side PI that puts the host cycle at ``offset_ns`` after each DC cycle boundary.

    Like the ec_sync() of SOEM's examples (pysoem users copy it): delta = phase
    of the DC time within the cycle minus the offset, folded into
    (-cycle/2, cycle/2]; an integral counts the sign of delta; the correction
    added to the next sleep is -delta/p_divisor - integral/i_divisor (ns).
    """

    cycle_ns: int = 1_000_000
    offset_ns: int = 50_000
    p_divisor: int = 100
    i_divisor: int = 20


@dataclass
class HostSync:
    """State of the host PI (one per master). ``step`` is called once per host cycle."""

    config: HostSyncConfig = field(default_factory=HostSyncConfig)
    integral: int = 0
    delta_ns: int = 0

    def step(self, dc_time_ns: int) -> int:
        """Given the DC system time read this cycle (ns), the correction (ns) to add to the next sleep.

        Positive = sleep longer. ``delta_ns`` keeps the phase error
        (DC phase - offset); it goes to 0 when the host is aligned.
        """
        c = self.config.cycle_ns
        delta = (dc_time_ns - self.config.offset_ns) % c
        if delta > c // 2:
            delta -= c
        self.delta_ns = delta
        if delta > 0:
            self.integral += 1
        elif delta < 0:
            self.integral -= 1
        return -_trunc_div(delta, self.config.p_divisor) - _trunc_div(self.integral, self.config.i_divisor)


def _trunc_div(a: int, b: int) -> int:
    q = abs(a) // abs(b)
    return q if (a >= 0) == (b > 0) else -q


def simulate_host_sync(
    cycles: int,
    *,
    host_drift_ppm: float = 50.0,
    initial_phase_ns: int = 300_000,
    config: HostSyncConfig | None = None,
    jitter_ns: float = 0.0,
    seed: int = 0,
) -> npt.NDArray[np.int64]:
    """Run the host PI against a perfect DC clock; returns delta (ns) for each cycle.

    The host wakes every cycle_ns x (1 + drift) plus the correction (its own
    clock drifts by ``host_drift_ppm`` against DC time), starting
    ``initial_phase_ns`` into a DC cycle, with uniform wake-up jitter of
    ±``jitter_ns``.
    """
    cfg = config or HostSyncConfig()
    sync = HostSync(cfg)
    rng = np.random.default_rng(seed)
    t = float(initial_phase_ns)
    out = np.empty(cycles, dtype=np.int64)
    for n in range(cycles):
        wake = t + (rng.uniform(-jitter_ns, jitter_ns) if jitter_ns else 0.0)
        corr = sync.step(round(wake))
        out[n] = sync.delta_ns
        t += (cfg.cycle_ns + corr) * (1.0 + host_drift_ppm * 1e-6)
    return out
