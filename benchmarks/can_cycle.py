"""CANopen cycle: fieldbus's backend against canopen's own PDO API, on the same emulated nodes, in one run.

Both masters drive the same N emulated CiA 402 nodes (``sim_slaves.canopen``,
demo_joint map) on python-can's virtual bus, in alternating rounds:

- **canopen**: a ``RemoteNode`` per node with its PDOs read from the node;
  each cycle writes controlword and target position through
  ``rpdo[n]['...'].raw``, ``rpdo.transmit()`` per RPDO, ``network.sync.transmit()``,
  then waits for every TPDO (on its ``receive_condition``; canopen's
  ``wait_for_reception`` clears the flag first and misses a TPDO that is
  already in) and reads statusword and position through ``.raw``;
- **fieldbus**: ``Operational.exchange()`` (scaled outputs, RPDOs + SYNC, TPDOs
  into the process image, per-node freshness).

- **floor**: no master at all - fieldbus's own prebuilt RPDO and SYNC frames
  sent on a bare python-can bus, then the awaited TPDOs received and thrown
  away: the round trip through the virtual bus and the emulated nodes, which
  neither master can beat.

The virtual bus (threads, a deep copy per receiver) and the emulated nodes
(Python threads sharing the interpreter lock with the master) dominate; the
ratios to the floor say what each master adds. ``--phases``: where one
fieldbus ``exchange()`` goes (:class:`fieldbus.platform.phases.PhaseTimer`),
for a good cycle, a lost one (node 1's TPDOs dropped by the emulator: the
cycle waits the receive timeout) and the one after. tracemalloc: net blocks
per ``exchange()``.

    python benchmarks/can_cycle.py [--axes 6] [--rounds 4] [--seconds 2] [--transport virtual|udp] [--phases N]

``--transport udp`` runs the emulated nodes in their own process on python-can's
udp_multicast interface (needs msgpack): the masters no longer share the
interpreter lock with the nodes, so the ratio is the masters' own.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import sys
import tempfile
import time
from collections.abc import Callable
from contextlib import ExitStack
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import can
import canopen

from benchmarks._common import RoundProgress, machine_note, table
from fieldbus.commands.demo import DEMO_MAP
from fieldbus.core.pdo import load_drive_map
from fieldbus.network import open_network
from fieldbus.platform.allocs import net_blocks
from fieldbus.platform.phases import PHASES, PhaseTimer
from fieldbus.platform.rt import RtConfig, realtime
from sim_slaves.can_process import CanChannel, can_emulator_process, udp_bus
from sim_slaves.canopen import CanopenSimulator
from sim_slaves.canopen.eds import to_canopen_od

TIMEOUT_S = 0.02


def _rate(step: Callable[[], object], seconds: float) -> float:
    """Cycles per second from the median cycle of ``seconds`` worth of them (a cycle descheduled by the
    rest of a busy machine, or one that waited the timeout, moves a mean but not the median)."""
    times = []
    t_end = time.perf_counter() + seconds
    while True:
        t0 = time.perf_counter()
        step()
        t1 = time.perf_counter()
        times.append(t1 - t0)
        if t1 >= t_end:
            break
    return 1.0 / statistics.median(times)


def fieldbus_round(net_file: Path, seconds: float) -> tuple[float, int]:
    with open_network(net_file) as net:
        op = net.bring_up()
        img = op["joints"]
        target, position = img.outputs["target_position"], img.inputs["position_actual_value"]
        misses = 0

        def step() -> None:
            nonlocal misses
            target[:] = position
            if not op.exchange().fresh:
                misses += 1

        for _ in range(20):
            step()
        misses = 0
        return _rate(step, seconds), misses


def floor_round(net_file: Path, seconds: float) -> tuple[float, int]:
    """The bus and the nodes alone: fieldbus's RPDO and SYNC frames sent on its own python-can bus (the
    nodes brought up by fieldbus), the awaited TPDOs taken off it, nothing copied, decoded or judged."""
    with open_network(net_file) as net:
        net.bring_up()
        backend: Any = net.backends[0]
        frames = [msg for msg, _, _ in backend._rpdos] + [backend._sync]
        awaited = {cob for cob, hit in backend._tpdos.items() if hit[2] >= 0}
        bus = backend._bus
        misses = 0

        def step() -> None:
            nonlocal misses
            for msg in frames:
                bus.send(msg)
            got = 0
            deadline = time.perf_counter() + TIMEOUT_S
            while got < len(awaited):
                msg = bus.recv(timeout=max(0.0, deadline - time.perf_counter()))
                if msg is None:
                    misses += 1
                    return
                got += msg.arbitration_id in awaited

        for _ in range(20):
            step()
        misses = 0
        return _rate(step, seconds), misses


def phase_breakdown(net_file: Path, sim: Any, losses: int) -> dict[str, dict[str, float]]:
    """Median µs per phase of fieldbus's exchange(): good cycles, lost ones (node 1's TPDOs dropped), the next."""
    kinds: dict[str, list[list[int]]] = {k: [[] for _ in PHASES] for k in ("good", "lost", "after")}
    totals: dict[str, list[int]] = {k: [] for k in kinds}
    with open_network(net_file) as net:
        op = net.bring_up()
        timer = PhaseTimer()
        op.phases = timer
        for _ in range(20):
            op.exchange()
        for _ in range(losses):
            for kind in ("good", "lost", "after"):
                if kind == "lost":
                    sim.drop_tpdos(1, 2)
                res = op.exchange()
                if (kind == "lost") == res.fresh:
                    continue  # not the kind of cycle asked for (a late TPDO on a busy machine)
                totals[kind].append(res.exchange_ns)
                for i, ns in enumerate(timer.last_ns):
                    kinds[kind][i].append(ns)
            for _ in range(3):
                op.exchange()
    return {
        k: {
            "exchange": statistics.median(totals[k]) / 1e3,
            **{name: statistics.median(v[i]) / 1e3 for i, name in enumerate(PHASES)},
        }
        for k, v in kinds.items()
        if totals[k]
    }


def canopen_round(bus_kwargs: dict[str, Any], ods: dict[int, Any], seconds: float) -> tuple[float, int]:
    network = canopen.Network()  # type: ignore[no-untyped-call]
    network.connect(**bus_kwargs)
    try:
        nodes = []
        for node_id in sorted(ods):
            node = canopen.RemoteNode(node_id, to_canopen_od(ods[node_id]))
            network.add_node(node)
            node.tpdo.read(from_od=False)
            node.rpdo.read(from_od=False)
            nodes.append(node)
        for node in nodes:
            node.nmt.state = "OPERATIONAL"
        time.sleep(0.05)
        rx = [(n.rpdo[1], n.rpdo[1]["controlword"], n.rpdo[1]["target_position"], n.rpdo[2]) for n in nodes]
        tx = [
            (n.tpdo[1], n.tpdo[1]["statusword"], n.tpdo[1]["position_actual_value"], n.tpdo[2]) for n in nodes
        ]
        misses = 0

        def step() -> None:
            nonlocal misses
            for (r1, cw, tp, r2), (_, _, pos, _) in zip(rx, tx, strict=True):
                cw.raw = 0x0F
                tp.raw = pos.raw
                r1.transmit()
                r2.transmit()
            for t1, _, _, t2 in tx:
                t1.is_received = t2.is_received = False
            network.sync.transmit()
            for t1, sw, pos, t2 in tx:
                # wait_for_reception() clears the flag first and would miss a TPDO already in: wait by hand
                for t in (t1, t2):
                    with t.receive_condition:
                        if not t.is_received:
                            t.receive_condition.wait(TIMEOUT_S)
                if not (t1.is_received and t2.is_received):
                    misses += 1
                _ = sw.raw, pos.raw

        for _ in range(20):
            step()
        misses = 0
        rate = _rate(step, seconds)
        for node in nodes:
            node.nmt.state = "PRE-OPERATIONAL"
        return rate, misses
    finally:
        network.disconnect()


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--axes", type=int, default=6)
    p.add_argument("--rounds", type=int, default=4)
    p.add_argument("--seconds", type=float, default=2.0)
    p.add_argument("--alloc-cycles", type=int, default=2000)
    p.add_argument(
        "--transport",
        choices=("virtual", "udp"),
        default="virtual",
        help="virtual: nodes in this process; udp: nodes in their own process over udp_multicast",
    )
    p.add_argument("--phases", type=int, default=0, help="lost cycles for the phase breakdown (virtual bus)")
    p.add_argument(
        "--rt-priority",
        type=int,
        help="SCHED_FIFO priority of this process's threads (set first: the nodes' and python-can's "
        "threads, started later, inherit it)",
    )
    args = p.parse_args()
    where = f"{args.transport} bus" + (", nodes in another process" if args.transport == "udp" else "")
    print(
        f"# CANopen cycle benchmark, {args.axes} CiA 402 nodes, {where}, rt priority {args.rt_priority}, "
        f"load {os.getloadavg()[0]:.1f} ({machine_note()})\n"
    )
    drive = load_drive_map(DEMO_MAP)
    ids = list(range(1, args.axes + 1))
    with tempfile.TemporaryDirectory() as tmp, ExitStack() as stack:
        if args.rt_priority is not None:  # first: every thread started from here on inherits it
            rt = realtime(RtConfig(priority=args.rt_priority), warn=lambda line: print(line, file=sys.stderr))
            stack.enter_context(rt)
        if args.transport == "virtual":
            channel = CanChannel("virtual", f"bench-can-{time.monotonic_ns()}")
            bus = stack.enter_context(can.Bus(interface="virtual", channel=channel.channel))
            sim = stack.enter_context(CanopenSimulator(bus, [(drive, n) for n in ids]))
        else:
            channel = udp_bus()
            stack.enter_context(can_emulator_process("canopen", DEMO_MAP, ids, channel))
            sim = None
        # the nodes' object dictionaries, for canopen's RemoteNode (built from the same map as the emulator's)
        with can.Bus(interface="virtual", channel=f"od-{time.monotonic_ns()}") as spare:
            ods = {n: CanopenSimulator(spare, [(drive, n)]).node(n).od for n in ids}
        bus_kwargs = {"interface": channel.interface, "channel": channel.channel, **dict(channel.options)}
        net_file = Path(tmp) / "can.yaml"
        net_file.write_text(
            f"cycle_time_us: 1000\nreceive_timeout_us: {int(TIMEOUT_S * 1e6)}\nbuses:\n"
            f"  - {{name: joints, type: canopen, {channel.network_keys()},\n"
            f"     slaves: [{{name: 'j{{i}}', map: {json.dumps(str(DEMO_MAP))}, node_id: 1, count: {args.axes}}}]}}\n"
        )
        rounds: list[dict[str, float]] = []
        misses = []
        shown = RoundProgress(args.rounds)
        contenders = ("canopen", "fieldbus", "floor")
        for k in range(args.rounds):
            order = contenders[k % 3 :] + contenders[: k % 3]
            got = {}
            for who in order:
                got[who] = (
                    canopen_round(bus_kwargs, ods, args.seconds)
                    if who == "canopen"
                    else fieldbus_round(net_file, args.seconds)
                    if who == "fieldbus"
                    else floor_round(net_file, args.seconds)
                )
            rounds.append({who: rate for who, (rate, _) in got.items()})
            misses.append(tuple(got[who][1] for who in contenders))
            shown.step()
        phases = phase_breakdown(net_file, sim, args.phases) if args.phases and sim is not None else {}
        with open_network(net_file) as net:
            op = net.bring_up()
            blocks = net_blocks(op.exchange, args.alloc_cycles, warmup=200)
        if sim is not None:
            assert not sim.errors, sim.errors

    def med(who: str) -> float:
        return statistics.median(r[who] for r in rounds)

    def ratio(a: str, b: str) -> float:  # within each round, then the median
        return statistics.median(r[a] / r[b] for r in rounds)

    print(
        table(
            [
                "nodes",
                "canopen PDO API [cycles/s]",
                "fieldbus [cycles/s]",
                "floor [cycles/s]",
                "fieldbus/canopen",
                "canopen/floor",
                "fieldbus/floor",
                "net blocks/cycle",
            ],
            [
                [
                    str(args.axes),
                    f"{med('canopen'):,.0f}",
                    f"{med('fieldbus'):,.0f}",
                    f"{med('floor'):,.0f}",
                    f"{ratio('fieldbus', 'canopen'):.2f}",
                    f"{ratio('canopen', 'floor'):.2f}",
                    f"{ratio('fieldbus', 'floor'):.2f}",
                    f"{blocks / args.alloc_cycles:.4f}",
                ]
            ],
        )
    )
    print(f"\nmissed cycles per round ({', '.join(contenders)}): {misses}")
    if phases:
        print("\nfieldbus exchange(), median us per phase:\n")
        print(
            table(
                ["cycle", "exchange", *PHASES],
                [[k, *(f"{v:.1f}" for v in row.values())] for k, row in phases.items()],
            )
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
