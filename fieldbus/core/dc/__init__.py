"""Distributed-clock model of an EtherCAT segment (pure, sans-IO; time is a parameter).

* ``model``: register map, timing assumptions, the ESC time-control loop;
* ``master``: frame timing on a line, propagation delays and offsets as SOEM
  computes them, SYNC0 start time, the host-side PI (``ec_sync``);
* ``sim``: ``simulate`` - a whole segment, vectorised over slaves.

The slave side (an ESC behind its 0x0900-0x09AF registers) is emulator code:
:mod:`sim_slaves.ethercat.dc_clock`. Units: ns and ppm. Assumptions and sources: docs/dc.md.
"""

from fieldbus.core.dc.master import (
    HostSync,
    HostSyncConfig,
    LineTiming,
    line_propagation_delays,
    line_timing,
    simulate_host_sync,
    soem_offsets,
    sync0_start_time,
    sync1_period_ns,
)
from fieldbus.core.dc.model import (
    CABLE_NS_PER_M,
    DcRegister,
    EscTiming,
    LoopConfig,
    LoopState,
    SyncActivation,
    cable_delay_ns,
    loop_step,
)
from fieldbus.core.dc.sim import DcSimResult, simulate, spread_drifts

__all__ = [
    "CABLE_NS_PER_M",
    "DcRegister",
    "DcSimResult",
    "EscTiming",
    "HostSync",
    "HostSyncConfig",
    "LineTiming",
    "LoopConfig",
    "LoopState",
    "SyncActivation",
    "cable_delay_ns",
    "line_propagation_delays",
    "line_timing",
    "loop_step",
    "simulate",
    "simulate_host_sync",
    "soem_offsets",
    "spread_drifts",
    "sync0_start_time",
    "sync1_period_ns",
]
