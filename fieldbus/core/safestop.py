"""What the safe stop writes into an axis group's outputs, chosen by its drive map.

The working-counter policy latches a safe stop after ``safe_stop_after``
misses in a row; from then on, every cycle, :class:`SafeStopWriter` writes the
group's safe outputs (master outputs, i.e. the drive's RxPDO) before they are
encoded, whatever the controller wrote. One strategy per kind of drive:

- **cia402** (the map has an unscaled controlword 0x6040): the CiA 402 quick
  stop command into the controlword (:func:`fieldbus.core.cia402.write_command_word`),
  plus any channel's ``safe_value``.
- **mit** (a ``rawcan:`` map, MIT-mode motors): the command fields' safe
  values; by default ``kp = kd = 0`` and zero feed-forward torque, so the
  motor exerts no torque (see :mod:`fieldbus.core.rawcan`). On close the
  backend also sends exit-motor-mode.
- **outputs** (plain I/O and anything else): every output channel that
  declares a ``safe_value`` gets it; the others hold their last value.
- **none**: nothing declared (the outputs hold; the loader's summary says so).

Safe values are in the units of the process image (engineering units for
scaled channels, raw integers otherwise). Nothing here allocates per cycle.
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import StrEnum
from typing import Any

import numpy as np
import numpy.typing as npt

from fieldbus.core.cia402 import SafeStop, write_command_word
from fieldbus.core.pdo.image import ProcessImage
from fieldbus.core.pdo.layout import MapLayout
from fieldbus.core.pdo.model import DriveMap
from fieldbus.core.pdo.names import CONTROLWORD


class SafeStopKind(StrEnum):
    CIA402 = "cia402"
    MIT = "mit"
    OUTPUTS = "outputs"
    NONE = "none"


@dataclass(frozen=True)
class SafeStopPlan:
    """The safe outputs of one drive map: a controlword command and channel values."""

    kind: SafeStopKind
    controlword: str | None = None  # channel name of 0x6040:00 (cia402 only)
    values: tuple[tuple[str, float], ...] = ()  # (output channel name, safe value in image units)

    def describe(self) -> str:
        parts = [f"{self.controlword} = quick stop (0x{SafeStop.QUICK_STOP:04X})"] if self.controlword else []
        parts += [f"{name} = {value:g}" for name, value in self.values]
        return f"{self.kind}: " + (", ".join(parts) if parts else "outputs hold their last values")


def safe_stop_plan(drive: DriveMap, lay: MapLayout) -> SafeStopPlan:
    """The plan for ``drive`` (``lay`` is its layout on the bus it sits on)."""
    cw = lay.outputs.find(CONTROLWORD)
    controlword = cw.name if cw is not None and not cw.channel.scaled else None
    values = tuple(
        (e.name, float(e.channel.safe_value))
        for e in lay.outputs.channels
        if e.channel.safe_value is not None
    )
    if controlword is not None:
        kind = SafeStopKind.CIA402
    elif drive.rawcan is not None:
        kind = SafeStopKind.MIT
    elif values:
        kind = SafeStopKind.OUTPUTS
    else:
        kind = SafeStopKind.NONE
    return SafeStopPlan(kind, controlword, values)


class SafeStopWriter:
    """Writes a :class:`SafeStopPlan` into one process image's outputs (all rows), allocation-free."""

    def __init__(self, plan: SafeStopPlan, image: ProcessImage) -> None:
        self.plan = plan
        out = image.outputs.values
        self._controlword: npt.NDArray[np.uint16] | None = out[plan.controlword] if plan.controlword else None
        self._values: list[tuple[npt.NDArray[Any], Any]] = [
            (out[name], out.dtype[name].type(value)) for name, value in plan.values
        ]

    def apply(self, word: SafeStop = SafeStop.QUICK_STOP) -> None:
        """Write the safe outputs; ``word``: the CiA 402 command (disable voltage on close)."""
        if self._controlword is not None:
            write_command_word(self._controlword, word)
        for view, value in self._values:
            view.fill(value)
