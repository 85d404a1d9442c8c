"""``Operational.exchange()`` on the sim backend: the ESC chain's lean path against its reference path.

    python benchmarks/sim_lean.py [--axes 3 12] [--rounds 10] [--batch-s 0.2]

Per ``--axes`` (CiA 402 drives of ``fieldbus/data/demo_joint.yaml``) and per
drive state, two networks are brought up on the sim backend, each on a
clock of its own that moves 1 ms per exchange (every call one bus cycle,
whatever the machine's load); one keeps the chain's lean path
(``EscChain.lean``, the default: cached datagram offsets, byte compares,
slice copies, the drive link in C, the drive bank's idle and CSP cycles one
C call each on arrays the kernel holds), the other runs the general path,
the reference (``chain.lean = False``: as before these, with the CSP
kernel's two calls per cycle of ``sim_slaves._motion``). One cycle: the
targets set to the positions read, ``op.exchange()`` - the LRW frame and the
DC datagram through the chain, the drives' step, the inputs decoded and
judged. States: ``idle`` (the drives as brought up, SWITCH ON DISABLED:
what ``fieldbus serve`` steps while no client has enabled them) and
``enabled`` (OPERATION ENABLED in CSP, holding position).

Rounds interleave the contenders in a shuffled order (benchmarks/_common.py);
reported per group: median µs per exchange by wall clock and by this
thread's CPU time, and the ratio reference / lean taken within each round
(median and quartiles). The machine's load average is printed before and
after: on the shared VM the absolute figures move with it, the ratio much less.
"""

from __future__ import annotations

import argparse
import os
import random
import statistics
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks._common import RoundProgress, cycles_per_batch, machine_note, table
from benchmarks.cycle import CycleTime, _net_file, sim_exchange_step
from fieldbus import Cia402Controller, Goal

CONTENDERS = ("lean", "reference")
ENABLE_CYCLES = 3000  # at most, to OPERATION ENABLED


def contender(net_file: Path, lean: bool, enabled: bool) -> tuple[Callable[[], object], Any]:
    """One network's cycle (targets := positions, exchange) on the lean or the reference path."""
    step, net = sim_exchange_step(net_file, CycleTime())
    chain = net.backends[0].chain
    chain.lean = lean
    if enabled:
        op = net._phase
        img = op["joints"]
        ctrl = Cia402Controller(img.n_axes)
        ctrl.set_goal(Goal.ENABLE)
        for _ in range(ENABLE_CYCLES):
            ctrl.step_image(img)
            step()
            if ctrl.all_reached:
                break
        else:
            raise RuntimeError("the drives did not reach OPERATION ENABLED")
    for _ in range(500):  # warm: caches, plans, first numpy calls
        step()
    want = 4 if enabled else 1  # State402: OPERATION ENABLED, SWITCH ON DISABLED
    if set(chain.bank.state.tolist()) != {want}:
        raise RuntimeError(f"drive states {chain.bank.state.tolist()}, wanted all {want}")
    return step, net


def time_batch(step: Callable[[], object], cycles: int) -> tuple[float, float]:
    """(wall, thread CPU) seconds per call over one batch."""
    t0, c0 = time.perf_counter_ns(), time.thread_time_ns()
    for _ in range(cycles):
        step()
    return (time.perf_counter_ns() - t0) / 1e9 / cycles, (time.thread_time_ns() - c0) / 1e9 / cycles


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--axes", type=int, nargs="+", default=[3, 12])
    p.add_argument("--rounds", type=int, default=10)
    p.add_argument("--batch-s", type=float, default=0.2, help="per round and contender")
    args = p.parse_args()
    print(f"# sim exchange(), lean chain vs reference ({machine_note()})")
    print(f"load average before: {' '.join(f'{x:.2f}' for x in os.getloadavg())}\n")
    nets = []
    groups: dict[str, dict[str, Callable[[], object]]] = {}
    with tempfile.TemporaryDirectory() as tmp_s:
        tmp = Path(tmp_s)
        try:
            for axes in args.axes:
                for state in ("idle", "enabled"):
                    d = tmp / f"{axes}-{state}"
                    d.mkdir()
                    f = _net_file(d, "sim", axes)
                    group: dict[str, Callable[[], object]] = {}
                    for name in CONTENDERS:
                        step, net = contender(f, name == "lean", state == "enabled")
                        nets.append(net)
                        group[name] = step
                    groups[f"{axes} drives, {state}"] = group
            rng = random.Random(0)
            batches = {
                g: {c: cycles_per_batch(s, args.batch_s) for c, s in cs.items()} for g, cs in groups.items()
            }
            wall: dict[str, dict[str, list[float]]] = {g: {c: [] for c in CONTENDERS} for g in groups}
            cpu: dict[str, dict[str, list[float]]] = {g: {c: [] for c in CONTENDERS} for g in groups}
            shown = RoundProgress(args.rounds)
            for _ in range(args.rounds):
                for g, cs in groups.items():
                    order = list(cs)
                    rng.shuffle(order)
                    for c in order:
                        w, u = time_batch(cs[c], batches[g][c])
                        wall[g][c].append(w)
                        cpu[g][c].append(u)
                shown.step()
        finally:
            for net in nets:
                net.close()
    rows = []
    for g in groups:
        row = [g]
        for samples in (wall[g], cpu[g]):
            lean, ref = samples["lean"], samples["reference"]
            r = [b / a for a, b in zip(lean, ref, strict=True)]
            q1, q3 = np.percentile(r, [25, 75])
            row += [
                f"{statistics.median(lean) * 1e6:.1f}",
                f"{statistics.median(ref) * 1e6:.1f}",
                f"{statistics.median(r):.2f} ({q1:.2f}-{q3:.2f})",
            ]
        rows.append(row)
    print(
        table(
            [
                "group",
                "lean [µs]",
                "reference [µs]",
                "ref/lean (IQR)",
                "lean CPU [µs]",
                "reference CPU [µs]",
                "ref/lean CPU (IQR)",
            ],
            rows,
        )
    )
    print(f"\nload average after: {' '.join(f'{x:.2f}' for x in os.getloadavg())}; {args.rounds} rounds")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
