"""A controlled stop on close (pure): quick stop until every drive says it is done, then disable voltage.

Invariant S6 of ``docs/safety.md``. On ``close()`` (and so on Ctrl-C or SIGTERM
in the CLI) every CiA 402 axis gets the quick stop command and keeps getting it
until its drive reports the stop complete; only then does disable voltage go
out. An axis is done when its statusword shows

- QUICK STOP ACTIVE with ``|velocity_actual_value|`` at or under the standstill
  threshold (when the map has the velocity channel), or
- a state without torque that the drive entered on its own (SWITCH ON
  DISABLED after a quick-stop ramp with 0x605A option 1-4, READY TO SWITCH
  ON, SWITCHED ON), or FAULT (the drive's own fault reaction ran).

Every step is bounded: a budget in cycles derived from the map (max velocity
over the quick-stop deceleration 0x6085, x1.5 plus 100 ms) and capped. A slave
is judged on its own: an axis is watched while its slave's inputs are fresh,
and given up as ``silent`` only when its slave was *heard not to answer* for
``dead_after`` cycles of its bus in a row (no reply at all on the bus, or a
short working counter the recovery can attribute to other slaves; see
:func:`fieldbus.core.wkc.answered_slaves`). A short reply that cannot be
attributed stales every slave of the bus but silences none: the quick stop
goes on to its budget. A bus that runs every n-th cycle is judged on the
cycles it ran. The outcome, per axis, is in :class:`WindDownReport`.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
import numpy.typing as npt

from fieldbus.core.cia402 import State402, decode_states
from fieldbus.core.pdo.image import ProcessImage
from fieldbus.core.pdo.model import DriveMap

DEFAULT_BUDGET_S = 3.0  # when the map gives neither 0x6085 nor a max velocity
MAX_BUDGET_S = 10.0  # the cap, whatever the map says
DISABLE_CYCLES = 5  # cycles of disable voltage after the quick stop is done
STANDSTILL_SCALED = 0.02  # |velocity| at or under this (engineering units / s) is standstill
STANDSTILL_RAW = 100  # likewise for an unscaled velocity channel, counts/s

QUICK_STOP_DECELERATION = 0x6085
MAX_VELOCITY_OBJECTS = (0x6080, 0x607F)  # max motor speed, max profile velocity
VELOCITY_ACTUAL = 0x606C
STATUSWORD = 0x6041
CONTROLWORD = 0x6040

_DONE_STATES = np.array(
    [
        State402.SWITCH_ON_DISABLED,
        State402.READY_TO_SWITCH_ON,
        State402.SWITCHED_ON,
        State402.FAULT,
    ],
    dtype=np.int8,
)


def _sdo_value(drive: DriveMap, index: int) -> float | None:
    for w in drive.sdo:
        if w.index == index and w.sub_index == 0 and isinstance(w.value, int | float):
            return float(w.value)
    return None


def stop_budget_s(drive: DriveMap, cap_s: float = MAX_BUDGET_S) -> float:
    """Seconds a drive of this map may take to quick-stop: max velocity / 0x6085, x1.5 + 0.1 s, capped."""
    decel = _sdo_value(drive, QUICK_STOP_DECELERATION)
    vmax = next((v for v in (_sdo_value(drive, i) for i in MAX_VELOCITY_OBJECTS) if v), None)
    if not decel or not vmax or decel <= 0:
        return min(DEFAULT_BUDGET_S, cap_s)
    return min(1.5 * abs(vmax) / decel + 0.1, cap_s)


@dataclass
class AxisOutcome:
    """How one axis ended its wind-down."""

    group: str
    axis: int
    state: str  # the last state read (or "unknown")
    velocity: float | None  # the last |velocity_actual_value| read before disable voltage (image units)
    cycles: int  # cycles of quick stop it took (or had when it was given up)
    how: str  # "stopped", "state" (the drive left OPERATION ENABLED on its own), "budget", "silent"


@dataclass
class WindDownReport:
    """The wind-down of one close(): per axis outcome, total cycles, whether a budget ran out."""

    axes: list[AxisOutcome] = field(default_factory=list)
    quick_stop_cycles: int = 0
    disable_cycles: int = 0

    @property
    def complete(self) -> bool:
        """Every axis reported its stop (no budget ran out, no bus fell silent)."""
        return all(a.how in ("stopped", "state") for a in self.axes)


class _GroupWatch:
    def __init__(self, name: str, image: ProcessImage, drive: DriveMap, budget_cycles: int) -> None:
        inputs = image.inputs.layout
        sw = inputs.find(STATUSWORD)
        vel = inputs.find(VELOCITY_ACTUAL)
        self.name = name
        self.statusword: npt.NDArray[np.uint16] | None = (
            image.inputs[sw.name] if sw is not None and not sw.channel.scaled else None
        )
        self.velocity: npt.NDArray[np.float64] | None = image.inputs[vel.name] if vel is not None else None
        self.standstill = (
            STANDSTILL_SCALED if vel is not None and vel.channel.scaled else float(STANDSTILL_RAW)
        )
        n = image.n_axes
        self.budget = budget_cycles
        self.done = np.zeros(n, dtype=bool) if self.statusword is not None else np.ones(n, dtype=bool)
        self.how = ["" for _ in range(n)]
        self.cycles = np.zeros(n, dtype=np.int64)
        self.state = np.full(n, -1, dtype=np.int8)
        self.unheard = np.zeros(n, dtype=np.int64)  # bus cycles in a row its slave did not answer
        self.last_velocity: list[float | None] = [None] * n


class WindDown:
    """Steps a close(): :meth:`step` once per cycle with each group's freshness; True when disable may go out.

    ``groups``: (name, image, drive map, rows fresh this cycle, rows heard not
    to answer this cycle) per axis group, one flag per slave; both arrays are
    read at every :meth:`step` (views the caller updates).
    """

    def __init__(
        self,
        groups: list[tuple[str, ProcessImage, DriveMap, npt.NDArray[np.bool_], npt.NDArray[np.bool_]]],
        cycle_time_us: int,
        *,
        cap_s: float = MAX_BUDGET_S,
        dead_after: int = 10,
    ) -> None:
        self._groups = [
            _GroupWatch(name, image, drive, max(1, round(stop_budget_s(drive, cap_s) * 1e6 / cycle_time_us)))
            for name, image, drive, _, _ in groups
        ]
        self._fresh = [g[3] for g in groups]
        self._unheard = [g[4] for g in groups]
        self.dead_after = dead_after
        self.report = WindDownReport()

    @property
    def budget_cycles(self) -> int:
        """The longest budget of any group, cycles."""
        return max((g.budget for g in self._groups), default=0)

    def step(self, ran: Sequence[bool] | None = None) -> bool:
        """Judge this cycle's inputs (call after the cycle's exchange); True: every axis is done.

        ``ran``: per group, its bus exchanged this cycle (default: all did); a
        group whose bus did not run is not judged, only its budget runs on.
        """
        self.report.quick_stop_cycles += 1
        all_done = True
        for k, g in enumerate(self._groups):
            if g.statusword is None or g.done.all():
                continue
            fresh, unheard = self._fresh[k], self._unheard[k]
            judged = ran is None or ran[k]
            if judged:
                decode_states(g.statusword, g.state)
            for i in np.flatnonzero(~g.done):
                g.cycles[i] += 1
                row = i * len(fresh) // len(g.done)  # fresh per slave; a multi-axis slave has rows
                if judged and fresh[row]:
                    g.unheard[i] = 0
                    v = abs(float(g.velocity[i])) if g.velocity is not None else None
                    g.last_velocity[i] = v
                    s = int(g.state[i])
                    if s == State402.QUICK_STOP_ACTIVE and v is not None and v <= g.standstill:
                        g.done[i], g.how[i] = True, "stopped"
                    elif s in _DONE_STATES:
                        g.done[i], g.how[i] = True, "state"
                elif judged and unheard[row]:
                    g.unheard[i] += 1
                if not g.done[i] and g.unheard[i] >= self.dead_after:
                    g.done[i], g.how[i] = True, "silent"
                elif not g.done[i] and g.cycles[i] >= g.budget:
                    g.done[i], g.how[i] = True, "budget"
            all_done = all_done and bool(g.done.all())
        return all_done

    def finish(self) -> WindDownReport:
        """Fill the report's per-axis outcomes (call once, after the last step)."""
        for g in self._groups:
            if g.statusword is None:
                continue
            for i in range(len(g.done)):
                s = int(g.state[i])
                self.report.axes.append(
                    AxisOutcome(
                        g.name,
                        i,
                        State402(s).name if s >= 0 else "unknown",
                        g.last_velocity[i],
                        int(g.cycles[i]),
                        g.how[i] or "budget",
                    )
                )
        return self.report
