"""Host sync over veth: how close the host PI holds the send phase to its target, PI on and off.

    python benchmarks/dc_host_sync.py [--rounds 6] [--cycles 2000] [--drift-ppm 100] [--slaves 4]

The real pysoem master in this process, emulated EPOS4 drives (SYNC0 as the
map asks) on a veth pair, the emulator in a child process (root only). The
reference clock runs ``--drift-ppm`` fast against the host, so a loop
without the PI walks off its phase. Each round runs one block of
``--cycles`` cycles with the PI's correction applied to the loop's deadline
(``run_cycles(adjust=op.dc_correction_ns)``, SOEM's ec_sync) and one without,
in a shuffled order; per block, the |phase error| of the cycles that came
back in time (DC time read in the frame against the host's target, half a
cycle in) over the block's second half. Reported: the medians over rounds of
each block's p50 and p99, and of the ratio off/on within a round - the
figure to compare between machines. ``tests/integration/test_dc_backend.py``
asserts what the backend computes in each cycle; this measures what the
machine's wake-ups let the PI achieve.
"""

from __future__ import annotations

import argparse
import json
import random
import statistics
import sys
import tempfile
from pathlib import Path

import numpy as np

from fieldbus.network import Operational, open_network
from fieldbus.platform.loop import run_cycles

REPO = Path(__file__).resolve().parent.parent
EPOS4 = REPO / "pdo_maps" / "maxon_epos4.yaml"
CYCLE_NS = 1_000_000
RECEIVE_TIMEOUT_US = 20_000


def block(op: Operational, cycles: int, pi: bool) -> tuple[float, float]:
    """One block of ``cycles`` cycles, the PI's correction applied or not: (p50, p99) of |phase error|, us,
    over the second half."""
    errors: list[int] = []

    def step(k: int) -> None:
        bus = op.exchange().buses[0]
        if bus.verdict == 0 and bus.dc_sync_error_ns is not None and k >= cycles // 2:
            errors.append(abs(bus.dc_sync_error_ns))

    def adjust() -> int:
        correction = op.dc_correction_ns()  # taken either way: the PI keeps stepping
        return correction if pi else 0

    run_cycles(step, CYCLE_NS / 1000, cycles, adjust=adjust)
    if not errors:
        return float("nan"), float("nan")
    p50, p99 = np.percentile(np.array(errors, dtype=np.float64), [50, 99]) / 1e3
    return float(p50), float(p99)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--rounds", type=int, default=6, help="rounds, one block each way per round (default 6)")
    p.add_argument("--cycles", type=int, default=2000, help="cycles per block (default 2000)")
    p.add_argument("--drift-ppm", type=float, default=100.0, help="reference clock's drift (default 100)")
    p.add_argument("--slaves", type=int, default=4, help="emulated EPOS4 drives (default 4)")
    p.add_argument("--seed", type=int, default=0)
    args = p.parse_args(argv)
    from sim_slaves.ethercat.veth import VethUnavailable, emulated_segment

    rng = random.Random(args.seed)
    results: dict[bool, list[tuple[float, float]]] = {True: [], False: []}
    ratios: list[float] = []
    with tempfile.TemporaryDirectory(prefix="fieldbus-dc-bench-") as tmp:
        try:
            segment = emulated_segment([EPOS4], count=args.slaves, workdir=Path(tmp))
            emu = segment.__enter__()
        except VethUnavailable as exc:
            print(f"needs a veth pair: {exc}", file=sys.stderr)
            return 1
        try:
            net_file = Path(tmp) / "net.yaml"
            net_file.write_text(
                f"cycle_time_us: {CYCLE_NS // 1000}\nreceive_timeout_us: {RECEIVE_TIMEOUT_US}\n"
                "safe_stop_after: 100000\nbuses:\n"
                f"  - {{name: bus, type: ethercat, interface: {emu.iface}, slaves: "
                f"[{{name: 'j{{i}}', map: {json.dumps(str(EPOS4))}, count: {args.slaves}}}]}}\n"
            )
            with open_network(net_file) as net:
                op = net.bring_up()
                drifts = [args.drift_ppm] + [0.0] * (args.slaves - 1)  # the reference clock (first DC slave)
                emu.command(cmd="dc_config", drift_ppm=drifts)
                for _ in range(args.rounds):
                    order = [True, False]
                    rng.shuffle(order)
                    got = {pi: block(op, args.cycles, pi) for pi in order}
                    for pi, figures in got.items():
                        results[pi].append(figures)
                    ratios.append(got[False][0] / got[True][0])
        finally:
            segment.__exit__(None, None, None)

    def median(pi: bool, i: int) -> float:
        return statistics.median(r[i] for r in results[pi])

    print(
        f"{args.slaves} EPOS4 over veth, {args.cycles} cycles per block, reference clock +{args.drift_ppm:g} ppm"
    )
    print("| host PI | |phase error| p50 (us) | p99 (us) |")
    print("|---|---|---|")
    for pi in (True, False):
        print(f"| {'on' if pi else 'off'} | {median(pi, 0):.1f} | {median(pi, 1):.1f} |")
    print(f"p50 off / on, median of {args.rounds} rounds: {statistics.median(ratios):.1f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
