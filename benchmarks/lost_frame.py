"""What a lost EtherCAT frame costs one ``exchange()``, phase by phase: before and after, in one run.

    python benchmarks/lost_frame.py [--rounds 8] [--losses 25] [--receive-timeout-us 500] [--rt-priority N] [--json]

The real pysoem master in this process, three emulated CiA 402 drives
(``python -m sim_slaves.ethercat``) on the peer end of a veth pair (root
only), paced at 1 kHz. Each loss: a few good cycles, the emulator told to
drop the next process-data frame (``{"cmd": "drop", "pd": true}``), the lost
cycle, the cycle right after it. Per kind of cycle (``good``: the one before
the drop, ``lost``, ``after``) the exchange() time and its phases
(:class:`fieldbus.platform.phases.PhaseTimer`), and how many cycles sent a
datagram beside the LRW (counted: the backend's one-datagram budget flag).

Two recoveries alternate round by round on the same network:

- ``passes-at-loss``: the recovery's pass starts in the cycle of the loss (a
  BRD of every slave's AL status waits its reply there) - the code before;
- ``deferred``: nothing is sent in the cycle of the loss; the next cycle's LRW
  with its full WKC ends the recovery (the backend's ``_recover`` now).

On a shared machine compare medians within the run; the load average is printed.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks._common import machine_note, table
from fieldbus.commands.demo import DEMO_MAP
from fieldbus.network import open_network
from fieldbus.platform.phases import PHASES, PhaseTimer

KINDS = ("good", "lost", "after")
VARIANTS = ("passes-at-loss", "deferred")
GOOD_BEFORE = 4  # good cycles between two losses (the last one is the "good" sample)


def _pct(values: list[int], q: float) -> float:
    s = sorted(values)
    return s[min(len(s) - 1, int(q * (len(s) - 1) + 0.5))] / 1e3


def run(rounds: int, losses: int, receive_timeout_us: int, rt_priority: int | None) -> dict[str, Any]:
    from fieldbus.platform.rt import RtConfig, realtime
    from sim_slaves.ethercat.veth import emulated_segment

    # per variant and kind: exchange_ns list, phases (list of per-phase ns lists), cycles with a datagram
    data: dict[str, dict[str, dict[str, Any]]] = {
        v: {k: {"ns": [], "phases": [[] for _ in PHASES], "datagram": 0} for k in KINDS} for v in VARIANTS
    }
    load = []
    with (
        tempfile.TemporaryDirectory() as tmp,
        emulated_segment([DEMO_MAP], count=3, workdir=Path(tmp)) as emu,
    ):
        net_file = Path(tmp) / "net.yaml"
        net_file.write_text(
            f"cycle_time_us: 1000\nreceive_timeout_us: {receive_timeout_us}\nsafe_stop_after: 100000\n"
            f"buses:\n  - {{name: bus, type: ethercat, interface: {emu.iface}, "
            f"slaves: [{{name: 'j{{i}}', map: {json.dumps(str(DEMO_MAP))}, count: 3}}]}}\n"
        )
        with open_network(net_file) as net:
            op = net.bring_up()
            backend: Any = net.backends[0]
            timer = PhaseTimer()
            op.phases = timer
            rt = realtime(RtConfig(priority=rt_priority), warn=lambda line: print(line, file=sys.stderr))
            with rt:
                for r in range(rounds):
                    order = VARIANTS if r % 2 == 0 else VARIANTS[::-1]
                    for variant in order:
                        if variant == "passes-at-loss":
                            backend._recover = backend._recover_passes  # the code before: BRD at the loss
                        else:
                            backend.__dict__.pop("_recover", None)
                        _losses(op, emu, backend, timer, losses, data[variant])
                    load.append(os.getloadavg()[0])
            misses = net.policies[0].stats.misses
    out: dict[str, Any] = {
        "machine": machine_note(),
        "receive_timeout_us": receive_timeout_us,
        "rounds": rounds,
        "losses_per_variant": rounds * losses,
        "load_avg_1min": {"min": min(load), "max": max(load)},
        "rt_priority": rt_priority,
        "misses": misses,
        "variants": {},
    }
    for v in VARIANTS:
        out["variants"][v] = {
            k: {
                "p50_us": _pct(d["ns"], 0.5),
                "p90_us": _pct(d["ns"], 0.9),
                "p99_us": _pct(d["ns"], 0.99),
                "max_us": max(d["ns"]) / 1e3,
                "cycles": len(d["ns"]),
                "cycles_with_datagram": d["datagram"],
                "phases_p50_us": {
                    name: statistics.median(d["phases"][i]) / 1e3 for i, name in enumerate(PHASES)
                },
            }
            for k, d in data[v].items()
        }
    return out


def _losses(op: Any, emu: Any, backend: Any, timer: PhaseTimer, losses: int, into: dict[str, Any]) -> None:
    """``losses`` times: good cycles, a dropped frame, the cycle after; paced at 1 kHz."""
    next_t = time.perf_counter()

    def cycle(kind: str | None) -> bool:
        nonlocal next_t
        res = op.exchange()
        fresh = bool(res.fresh)
        if kind is not None:
            d = into[kind]
            d["ns"].append(res.exchange_ns)
            for i, ns in enumerate(timer.last_ns):
                d["phases"][i].append(ns)
            d["datagram"] += bool(backend._frame_sent)
        next_t += 0.001
        pause = next_t - time.perf_counter()
        if pause > 0:
            time.sleep(pause)
        else:
            next_t = time.perf_counter()
        return fresh

    for _ in range(losses):
        for g in range(GOOD_BEFORE):
            cycle("good" if g == GOOD_BEFORE - 1 else None)
        emu.command(cmd="drop", count=1, pd=True)
        next_t = time.perf_counter()
        if cycle("lost"):
            raise RuntimeError("the dropped frame's cycle came back fresh: the emulator did not drop it")
        cycle("after")


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--rounds", type=int, default=8)
    p.add_argument("--losses", type=int, default=25, help="losses per variant per round")
    p.add_argument("--receive-timeout-us", type=int, default=500)
    p.add_argument("--rt-priority", type=int, help="SCHED_FIFO priority of the measuring thread")
    p.add_argument("--json", action="store_true")
    args = p.parse_args(argv)
    out = run(args.rounds, args.losses, args.receive_timeout_us, args.rt_priority)
    if args.json:
        print(json.dumps(out, indent=1))
        return 0
    t = args.receive_timeout_us
    print(
        f"# lost EtherCAT frame, {out['losses_per_variant']} losses per variant, receive timeout {t} us, "
        f"rt priority {args.rt_priority}, load {out['load_avg_1min']['min']:.1f}-{out['load_avg_1min']['max']:.1f} "
        f"({out['machine']})\n"
    )
    rows = []
    for v in VARIANTS:
        for k in KINDS:
            r = out["variants"][v][k]
            ph = r["phases_p50_us"]
            rows.append(
                [v, k, f"{r['p50_us']:.0f}", f"{r['p90_us']:.0f}", f"{r['p99_us']:.0f}", f"{r['max_us']:.0f}"]
                + [f"{ph[name]:.1f}" for name in PHASES]
                + [f"{r['cycles_with_datagram']}/{r['cycles']}"]
            )
    print(
        table(
            ["recovery", "cycle", "p50", "p90", "p99", "max", *[f"{n} p50" for n in PHASES], "+datagram"],
            rows,
        )
    )
    for v in VARIANTS:
        lost = out["variants"][v]["lost"]
        print(
            f"\n{v}: lost cycle p50 = timeout + {lost['p50_us'] - t:.0f} us, "
            f"p99 = timeout + {lost['p99_us'] - t:.0f} us"
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())
