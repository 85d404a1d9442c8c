"""Soak harness: run the cycle against an emulator with scheduled and random faults, account for each.

A fault spec is ``kind=value`` pairs separated by commas, for example
``loss=0.01,power_cycles=3,bursts=1,sdo_aborts=1``:

- ``loss`` (probability per cycle): the cycle's process-data frame is lost;
- ``delay`` (probability): the reply comes back later than the receive timeout;
- ``wkc`` (probability): one slave's working-counter share goes missing;
- ``power_cycles`` (count, spread evenly): a slave (chosen at random) loses power;
- ``bursts`` (count, spread evenly): ``safe_stop_after`` frames lost in a row;
- ``sdo_aborts`` (count): bring-up attempts where one drive refuses a start-up SDO;
- ``emcys`` (count, CANopen): a node sends an EMCY; it must be reported with its name;
- ``heartbeats`` (count, CANopen): a node's heartbeat goes silent until the loss is reported;
- ``bus_offs`` (count, CANopen): a node goes bus-off for 20 cycles, then recovers and boots.

On CANopen ``loss`` drops one TPDO of one node (that node is stale, the others
fresh, the cycle not fresh); ``delay`` and ``wkc`` are EtherCAT faults.

Invariants checked every cycle (a broken one is a *violation*, never an
exception): an injected loss is reported as a miss in the same cycle and its
inputs are not called fresh; the safe stop fires exactly when the
consecutive-miss count reaches the threshold; no cycle's ``exchange()`` takes
longer than the receive timeout plus ``margin_us`` (lost frames, recovery steps
and acyclic SDOs included); after a safe stop, the first
delivered cycle leaves no emulated drive in OPERATION ENABLED; a power-cycled
slave is back in OP within ``recovery_cycles`` without user action; no
exception escapes the loop; ``close()`` leaves every drive below OPERATION
ENABLED and every slave in INIT.

The emulator is driven through one callable, ``control(**msg)``, taking the
commands of ``sim_slaves.ethercat.runner.handle_control`` (drop, delay,
corrupt_wkc, power_cycle, abort_sdo, clear, status).
"""

from __future__ import annotations

import random
import time
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, TextIO

import numpy as np

from fieldbus.core.al import AL_INIT, AL_OP
from fieldbus.core.cia402 import Cia402Controller, Goal, State402
from fieldbus.core.emcy import Emergency
from fieldbus.cycle.status import CycleResult
from fieldbus.errors import FieldbusError, SdoAbortError
from fieldbus.network import Network, Operational
from fieldbus.operations.monitor import monitor_context
from fieldbus.platform.loop import gc_held, progress
from fieldbus.platform.phases import PHASES, PhaseTimer
from fieldbus.platform.timing import CycleTimer

Control = Callable[..., dict[str, Any]]
Opener = Callable[[], tuple[Network, Control]]  # a fresh Network and the control of its emulator
RATES = ("loss", "delay", "wkc")
COUNTS = ("power_cycles", "bursts", "sdo_aborts", "emcys", "heartbeats", "bus_offs")
CAN_ONLY = ("emcys", "heartbeats", "bus_offs")
BUS_OFF_CYCLES = 20  # a node stays off the bus this long, then recovers and boots  # EMCY frames and heartbeat silence: CANopen faults
ETHERCAT_ONLY = ("delay", "wkc")  # a late reply / a short working counter: EtherCAT faults
EMCY_CODE = 0x2310  # continuous over-current
IN_FLIGHT = ("loss", "burst", "delay", "wkc")  # faults aimed at "the next frame" the emulator gets
NOTICED = ("emcy", "heartbeat")  # faults that are reported, not seen as a lost cycle
NOTICE_CYCLES = 200  # an EMCY or a heartbeat loss must be noticed within this many cycles
# exchange() may take the receive timeout plus this (recovery steps, the emulated drives, and the
# scheduling of a shared, non-real-time machine); tighten it with --margin-us on a real-time one
DEFAULT_MARGIN_US = 5000.0
OE = int(State402.OPERATION_ENABLED)


