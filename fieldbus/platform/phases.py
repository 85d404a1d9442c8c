"""Where one ``exchange()`` spends its time: an optional per-phase timer (off: nothing is timed).

    timer = PhaseTimer()
    op.phases = timer           # from now on every exchange() marks its phases
    op.exchange()
    timer.last_us()             # {"encode": 3.1, "send": 12.4, "wait": 503.0, ...}, the last exchange

The network calls :meth:`PhaseTimer.mark` at the end of each phase only when
a timer is set (``Operational.phases``, default None: one attribute test per
phase, no clock read). The phases, summed over the buses that ran:

- ``encode``: the safe outputs (while latched) and outputs into wire bytes;
- ``send``: the backend's send (EtherCAT: IO map copy, stale frames dropped, the LRW sent;
  CANopen: RPDOs and SYNC written);
- ``wait``: the backend's receive (EtherCAT: the LRW's reply or the receive timeout, inputs
  out of SOEM's IO map; CANopen: the TPDOs or the deadline);
- ``judge``: the safety policy's verdict, the bus status and its events;
- ``accept``: fresh rows into the image, decoded to engineering units; drive-fault watch;
- ``contract``: the recovery step after a miss or while recovering (EtherCAT: at most one datagram);
- ``acyclic``: the SDO transfer step (at most one datagram) and the fault-code follow-ups;
- ``observers``: events and captures of recordings and probes, the safe outputs of a latch.

Times are ``time.perf_counter_ns`` differences, so the phases add up to the
whole ``exchange()``. Not for the cycle's own decisions: a benchmark's and
``fieldbus soak --phases``' view.
"""

from __future__ import annotations

import time

PHASES = ("encode", "send", "wait", "judge", "accept", "contract", "acyclic", "observers")
ENCODE, SEND, WAIT, JUDGE, ACCEPT, CONTRACT, ACYCLIC, OBSERVERS = range(len(PHASES))


class PhaseTimer:
    """Per-phase nanoseconds of the last ``exchange()`` (:attr:`last_ns`, indexed as :data:`PHASES`)."""

    __slots__ = ("_t", "last_ns")

    def __init__(self) -> None:
        self._t = 0
        self.last_ns = [0] * len(PHASES)

    def start(self, t0_ns: int) -> None:
        """A new exchange() began at ``t0_ns`` (perf_counter_ns): every phase back to 0."""
        self._t = t0_ns
        last = self.last_ns
        for i in range(len(last)):
            last[i] = 0

    def mark(self, phase: int) -> None:
        """The time since the previous mark (or the start) goes to ``phase``."""
        now = time.perf_counter_ns()
        self.last_ns[phase] += now - self._t
        self._t = now

    def last_us(self) -> dict[str, float]:
        """The last exchange's phases in µs, by name."""
        return {name: ns / 1e3 for name, ns in zip(PHASES, self.last_ns, strict=True)}
