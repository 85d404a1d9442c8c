"""A controller in its own process: the demo's sine through fieldbus.remote (run by test_dds_serve.py).

    python remote_client.py NAMESPACE DOMAIN CLIENT_ID CYCLES [--keep-going]   (CYCLES 0: until killed)

Prints one JSON line when commanding starts and one with the summary at the end.
``--keep-going``: after the summary, keep commanding the last target until killed.
"""

from __future__ import annotations

import json
import math
import sys

import numpy as np

import fieldbus.remote

AMPLITUDE_RAD, FREQUENCY_HZ = 0.5, 0.5


def main() -> int:
    namespace, domain, client, cycles = sys.argv[1], int(sys.argv[2]), sys.argv[3], int(sys.argv[4])
    keep_going = "--keep-going" in sys.argv[5:]
    op = fieldbus.remote.connect(namespace, domain=domain, client_id=client, deadline_s=0.5)
    legs = op["joints"]
    op.claim("joints")
    op.enable("joints")
    position = legs.inputs["position_actual_value"]
    target = legs.outputs["target_position"]
    start = position.copy()
    target[:] = start
    prev = start.copy()
    dt = op.cycle_time_us / 1e6
    print(json.dumps({"commanding": True}), flush=True)
    max_err, lo, hi, states, k = 0.0, np.inf, -np.inf, set(), 0
    while cycles == 0 or k < cycles:
        t = k * dt
        target[:] = start + AMPLITUDE_RAD * (1.0 - math.cos(2 * math.pi * FREQUENCY_HZ * t))
        res = op.exchange()
        states.add(res.gate["joints"].name)
        if k > 2 and not res.late:
            max_err = max(max_err, float(np.abs(position - prev).max()))
        lo, hi = min(lo, float(position.min() - start.min())), max(hi, float(position.max() - start.max()))
        prev[:] = target
        k += 1
    summary = {
        "cycles": k,
        "max_error_rad": max_err,
        "span_rad": hi - lo,
        "gates": sorted(states),
        "misses": op.misses,
        "drive_state": legs.drive_state.tolist(),
    }
    print(json.dumps(summary), flush=True)
    while keep_going:  # hold the last target until killed
        op.exchange()
    op.close()
    return 0


if __name__ == "__main__":
    sys.exit(main())