class FaultSpecError(FieldbusError, ValueError):
    """A ``--faults`` string that does not parse."""


@dataclass(frozen=True)
class FaultSpec:
    loss: float = 0.0
    delay: float = 0.0
    wkc: float = 0.0
    power_cycles: int = 0
    bursts: int = 0
    sdo_aborts: int = 0
    emcys: int = 0
    heartbeats: int = 0
    bus_offs: int = 0

    @classmethod
    def parse(cls, text: str) -> FaultSpec:
        """``loss=0.01,power_cycles=3`` -> FaultSpec; raises :class:`FaultSpecError` naming the bad part."""
        values: dict[str, Any] = {}
        for part in filter(None, (p.strip() for p in text.split(","))):
            key, sep, raw = part.partition("=")
            key = key.strip()
            if not sep or key not in RATES + COUNTS:
                raise FaultSpecError(
                    f"fault '{part}': expected one of {', '.join(RATES + COUNTS)} as kind=value"
                )
            try:
                value: float | int = float(raw) if key in RATES else int(raw)
            except ValueError:
                raise FaultSpecError(f"fault '{part}': '{raw}' is not a number") from None
            if value < 0 or (key in RATES and value > 0.5):
                raise FaultSpecError(f"fault '{part}': out of range ({'0..0.5' if key in RATES else '>= 0'})")
            values[key] = value
        return cls(**values)


@dataclass
class SoakReport:
    cycles: int = 0
    injected: Counter[str] = field(default_factory=Counter)
    detected: Counter[str] = field(default_factory=Counter)
    violations: list[str] = field(default_factory=list)
    violation_count: int = 0
    safe_stops: int = 0
    missed: int = 0
    recovered: int = 0
    reenabled: int = 0
    seconds: float = 0.0
    # time spent in exchange(), ns, per kind of cycle: fresh, missed, and with recovery under way
    exchange_ns: dict[str, list[int]] = field(
        default_factory=lambda: {"good": [], "miss": [], "recovery": []}
    )
    # with phases on: per kind of cycle (as above, and "after_miss": the first fresh one after a miss),
    # per phase of exchange() (fieldbus.platform.phases.PHASES), ns
    phase_ns: dict[str, list[list[int]]] = field(default_factory=dict)

    def violate(self, cycle: int, what: str) -> None:
        self.violation_count += 1
        if len(self.violations) < 20:
            self.violations.append(f"cycle {cycle}: {what}")

    def to_json(self) -> dict[str, Any]:
        return {
            "cycles": self.cycles,
            "missed": self.missed,
            "safe_stops": self.safe_stops,
            "injected": dict(self.injected),
            "detected": dict(self.detected),
            "violation_count": self.violation_count,
            "violations": self.violations,
            "recovered_power_cycles": self.recovered,
            "reenabled_after_safe_stop": self.reenabled,
            "seconds": round(self.seconds, 3),
            "exchange_us": {kind: _percentiles(ns) for kind, ns in self.exchange_ns.items()},
            **({"phases_us": _phase_medians(self.phase_ns)} if self.phase_ns else {}),
        }

    def note_phases(self, kind: str, last_ns: list[int]) -> None:
        """One cycle's phases (:attr:`PhaseTimer.last_ns`) under ``kind``."""
        rows = self.phase_ns.setdefault(kind, [[] for _ in PHASES])
        for row, ns in zip(rows, last_ns, strict=True):
            row.append(ns)


def _phase_medians(phase_ns: dict[str, list[list[int]]]) -> dict[str, dict[str, float | int]]:
    """Per kind of cycle: how many, and the median µs of each phase."""
    return {
        kind: {
            "cycles": len(rows[0]),
            **{name: round(float(np.median(row)) / 1000, 1) for name, row in zip(PHASES, rows, strict=True)},
        }
        for kind, rows in phase_ns.items()
    }


def _percentiles(ns: list[int]) -> dict[str, float | int]:
    """Cycles, p50, p99 and max of durations in ns, as µs."""
    if not ns:
        return {"cycles": 0}
    a = np.asarray(ns, dtype=np.float64) / 1000.0
    return {
        "cycles": len(ns),
        "p50": round(float(np.percentile(a, 50)), 1),
        "p99": round(float(np.percentile(a, 99)), 1),
        "max": round(float(a.max()), 1),
    }


