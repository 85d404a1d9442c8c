"""What a raw-CAN motor is commanded after a transition: hold where it is (S12, no I/O).

A transition (the safe stop's latch opening, a motor recovered with ``backend.recover``, a mode switch
with ``backend.set_mode``) must not start motion by itself: the command a motor gets next must not be the
target, speed, torque or gains the image held from before it. :func:`hold_row` writes the hold command
into one row of a raw-CAN group's outputs:

- ``position`` <- the position last read (``inputs["position"]``, when the map has both);
- ``velocity``, ``torque``, ``current``, ``duty``, ``brake_current`` <- 0 (a mode's channels
  ``<mode>.<field>`` alike) (MIT: no speed and no
  feed-forward torque; Damiao velocity / position-velocity: no speed; CubeMars servo: no current);
- the gains (``kp``, ``kd``) and every other field stay as the image has them: after a safe stop that is
  what the safe-stop frames carried (by default kp = kd = 0: no stiffness), after a recovery the
  controller's own gains (an MIT motor then holds where it is).

:class:`TransitionHold` does this for the rows of one axis group and restarts the group's output rules
from the seed (:meth:`~fieldbus.core.output_rules.OutputRules.rebase`), so a NaN written afterwards keeps
the seed, not the target sent before the transition, and a step limit ramps from where the motor is.
A "new command" is any value written into the image after the seed: after the ``exchange()`` in which
the latch opened returns (or ``clear_safe_stop()`` that opened it), after ``recover()`` or ``set_mode()``.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import numpy.typing as npt

from fieldbus.core.output_rules import OutputRules
from fieldbus.core.pdo.image import ProcessImage

ZERO_FIELDS = ("velocity", "torque", "current", "duty", "brake_current")  # commands held at 0


def hold_row(out: Any, inp: Any) -> None:
    """One motor's outputs ``out`` (a structured row of the image) hold where ``inp`` says it is; a mode's
    own channels (``<mode>.<field>``: ``velocity.velocity``, ``pos_vel.position``) by their field too, so
    a mode switched to later never sends a value left there from an earlier use."""
    names, read = out.dtype.names or (), inp.dtype.names or ()
    here = "position" in read
    for n in names:
        field = n.rpartition(".")[2]
        if field in ZERO_FIELDS:
            out[n] = 0
        elif field == "position" and here:
            out[n] = inp["position"]


class TransitionHold:
    """The hold command for one raw-CAN axis group (``image``), its output rules restarted from it."""

    def __init__(self, image: ProcessImage, rules: OutputRules) -> None:
        self.image = image
        self.rules = rules
        self.held = np.zeros(image.n_axes, dtype=bool)  # rows seeded by the last call (read, do not keep)

    def seed(self, rows: npt.NDArray[np.bool_] | None = None) -> None:
        """Write the hold command into ``rows`` (None: every row), then rebase the rules on it."""
        if rows is None:
            self.held.fill(True)
        else:
            np.copyto(self.held, rows)
        out, inp = self.image.outputs.values, self.image.inputs.values
        for r in np.flatnonzero(self.held):
            hold_row(out[r], inp[r])
        self.rules.rebase(self.held)
