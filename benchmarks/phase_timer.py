"""What the exchange() phase timer costs: the sim backend's exchange() with ``phases`` off and on, one run.

    python benchmarks/phase_timer.py [--axes 12] [--rounds 15] [--batch-s 0.2]

One in-process network (the ethercat backend on the emulated ESC chain, no
wire: the cycle is all host work, so any cost of the hooks shows in full).
Contenders in shuffled order each round (:func:`benchmarks._common.interleaved`):
``off`` (``Operational.phases`` None, the default) and ``on`` (a
:class:`fieldbus.platform.phases.PhaseTimer`: eight clock reads per exchange).
Reported: median µs per exchange and the within-round ratios on/off.
A third contender, ``off-again``, is ``off`` timed twice, so the noise of
the machine between two identical contenders is in the same table.
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks._common import interleaved, machine_note, table
from fieldbus.commands.demo import demo_network
from fieldbus.network import open_network
from fieldbus.platform.loop import gc_held
from fieldbus.platform.phases import PhaseTimer


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--axes", type=int, default=12)
    p.add_argument("--rounds", type=int, default=15)
    p.add_argument("--batch-s", type=float, default=0.2)
    args = p.parse_args(argv)
    timer = PhaseTimer()
    with (
        tempfile.TemporaryDirectory() as tmp,
        demo_network("sim", args.axes, 1000.0, Path(tmp)) as setup,
        open_network(setup.net_file, backend="sim") as net,
    ):
        op = net.bring_up()

        def off() -> None:
            op.phases = None
            op.exchange()

        def on() -> None:
            op.phases = timer
            op.exchange()

        with gc_held():
            samples = interleaved(
                {"sim": {"off": off, "on": on, "off-again": off}}, args.rounds, args.batch_s
            )["sim"]
    print(
        f"# exchange() with the phase timer off and on, sim backend, {args.axes} axes, {args.rounds} rounds, "
        f"load {os.getloadavg()[0]:.1f} ({machine_note()})\n"
    )
    rows = [
        [name, f"{samples.median_us(name):.1f}", f"{samples.ratio(name, 'off'):.3f}"]
        for name in ("off", "off-again", "on")
    ]
    print(table(["phases", "us per exchange (median)", "÷ off (within-round median)"], rows))
    return 0


if __name__ == "__main__":
    sys.exit(main())
