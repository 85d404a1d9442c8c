"""Vectorised simulation of one EtherCAT line segment's distributed clocks (pure, numpy).

The master configures DC the way SOEM does (latch, delays, offsets), then sends
one frame per cycle carrying an FRMW of the reference clock's system time
(slave 0); every other ESC's time-control loop adjusts its clock speed. Times
are floats in ns relative to the master's time at configuration (0), so that
float64 keeps sub-ns resolution over hours.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt

from fieldbus.core.dc.master import line_propagation_delays, line_timing, sync0_start_time
from fieldbus.core.dc.model import CABLE_NS_PER_M, EscTiming, LoopConfig, LoopState, loop_step

FloatArray = npt.NDArray[np.float64]


@dataclass(frozen=True)
class DcSimResult:
    """Outcome of ``simulate``. Series have one entry per cycle; times in ms, spreads in ns.

    ``spread_ns[n]``: max - min of all slaves' system times at the same true
    instant (just before cycle n's frame). ``sync0_edges_ns[n, i]``: true time of
    slave i's next SYNC0 pulse seen at cycle n, relative to the ideal pulse
    (the reference's), NaN before SYNC0 starts; ``sync0_spread_ns[n]`` its
    max - min. ``converged_after_ms``: first time after which ``spread_ns`` stays
    below ``threshold_ns`` to the end (None if never).
    """

    n_slaves: int
    seconds: float
    cycle_ns: int
    compensation: bool
    threshold_ns: float
    drifts_ppm: FloatArray
    delays_ns: npt.NDArray[np.int64]
    true_delays_ns: FloatArray
    times_ms: FloatArray
    spread_ns: FloatArray
    sync0_edges_ns: FloatArray
    sync0_spread_ns: FloatArray
    sync0_start_ns: int
    final_spread_ns: float
    converged_after_ms: float | None
    max_spread_after_convergence_ns: float | None

    @property
    def final_sync0_spread_ns(self) -> float | None:
        """SYNC0 spread at the last cycle (ns), None if SYNC0 never started."""
        v = float(self.sync0_spread_ns[-1]) if len(self.sync0_spread_ns) else math.nan
        return None if math.isnan(v) else v

    @property
    def max_delay_error_ns(self) -> float:
        """Largest |computed - true| propagation delay (ns): the static spread the loop cannot see."""
        return float(np.max(np.abs(self.delays_ns - self.true_delays_ns)))


def spread_drifts(n_slaves: int, drift_ppm: float, seed: int) -> FloatArray:
    """Drifts evenly spread over ±drift_ppm (both extremes included), in a seeded random order."""
    if n_slaves < 1:
        raise ValueError(f"need at least 1 slave, not {n_slaves}")
    d = np.linspace(-drift_ppm, drift_ppm, n_slaves) if n_slaves > 1 else np.array([drift_ppm])
    return np.random.default_rng(seed).permutation(d)


def converged_after(spread: FloatArray, times_ms: FloatArray, threshold: float) -> float | None:
    """First time (ms) after which ``spread`` stays below ``threshold`` until the end; None if never."""
    above = np.flatnonzero(~(spread < threshold))
    if len(above) == 0:
        return float(times_ms[0]) if len(times_ms) else None
    last = int(above[-1])
    return None if last + 1 >= len(times_ms) else float(times_ms[last + 1])


def convergence_bound_ms(
    drift_span_ppm: float,
    initial_error_ns: float,
    threshold_ns: float = 100.0,
    loop: LoopConfig | None = None,
) -> float:
    """Estimated time (ms) until the spread stays below ``threshold_ns`` (derivation in docs/dc.md).

    ``drift_span_ppm``: max - min drift of the slaves (200 for ±100 ppm);
    ``initial_error_ns``: largest initial system-time error against the
    reference (after SOEM's offsets: the largest propagation delay). Slew phase
    at full correction, initial_error / (c_max - span), then the linear
    critically damped loop, whose error to a frequency step falls as
    span x t x exp(-t / tau); x* solves x e^-x = threshold / (span x tau).
    """
    cfg = loop or LoopConfig()
    span = drift_span_ppm * 1e-6
    headroom = cfg.max_correction_frac - span
    if headroom <= 0:
        raise ValueError(f"drift span {drift_span_ppm} ppm exceeds the loop's correction range")
    t_slew = initial_error_ns / headroom
    target = threshold_ns / (span * cfg.tau_ns) if span > 0 else math.inf
    x = 0.0
    if target < 1.0 / math.e:  # otherwise the linear phase never exceeds the threshold
        x = 1.0 - math.log(target)
        for _ in range(50):  # Newton on ln(x) - x - ln(target) = 0, root above x = 1
            x = x - (math.log(x) - x - math.log(target)) / (1.0 / x - 1.0)
    return (t_slew + x * cfg.tau_ns) / 1e6


def simulate(
    n_slaves: int,
    drift_ppm: float,
    seconds: float,
    cycle_ns: int = 1_000_000,
    seed: int = 0,
    compensation: bool = True,
    *,
    drifts_ppm: Sequence[float] | None = None,
    esc: EscTiming | Sequence[EscTiming] | None = None,
    cable_m: float | Sequence[float] = 1.0,
    ns_per_m: float = CABLE_NS_PER_M,
    loop: LoopConfig | None = None,
    master_t_diff_ns: int | None = None,
    jitter_ns: float = 5.0,
    threshold_ns: float = 100.0,
    sync0_cycle_ns: int | None = None,
    sync0_shift_ns: int = 0,
) -> DcSimResult:
    """Simulate ``seconds`` of a line of ``n_slaves`` DC slaves; slave 0 is the reference clock.

    Drifts: ``drifts_ppm`` if given, else spread evenly over ±``drift_ppm``
    (order shuffled by ``seed``). Each slave's local clock starts at a random
    value. Configuration follows SOEM's ecx_configdc: latch, delays from the
    receive times (``master_t_diff_ns``: the t_Diff correction the master applies;
    None = it knows the ESCs' true t_Diff, 0 = plain SOEM), offsets = master time
    - local receive time. Then one FRMW per cycle (``cycle_ns``) distributes the
    reference time; with ``compensation`` off the slaves ignore it. Each
    received-time comparison carries uniform noise of ±``jitter_ns`` (the 10 ns
    tick of the ESC clock). SYNC0 starts as SOEM's ecx_dcsync0 does (100 ms
    after configuration, on a multiple of the cycle, plus ``sync0_shift_ns``).
    """
    if seconds <= 0 or cycle_ns <= 0:
        raise ValueError("seconds and cycle_ns must be > 0")
    rng = np.random.default_rng(seed)
    drifts = _drifts(n_slaves, drift_ppm, drifts_ppm, seed)
    escs = [esc] * n_slaves if esc is None or isinstance(esc, EscTiming) else list(esc)
    escs = [e or EscTiming() for e in escs]
    if len(escs) != n_slaves:
        raise ValueError(f"esc needs {n_slaves} entries")
    cables = [float(cable_m)] * n_slaves if isinstance(cable_m, int | float) else list(cable_m)
    cfg = loop or LoopConfig()
    speed = 1.0 + drifts * 1e-6
    # --- configuration (SOEM ecx_configdc): latch at true time 0, master time 0
    lt = line_timing(0.0, escs, cables, ns_per_m)
    local0 = rng.uniform(0.0, 2.0**40, n_slaves)  # arbitrary power-up local times
    t_diff = round(escs[0].t_diff_ns) if master_t_diff_ns is None else master_t_diff_ns
    delays = _measured_delays(lt, local0, speed, t_diff)
    true_delays = lt.epu_ns - lt.epu_ns[0]
    # --- cycles
    n_cycles = max(1, round(seconds * 1e9 / cycle_ns))
    t0 = float(cycle_ns)  # first cyclic frame one cycle after configuration
    times: FloatArray = t0 + np.arange(n_cycles, dtype=np.float64) * float(cycle_ns)
    s0_cycle = int(sync0_cycle_ns or cycle_ns)
    sync0_start = sync0_start_time(0, s0_cycle, sync0_shift_ns)
    noise = rng.uniform(-jitter_ns, jitter_ns, (n_cycles, n_slaves)) if jitter_ns > 0 else None
    sync0 = (sync0_start, s0_cycle)
    spread, edges = _cycles(times, lt.epu_ns, delays, speed, cfg, noise, compensation, sync0)
    times_ms: FloatArray = ((times - t0) / 1e6).astype(np.float64)
    conv = converged_after(spread, times_ms, threshold_ns)
    return DcSimResult(
        n_slaves=n_slaves,
        seconds=float(seconds),
        cycle_ns=int(cycle_ns),
        compensation=compensation,
        threshold_ns=float(threshold_ns),
        drifts_ppm=drifts,
        delays_ns=delays,
        true_delays_ns=true_delays,
        times_ms=times_ms,
        spread_ns=spread,
        sync0_edges_ns=edges,
        sync0_spread_ns=np.where(np.isnan(edges[:, 0]), np.nan, np.ptp(np.nan_to_num(edges), axis=1)),
        sync0_start_ns=int(sync0_start),
        final_spread_ns=float(spread[-1]),
        converged_after_ms=conv,
        max_spread_after_convergence_ns=None if conv is None else float(spread[times_ms >= conv].max()),
    )


def _cycles(
    times: FloatArray,
    epu_ns: FloatArray,
    delays: npt.NDArray[np.int64],
    speed: FloatArray,
    cfg: LoopConfig,
    noise: FloatArray | None,
    compensation: bool,
    sync0: tuple[float, int],
) -> tuple[FloatArray, FloatArray]:
    """The cyclic frames at true ``times`` (ns): per cycle the spread of the slaves' system times just
    before the frame and each slave's SYNC0 edge (NaN before SYNC0 starts; ``sync0``: its start in
    system time and cycle, ns); with ``compensation`` each follower's time-control loop steps on the
    frame's FRMW (``epu_ns``: the frame's arrival at each slave's EPU after it is sent, ns)."""
    n_cycles, n_slaves = len(times), len(epu_ns)
    sync0_start, s0_cycle = sync0
    # offset = master time (0) - local EPU time => system time is 0 when the frame passed
    anchor_t = epu_ns.copy()  # true time of each slave's anchor
    anchor_s = np.zeros(n_slaves)  # system time at the anchor
    state = LoopState.reset(n_slaves)
    rate = speed.copy()
    followers = np.arange(n_slaves) > 0
    spread = np.empty(n_cycles)
    edges = np.full((n_cycles, n_slaves), np.nan)
    for n in range(n_cycles):
        t = times[n]
        sys_now = anchor_s + (t - anchor_t) * rate
        spread[n] = sys_now.max() - sys_now.min()
        if sys_now[0] >= sync0_start - s0_cycle:  # SYNC0 has started on the reference
            edges[n] = _sync0_edges(t, sys_now, rate, sync0_start, s0_cycle)
        if not compensation:
            continue
        arr = t + epu_ns  # a frame sent at t reaches slave i's EPU at t + epu_ns[i]
        sys_arr = anchor_s + (arr - anchor_t) * rate
        received = sys_arr[0]
        delta = sys_arr - delays - received
        if noise is not None:
            delta = delta + noise[n]
        interval = (arr - anchor_t) * rate
        state = loop_step(state, delta, interval, cfg, mask=followers)
        anchor_s = np.where(followers, sys_arr, anchor_s)
        anchor_t = np.where(followers, arr, anchor_t)
        rate = speed * (1.0 + state.correction_frac)
    return spread, edges


def _drifts(n_slaves: int, drift_ppm: float, drifts_ppm: Sequence[float] | None, seed: int) -> FloatArray:
    """Each slave's clock drift, ppm: ``drifts_ppm``, else spread evenly over ±``drift_ppm``."""
    if drifts_ppm is None:
        return spread_drifts(n_slaves, drift_ppm, seed)
    drifts = np.asarray(drifts_ppm, dtype=np.float64)
    if drifts.shape != (n_slaves,):
        raise ValueError(f"drifts_ppm needs {n_slaves} values")
    return drifts


def _measured_delays(lt: Any, local0: FloatArray, speed: FloatArray, t_diff: int) -> npt.NDArray[np.int64]:
    """The propagation delays the master computes from the latched receive times (ports 0 and 1, 32-bit
    local times at the true times ``lt`` gives) as SOEM does, with its t_Diff correction ``t_diff``, ns."""

    def latched(t: FloatArray) -> list[int]:
        return [int(v) & 0xFFFF_FFFF for v in np.floor(local0 + t * speed)]

    p0 = latched(lt.port0_ns)
    p1_all = latched(np.nan_to_num(lt.port1_ns))
    p1: list[int | None] = [None if math.isnan(lt.port1_ns[i]) else p1_all[i] for i in range(len(p0))]
    return np.array(line_propagation_delays(p0, p1, t_diff), dtype=np.int64)


def _sync0_edges(
    t: float, sys_now: FloatArray, rate: FloatArray, sync0_start: float, s0_cycle: int
) -> FloatArray:
    """True time of each slave's next SYNC0 pulse at or after the reference's system time (at true time
    ``t``), relative to the reference's pulse, ns."""
    k = max(0, math.ceil((sys_now[0] - sync0_start) / s0_cycle))
    target = sync0_start + k * s0_cycle
    true_edges = t + (target - sys_now) / rate
    out: FloatArray = true_edges - true_edges[0]
    return out
