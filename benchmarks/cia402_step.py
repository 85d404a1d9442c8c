"""Cost of the CiA 402 controller's steady cycle: the full table step against the fast path, side by side.

    python benchmarks/cia402_step.py [--rounds 10] [--batch-s 0.2]

A steady cycle is the common one: every axis OPERATION ENABLED in CSP and nothing to do but hold the
goal. Contenders, each a :class:`~fieldbus.core.cia402.Cia402Controller` with ``fast_path`` off
(``full``: every cycle runs the whole table step, decode, lookup, mode gate, fault-reset pulse and
progress counts, as before the fast path) or on (``fast``):

- ``3 axes`` and ``12 axes``: :meth:`~fieldbus.core.cia402.Cia402Controller.step` alone, with a mode
  display and modes_of_operation (the DDS server's call, ``fieldbus/dds/server.py``: channel views of
  the process image's rows), statuswords of enabled drives (target reached, following the target);
- ``3 joints, sim``: one 1 kHz cycle of a user loop on the sim backend (``open_network(...,
  backend="sim")``, 3 drives of ``fieldbus/data/demo_joint.yaml``, virtual clock, one bus cycle per
  exchange): ``step_image``, a new CSP target, ``exchange()``; the emulated chain's time included.

Interleaved rounds (benchmarks/_common.py); reported: µs per cycle (median, IQR over rounds) and
the ratio full/fast within each round.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks._common import interleaved, machine_note, table
from benchmarks.cycle import CycleTime, _net_file
from fieldbus.core.cia402 import STATUSWORD_STATE_BITS, Cia402Controller, Goal, Mode, State402
from fieldbus.network import open_network

ENABLED = STATUSWORD_STATE_BITS[State402.OPERATION_ENABLED] | 0x1600  # + target reached, follows target


def controller_step(n: int, fast: bool) -> Callable[[], None]:
    """One steady :meth:`Cia402Controller.step` of ``n`` enabled axes with modes."""
    ctrl = Cia402Controller(n)
    ctrl.fast_path = fast
    ctrl.set_goal(Goal.ENABLE)
    # channel views of a process image's rows (strided fields), as the DDS server passes them
    inp = np.zeros(n, dtype=[("statusword", "<u2"), ("position_actual_value", "<i4"), ("display", "i1")])
    out = np.zeros(n, dtype=[("controlword", "<u2"), ("target_position", "<i4"), ("modes", "i1")])
    inp["statusword"], inp["display"] = ENABLED, int(Mode.CSP)
    sw, cw, md, mo = inp["statusword"], out["controlword"], inp["display"], out["modes"]
    for _ in range(3):
        ctrl.step(sw, cw, md, mo)
    assert ctrl.all_reached, "the axes are not at their goal"

    def step() -> None:
        ctrl.step(sw, cw, md, mo)

    return step


def sim_cycle(tmp: Path, n: int, fast: bool, nets: list[Any]) -> Callable[[], None]:
    """One cycle of a user loop on the sim backend: step_image, a new target, exchange()."""
    clock = CycleTime()
    d = tmp / ("fast" if fast else "full")
    d.mkdir()
    net = open_network(_net_file(d, "sim", n), backend="sim", clock=clock)
    nets.append(net)
    op = net.bring_up()
    img = op["joints"]
    target = img.outputs["target_position"]
    ctrl = Cia402Controller(n)
    ctrl.fast_path = fast
    ctrl.set_goal(Goal.ENABLE)
    clock.start()
    for _ in range(100):
        clock.tick()
        ctrl.step_image(img)
        op.exchange()
    assert ctrl.all_reached, "the drives did not enable"

    def cycle() -> None:
        clock.tick()
        ctrl.step_image(img)
        target[:] += 1e-6  # a slow ramp, written after step_image as a loop does
        op.exchange()

    return cycle


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--rounds", type=int, default=10, help="interleaved rounds (default 10)")
    p.add_argument("--batch-s", type=float, default=0.2, help="seconds per batch (default 0.2)")
    args = p.parse_args(argv)
    nets: list[Any] = []
    with tempfile.TemporaryDirectory() as tmp:
        groups = {
            "3 axes": {"full": controller_step(3, False), "fast": controller_step(3, True)},
            "12 axes": {"full": controller_step(12, False), "fast": controller_step(12, True)},
            "3 joints, sim": {
                "full": sim_cycle(Path(tmp), 3, False, nets),
                "fast": sim_cycle(Path(tmp), 3, True, nets),
            },
        }
        try:
            found = interleaved(groups, args.rounds, args.batch_s)
        finally:
            for net in nets:
                net.close()
    rows = []
    for group, s in found.items():
        cells = []
        for name in ("full", "fast"):
            lo, hi = s.quartiles_us(name)
            cells.append(f"{s.median_us(name):.1f} ({lo:.1f}-{hi:.1f})")
        lo, hi = s.ratio_quartiles("full", "fast")
        saved = s.median_us("full") - s.median_us("fast")
        rows.append([group, *cells, f"{saved:.1f}", f"{s.ratio('full', 'fast'):.1f} ({lo:.1f}-{hi:.1f})"])
    print(machine_note())
    print(f"steady cycle, median of {args.rounds} interleaved rounds")
    print(table(["", "full step [us] (IQR)", "fast path [us] (IQR)", "saved [us]", "full / fast"], rows))
    return 0


if __name__ == "__main__":
    sys.exit(main())
