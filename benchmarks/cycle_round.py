"""One round of ``benchmarks/cycle.py --before-src``: bring one network up, time ``exchange()``, print JSON.

Run in a child process so that the ``fieldbus`` imported is the checkout under
test: ``python benchmarks/cycle_round.py --src DIR --net FILE [--backend sim]
--seconds S``. Uses only the API both checkouts have (``open_network``,
``bring_up``, scaled channels, ``exchange().fresh``). Prints one JSON object:
``rate`` (cycles/s), ``bad`` (cycles not fresh), ``codec`` (the C codec was
built in that checkout).
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import sys
import time
from pathlib import Path


def main() -> int:
    p = argparse.ArgumentParser()
    p.add_argument("--src", type=Path, required=True)
    p.add_argument("--net", type=Path, required=True)
    p.add_argument("--backend", default=None)
    p.add_argument("--seconds", type=float, default=2.0)
    args = p.parse_args()
    sys.path.insert(0, str(args.src.resolve()))
    from fieldbus.network import open_network

    codec = importlib.util.find_spec("fieldbus._codec") is not None
    if importlib.util.find_spec("pysoem") is not None:
        import pysoem

        # SOEM's bring-up frames wait 20 ms, not 2: on a loaded machine the emulator may answer late and
        # config_init then finds no slave (as the tests' generous_pysoem_timeouts); the cycle is unchanged
        pysoem.settings.timeouts.ret = max(int(pysoem.settings.timeouts.ret), 20_000)
    with open_network(args.net, backend=args.backend) as net:
        op = net.bring_up()
        img = op["joints"]
        target, position = img.outputs["target_position"], img.inputs["position_actual_value"]
        bad = 0

        def step() -> None:
            nonlocal bad
            target[:] = position
            if not op.exchange().fresh:
                bad += 1

        for _ in range(200):
            step()
        bad, n = 0, 0
        t0 = time.perf_counter()
        end = t0 + args.seconds
        while True:
            for _ in range(50):
                step()
            n += 50
            if time.perf_counter() >= end:
                break
        rate = n / (time.perf_counter() - t0)
    print(json.dumps({"rate": rate, "bad": bad, "codec": codec, "src": str(args.src)}))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
