"""What reading the ESC error counters in OP costs a cycle: ``exchange()`` with and without ``error_counters``.

    python benchmarks/error_counters.py [--cycles 3000] [--slaves 12] [--json]

The real pysoem master over veth (root), the emulator (``python -m
sim_slaves.ethercat``, no drive models) on the peer end; the two settings run
side by side in one process, in alternating blocks of 500 cycles, so a loaded
machine weighs on both alike. Reported: median and 99th percentile of
``CycleResult.exchange_ns`` per setting and their ratio, and the watch's
datagrams per cycle (at most one: one FPRD of 20 or 2 data bytes).
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import tempfile
from contextlib import ExitStack
from pathlib import Path
from typing import Any

import fieldbus

BLOCK = 500


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--cycles", type=int, default=3000)
    p.add_argument("--slaves", type=int, default=12)
    p.add_argument("--json", action="store_true")
    args = p.parse_args()
    from fieldbus.testing import emulate

    generic = fieldbus.PDO_MAPS / "generic_cia402.yaml"
    with tempfile.TemporaryDirectory() as tmp, ExitStack() as stack:
        net = Path(tmp) / "line.yaml"
        net.write_text(
            "cycle_time_us: 1000\nreceive_timeout_us: 20000\nbuses:\n"
            f"  - {{name: arm, type: ethercat, interface: eth0,\n"
            f"     slaves: [{{name: 'j{{i}}', map: {json.dumps(str(generic))}, count: {args.slaves}}}]}}\n"
        )
        emus = {
            on: stack.enter_context(
                emulate(
                    net,
                    ethercat="veth",
                    bus_options={"arm": {"error_counters": on}},
                )
            )
            for on in (False, True)
        }
        times: dict[bool, list[int]] = {False: [], True: []}
        done = 0
        while done < args.cycles:
            for on, emu in emus.items():
                for _ in range(BLOCK):
                    times[on].append(emu.op.exchange().exchange_ns)
            done += BLOCK
        watch_b = emus[True].network.backend("arm")
        datagrams = int(getattr(watch_b, "diag_datagrams", 0))
    out: dict[str, Any] = {"cycles": done, "slaves": args.slaves, "load": os.getloadavg()[0]}
    for on, label in ((False, "off"), (True, "on")):
        t = sorted(times[on])
        out[label] = {"p50_us": statistics.median(t) / 1e3, "p99_us": t[int(0.99 * (len(t) - 1))] / 1e3}
    out["ratio_p50"] = out["on"]["p50_us"] / out["off"]["p50_us"]
    out["ratio_p99"] = out["on"]["p99_us"] / out["off"]["p99_us"]
    out["watch_datagrams_per_cycle"] = datagrams / done
    if args.json:
        print(json.dumps(out))
    else:
        print(
            f"{done} cycles x 2, {args.slaves} slaves, load {out['load']:.1f}: exchange p50 "
            f"{out['off']['p50_us']:.0f} -> {out['on']['p50_us']:.0f} µs (x{out['ratio_p50']:.2f}), p99 "
            f"{out['off']['p99_us']:.0f} -> {out['on']['p99_us']:.0f} µs (x{out['ratio_p99']:.2f}); "
            f"{out['watch_datagrams_per_cycle']:.2f} watch datagrams per cycle"
        )


if __name__ == "__main__":
    main()
