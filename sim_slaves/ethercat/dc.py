"""Distributed-clock unit of one emulated ESC: registers 0x0900-0x09AF backed by the DC model.

:class:`EscDc` wraps a :class:`sim_slaves.ethercat.dc_clock.DcSlaveClock` (local
clock with drift, time-control loop, SYNC unit) and knows where its ESC sits
on the line: ``port0_ns``/``port1_ns`` are the true times, after the master
sent a frame, at which the frame reaches this ESC's port 0 (and processing
unit) and comes back at its port 1 (None: port 1 closed, the last slave).
:class:`~sim_slaves.ethercat.chain.EscChain` places its slaves with
:func:`fieldbus.core.dc.master.line_timing`.

Time: every ``now_ns`` taken here is the chain's "the master sent this frame"
time (the emulator's monotonic clock); the unit adds its port offset before
asking the clock. :attr:`EscDc.clock` takes true time as it is.

Registers with behaviour (ESC datasheet Section II; ETG.1000.4):

* write to 0x0900: latch the receive times of port 0 and the processing unit
  (0x0900, 0x0918) when the frame passes port 0, and of port 1 (0x0904) when
  it comes back; ports 2/3 (0x0908/0x090C) stay 0;
* 0x0910 read: the local copy of the system time when the frame passes;
  write (FPWR/BWR/ARMW/FRMW): the time-control loop compares it (lower 32 bits)
  with its own system time minus 0x0928 and adjusts the clock speed;
* 0x0920 offset, 0x0928 delay, 0x0930 speed counter start (a write resets the
  loop), 0x0934/0x0935 filter depths, 0x0980 cyclic unit control, 0x0981
  activation, 0x0990 start time, 0x09A0/0x09A4 SYNC0/SYNC1 cycle times.

:class:`DcLine` is the chain's line of units: it places them
(:func:`fieldbus.core.dc.master.line_timing`) and carries the system-time
distribution of the cycle frame's ARMW/FRMW (at most one sample per
:data:`DC_MIN_SAMPLE_INTERVAL_NS` goes to the loops, see :class:`DcLine`).
A distribution only queues the sample (one tuple, with its time); the queue
is worked off by :meth:`DcLine.flush` when the I/O layer has nothing else to
do, at the latest before any other access to a unit of the line. So every
read sees every earlier write, in order, and the result does not depend on
when the work is done.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from fieldbus.core.dc.master import line_timing
from fieldbus.core.dc.model import FILTER_REF_INTERVAL_NS, DcRegister, EscTiming
from sim_slaves.ethercat.dc_clock import DC_END, DC_FIRST, ClockArrays, DcSlaveClock, LineClock

__all__ = ["DC_END", "DC_FIRST", "DC_MIN_SAMPLE_INTERVAL_NS", "DcLine", "EscDc"]

#: default :attr:`DcLine.min_sample_interval_ns`
DC_MIN_SAMPLE_INTERVAL_NS = 500_000
_SYSTEM_TIME = int(DcRegister.SYSTEM_TIME)
_RECEIVE_TIME_PORT0 = int(DcRegister.RECEIVE_TIME_PORT0)


class EscDc:
    """The DC registers of one ESC: a :class:`DcSlaveClock` plus the ESC's place on the line.

    ``drift_ppm``: crystal drift (positive = fast). ``initial_local_ns``: local
    time at true time 0. ``timing``: the ESC's processing/forwarding delays.
    A power-on reset (:meth:`power_on`) clears the registers and the loop and
    puts the local clock back on its uncorrected course from ``initial_local_ns``
    (a real ESC restarts from 0; either way an arbitrary value the master has
    to measure again).
    """

    def __init__(
        self, *, drift_ppm: float = 0.0, initial_local_ns: int = 0, timing: EscTiming | None = None
    ) -> None:
        self.timing = timing or EscTiming()
        self.port0_ns = 0
        self.port1_ns: int | None = None
        self.initial_local_ns = int(initial_local_ns)
        self.line: DcLine | None = None  # set by DcLine: its queued samples are applied before any access
        self._clock = DcSlaveClock(drift_ppm=drift_ppm, initial_local_ns=initial_local_ns, timing=self.timing)

    def place(self, port0_ns: int, port1_ns: int | None) -> None:
        """A frame sent at t reaches port 0 at t + ``port0_ns``, comes back at port 1 at t + ``port1_ns``."""
        self.port0_ns = int(port0_ns)
        self.port1_ns = None if port1_ns is None else int(port1_ns)

    def power_on(self) -> None:
        """Power-on reset: registers and loop cleared, drift and timing kept."""
        _ = self.clock  # queued samples of the line first (they belong to the time before)
        self._clock = DcSlaveClock(
            drift_ppm=self._clock.drift_ppm, initial_local_ns=self.initial_local_ns, timing=self.timing
        )
        if self.line is not None:
            self.line.adopt(self)

    @property
    def clock(self) -> DcSlaveClock:
        """The model clock, up to date (queued time-control samples applied). It takes true time."""
        line = self.line
        if line is not None and line.pending:
            line.flush()
        return self._clock

    @property
    def drift_ppm(self) -> float:
        """The crystal's drift (ppm, positive = fast)."""
        return self._clock.drift_ppm

    def set_drift(self, drift_ppm: float, now_ns: int) -> None:
        """The crystal runs ``drift_ppm`` off from true time ``now_ns`` on."""
        self.clock.set_drift(drift_ppm, now_ns)

    # -- wire access (now_ns = when the master sent the frame) --

    def read(self, addr: int, n: int, now_ns: int) -> bytes:
        """``n`` bytes of registers from ``addr`` (within 0x0900-0x09AF) as the frame passes."""
        return self.clock.read_register(addr, n, now_ns + self.port0_ns)

    def write(self, addr: int, data: bytes | memoryview, now_ns: int) -> None:
        """A master write of ``data`` at ``addr`` (within 0x0900-0x09AF) as the frame passes."""
        clock = self.clock
        data = bytes(data)
        t = now_ns + self.port0_ns
        end = addr + len(data)
        if addr < _SYSTEM_TIME < end:
            # a write across 0x0910 that starts below it: the part from 0x0910 on is the time-control input
            cut = _SYSTEM_TIME - addr
            clock.write_register(addr, data[:cut], t)
            clock.write_register(_SYSTEM_TIME, data[cut:], t)
        else:  # (one starting inside 0x0911-0x0917 compares nothing: the model stores it and moves on)
            clock.write_register(addr, data, t)
        if addr <= _RECEIVE_TIME_PORT0 < end and self.port1_ns is not None:
            clock.latch_port(1, now_ns + self.port1_ns)

    def system_time(self, now_ns: int) -> int:
        """System time (0x0910) when a frame sent at ``now_ns`` reaches the processing unit."""
        return self.clock.system_time(now_ns + self.port0_ns)


