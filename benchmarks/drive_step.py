"""Cost of one 1 kHz step of the emulated CiA 402 drives: scalar drives one by one, and the drive bank.

    python benchmarks/drive_step.py [--axes 64] [--small 4] [--large 128] [--kernel-sizes 3 64]
                                    [--rounds 10] [--batch-s 0.2]

Contenders, each ``--axes`` enabled drives following a sine in CSP at 1 kHz:
``scalar`` (one :class:`sim_slaves.drive402.Cia402Drive` built alone per
axis, each stepped through its object dictionary: a drive alone is a bank of
one, so this is the bank's code paid once per drive) and ``bank`` (one
:class:`sim_slaves.drive_bank.DriveBank` stepped as a whole).
Interleaved rounds (benchmarks/_common.py); reported: µs per 1 kHz cycle for
all axes, per axis, and the share of the 1 ms cycle, with the ratio
scalar/bank within each round. Then the bank's cost against its size: a bank
of ``--small`` and one of ``--large`` drives side by side, and their ratio
(on the numpy path nearly flat: one set of array operations per step,
whatever the number of drives; with the C kernel the arithmetic per drive
shows: 128 drives about 2.5x 4). Both were unit tests' wall-clock bounds (64 scalar axes under 1 ms
per cycle; 128 drives within 2x of 4); on a loaded machine they measured the
load, so the figures live here. Last, for each of ``--kernel-sizes``, a bank
stepped with the C kernel of the plain CSP path (``sim_slaves._motion``,
where built) and with its numpy path (``drive_bank.motion_kernel`` None),
side by side, and their ratio numpy/C.

Measured 28 Nov 2026 on the shared 2-CPU development VM (load average
1.5-2.3), three runs of 8-10 rounds: a bank of 3 drives 10-13 µs per 1 kHz
cycle with the kernel, 100-154 µs on the numpy path in the same runs
(numpy / C 10.4-11.4); a bank of 64, 19-24 µs against 123-137 µs (5.3-6.0).
The checkout before the kernel, its own run of this benchmark alternated
with these: a bank of 3 94-112 µs, a bank of 64 101-105 µs.
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
from sim_slaves import drive_bank
from sim_slaves.drive402 import Cia402Drive, DictObjectStore, DriveParams
from sim_slaves.drive_bank import DriveBank

DT = 1e-3
COUNTS_PER_RAD = (1 << 17) / (2 * math.pi)
ENABLE = (0x00, 0x06, 0x07, 0x0F)  # controlwords: disable voltage, shutdown, switch on, enable operation
BUILT = drive_bank.motion_kernel  # the C kernel of the plain CSP path, or None where not built


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
        drive_bank.motion_kernel = BUILT  # (the numpy contenders below set it to None for their turns)
        target = round(COUNTS_PER_RAD * math.sin(2 * math.pi * k * DT))
        for d, od in zip(drives, ods, strict=True):
            od.values[(0x607A, 0)] = target
            d.step(od, DT)

    return step


def bank(n: int, c_kernel: bool = True) -> Callable[[], None]:
    """One 1 kHz cycle of a bank of ``n`` drives, stepped as a whole: with the C kernel where built, or
    (``c_kernel`` False) on the numpy path."""
    kernel = BUILT if c_kernel else None
    drive_bank.motion_kernel = kernel
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
        drive_bank.motion_kernel = kernel  # contenders of both kinds take turns in one process
        b.target_position[:] = round(COUNTS_PER_RAD * math.sin(2 * math.pi * k * DT))
        b.step(0, n, DT)

    assert (b.state == State402.OPERATION_ENABLED).all(), "the bank's drives are not OPERATION ENABLED"
    return step


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--axes", type=int, default=64, help="drives, scalar against the bank (default 64)")
    p.add_argument("--small", type=int, default=4, help="the small bank (default 4)")
    p.add_argument("--large", type=int, default=128, help="the large bank (default 128)")
    p.add_argument(
        "--kernel-sizes", type=int, nargs="*", default=[3, 64], help="banks, C kernel against numpy (3 64)"
    )
    p.add_argument("--rounds", type=int, default=10, help="interleaved rounds (default 10)")
    p.add_argument("--batch-s", type=float, default=0.2, help="seconds per batch (default 0.2)")
    args = p.parse_args(argv)
    axes, size = f"{args.axes} axes", "bank size"
    small, large = f"bank of {args.small}", f"bank of {args.large}"
    kernel_sizes = args.kernel_sizes if BUILT is not None else []
    if BUILT is None:
        print(
            "sim_slaves._motion is not built: no C kernel against numpy (python setup.py build_ext --inplace)"
        )
    found = interleaved(
        {
            axes: {"scalar": scalar(args.axes), "bank": bank(args.axes)},
            size: {small: bank(args.small), large: bank(args.large)},
            **{f"kernel {n}": {"C": bank(n), "numpy": bank(n, c_kernel=False)} for n in kernel_sizes},
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
    if kernel_sizes:
        rows = []
        for n in kernel_sizes:
            got = found[f"kernel {n}"]
            lo, hi = got.ratio_quartiles("numpy", "C")
            c_us, np_us = got.median_us("C"), got.median_us("numpy")
            rows.append(
                [
                    f"bank of {n}",
                    f"{c_us:.1f}",
                    f"{np_us:.1f}",
                    f"{got.ratio('numpy', 'C'):.1f} ({lo:.1f}-{hi:.1f})",
                ]
            )
        print("plain CSP path, C kernel (sim_slaves._motion) against numpy, us per 1 kHz cycle (medians):")
        print(table(["drives", "C", "numpy", "numpy / C (IQR)"], rows))
    drive_bank.motion_kernel = BUILT
    return 0


if __name__ == "__main__":
    sys.exit(main())
