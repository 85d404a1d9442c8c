"""``fieldbus latency NETWORK``: each axis's command-to-feedback delay, in cycles, measured.

Enables every CiA 402 axis in cyclic synchronous position mode, holds it,
then dithers its target by a small step (+A, hold, -A, hold, ...) and
watches the actual position: the delay of one step is the number of cycles
from the exchange that carried the new target to the first exchange whose
feedback left the noise band of the hold before it. The median over the
steps is reported per axis, as ``round_trip_cycles`` and as
``drive_delay_cycles`` = round trip - 1 (an ideal drive answers in the next
exchange: inputs are sampled after the outputs of the previous frame took
effect). Run it on real drives to see what they do; on the emulators a
configured ``emulator: {command_delay_cycles: N}`` comes back as N.
"""

from __future__ import annotations

import argparse
import json
import math
from typing import Any

import numpy as np
import numpy.typing as npt

from fieldbus.commands import cycleopts
from fieldbus.commands.argtypes import integer, positive
from fieldbus.commands.usage import add_command
from fieldbus.core.cia402 import Cia402Controller, Goal, Mode
from fieldbus.errors import FieldbusError
from fieldbus.network import Operational, open_network

STEP_RAD = 0.002  # dither amplitude (about 40 counts of a 17-bit encoder)
HOLD_CYCLES = 40  # cycles each level is held: long enough for the response to settle
STEPS = 8  # dither steps per axis
ENABLE_TIMEOUT_S = 3.0
MAX_DETECT_CYCLES = HOLD_CYCLES - 2  # a response later than this is "none"


def register(sub: Any) -> None:
    p = add_command(
        sub,
        "latency",
        help="measure each axis's command-to-feedback delay in cycles (CiA 402, CSP)",
        doc=__doc__,
        codes=[
            (0, "every axis answered every step"),
            (1, "bring-up or file error"),
            (3, "an axis never enabled or did not answer a step within the hold time"),
        ],
        live_bus=True,
    )
    p.add_argument("network", metavar="NETWORK.yaml", help="network file with CiA 402 axes")
    p.add_argument("--backend", choices=("sim", "ethercat"), help="run every bus on this backend instead")
    p.add_argument(
        "--step", type=positive("rad"), default=STEP_RAD, help=f"dither step in rad, > 0 (default {STEP_RAD})"
    )
    p.add_argument(
        "--steps", type=integer(1), default=STEPS, help=f"dither steps per axis, >= 1 (default {STEPS})"
    )
    p.add_argument(
        "--hold", type=integer(4), default=HOLD_CYCLES, help=f"cycles per level, >= 4 (default {HOLD_CYCLES})"
    )
    p.add_argument("--json", action="store_true", help="one JSON object on stdout")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    report = measure_latency(args.network, args.backend, step_rad=args.step, steps=args.steps, hold=args.hold)
    if args.json:
        print(json.dumps(report))
    else:
        print(describe(report))
    ok = report["enabled"] and all(a["answered"] == a["steps"] for a in report["axes"])
    return 0 if ok else 3


def describe(r: dict[str, Any]) -> str:
    lines = [
        f"command-to-feedback delay, {r['cycle_time_us']} us cycle ({r['backend'] or 'network backends'})"
    ]
    if not r["enabled"]:
        lines.append("  not every axis reached OPERATION ENABLED: nothing measured")
    for a in r["axes"]:
        d = a["drive_delay_cycles"]
        what = (
            "no answer" if d is None else f"{d:g} cycles drive delay ({a['round_trip_cycles']:g} round trip)"
        )
        lines.append(
            f"  {a['group']}/{a['axis']}: {what}, {a['answered']}/{a['steps']} steps, spread {a['spread_cycles']}"
        )
    return "\n".join(lines)