def schedule(
    spec: FaultSpec, cycles: int, n_slaves: int, rng: random.Random, warmup: int
) -> dict[int, tuple[str, int]]:
    """Cycle -> (fault kind, slave) for the run; counted faults spread evenly, rates drawn per cycle."""
    plan: dict[int, tuple[str, int]] = {}
    span = cycles - warmup
    counted = (
        ("power_cycle", spec.power_cycles),
        ("burst", spec.bursts),
        ("emcy", spec.emcys),
        ("heartbeat", spec.heartbeats),
        ("bus_off", spec.bus_offs),
    )
    for kind, count in counted:
        for i in range(count):
            k = (
                warmup
                + (i + 1) * span // (count + 1)
                + {"burst": 7, "emcy": 13, "heartbeat": 29, "bus_off": 41}.get(kind, 0)
            )
            plan[k] = (kind, rng.randrange(n_slaves))
    for k in range(warmup, cycles):
        if k in plan:
            continue
        r = rng.random()
        for kind in RATES:
            p = getattr(spec, kind)
            if r < p:
                plan[k] = (kind, rng.randrange(n_slaves))
                break
            r -= p
    return plan


class Soak:
    """One soak run on a network whose single bus is emulated; ``opener`` opens it (again after an abort)."""

    def __init__(
        self,
        opener: Opener,
        spec: FaultSpec,
        *,
        seed: int = 0,
        warmup: int = 200,
        recovery_cycles: int = 5000,
        cycle_time_us: float | None = None,
        margin_us: float = DEFAULT_MARGIN_US,
    ) -> None:
        self.opener = opener
        self.net, self.control = opener()
        if len(self.net.backends) != 1:
            raise FieldbusError("soak runs one bus at a time")
        self.spec = spec
        self.rng = random.Random(seed)
        self.warmup = warmup
        self.recovery_cycles = recovery_cycles
        self.cycle_time_us = cycle_time_us
        self.margin_us = margin_us  # a cycle's exchange() may take the receive timeout plus this
        self.report = SoakReport()
        self.timer = CycleTimer()
        self.monitor = False  # the live view (--monitor) while the soak runs
        self.phases = False  # time exchange() phase by phase (SoakReport.phase_ns, "phases_us" in the JSON)

    # -- bring-up with SDO aborts --------------------------------------------------------
    def bring_up(self) -> Operational:
        """Bring-up attempts with an injected SDO abort (each must fail, naming drive and object), then OP."""
        for _ in range(self.spec.sdo_aborts):
            backend = self.net.backends[0]
            slave = self.rng.randrange(backend.n_slaves)
            startup = backend.areas[slave].slave.map.sdo
            index, sub = (startup[0].index, startup[0].sub_index) if startup else (0x1C12, 0)
            self.control(cmd="abort_sdo", slave=slave, index=index, sub=sub, code=0x06090030)
            self.report.injected["sdo_abort"] += 1
            try:
                self.net.pre_op()
            except SdoAbortError as exc:
                if exc.slave == backend.areas[slave].slave.name and exc.index == index:
                    self.report.detected["sdo_abort"] += 1
                else:
                    self.report.violate(0, f"SDO abort on slave {slave} reported as {exc}")
            else:
                self.report.violate(0, f"SDO abort on slave {slave} 0x{index:04X} not reported")
            states = self.control(cmd="status")["drive_states"]
            if OE in states:
                self.report.violate(0, f"a drive is enabled after a failed bring-up: {states}")
            self.control(cmd="clear")
            self.net.close()
            self.net, self.control = self.opener()
        return self.net.bring_up()

    # -- the run ----------------------------------------------------------------------
    def run(self, cycles: int, *, status: TextIO | None = None) -> SoakReport:
        """Bring up, then ``cycles`` cycles under the fault plan; ``status``: a progress line each second."""
        rep = self.report
        t_start = time.perf_counter()
        next_status = 0
        op = self.bring_up()
        run = _SoakRun(self, op, cycles)
        # gc held as run_cycles holds it (fieldbus run): a full collection of a large heap is a pause of
        # many ms in whichever cycle it lands, the harness's doing, not the bus's
        with monitor_context(op, None, self.monitor), gc_held():
            for k in range(cycles):
                event = run.defer_in_flight(k, run.plan.get(k))
                lost_now = run.inject(k, event)
                t0 = time.perf_counter_ns()
                try:
                    res = op.exchange()
                except Exception as exc:  # the invariant is that this never happens
                    rep.violate(k, f"exception escaped exchange(): {type(exc).__name__}: {exc}")
                    break
                run.time_exchange(k, res)
                if res.fresh and not run.stop_latched:
                    run.ctrl.step(run.sw, run.cw)
                self.timer.add(time.perf_counter_ns() - t0)
                rep.cycles += 1
                if status is not None and t0 >= next_status:
                    next_status = t0 + 1_000_000_000
                    elapsed = t0 - int(t_start * 1e9)
                    status.write(f"\r{progress(k + 1, cycles, elapsed)} violations {len(rep.violations)}   ")
                    status.flush()
                run.judge(k, event, lost_now, res)
                run.pace()
        if status is not None:
            status.write("\n")
        rep.seconds = time.perf_counter() - t_start
        if run.recovering:
            rep.violate(rep.cycles, "run ended while a power-cycled slave was still recovering")
        return rep

    def close(self) -> None:
        """Close the network and check that every drive is down and every slave in INIT."""
        try:
            self.net.close()
        except Exception as exc:
            self.report.violate(self.report.cycles, f"close() raised {type(exc).__name__}: {exc}")
        can = self.net.backends[0].kind == "canopen"
        deadline = time.monotonic() + 0.5  # CAN emulators run in a thread: let them take the NMT command
        while True:
            status = self.control(cmd="status")
            down = (
                all(s != AL_OP for s in status["states"])
                if can
                else all(s == AL_INIT for s in status["states"])
            )
            if (down and OE not in status["drive_states"]) or time.monotonic() > deadline:
                break
            time.sleep(0.01)
        if OE in status["drive_states"]:
            self.report.violate(self.report.cycles, f"drive enabled after close(): {status['drive_states']}")
        if not down:
            want = "below OPERATIONAL" if can else "in INIT"
            self.report.violate(self.report.cycles, f"slaves not {want} after close(): {status['states']}")


