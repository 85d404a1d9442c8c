"""Full cycle rate of fieldbus against pysoem's bare send/receive loop, on the same emulator, in one run.

Over veth (root): one emulator process (``sim_slaves.ethercat``, N CiA 402
drives of ``fieldbus/data/demo_joint.yaml``) serves both contenders in
alternating rounds:

- **bare pysoem**: ``slave.output = <prepacked bytes>`` per slave,
  ``send_processdata``, ``receive_processdata``, ``slave.input`` per slave;
- **fieldbus**: ``Operational.exchange()`` with scaled outputs written
  (``target_position`` in rad) and scaled inputs decoded, the WKC policy
  judged - the whole cycle a controller calls.

Each round brings one master up, runs a batch of cycles as fast as the
round trip allows, and closes it; the ratio fieldbus/bare is taken within
each pair of rounds (target: at least 0.8). In-process, the ``sim`` backend's
``exchange()`` is compared with a bare LRW through the ESC chain in short
alternating batches, by wall clock and by this thread's CPU time (the second
stays readable on a machine busy with other work; target: at least 0.8).

tracemalloc: net allocated blocks per cycle over 10,000 ``exchange()`` calls
(target 0), for the sim backend and, with root, over veth.

``--before-src DIR``: a second checkout (``git worktree add --detach /tmp/before <commit>``;
build its C codec there too, ``python setup.py build_ext --inplace``, or it runs
numpy-only and the comparison says so). Then each round also brings up this
checkout and that one, each in a child process (:mod:`benchmarks.cycle_round`)
in a shuffled order, over veth beside bare pysoem and in-process on the sim
backend; ratios after/before are taken within each round. Over veth it also
times the part of the EtherCAT cycle that moves process data between the
images and SOEM's IO map, in this process on one bring-up: one copy per
group through the IO map view against pysoem's per-slave ``bytes``
(``iomap="bytes"``, the path before), alternating.

``--in-process``: instead, the ethercat backend on its in-process transport
(``transport="in-process"``) against the sim backend on the same network, one
process, alternating rounds, ratio within each round.

``--record``: instead, the cost of recording (``Operational.record``, docs/observability.md).
One in-process sim network runs unpaced in alternating rounds with recording on
(a fresh recorder per round, closed after it) and off; the ratio on/off is taken
within each pair of rounds (target: at least 0.9), and net blocks per cycle are
counted with recording on.

    python benchmarks/cycle.py [--axes 12] [--rounds 5] [--seconds 2] [--record] [--before-src DIR] [--in-process]
"""

from __future__ import annotations

import argparse
import json
import os
import random
import statistics
import struct
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks._common import RoundProgress, machine_note, table
from fieldbus.commands.demo import DEMO_MAP
from fieldbus.network import Operational, open_network
from fieldbus.platform import capabilities
from fieldbus.platform.allocs import net_blocks

RECEIVE_TIMEOUT_US = 10_000


def _net_file(tmp: Path, iface: str, axes: int) -> Path:
    f = tmp / "bench.yaml"
    f.write_text(
        f"cycle_time_us: 1000\nreceive_timeout_us: {RECEIVE_TIMEOUT_US}\nbuses:\n"
        f"  - {{name: joints, type: ethercat, interface: {iface},\n"
        f"     slaves: [{{name: 'j{{i}}', map: {json.dumps(str(DEMO_MAP))}, count: {axes}}}]}}\n"
    )
    return f


def _rate(step: Callable[[], object], seconds: float) -> float:
    """Cycles per second of ``step`` over about ``seconds``."""
    n = 0
    t0 = time.perf_counter()
    end = t0 + seconds
    while True:
        for _ in range(50):
            step()
        n += 50
        if time.perf_counter() >= end:
            return n / (time.perf_counter() - t0)


def fieldbus_round(net_file: Path, seconds: float, backend: str | None = None) -> tuple[float, int]:
    """(cycles/s of exchange(), cycles not fresh) for one bring-up of the network."""
    with open_network(net_file, backend=backend) as net:
        op = net.bring_up()
        img = op["joints"]
        target = img.outputs["target_position"]
        position = img.inputs["position_actual_value"]
        bad = 0

        def step() -> None:
            nonlocal bad
            target[:] = position  # a controller's write (scaled, rad) from the last inputs
            if not op.exchange().fresh:
                bad += 1

        for _ in range(200):
            step()
        bad = 0
        return _rate(step, seconds), bad


