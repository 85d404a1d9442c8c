"""The safe stop of a running network: the writers, the latch's effect on the outputs, its release, the wind-down.

While any bus's latch holds (S4), every axis group's safe outputs overwrite
what the controller wrote, before the cycle encodes them (S9: what each map
declares, :func:`~fieldbus.core.safestop.safe_stop_plan`). The latch is
released only through :meth:`SafeStopController.clear` (refused during an
outage) and ``release_after`` fresh cycles. Closing from OP is a controlled
stop (S6, :meth:`SafeStopController.wind_down`): quick stop until every CiA 402
axis is done, at most a budget, then disable voltage; a slave heard not to
answer is given up alone.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import numpy as np
import numpy.typing as npt

from fieldbus.backends.base import AxisGroup
from fieldbus.core.cia402 import SafeStop
from fieldbus.core.safestop import SafeStopWriter, safe_stop_plan
from fieldbus.core.safety import Verdict
from fieldbus.core.winddown import DISABLE_CYCLES, WindDown, WindDownReport
from fieldbus.cycle.buscycle import BusCycle
from fieldbus.cycle.status import CycleResult

CLOSE_CYCLES = DISABLE_CYCLES  # cycles of disable voltage sent on close, after the quick stop is done


class SafeStopController:
    """The safe stop of the buses ``cycles`` (their groups' writers, their latches) in ``result``."""

    def __init__(self, groups: dict[str, AxisGroup], cycles: Sequence[BusCycle], result: CycleResult) -> None:
        # what the safe stop writes, per axis group (chosen by its drive map)
        self.writers: dict[str, SafeStopWriter] = {}
        for name, g in groups.items():
            plan = safe_stop_plan(g.slaves[0].map, g.image.layout)
            self.writers[name] = SafeStopWriter(plan, g.image)
        self._writers = list(self.writers.values())
        self.cycles = list(cycles)
        self.result = result
        self.released = False  # the latch opened in the last cycle

    def apply(self, word: SafeStop = SafeStop.QUICK_STOP) -> None:
        """Every group's safe outputs over the controller's; ``word``: the CiA 402 command (disable
        voltage at the end of a wind-down)."""
        for w in self._writers:
            w.apply(word)

    def before_cycle(self) -> None:
        """While latched, the safe outputs overwrite the controller's before anything is encoded (S4)."""
        if self.result.safe_stop:
            self.apply()

    def after_cycle(self, any_stop: bool) -> bool:
        """Record this cycle's latch (``any_stop``: some bus's latch holds); True when it closed now,
        after which the safe outputs are written at once (effective from the next cycle's outputs)."""
        res = self.result
        latched = any_stop and not res.safe_stop
        self.released = res.safe_stop and not any_stop  # then seed_holds() after the observers (S12)
        res.safe_stop = any_stop
        return latched

    def seed_holds(self) -> None:
        """Every raw-CAN group's outputs hold where its motors are (S12, :mod:`fieldbus.core.hold`)."""
        for bc in self.cycles:
            for hold in bc.holds.values():
                hold.seed()

    def clear(self) -> bool:
        """Ask every bus's latch to open (S4); True when all are open now. Raises
        :class:`~fieldbus.core.safety.SafeStopClearError` (nothing changed) while a latched bus is missing."""
        for bc in self.cycles:
            policy = bc.policy
            if policy.safe_stop and policy.last_verdict is not Verdict.OK:
                policy.clear_safe_stop()  # raises SafeStopClearError with this bus's reason
        for bc in self.cycles:
            bc.policy.clear_safe_stop()
            bc.status.safe_stop = bc.policy.safe_stop
            bc.status.release_pending = bc.policy.clear_requested
        was = self.result.safe_stop
        self.result.safe_stop = any(bc.policy.safe_stop for bc in self.cycles)
        if was and not self.result.safe_stop:  # opened at once: the next cycle sends the hold (S12)
            self.seed_holds()
        return not self.result.safe_stop

    def wind_down(
        self,
        receive: Callable[[int, int], None],
        cycle_time_us: int,
        cap_s: float,
        sleep: Callable[[float], None],
        on_report: Callable[[WindDownReport], None] | None = None,
    ) -> WindDownReport:
        """A controlled stop (S6): quick stop until every drive reports it done, then disable voltage.

        Each cycle goes through the same never-raising path as a cycle of the
        network (``receive(k, cycle)``: bus ``k``'s receive, judge, accept and
        acyclic steps); a bus that fails keeps its miss, the others still get
        their cycles. The quick stop lasts until every CiA 402 axis is done
        (:class:`~fieldbus.core.winddown.WindDown`), at most its budget; then
        ``CLOSE_CYCLES`` cycles of disable voltage, one every ``cycle_time_us``
        (``sleep`` in seconds). A KeyboardInterrupt meanwhile does not cut it
        short; it is raised again afterwards. ``on_report`` gets the report
        before the first cycle (it fills in as the stop goes on).
        """
        # per bus, its slaves heard not to answer in this wind-down cycle (S6: a slave is given up alone)
        unheard = [np.zeros(bc.backend.n_slaves, dtype=bool) for bc in self.cycles]
        groups = []
        group_bus: list[int] = []
        for k, bc in enumerate(self.cycles):
            for g in bc.backend.groups:
                rows = slice(g.first, g.first + len(g.slaves))
                groups.append((g.name, g.image, g.slaves[0].map, bc.policy.fresh[rows], unheard[k][rows]))
                group_bus.append(k)
        dead_after = min(bc.policy.config.safe_stop_after for bc in self.cycles)
        wd = WindDown(groups, cycle_time_us, cap_s=cap_s, dead_after=dead_after)
        if on_report is not None:
            on_report(wd.report)
        first: BaseException | None = None
        period_s = cycle_time_us / 1e6
        done = False
        statuses = [bc.status for bc in self.cycles]
        for _ in range(wd.budget_cycles + 1):
            try:
                self._cycle(SafeStop.QUICK_STOP, receive, unheard)
                done = wd.step([statuses[k].ran for k in group_bus])
            except BaseException as exc:  # a second Ctrl-C: finish stopping the drives first
                first = first or exc
            if done:
                break
            sleep(period_s)
        wd.finish()
        for _ in range(CLOSE_CYCLES):
            try:
                self._cycle(SafeStop.DISABLE_VOLTAGE, receive, unheard)
                wd.report.disable_cycles += 1
            except BaseException as exc:
                first = first or exc
            sleep(period_s)
        if first is not None:
            raise first
        return wd.report

    def _cycle(
        self, word: SafeStop, receive: Callable[[int, int], None], unheard: list[npt.NDArray[np.bool_]]
    ) -> None:
        """One wind-down cycle on every bus that is due (each at its own rate), the safe outputs with
        ``word`` written first; a short reply judged per slave (:meth:`BusCycle.settle_answered`)."""
        self.apply(word)
        res = self.result
        cycle = res.cycle
        for bc in self.cycles:
            if bc.due(cycle):
                bc.send(cycle, res.events)
        for k, bc in enumerate(self.cycles):
            if not bc.status.ran:
                continue
            receive(k, cycle)
            bc.settle_answered(unheard[k])
        res.cycle = cycle + 1
