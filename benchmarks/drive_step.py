"""Cost of one 1 kHz step of the emulated CiA 402 drives: scalar drives one by one, and the drive bank.

    python benchmarks/drive_step.py [--axes 64] [--small 4] [--large 128] [--rounds 10] [--batch-s 0.2]

Contenders, each ``--axes`` enabled drives following a sine in CSP at 1 kHz:
``scalar`` (one :class:`sim_slaves.drive402.Cia402Drive` built alone per
axis, each stepped through its object dictionary: a drive alone is a bank of
one, so this is the bank's code paid once per drive) and ``bank`` (one
:class:`sim_slaves.drive_bank.DriveBank` stepped as a whole).
Interleaved rounds (benchmarks/_common.py); reported: µs per 1 kHz cycle for
all axes, per axis, and the share of the 1 ms cycle, with the ratio
scalar/bank within each round. Then the bank's cost against its size: a bank
of ``--small`` and one of ``--large`` drives side by side, and their ratio
(nearly flat: one set of array operations per step, whatever the number of
drives). Both were unit tests' wall-clock bounds (64 scalar axes under 1 ms
per cycle; 128 drives within 2x of 4); on a loaded machine they measured the
load, so the figures live here.
"""

from __future__ import annotations

import argparse
import math
import sys
from collections.abc import Callable
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks._common import interleaved, machine_note, table
from fieldbus.core.cia402 import State402
from sim_slaves.drive402 import Cia402Drive, DictObjectStore, DriveParams
from sim_slaves.drive_bank import DriveBank

DT = 1e-3
COUNTS_PER_RAD = (1 << 17) / (2 * math.pi)
ENABLE = (0x00, 0x06, 0x07, 0x0F)  # controlwords: disable voltage, shutdown, switch on, enable operation


def scalar(n: int) -> Callable[[], None]:
    """One 1 kHz cycle of ``n`` scalar drives, each through its own dict OD."""
    drives = [Cia402Drive() for _ in range(n)]
    ods = [DictObjectStore() for _ in range(n)]
    for d, od in zip(drives, ods, strict=True):
        for cw in ENABLE:
            od.values[(0x6040, 0)] = cw
            d.step(od, DT)
    k = 0

    def step() -> None:
        nonlocal k
        k += 1
        target = round(COUNTS_PER_RAD * math.sin(2 * math.pi * k * DT))
        for d, od in zip(drives, ods, strict=True):
            od.values[(0x607A, 0)] = target
            d.step(od, DT)

    return step


def bank(n: int) -> Callable[[], None]:
    """One 1 kHz cycle of a bank of ``n`` drives, stepped as a whole."""
    b = DriveBank([DriveParams()] * n)
    for d in b.drives:
        d.bind(DictObjectStore())
    b.mode_request[:] = 8  # CSP
    for cw in ENABLE:
        b.controlword[:] = cw
        b.step(0, n, DT)
    k = 0

    def step() -> None:
        nonlocal k
        k += 1
        b.target_position[:] = round(COUNTS_PER_RAD * math.sin(2 * math.pi * k * DT))
        b.step(0, n, DT)

    assert (b.state == State402.OPERATION_ENABLED).all(), "the bank's drives are not OPERATION ENABLED"
    return step


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--axes", type=int, default=64, help="drives, scalar against the bank (default 64)")
    p.add_argument("--small", type=int, default=4, help="the small bank (default 4)")
    p.add_argument("--large", type=int, default=128, help="the large bank (default 128)")
    p.add_argument("--rounds", type=int, default=10, help="interleaved rounds (default 10)")
    p.add_argument("--batch-s", type=float, default=0.2, help="seconds per batch (default 0.2)")
    args = p.parse_args(argv)
    axes, size = f"{args.axes} axes", "bank size"
    small, large = f"bank of {args.small}", f"bank of {args.large}"
    found = interleaved(
        {
            axes: {"scalar": scalar(args.axes), "bank": bank(args.axes)},
            size: {small: bank(args.small), large: bank(args.large)},
        },
        args.rounds,
        args.batch_s,
    )
    rows = []
    for group, name, n in (
        (axes, "scalar", args.axes),
        (axes, "bank", args.axes),
        (size, small, args.small),
        (size, large, args.large),
    ):
        us = found[group].median_us(name)
        lo, hi = found[group].quartiles_us(name)
        rows.append(
            [f"{name} ({n} drives)", f"{us:.0f} ({lo:.0f}-{hi:.0f})", f"{us / n:.2f}", f"{us / 10:.0f} %"]
        )
    print(machine_note())
    print(table(["drives", "us per cycle (IQR)", "us per axis", "of a 1 ms cycle"], rows))
    for group, a, b in ((axes, "scalar", "bank"), (size, large, small)):
        lo, hi = found[group].ratio_quartiles(a, b)
        print(
            f"{a} / {b}, median of {args.rounds} rounds: {found[group].ratio(a, b):.1f} ({lo:.1f}-{hi:.1f})"
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())
