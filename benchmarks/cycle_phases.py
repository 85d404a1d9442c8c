"""Where the in-process EtherCAT cycle's time goes: ``exchange()`` phase by phase, the chain apart.

The sim backend (``open_network(..., backend="sim")``, N CiA 402 drives of
``fieldbus/data/demo_joint.yaml``) runs on a virtual clock (one bus cycle per
exchange, :class:`benchmarks.cycle.CycleTime`), the controller writing
``target_position`` from the last inputs. ``Operational.phases`` (a
:class:`~fieldbus.platform.phases.PhaseTimer`) splits each exchange; the
emulated chain's own share of the ``wait`` phase (``EscChain.process_into``)
is timed apart, so ``wait - chain`` is the in-process master and the backend's
receive. Medians and means over ``--cycles`` exchanges (perf_counter, so a busy
machine inflates them; compare runs taken side by side). The bare LRW loop of
``benchmarks/cycle.py`` runs the same chain alone, for scale.

    python benchmarks/cycle_phases.py [--axes 12] [--cycles 10000]
"""

from __future__ import annotations

import argparse
import statistics
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks._common import machine_note, table
from benchmarks.cycle import CycleTime, _net_file, sim_bare_step
from fieldbus.network import open_network
from fieldbus.platform import phases as ph
from sim_slaves.ethercat.chain import EscChain


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--axes", type=int, default=12)
    p.add_argument("--cycles", type=int, default=10_000)
    args = p.parse_args()
    spent = [0]
    process_into = EscChain.process_into

    def timed(chain: EscChain, *a: Any, **k: Any) -> int:
        t = time.perf_counter_ns()
        try:
            return process_into(chain, *a, **k)
        finally:
            spent[0] += time.perf_counter_ns() - t

    print(f"# exchange() phases, {args.axes} CiA 402 axes, sim backend ({machine_note()})\n")
    with tempfile.TemporaryDirectory() as tmp:
        clock = CycleTime()
        net = open_network(_net_file(Path(tmp), "sim", args.axes), backend="sim", clock=clock)
        try:
            op = net.bring_up()
            img = op["joints"]
            target, position = img.outputs["target_position"], img.inputs["position_actual_value"]
            clock.start()
            bare = sim_bare_step(args.axes, CycleTime())
            for _ in range(500):
                clock.tick()
                target[:] = position
                op.exchange()
            timer = ph.PhaseTimer()
            op.phases = timer
            rows: dict[str, list[int]] = {name: [] for name in (*ph.PHASES, "chain", "total")}
            EscChain.process_into = timed  # type: ignore[method-assign]
            try:
                for _ in range(args.cycles):
                    clock.tick()
                    target[:] = position
                    spent[0] = 0
                    op.exchange()
                    for name, ns in zip(ph.PHASES, timer.last_ns, strict=True):
                        rows[name].append(ns)
                    rows["chain"].append(spent[0])
                    rows["total"].append(sum(timer.last_ns))
            finally:
                EscChain.process_into = process_into  # type: ignore[method-assign]
            t = time.perf_counter_ns()
            for _ in range(args.cycles):
                bare()
            bare_us = (time.perf_counter_ns() - t) / args.cycles / 1e3
        finally:
            net.close()
    out = [
        [name, f"{statistics.median(v) / 1e3:.1f}", f"{statistics.fmean(v) / 1e3:.1f}"]
        for name, v in rows.items()
    ]
    mean = {name: statistics.fmean(v) / 1e3 for name, v in rows.items()}
    out.append(["total - chain (fieldbus's own work)", "", f"{mean['total'] - mean['chain']:.1f}"])
    out.append(["bare LRW loop (the chain alone), per cycle", "", f"{bare_us:.1f}"])
    print(table(["phase", "median [µs]", "mean [µs]"], out))
    print(
        "\n`wait` holds `chain`: the emulated slaves' work; the rest of `wait` is the master and the backend."
    )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