def bare_round(iface: str, axes: int, seconds: float) -> tuple[float, int]:
    """(cycles/s, cycles with a wrong WKC) of pysoem's bare loop on the same emulator."""
    import pysoem

    m = pysoem.Master()
    m.open(iface)
    try:
        if m.config_init() != axes:
            raise RuntimeError("bare pysoem: slave count differs")
        m.config_map()
        m.state = pysoem.OP_STATE
        m.write_state()
        slaves = list(m.slaves)
        out = [struct.pack("<HiHb", 0, 0, 0, 8)[: len(s.output)].ljust(len(s.output), b"\0") for s in slaves]
        for _ in range(2000):
            m.send_processdata()
            m.receive_processdata(RECEIVE_TIMEOUT_US)
            if m.state_check(pysoem.OP_STATE, 1000) == pysoem.OP_STATE:
                break
        expected = m.expected_wkc
        bad = 0

        def step() -> None:
            nonlocal bad
            for s, o in zip(slaves, out, strict=True):
                s.output = o
            m.send_processdata()
            if m.receive_processdata(RECEIVE_TIMEOUT_US) != expected:
                bad += 1
            for s in slaves:
                _ = s.input

        for _ in range(200):
            step()
        bad = 0
        return _rate(step, seconds), bad
    finally:
        m.state = pysoem.INIT_STATE
        m.write_state()
        m.close()


BATCH_S = 0.01  # in-process: one contender's batch, well below the emulated slaves' watchdog (100 ms)


