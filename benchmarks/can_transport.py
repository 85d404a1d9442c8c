"""CAN between processes: python-can's udp_multicast against fieldbus_udp, the same master and nodes, in one run.

The master (the raw-CAN backend, ``Operational.exchange()``) runs here; MIT-mode
motors (``cubemars_ak80_9_mit.yaml``, ``sim_slaves.mit_motor``) run in child
processes (``sim_slaves.can_process``) on either transport: one process serving
every bus (``--emulators one``, the default: one thread, one ``select`` over the
buses) or one process per bus (``--emulators per-bus``):

- **udp_multicast**: python-can's interface (msgpack per frame, the master
  reads back every frame it sends);
- **fieldbus_udp**: ``fieldbus.backends.udpcan`` (fixed 24-byte datagrams,
  one preallocated receive buffer, own frames dropped by a tag).

Rounds alternate the order of the two transports. Each round, per transport:

a) 1 bus x 3 motors, ``exchange()`` back to back: p50 / p99 (µs);
b) the seed's layout, 4 buses x 3 motors, paced at 1 kHz (``run_cycles``, as
   ``fieldbus run`` does): ``exchange()`` p50 / p99 / max, overruns (cycles
   that ended after their deadline), counted misses (bus cycles without every
   reply), safe stops (10 misses in a row on a bus, the seed's rule).

``--families mit,damiao`` (the default) runs both actuator families on each
transport: the MIT motors above and Damiao DM-J4310 motors
(``damiao_dm_j4310.yaml``, ``sim_slaves.damiao``: bring-up with register
read-back, MIT mode, replies on MST_ID), and gives the ratio damiao / mit of the
p50s per transport within each round.

Both transports' emulator processes are started once and idle while the other
transport runs. Percentiles are per round; the table shows their median over
rounds (max: over all rounds), counts summed over rounds, and the ratio
udp_multicast / fieldbus_udp of the p50s taken within each round (median).

    python benchmarks/can_transport.py [--rounds 4] [--exchanges 1000] [--cycles 2000]
        [--emulators one|per-bus] [--families mit,damiao] [--transports udp_multicast,fieldbus_udp]
        [--rt-priority N] [--json]

The header (and ``--json``) names the machine and its load average at the start and at the end.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import sys
import tempfile
import time
from contextlib import ExitStack
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import can
import numpy as np

from benchmarks._common import RoundProgress, machine_note, table
from fieldbus import PDO_MAPS
from fieldbus.core.pdo import load_drive_map
from fieldbus.network import open_network
from fieldbus.operations.report import run_report
from fieldbus.platform.loop import gc_held, run_cycles
from fieldbus.platform.rt import RtConfig, realtime
from fieldbus.platform.timing import CycleTimer
from sim_slaves.can_process import CanChannel, can_emulator_process, udp_bus
from sim_slaves.damiao import DamiaoSimulator
from sim_slaves.mit_motor import MitMotorSimulator

MIT_MAP = Path(PDO_MAPS) / "cubemars_ak80_9_mit.yaml"
DAMIAO_MAP = Path(PDO_MAPS) / "damiao_dm_j4310.yaml"
FAMILIES = {"mit": MIT_MAP, "damiao": DAMIAO_MAP}  # family (also the emulator process's --kind) -> map
TRANSPORTS = ("udp_multicast", "fieldbus_udp")
BUSES, MOTORS = 4, 3
BACK_TO_BACK_TIMEOUT_US = 20_000  # (a): a round trip, never a timeout


def network_text(
    buses: list[CanChannel], timeout_us: int, safe_stop_after: int = 10, drive_map: Path = MIT_MAP
) -> str:
    """A network file: one rawcan bus of MOTORS motors of ``drive_map`` (MIT by default) per channel, 1 kHz."""
    return (
        f"cycle_time_us: 1000\nreceive_timeout_us: {timeout_us}\nsafe_stop_after: {safe_stop_after}\nbuses:\n"
        + "".join(
            f"  - {{name: leg{i}, type: rawcan, {b.network_keys()},\n"
            f"     slaves: [{{name: 'leg{i}_m{{i}}', map: {json.dumps(str(drive_map))}, node_id: 1, count: {MOTORS}}}]}}\n"
            for i, b in enumerate(buses)
        )
    )


def percentiles_us(ns: np.ndarray[Any, np.dtype[np.int64]]) -> tuple[float, float, float]:
    """p50, p99 and max of durations in ns, as µs."""
    p50, p99 = np.percentile(ns, [50, 99])
    return float(p50) / 1e3, float(p99) / 1e3, float(ns.max()) / 1e3


def back_to_back(net_file: Path, exchanges: int, warmup: int = 100) -> dict[str, float]:
    """(a) ``exchange()`` back to back: p50 / p99 (µs) and missed cycles."""
    with open_network(net_file) as net:
        op = net.bring_up()
        for _ in range(warmup):
            op.exchange()
        ns = np.zeros(exchanges, dtype=np.int64)
        missed = 0
        with gc_held():
            for k in range(exchanges):
                res = op.exchange()
                ns[k] = res.exchange_ns
                missed += not res.fresh
    p50, p99, _ = percentiles_us(ns)
    return {"p50_us": p50, "p99_us": p99, "missed": missed}


def paced(net_file: Path, cycles: int) -> dict[str, float]:
    """(b) every bus at 1 kHz on an absolute schedule: exchange percentiles, overruns, misses, safe stops."""
    with open_network(net_file) as net:
        op = net.bring_up()
        ns = np.zeros(cycles, dtype=np.int64)

        def step(k: int) -> None:
            ns[k] = op.exchange().exchange_ns

        timer = run_cycles(step, float(op.cycle_time_us), cycles, timer=CycleTimer(cycles))
        report = run_report(op, timer, float(op.cycle_time_us))
        fresh_at_end = bool(op.result.fresh)
    p50, p99, mx = percentiles_us(ns)
    return {
        "p50_us": p50,
        "p99_us": p99,
        "max_us": mx,
        "overruns": report["overruns"],
        "missed": report["missed"],
        "safe_stops": report["safe_stops"],
        "fresh_at_end": fresh_at_end,
    }


def emulator_frame_us(family: str = "mit", frames: int = 500, batches: int = 5) -> float:
    """An emulator's own work per MIT command frame (µs of this thread's CPU time, so a busy machine's
    preemptions do not count; median of ``batches``), here on a virtual bus (``family`` damiao: the
    Damiao emulator, its motors enabled first)."""
    drive = load_drive_map(FAMILIES[family])
    kind = DamiaoSimulator if family == "damiao" else MitMotorSimulator
    with can.Bus(interface="virtual", channel=f"frame-cost-{time.monotonic_ns()}") as bus:
        sim = kind(bus, [(drive, n) for n in range(1, MOTORS + 1)], dt_s=0.001)
        sim.deliver(can.Message(arbitration_id=1, data=bytes([0xFF] * 7 + [0xFC]), is_extended_id=False))
        msg = can.Message(arbitration_id=1, data=bytes(8), is_extended_id=False)
        for _ in range(100):
            sim.deliver(msg)
        per_batch = []
        for _ in range(batches):
            t0 = time.thread_time()
            for _ in range(frames):
                sim.deliver(msg)  # 1 ms of physics (dt_s: the frame clock) and the reply
            per_batch.append((time.thread_time() - t0) / frames * 1e6)
        return statistics.median(per_batch)


def summary(rounds: list[dict[str, dict[str, Any]]], who: str, scenario: str) -> dict[str, float]:
    """Medians over ``rounds`` of one contender (``who``: a transport, or "damiao/fieldbus_udp") in ``scenario``."""
    rows = [r[who][scenario] for r in rounds]
    out: dict[str, float] = {
        "p50_us": statistics.median(x["p50_us"] for x in rows),
        "p99_us": statistics.median(x["p99_us"] for x in rows),
        "missed": sum(x["missed"] for x in rows),
    }
    if scenario == "paced":
        out["max_us"] = max(x["max_us"] for x in rows)
        out["overruns"] = sum(x["overruns"] for x in rows)
        out["safe_stops"] = sum(x["safe_stops"] for x in rows)
    return out


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--rounds", type=int, default=4)
    p.add_argument("--exchanges", type=int, default=1000, help="(a) back-to-back exchanges per round")
    p.add_argument("--cycles", type=int, default=2000, help="(b) paced 1 kHz cycles per round")
    p.add_argument(
        "--timeout-us", type=int, default=2000, help="(b) receive timeout per bus (µs, default 2000)"
    )
    p.add_argument(
        "--emulators",
        choices=("one", "per-bus"),
        default="one",
        help="one emulator process serving every bus (default) or one process per bus",
    )
    p.add_argument(
        "--families",
        default="mit,damiao",
        help="actuator families, comma-separated: mit (CubeMars AK80-9), damiao (DM-J4310); default both",
    )
    p.add_argument(
        "--transports",
        default=",".join(TRANSPORTS),
        help="comma-separated: udp_multicast, fieldbus_udp (default both; the ratios between them need both)",
    )
    p.add_argument(
        "--rt-priority",
        type=int,
        help="SCHED_FIFO priority of this process, set first: the emulator processes it starts inherit it",
    )
    p.add_argument("--json", action="store_true", help="one JSON object on stdout")
    args = p.parse_args()
    transports = [t.strip() for t in args.transports.split(",") if t.strip()]
    if not transports or any(t not in TRANSPORTS for t in transports):
        p.error(f"--transports: a comma-separated list of {', '.join(TRANSPORTS)}")
    families = [f.strip() for f in args.families.split(",") if f.strip()]
    if not families or any(f not in FAMILIES for f in families):
        p.error(f"--families: a comma-separated list of {', '.join(FAMILIES)}")
    who_all = [_who(f, t) for f in families for t in TRANSPORTS if t in transports]
    both = len(set(transports)) == len(TRANSPORTS)  # the transport ratios need both
    rounds: list[dict[str, dict[str, Any]]] = []
    # before any emulator process runs; the families' batches alternated, so a change of the machine's
    # load between them does not read as a difference of the emulators
    batches: dict[str, list[float]] = {f: [] for f in families}
    for _ in range(5):
        for f in families:
            batches[f].append(emulator_frame_us(f, batches=1))
    frame_us = {f: statistics.median(us) for f, us in batches.items()}
    load = [os.getloadavg()[0]]  # the machine's 1-minute load average, at the start and at the end
    with tempfile.TemporaryDirectory() as tmp, ExitStack() as stack:
        if args.rt_priority is not None:  # first: the emulator processes started from here on inherit it
            stack.enter_context(
                realtime(RtConfig(priority=args.rt_priority), warn=lambda line: print(line, file=sys.stderr))
            )
        files: dict[str, tuple[Path, Path]] = {}
        for f_no, family in enumerate(families):
            drive_map = FAMILIES[family]
            for t, transport in enumerate(TRANSPORTS):
                if transport not in transports:
                    continue
                who = _who(family, transport)
                buses = [udp_bus(20 * f_no + 10 * t + i, interface=transport) for i in range(BUSES)]
                groups = [buses] if args.emulators == "one" else [[b] for b in buses]
                for g in groups:
                    stack.enter_context(
                        can_emulator_process(
                            family, drive_map, range(1, MOTORS + 1), g
                        )  # physics on the clock
                    )
                one, four = (
                    Path(tmp) / f"{family}-{transport}-1.yaml",
                    Path(tmp) / f"{family}-{transport}-4.yaml",
                )
                one.write_text(network_text(buses[:1], BACK_TO_BACK_TIMEOUT_US, drive_map=drive_map))
                four.write_text(network_text(buses, args.timeout_us, drive_map=drive_map))
                files[who] = (one, four)
        shown = RoundProgress(args.rounds)
        for k in range(args.rounds):
            order = who_all if k % 2 == 0 else who_all[::-1]
            got: dict[str, dict[str, Any]] = {who: {} for who in who_all}
            for who in order:
                got[who]["back_to_back"] = back_to_back(files[who][0], args.exchanges)
            for who in order:
                got[who]["paced"] = paced(files[who][1], args.cycles)
            rounds.append(got)
            shown.step()
    load.append(os.getloadavg()[0])
    result = {
        "machine": machine_note(),
        "load_average": load,
        "rt_priority": args.rt_priority,
        "rounds": args.rounds,
        "exchanges": args.exchanges,
        "cycles": args.cycles,
        "timeout_us": args.timeout_us,
        "emulators": args.emulators,
        "families": families,
        "emulator_frame_us": frame_us,
        "summary": {who: {s: summary(rounds, who, s) for s in ("back_to_back", "paced")} for who in who_all},
        # udp_multicast / fieldbus_udp per family (the MIT family under its old key)
        "ratio_p50": {
            s: _ratio(rounds, _who(families[0], "udp_multicast"), _who(families[0], "fieldbus_udp"), s)
            for s in ("back_to_back", "paced")
            if both
        },
        "ratio_transport_p50": {
            family: {
                s: _ratio(rounds, _who(family, "udp_multicast"), _who(family, "fieldbus_udp"), s)
                for s in ("back_to_back", "paced")
            }
            for family in families
            if both
        },
        # the other families against the first (damiao / mit), per transport
        "ratio_family_p50": {
            f"{family}/{families[0]}": {
                t: {
                    s: _ratio(rounds, _who(family, t), _who(families[0], t), s)
                    for s in ("back_to_back", "paced")
                }
                for t in transports
            }
            for family in families[1:]
        },
        # the same, of the p99s: the tail a family's bring-up and framing add
        "ratio_family_p99": {
            f"{family}/{families[0]}": {
                t: {
                    s: _ratio(rounds, _who(family, t), _who(families[0], t), s, "p99_us")
                    for s in ("back_to_back", "paced")
                }
                for t in transports
            }
            for family in families[1:]
        },
        "per_round": rounds,
    }
    if args.json:
        print(json.dumps(result))
        return 0
    print(
        f"# CAN between processes: {' vs '.join(transports)} ({machine_note()}; load average "
        f"{load[0]:.1f} at the start, {load[1]:.1f} at the end; rt priority {args.rt_priority})\n"
    )
    s = result["summary"]
    print(
        f"(a) 1 bus x {MOTORS} motors, exchange() back to back, {args.exchanges} per round, {args.rounds} rounds\n"
    )
    print(
        table(
            ["family / transport", "p50 [µs]", "p99 [µs]", "missed"],
            [
                [
                    who,
                    f"{s[who]['back_to_back']['p50_us']:.0f}",
                    f"{s[who]['back_to_back']['p99_us']:.0f}",
                    str(s[who]["back_to_back"]["missed"]),
                ]
                for who in who_all
            ],
        )
    )
    total = args.cycles * args.rounds
    print(
        f"\n(b) {BUSES} buses x {MOTORS} motors, paced at 1 kHz, receive timeout {args.timeout_us} µs, "
        f"{args.cycles} cycles per round ({total} in all), emulators: "
        f"{'one process for every bus' if args.emulators == 'one' else 'one process per bus'}\n"
    )
    print(
        table(
            [
                "family / transport",
                "p50 [µs]",
                "p99 [µs]",
                "max [µs]",
                "overruns",
                "missed (bus cycles)",
                "safe stops",
            ],
            [
                [
                    who,
                    f"{s[who]['paced']['p50_us']:.0f}",
                    f"{s[who]['paced']['p99_us']:.0f}",
                    f"{s[who]['paced']['max_us']:.0f}",
                    f"{s[who]['paced']['overruns']} / {total}",
                    f"{s[who]['paced']['missed']} / {total * BUSES}",
                    str(s[who]["paced"]["safe_stops"]),
                ]
                for who in who_all
            ],
        )
    )
    print("\nratios of the p50s within a round (median over rounds):")
    for family, r in result["ratio_transport_p50"].items():
        print(
            f"  {family}: udp_multicast / fieldbus_udp {r['back_to_back']:.2f} back to back, {r['paced']:.2f} paced"
        )
    for pair, per in result["ratio_family_p50"].items():
        for t, r in per.items():
            print(f"  {pair} on {t}: {r['back_to_back']:.2f} back to back, {r['paced']:.2f} paced")
    print("ratios of the p99s within a round (median over rounds):")
    for pair, per in result["ratio_family_p99"].items():
        for t, r in per.items():
            print(f"  {pair} on {t}: {r['back_to_back']:.2f} back to back, {r['paced']:.2f} paced")
    for family, us in frame_us.items():
        print(
            f"\nthe {family} emulator's own work: {us:.0f} µs per command frame ({BUSES * MOTORS} frames per "
            f"cycle: {BUSES * MOTORS * us / 1000:.2f} ms of CPU per 1 ms cycle in the emulator processes)"
        )
    return 0


def _who(family: str, transport: str) -> str:
    """A contender's key: the family and the transport, e.g. ``damiao/fieldbus_udp``."""
    return f"{family}/{transport}"


def _ratio(
    rounds: list[dict[str, dict[str, Any]]], top: str, bottom: str, scenario: str, key: str = "p50_us"
) -> float:
    """Median over rounds of ``top`` / ``bottom`` (``key``: p50 by default), each pair from one round."""
    return statistics.median(r[top][scenario][key] / r[bottom][scenario][key] for r in rounds)


if __name__ == "__main__":
    raise SystemExit(main())