class DcLine:
    """The DC units of a chain in wire order (unit 0 next to the master), and the FRMW queue.

    ``min_sample_interval_ns``: a distribution that comes less than this
    after the last one the loops took is answered (the reference's time goes
    into the datagram) but not given to the loops. A real ESC takes every
    one; the model's loop weighs each sample by the time since the previous
    one (docs/dc.md), so for a master cycling faster than this the result is
    the same to within a few ns while the emulator saves the loop work of a
    sample (3-4 us for the line with ``sim_slaves._dcloop``, about 1.5 us per
    slave without). At the default (0.5 ms) masters with cycles of 0.5 ms and
    longer feed every sample; 0 feeds every sample at any rate.
    """

    #: queue length at which :meth:`distribute` works the queue off itself
    MAX_PENDING = 64

    def __init__(
        self, units: Sequence[EscDc], *, min_sample_interval_ns: int = DC_MIN_SAMPLE_INTERVAL_NS
    ) -> None:
        self.units = list(units)
        self.min_sample_interval_ns = int(min_sample_interval_ns)
        #: queued distributions: (reference index, what the master sent, reference time, frame time)
        self.pending: list[tuple[int, int, int, int]] = []
        self.samples = 0  # distributions given to the loops
        self.skipped = 0  # distributions answered but not given to the loops (min_sample_interval_ns)
        self._last_sample_ns: int | None = None
        self._only_ref = -1  # the reference of every queued distribution (-1: they differ)
        n = len(self.units)
        self.clocks = ClockArrays(n)  # the units' loop state, stepped together by flush()
        self._port0 = np.zeros(n, dtype=np.int64)
        for u in self.units:
            u.line = self
            self.adopt(u)

    def adopt(self, unit: EscDc) -> None:
        """Move ``unit``'s clock state into :attr:`clocks` (at the unit's place on the line)."""
        i = self.units.index(unit)
        unit._clock = LineClock(self.clocks, i, unit._clock)
        self._port0[i] = unit.port0_ns

    def place(self, timing: EscTiming, cable_m: float) -> None:
        """Every ESC with delays ``timing``, ``cable_m`` metres of cable per hop (master -> 0 included)."""
        self.flush()
        n = len(self.units)
        if n == 0:
            return
        lt = line_timing(0.0, [timing] * n, [cable_m] * n)
        for i, u in enumerate(self.units):
            p1 = float(lt.port1_ns[i])
            u.timing = timing
            u.place(round(float(lt.port0_ns[i])), None if math.isnan(p1) else round(p1))
            self._port0[i] = u.port0_ns

    def reference_time(self, reference: int, now_ns: int) -> int:
        """System time of unit ``reference`` as a frame sent at ``now_ns`` passes it.

        Queued distributions with this same reference never feed its own loop,
        so they stay queued.
        """
        if self.pending and self._only_ref != reference:
            self.flush()
        u = self.units[reference]
        return u._clock.system_time(now_ns + u.port0_ns)

    def distribute(self, reference: int, sent: int, ref_time: int, now_ns: int) -> None:
        """An ARMW/FRMW on 0x0910 of unit ``reference`` sent at ``now_ns``: queue the loop samples.

        Units before the reference compare ``sent`` (the datagram as the master
        sent it), units after it ``ref_time`` (what the reference put in).
        """
        last = self._last_sample_ns
        if last is not None and 0 <= now_ns - last < self.min_sample_interval_ns:
            self.skipped += 1
            return
        self._last_sample_ns = now_ns
        self.samples += 1
        if len(self.pending) >= self.MAX_PENDING:
            self.flush()
        if not self.pending:
            self._only_ref = reference
        elif reference != self._only_ref:
            self._only_ref = -1
        self.pending.append((reference, sent, ref_time, now_ns))

    def flush(self) -> None:
        """Give the queued system times to the units' time-control loops, in order."""
        if not self.pending:
            return
        pending, self.pending = self.pending, []
        clocks, units, n = self.clocks, self.units, len(self.units)
        loop = clocks.loop
        for ref, sent, ref_time, now in pending:
            # units before the reference compare what the master sent, units after it the reference's time
            if loop is not None:
                times = self._port0 + now
                loop(clocks.rec, sent, times, 0, ref, FILTER_REF_INTERVAL_NS)
                loop(clocks.rec, ref_time, times, ref + 1, n, FILTER_REF_INTERVAL_NS)
                continue
            for u in units[:ref]:
                u._clock.time_control_input(sent, now + u.port0_ns)
            for u in units[ref + 1 :]:
                u._clock.time_control_input(ref_time, now + u.port0_ns)