def in_process_pairs(
    ours: Callable[[], object], bare: Callable[[], object], rounds: int, seconds: float
) -> tuple[list[tuple[float, float]], list[tuple[float, float]]]:
    """Per round (fieldbus, bare) cycles/s, by wall clock and by this thread's CPU time, over batches of
    :data:`BATCH_S`, alternating: a busy machine's slow moments hit both contenders, and neither chain
    goes without frames long enough for its slaves' process-data watchdog to stop them (rounds of a
    second each did: the fieldbus contender then paid for a miss, a safe stop and a recovery at every
    round's start, the bare one ran stopped drives). Nothing here waits, so the CPU time is the work
    itself (what other processes take from this one is not in it)."""
    wall: list[tuple[float, float]] = []
    cpu: list[tuple[float, float]] = []
    batches = max(1, round(seconds / 2 / BATCH_S))
    for _ in range(rounds):
        spent = {"ours": [0, 0, 0], "bare": [0, 0, 0]}  # cycles, wall ns, CPU ns
        for k in range(2 * batches):
            who = ("ours", "bare")[(k + k // 2) % 2]  # ours, bare, bare, ours, ours, bare, ...
            step = ours if who == "ours" else bare
            w0, c0 = time.perf_counter_ns(), time.thread_time_ns()
            n = 0
            end = w0 + int(BATCH_S * 1e9)
            while True:
                for _ in range(10):
                    step()
                n += 10
                if time.perf_counter_ns() >= end:
                    break
            got = spent[who]
            got[0] += n
            got[1] += time.perf_counter_ns() - w0
            got[2] += time.thread_time_ns() - c0
        (no, wo, co), (nb, wb, cb) = spent["ours"], spent["bare"]
        wall.append((no / wo * 1e9, nb / wb * 1e9))
        cpu.append((no / co * 1e9, nb / cb * 1e9))
    return wall, cpu


class CycleTime:
    """The emulated chain's time: the wall clock until :meth:`start`, then ``cycle_ns`` more per
    :meth:`tick` - every cycle emulates one bus cycle whatever the machine's load, and no gap (a
    batch of the other contender, this process preempted) trips the slaves' watchdogs."""

    def __init__(self, cycle_ns: int = 1_000_000) -> None:
        self.cycle_ns = cycle_ns
        self.t: int | None = None

    def __call__(self) -> int:
        return time.monotonic_ns() if self.t is None else self.t

    def start(self) -> None:
        self.t = time.monotonic_ns()

    def tick(self) -> int:
        assert self.t is not None
        self.t += self.cycle_ns
        return self.t


def sim_bare_step(axes: int, clock: CycleTime | None = None) -> Callable[[], object]:
    """One LRW through an in-process ESC chain in OP, with no master logic around it (``clock``: its
    time, one cycle per LRW; default the wall clock)."""
    from fieldbus.core.ecat import decode_frame
    from fieldbus.core.pdo import load_drive_map
    from sim_slaves.ethercat.bringup import bring_up
    from sim_slaves.ethercat.chain import EscChain

    chain = EscChain.from_maps([load_drive_map(DEMO_MAP)] * axes)
    if clock is not None:
        clock.start()
    now = clock if clock is not None else time.monotonic_ns
    # brought up on the time its cycles run on: at time 0 the first LRW, a "second" later, found the
    # process-data watchdog expired and every slave fell back to SAFE-OP (outputs ignored, drives idle)
    plan = bring_up(chain, now())
    frame = bytearray(plan.lrw())
    probe = bytearray(frame)
    chain.process_into(probe, len(probe), clock.tick() if clock is not None else now())
    got = decode_frame(probe).datagrams[0].wkc
    if got != plan.expected_wkc:
        raise RuntimeError(f"bare LRW: WKC {got}, expected {plan.expected_wkc} (slaves not in OP)")

    if clock is not None:
        tick = clock.tick

        def cycle() -> object:
            return chain.process_into(frame, len(frame), tick())

        return cycle

    def step() -> object:
        return chain.process_into(frame, len(frame), time.monotonic_ns())

    return step


def sim_exchange_step(net_file: Path, clock: CycleTime | None = None) -> tuple[Callable[[], object], Any]:
    """``exchange()`` of the sim backend with a controller's write (``clock``: the chain's time, one
    cycle per exchange from the end of the bring-up; default the wall clock)."""
    net = open_network(net_file, backend="sim", **({"clock": clock} if clock is not None else {}))
    op = net.bring_up()
    img = op["joints"]
    target, position = img.outputs["target_position"], img.inputs["position_actual_value"]

    if clock is not None:
        clock.start()
        tick = clock.tick

        def cycle() -> object:
            tick()
            target[:] = position
            return op.exchange()

        return cycle, net

    def step() -> object:
        target[:] = position
        return op.exchange()

    return step, net


def record_rounds(
    net_file: Path, tmp: Path, rounds: int, seconds: float, alloc_cycles: int
) -> dict[str, Any]:
    """Recording on against off on one sim network: per-round rates (cycles/s) and net blocks per cycle."""
    step, net = sim_exchange_step(net_file)
    try:
        op = net._phase
        assert isinstance(op, Operational)
        for _ in range(500):
            step()
        on: list[float] = []
        off: list[float] = []
        shown = RoundProgress(rounds)
        for k in range(rounds):
            for who in ("on", "off") if k % 2 == 0 else ("off", "on"):
                if who == "off":
                    off.append(_rate(step, seconds))
                    continue
                rec = op.record(tmp / "bench.mcap")
                for _ in range(200):
                    step()
                on.append(_rate(step, seconds))
                rec.close()
                if rec.error is not None or rec.dropped_blocks:
                    raise RuntimeError(f"recording failed: {rec.error}, {rec.dropped_blocks} blocks dropped")
            shown.step()
        # blocks larger than the count: the writer stays idle, what is counted is the cycle's copy (the
        # emulated drives allocate now and then in exchange(): the same count with recording off beside it)
        blocks_off = net_blocks(step, alloc_cycles)
        rec = op.record(tmp / "alloc.mcap", block_cycles=alloc_cycles + 2000, ring_blocks=2)
        blocks = net_blocks(step, alloc_cycles)
        rec.close()
    finally:
        net.close()
    return {"on": on, "off": off, "blocks": blocks, "blocks_off": blocks_off}


def print_record(axes: int, r: dict[str, Any], alloc_cycles: int) -> None:
    ratios = [a / b for a, b in zip(r["on"], r["off"], strict=True)]
    q1, q3 = np.percentile(ratios, [25, 75])
    med = statistics.median(ratios)
    print(
        table(
            [
                "path",
                "off [cycles/s]",
                "on [cycles/s]",
                "on/off (IQR)",
                "min-max",
                "net blocks/cycle (off/on)",
            ],
            [
                [
                    f"in-process sim, {axes} axes, unpaced",
                    f"{statistics.median(r['off']):,.0f}",
                    f"{statistics.median(r['on']):,.0f}",
                    f"{med:.3f} ({q1:.3f}-{q3:.3f})",
                    f"{min(ratios):.3f}-{max(ratios):.3f}",
                    f"{r['blocks_off'] / alloc_cycles:.4f} / {r['blocks'] / alloc_cycles:.4f}",
                ]
            ],
        )
    )
    print(f"\nper-round on/off: {', '.join(f'{x:.3f}' for x in ratios)}")
    print(f"[{'met' if med >= 0.9 else 'MISSED'}] recording on >= 0.9x the rate with it off: {med:.3f}")


def child_round(src: Path, net_file: Path, seconds: float, backend: str | None = None) -> dict[str, Any]:
    """One round of ``benchmarks/cycle_round.py`` with ``src``'s fieldbus, in a child process."""
    cmd = [sys.executable, str(Path(__file__).with_name("cycle_round.py")), "--src", str(src)]
    cmd += ["--net", str(net_file), "--seconds", str(seconds)] + (["--backend", backend] if backend else [])
    env = {**os.environ, "PYTHONPATH": str(src)}
    for _ in range(3):  # a bring-up that failed on a loaded machine (no slave found in time) is tried again
        out = subprocess.run(cmd, env=env, capture_output=True, text=True, check=False, timeout=300)
        if out.returncode == 0:
            break
    else:
        raise RuntimeError(f"round with {src} failed 3 times: {out.stderr.strip()[-2000:]}")
    got: dict[str, Any] = json.loads(out.stdout.strip().splitlines()[-1])
    return got


def before_after(
    here: Path,
    before: Path,
    net_file: Path,
    rounds: int,
    seconds: float,
    backend: str | None,
    bare: Any = None,
) -> dict[str, list[float]]:
    """Per round: this checkout and ``before`` (and ``bare()``, a rate, when given), in a shuffled order."""
    rates: dict[str, list[float]] = {"after": [], "before": [], "bare": []}
    codec: dict[str, bool] = {}
    shown = RoundProgress(rounds)
    for _ in range(rounds):
        order = ["after", "before"] + (["bare"] if bare is not None else [])
        random.shuffle(order)
        for who in order:
            if who == "bare":
                rates["bare"].append(bare())
                continue
            got = child_round(here if who == "after" else before, net_file, seconds, backend)
            rates[who].append(got["rate"])
            codec[who] = got["codec"]
        shown.step()
    if not all(codec.values()):
        print(
            f"NOTE: C codec missing in {[k for k, v in codec.items() if not v]} (numpy path): not comparable"
        )
    return rates


def copy_rounds(net_file: Path, rounds: int, seconds: float) -> dict[str, list[float]]:
    """Process-data copies of the EtherCAT cycle alone (12 slaves): IO map view vs per-slave ``bytes``."""
    import numpy as np

    rates: dict[str, list[float]] = {"view": [], "bytes": []}
    with open_network(net_file, backend="ethercat") as net:
        net.bring_up()
        b: Any = net.backends[0]
        if b.iomap is None:
            raise RuntimeError("the IO map view was not proven on this pysoem: nothing to compare")
        out_views, in_views, out_copies, in_copies = b._out_views, b._in_views, b._out_copies, b._in_copies

        def per_slave() -> None:  # the cycle's copies before (and with iomap="bytes")
            for s, mv in out_views:
                s.output = bytes(mv)
            for s, mv in in_views:
                mv[:] = s.input

        def view() -> None:
            for dst, src in out_copies:
                np.copyto(dst, src)
            for dst, src in in_copies:
                np.copyto(dst, src)

        for k in range(rounds):
            for who in ("view", "bytes") if k % 2 == 0 else ("bytes", "view"):
                rates[who].append(_rate(view if who == "view" else per_slave, seconds / 4))
    return rates


def print_before_after(results: dict[str, dict[str, list[float]]]) -> None:
    rows = []
    for label, r in results.items():
        a, b = r.get("after") or r["view"], r.get("before") or r["bytes"]
        ratio = [x / y for x, y in zip(a, b, strict=True)]
        q1, q3 = np.percentile(ratio, [25, 75])
        bare = r.get("bare") or []
        vs_bare = (
            f"{statistics.median(x / y for x, y in zip(a, bare, strict=True)):.2f} / "
            f"{statistics.median(x / y for x, y in zip(b, bare, strict=True)):.2f}"
            if bare
            else "-"
        )
        rows.append(
            [
                label,
                f"{statistics.median(b):,.0f}",
                f"{statistics.median(a):,.0f}",
                f"{statistics.median(ratio):.3f} ({q1:.3f}-{q3:.3f})",
                f"{min(ratio):.3f}-{max(ratio):.3f}",
                vs_bare,
            ]
        )
    print(
        table(
            ["path", "before [/s]", "after [/s]", "after/before (IQR)", "min-max", "after / before vs bare"],
            rows,
        )
    )


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--axes", type=int, default=12)
    p.add_argument("--rounds", type=int, default=5)
    p.add_argument("--seconds", type=float, default=2.0, help="per round and contender")
    p.add_argument("--alloc-cycles", type=int, default=10_000)
    p.add_argument("--record", action="store_true", help="recording on against off (sim, in-process) only")
    p.add_argument("--before-src", type=Path, help="a second checkout, timed alternately with this one")
    p.add_argument("--in-process", action="store_true", help="ethercat backend in-process against sim only")
    args = p.parse_args()
    print(f"# cycle benchmark, {args.axes} CiA 402 axes ({machine_note()})\n")
    results: dict[str, Any] = {}
    with tempfile.TemporaryDirectory() as tmp_s:
        tmp = Path(tmp_s)
        if args.record:
            costs = record_rounds(
                _net_file(tmp, "sim", args.axes), tmp, args.rounds, args.seconds, args.alloc_cycles
            )
            print_record(args.axes, costs, args.alloc_cycles)
            return 0
        if args.before_src is not None:
            return run_before_after(args, tmp)
        if args.in_process:
            return run_in_process(args, tmp)
        # -- in-process: sim backend vs a bare LRW through the chain --
        sim_file = _net_file(tmp, "sim", args.axes)
        bare = sim_bare_step(args.axes, CycleTime())  # both chains on a time of their own: 1 ms a cycle
        step, net = sim_exchange_step(sim_file, CycleTime())
        missed = 0

        def ours() -> object:
            nonlocal missed
            res = step()
            missed += not res.fresh  # type: ignore[attr-defined]
            return res

        try:
            for _ in range(200):
                ours()
                bare()
            missed = 0
            pairs, cpu_pairs = in_process_pairs(ours, bare, args.rounds, args.seconds)
            results["sim_missed"] = missed
            blocks = net_blocks(step, args.alloc_cycles)
        finally:
            net.close()
        results["sim"] = (pairs, blocks)
        results["sim_cpu"] = (cpu_pairs, blocks)
        # -- over veth: fieldbus vs bare pysoem on one emulator --
        if not capabilities.missing(capabilities.CAP_NET_ADMIN, capabilities.CAP_NET_RAW):
            from sim_slaves.ethercat.veth import emulated_segment

            with emulated_segment([DEMO_MAP], count=args.axes, workdir=tmp) as emu:
                net_file = _net_file(tmp, emu.iface, args.axes)
                pairs, bads = [], []
                for k in range(args.rounds):
                    order = ("bare", "fieldbus") if k % 2 == 0 else ("fieldbus", "bare")
                    got: dict[str, tuple[float, int]] = {}
                    for who in order:
                        got[who] = (
                            bare_round(emu.iface, args.axes, args.seconds)
                            if who == "bare"
                            else fieldbus_round(net_file, args.seconds)
                        )
                    pairs.append((got["fieldbus"][0], got["bare"][0]))
                    bads.append((got["fieldbus"][1], got["bare"][1]))
                with open_network(net_file) as vnet:
                    vop = vnet.bring_up()
                    vblocks = net_blocks(vop.exchange, args.alloc_cycles)
            results["veth"] = (pairs, vblocks)
            results["veth_bad"] = bads
    rows = []
    for name, label in (
        ("sim", "in-process (sim backend vs bare LRW)"),
        ("sim_cpu", "in-process, thread CPU time (the same batches)"),
        ("veth", "veth (fieldbus vs bare pysoem)"),
    ):
        if name not in results:
            rows.append([label, "-", "-", "-", "(needs root)"])
            continue
        pairs, blocks = results[name]
        f = statistics.median(x for x, _ in pairs)
        b = statistics.median(y for _, y in pairs)
        r = [x / y for x, y in pairs]
        q1, q3 = np.percentile(r, [25, 75])
        rows.append(
            [
                label,
                f"{b:,.0f}",
                f"{f:,.0f}",
                f"{statistics.median(r):.2f} ({q1:.2f}-{q3:.2f})",
                f"{blocks / args.alloc_cycles:.4f}",
            ]
        )
    print(
        table(
            ["path", "bare [cycles/s]", "fieldbus [cycles/s]", "ratio (IQR)", "net blocks/cycle"],
            rows,
        )
    )
    if "sim_missed" in results:
        print(f"\nin-process: cycles not fresh while timed: {results['sim_missed']}")
    if "veth_bad" in results:
        print(f"\ncycles not fresh / wrong WKC per round (fieldbus, bare): {results['veth_bad']}")
    return 0


def run_in_process(args: argparse.Namespace, tmp: Path) -> int:
    """``--in-process``: ``exchange()`` of the ethercat backend on the in-process transport against the sim
    backend, both up at once on the same network file, alternating rounds (cycles/s, ratio per round)."""
    net_file = _net_file(tmp, "none0", args.axes)
    steps: dict[str, Callable[[], object]] = {}
    with (
        open_network(net_file, backend="sim") as sim,
        open_network(net_file, backend="ethercat", transport="in-process") as ecat,
    ):
        for name, net in (("sim", sim), ("ethercat in-process", ecat)):
            op = net.bring_up()
            steps[name] = op.exchange
        rates: dict[str, list[float]] = {k: [] for k in steps}
        for k in range(args.rounds):
            for name in list(steps) if k % 2 == 0 else list(steps)[::-1]:
                rates[name].append(_rate(steps[name], args.seconds))
    ratio = [e / s for e, s in zip(rates["ethercat in-process"], rates["sim"], strict=True)]
    q1, q3 = np.percentile(ratio, [25, 75])
    print(
        table(
            ["path", "sim [cycles/s]", "ethercat in-process [cycles/s]", "ratio (IQR)", "min-max"],
            [
                [
                    f"{args.axes} axes, unpaced",
                    f"{statistics.median(rates['sim']):,.0f}",
                    f"{statistics.median(rates['ethercat in-process']):,.0f}",
                    f"{statistics.median(ratio):.2f} ({q1:.2f}-{q3:.2f})",
                    f"{min(ratio):.2f}-{max(ratio):.2f}",
                ]
            ],
        )
    )
    return 0


def run_before_after(args: argparse.Namespace, tmp: Path) -> int:
    """``--before-src``: this checkout against ``args.before_src`` in one run (see the module)."""
    here, before = Path(__file__).resolve().parents[1], args.before_src.resolve()
    print(f"after: {here}\nbefore: {before}\n")
    results: dict[str, dict[str, list[float]]] = {}
    bare = sim_bare_step(args.axes)
    results["in-process sim backend"] = before_after(
        here, before, _net_file(tmp, "sim", args.axes), args.rounds, args.seconds, "sim",
        lambda: _rate(bare, args.seconds),
    )  # fmt: skip
    if not capabilities.missing(capabilities.CAP_NET_ADMIN, capabilities.CAP_NET_RAW):
        import pysoem

        from sim_slaves.ethercat.veth import emulated_segment

        pysoem.settings.timeouts.ret = max(int(pysoem.settings.timeouts.ret), 20_000)  # as cycle_round.py
        with emulated_segment([DEMO_MAP], count=args.axes, workdir=tmp) as emu:
            net_file = _net_file(tmp, emu.iface, args.axes)
            results["veth, ethercat backend"] = before_after(
                here, before, net_file, args.rounds, args.seconds, None,
                lambda: bare_round(emu.iface, args.axes, args.seconds)[0],
            )  # fmt: skip
            results["veth, process-data copies only (view vs bytes)"] = copy_rounds(
                net_file, args.rounds, args.seconds
            )
    else:
        print("(veth rounds need root)")
    print_before_after(results)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
