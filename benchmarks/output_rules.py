"""The output path's rules per cycle, against the pack they guard (issue 33).

One cycle for N axes of the CiA 402 CSP map of ``pack_unpack.py`` with limits on every target (a
position window and a rate, a velocity and a torque window; the statusword says operation enabled, so
the step rule runs):

- ``pack``: write the controller's targets into the image and ``outputs.to_wire()`` (the existing pack);
- ``rules+pack``: the same with :meth:`~fieldbus.core.output_rules.OutputRules.apply` before the pack
  (a clean cycle: nothing refused);
- ``rules+pack, NaN``: one axis's position is NaN every cycle (the refused path, counted; events are
  not built: ``exchange()`` builds them only on the first cycle of a streak).

Interleaved rounds, medians and within-round ratios (``_common.interleaved``); gc held while timing.

    python benchmarks/output_rules.py            # ~30 s
    python benchmarks/output_rules.py --quick    # ~5 s
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

from _common import interleaved, machine_note, table
from pack_unpack import CSP_YAML, Data

from fieldbus.core.output_rules import OutputRules, channel_limits
from fieldbus.core.pdo import drive_map_from_text
from fieldbus.core.pdo.image import ProcessImage
from fieldbus.core.pdo.layout import layout
from fieldbus.platform.allocs import net_blocks
from fieldbus.platform.loop import gc_held

AXES = (12, 64)
LIMITS = """\
limits:
  target_position: {min: -3.2, max: 3.2, max_rate: 25.0}
  target_velocity: {max: 25.0}
  target_torque: {max: 2.4}
"""


def contenders(n: int) -> dict[str, object]:
    drive = drive_map_from_text(CSP_YAML + LIMITS, "bench_limits.yaml")
    d = Data(n)
    out: dict[str, object] = {}
    for name, rules_on, nan in (
        ("pack", False, False),
        ("rules+pack", True, False),
        ("rules+pack, NaN", True, True),
    ):
        img = ProcessImage(layout(drive), n)
        inp = img.inputs
        limits = channel_limits(drive, img.layout.outputs, 0.001)
        rules = OutputRules("g", img.outputs, limits, inp["statusword"], inp["modes_of_operation_display"])
        inp["statusword"][:], inp["modes_of_operation_display"][:] = 0x0237, 8  # CSP, enabled: steps apply
        q = d.q.copy()
        if nan:
            q[0] = math.nan
        views = [(img.outputs["target_position"], q), (img.outputs["target_velocity"], d.dq)]
        views += [(img.outputs["target_torque"], d.tau), (img.outputs["controlword"], d.cw)]
        enc = img.outputs

        def step(views=views, enc=enc, rules=rules, rules_on=rules_on) -> None:  # type: ignore[no-untyped-def]
            for v, src in views:
                np.copyto(v, src, casting="unsafe")
            if rules_on:
                rules.apply()
            enc.to_wire()

        step()
        out[name] = step
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="few rounds (smoke)")
    ap.add_argument("--json", action="store_true", help="print one JSON object")
    ap.add_argument("--rounds", type=int, help="interleaved rounds (default 31, --quick 5)")
    args = ap.parse_args(argv)
    rounds = args.rounds or (5 if args.quick else 31)
    groups = {f"{n} axes": contenders(n) for n in AXES}
    allocs = {g: {c: net_blocks(s, cycles=2000) for c, s in cs.items()} for g, cs in groups.items()}  # type: ignore[arg-type]
    with gc_held():
        samples = interleaved(groups, rounds, 0.05 if args.quick else 0.2)  # type: ignore[arg-type]
    rows = []
    result: dict[str, object] = {"machine": machine_note(), "rounds": rounds, "groups": {}}
    for g, s in samples.items():
        for c in s.per_round:
            lo, hi = s.quartiles_us(c)
            ratio = s.ratio(c, "pack")
            rows.append(
                [g, c, f"{s.median_us(c):.2f} ({lo:.2f}-{hi:.2f})", f"{ratio:.2f}", str(allocs[g][c])]
            )
            result["groups"].setdefault(g, {})[c] = {  # type: ignore[union-attr]
                "median_us": s.median_us(c),
                "ratio_to_pack": ratio,
                "net_blocks": allocs[g][c],
            }
    if args.json:
        print(json.dumps(result))
    else:
        print(machine_note(), f"- {rounds} rounds")
        print(table(["axes", "contender", "µs/cycle median (IQR)", "÷ pack", "net blocks"], rows))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