class DitherProbe:
    """One axis group: enable in CSP, hold, dither the targets, time each step's first response."""

    def __init__(
        self, op: Operational, group: str, *, step_rad: float, steps: int, hold: int, rate_hz: float
    ):
        img = op[group]
        self.statusword = img.inputs["statusword"]
        self.position = img.inputs["position_actual_value"]
        self.mode_display = img.inputs["modes_of_operation_display"]
        self.controlword = img.outputs["controlword"]
        self.target = img.outputs["target_position"]
        self.mode = img.outputs["modes_of_operation"]
        n = len(self.position)
        self.n = n
        self.ctrl = Cia402Controller(n, mode=Mode.CSP, timeout_cycles=int(ENABLE_TIMEOUT_S * rate_hz))
        self.ctrl.set_goal(Goal.ENABLE)
        self.step_rad, self.steps, self.hold = step_rad, steps, hold
        self.base = np.zeros(n)
        self.enabled_at: int | None = None
        self.level = 0.0
        self.sent_at = -1  # exchange index that carried the current step's target
        self.band = np.zeros(n)  # noise band of the hold before the step [rad]
        self.ref = np.zeros(n)  # mean feedback over that hold
        self.window: list[npt.NDArray[np.float64]] = []
        self.found = np.full(n, -1)
        self.delays: list[list[int]] = [[] for _ in range(n)]
        self.done_steps = 0
        self.fresh_since = 0  # fresh exchanges since every axis was enabled

    @property
    def finished(self) -> bool:
        return self.done_steps >= self.steps

    def step(self, k: int) -> None:
        """Exchange ``k`` has just returned: read feedback, write the next targets."""
        self.ctrl.step(self.statusword, self.controlword, self.mode_display, self.mode)
        if self.enabled_at is None:
            self.target[:] = self.position  # follow the joint while enabling
            if self.ctrl.all_reached:
                self.enabled_at = k
                self.base[:] = self.position
            return
        # phases count the exchanges that returned (a lost frame must not skip a step's start or
        # end); delays count every cycle from the one that carried the step
        self.fresh_since += 1
        t = self.fresh_since
        if t < self.hold or self.finished:  # settle before the first step; stay after the last
            self.window.append(np.array(self.position, dtype=np.float64))
            return
        phase = (t - self.hold) % self.hold
        if phase == 0:  # a new step: note the hold's band, write the new level
            if self.sent_at >= 0:
                self._close_step()
            hist = np.array(self.window[-(self.hold // 2) :])
            self.ref = hist.mean(axis=0)
            self.band = np.abs(hist - self.ref).max(axis=0)
            self.window.clear()
            self.level = self.step_rad if self.level <= 0 else -self.step_rad
            self.target[:] = self.base + self.level
            self.sent_at = k + 1  # written now, carried by the next exchange
            self.found[:] = -1
            return
        pos = np.array(self.position, dtype=np.float64)
        self.window.append(pos)
        moved = np.abs(pos - self.ref) > np.maximum(2.0 * self.band, 0.25 * self.step_rad)
        toward = np.sign(pos - self.ref) == np.sign(self.base + self.level - self.ref)
        first = (self.found < 0) & moved & toward
        self.found[first] = k - self.sent_at
        if phase == self.hold - 1:
            self._close_step()
            self.sent_at = -1

    def _close_step(self) -> None:
        for i in range(self.n):
            if 0 <= self.found[i] <= MAX_DETECT_CYCLES:
                self.delays[i].append(int(self.found[i]))
        self.done_steps += 1

    def results(self, group: str) -> list[dict[str, Any]]:
        out = []
        for i in range(self.n):
            d = self.delays[i]
            med = float(np.median(d)) if d else None
            out.append(
                {
                    "group": group,
                    "axis": i,
                    "round_trip_cycles": med,
                    "drive_delay_cycles": None if med is None else med - 1,
                    "answered": len(d),
                    "steps": self.done_steps,
                    "spread_cycles": [min(d), max(d)] if d else None,
                }
            )
        return out


def measure_latency(
    network: str,
    backend: str | None,
    *,
    step_rad: float = STEP_RAD,
    steps: int = STEPS,
    hold: int = HOLD_CYCLES,
) -> dict[str, Any]:
    """Bring the network up, measure every CiA 402 group, return the report (see the module docstring)."""
    with open_network(network, backend=backend) as net:
        op = net.bring_up()
        rate_hz = 1e6 / op.cycle_time_us
        probes = {}
        for group in op:
            names = op[group].inputs.values.dtype.names or ()
            if "statusword" in names and "position_actual_value" in names:
                probes[group] = DitherProbe(
                    op, group, step_rad=step_rad, steps=steps, hold=hold, rate_hz=rate_hz
                )
        if not probes:
            raise FieldbusError(
                f"{network}: no CiA 402 axis group (statusword, position_actual_value) to measure"
            )
        enable = int(ENABLE_TIMEOUT_S * rate_hz)
        cycles = enable + hold * (steps + 2)

        def step(k: int) -> bool:
            res = op.exchange()
            if not res.fresh:
                return False
            for p in probes.values():
                p.step(k)
            if any(p.enabled_at is None for p in probes.values()) and k > enable:
                return True  # give up: not every axis enabled
            return all(p.finished for p in probes.values())

        cycleopts.run_timed(op, step, float(op.cycle_time_us), cycles, status=False)
        enabled = all(p.enabled_at is not None for p in probes.values())
        axes = [a for g, p in probes.items() for a in p.results(g)]
    return {
        "backend": backend,
        "cycle_time_us": op.cycle_time_us,
        "enabled": enabled,
        "step_rad": step_rad,
        "axes": axes,
        "max_drive_delay_cycles": max(
            (a["drive_delay_cycles"] for a in axes if a["drive_delay_cycles"] is not None), default=math.nan
        ),
    }