class _SoakRun:
    """The state of one soak run between cycles: the fault plan, what is still to be noticed, the latch."""

    def __init__(self, soak: Soak, op: Operational, cycles: int) -> None:
        self.soak, self.op, self.rep, self.control = soak, op, soak.report, soak.control
        backend, policy = soak.net.backends[0], soak.net.policies[0]
        self.backend = backend
        self.threshold = policy.config.safe_stop_after
        n = backend.n_slaves
        img = next(iter(soak.net.groups.values())).image
        self.sw, self.cw = img.inputs["statusword"], img.outputs["controlword"]
        self.ctrl = Cia402Controller(n, timeout_cycles=100_000)
        self.ctrl.set_goal(Goal.ENABLE)
        self.can = backend.kind == "canopen"
        for kind in CAN_ONLY if not self.can else ETHERCAT_ONLY:
            if getattr(soak.spec, kind):
                raise FaultSpecError(f"fault '{kind}' has no meaning on a {backend.kind} bus")
        self.plan = schedule(soak.spec, cycles, n, soak.rng, soak.warmup)
        self.notices: list[
            tuple[str, int, int, int]
        ] = []  # (kind, slave, injected at cycle, emcy count before)
        self.bus_off_until: list[tuple[int, int]] = []  # (cycle, slave): back on the bus then
        self.burst_left = 0
        self.consecutive = 0
        self.stop_latched = False
        self.check_quick_stop = False
        self.recovering: list[int] = []  # cycles at which a power cycle is still being recovered
        self.fresh_streak = 0
        # paced at the network's cycle time unless told otherwise (0: as fast as it goes)
        period_us = soak.cycle_time_us if soak.cycle_time_us is not None else backend.bus.cycle_time_us
        self.period_ns = int(period_us * 1000)
        self.limit_ns = int((backend.bus.receive_timeout_us + soak.margin_us) * 1000)
        self.deadline = time.perf_counter_ns()
        self.prev_fresh = True
        self.phase_timer = op.phases = PhaseTimer() if soak.phases else None

    # -- before the exchange: the fault injection step ----------------------------------
    def defer_in_flight(self, k: int, event: tuple[str, int] | None) -> tuple[str, int] | None:
        """The fault to inject at cycle ``k``: one aimed at the next frame waits for a fresh cycle.

        The last cycle's frame may still be on its way to the emulator (its reply was late): "drop the
        next frame" could hit that one. Inject once a cycle came back fresh.
        """
        if event is not None and event[0] in IN_FLIGHT and not self.prev_fresh:
            later = k + 1
            while later in self.plan:
                later += 1
            self.plan[later] = event
            return None
        return event

    def inject(self, k: int, event: tuple[str, int] | None) -> bool:
        """Tell the emulator to commit ``event`` (and end bus-offs due); True: this cycle must be a miss."""
        lost_now = False
        if event is not None:
            kind, slave = event
            lost_now = kind not in NOTICED
            self._commit(k, kind, slave)
            self.rep.injected[kind] += 1
        if self.burst_left:
            lost_now = True
            self.burst_left -= 1
        for until, slave_off in list(self.bus_off_until):
            if k >= until:
                self.control(cmd="bus_off", slave=slave_off, off=False)
                self.bus_off_until.remove((until, slave_off))
                self.recovering.append(k)
        return lost_now

    def _commit(self, k: int, kind: str, slave: int) -> None:
        """One fault of ``kind`` on ``slave`` at cycle ``k``, through the emulator's control."""
        control, backend = self.control, self.backend
        if kind == "loss":
            if self.can:
                control(cmd="drop_frame", slave=slave)
            else:
                control(cmd="drop", count=1, pd=True)
        elif kind == "emcy":
            before = len(backend.emergencies)
            control(cmd="emergency", slave=slave, code=EMCY_CODE)
            self.notices.append((kind, slave, k, before))
        elif kind == "heartbeat":
            control(cmd="heartbeat", slave=slave, silent=True)
            self.notices.append((kind, slave, k, 0))
        elif kind == "bus_off":
            control(cmd="bus_off", slave=slave, off=True)
            self.bus_off_until.append((k + BUS_OFF_CYCLES, slave))
        elif kind == "delay":
            timeout_s = backend.bus.receive_timeout_us / 1e6
            control(cmd="delay", seconds=timeout_s * 2 + 0.001, count=1)
        elif kind == "wkc":
            control(cmd="corrupt_wkc", delta=-1, count=1)
        elif kind == "power_cycle":
            control(cmd="power_cycle", slave=slave)
            self.recovering.append(k)
        elif kind == "burst":
            control(cmd="drop", count=self.threshold, pd=True)
            self.burst_left = self.threshold

    # -- after the exchange: the judge ---------------------------------------------------
    def time_exchange(self, k: int, res: CycleResult) -> None:
        """File the exchange's duration under its kind of cycle; over the limit is a violation."""
        rep, timer = self.rep, self.phase_timer
        # a miss is a miss even when a recovery step ran in it; "recovery": fresh, but still recovering
        kind_of_cycle = (
            "miss" if not res.fresh else "recovery" if any(st.recovering for st in res.buses) else "good"
        )
        rep.exchange_ns[kind_of_cycle].append(res.exchange_ns)
        if timer is not None:
            rep.note_phases(kind_of_cycle, timer.last_ns)
            if res.fresh and not self.prev_fresh:
                rep.note_phases("after_miss", timer.last_ns)
        if res.exchange_ns > self.limit_ns:
            rep.violate(
                k,
                f"exchange() took {res.exchange_ns / 1e3:.0f} us on a {kind_of_cycle} cycle, more than the "
                f"receive timeout plus {self.soak.margin_us:g} us",
            )

    def judge(self, k: int, event: tuple[str, int] | None, lost_now: bool, res: CycleResult) -> None:
        """The invariants of cycle ``k``: losses seen, faults noticed, the safe stop, recovery."""
        rep, fresh = self.rep, res.fresh
        if lost_now and fresh:
            rep.violate(k, f"injected {event[0] if event else 'burst'} but the cycle was reported fresh")
        if event is not None and not fresh and event[0] not in NOTICED:
            rep.detected[event[0]] += 1
        self._judge_notices(k)
        self._judge_safe_stop(k, res)
        self.fresh_streak = self.fresh_streak + 1 if fresh else 0
        self.prev_fresh = fresh
        self._judge_recovery(k)
        if self.stop_latched and self.fresh_streak >= 20 and not self.recovering and not self.burst_left:
            self.op.clear_safe_stop()  # what an operator or a supervisor would do: then re-enable
            self.stop_latched = False
            self.ctrl.set_goal(Goal.ENABLE)
            rep.reenabled += 1

    def _judge_notices(self, k: int) -> None:
        """An EMCY must be reported with its name, a heartbeat loss seen, within NOTICE_CYCLES."""
        for note in list(self.notices):
            kind, slave, at, before = note
            if kind == "emcy":
                seen = [
                    e
                    for e in self.backend.emergencies[before:]
                    if isinstance(e, Emergency) and e.code == EMCY_CODE
                ]
                done = bool(seen) and "over-current" in seen[0].name
            else:
                done = bool(self.backend.heartbeat_lost[slave])  # type: ignore[attr-defined]
                if done:
                    self.control(cmd="heartbeat", slave=slave, silent=False)
                    self.recovering.append(k)  # the node is configured again when it comes back
            if done:
                self.rep.detected[kind] += 1
                self.notices.remove(note)
            elif k - at > NOTICE_CYCLES:
                self.rep.violate(k, f"{kind} on slave {slave} not reported within {NOTICE_CYCLES} cycles")
                self.notices.remove(note)

    def _judge_safe_stop(self, k: int, res: CycleResult) -> None:
        """The safe stop fires exactly at the threshold; the first delivered cycle after it has no drive in OE."""
        rep, fresh, threshold = self.rep, res.fresh, self.threshold
        self.consecutive = 0 if fresh else self.consecutive + 1
        if not fresh:
            rep.missed += 1
        if res.safe_stop and not self.stop_latched:
            rep.safe_stops += 1
            self.stop_latched = True
            self.check_quick_stop = True
            if self.consecutive != threshold:
                rep.violate(
                    k, f"safe stop after {self.consecutive} consecutive misses, threshold {threshold}"
                )
        elif not self.stop_latched and self.consecutive >= threshold:
            rep.violate(k, f"{self.consecutive} consecutive misses and no safe stop (threshold {threshold})")
        if self.check_quick_stop and fresh:
            self.check_quick_stop = False
            states = self.control(cmd="status")["drive_states"]
            if OE in states:
                rep.violate(
                    k,
                    f"drives still OPERATION ENABLED one delivered cycle after the safe stop: {states}",
                )

    def _judge_recovery(self, k: int) -> None:
        """A power-cycled (or rebooted) slave is back in OP within the soak's ``recovery_cycles``."""
        if self.recovering and self.fresh_streak >= 20:
            emulated = self.control(cmd="status")
            if all(s == AL_OP for s in emulated["states"]):
                self.rep.recovered += len(self.recovering)
                self.recovering.clear()
        if self.recovering and k - self.recovering[0] > self.soak.recovery_cycles:
            self.rep.violate(k, f"power-cycled slave not back in OP after {self.soak.recovery_cycles} cycles")
            self.recovering.clear()

    def pace(self) -> None:
        """Busy-wait to the next cycle's deadline (no wait when the period is 0)."""
        if self.period_ns:
            self.deadline += self.period_ns
            while time.perf_counter_ns() < self.deadline:
                pass
