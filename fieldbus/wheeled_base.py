"""A wheeled base on a running network: ``cmd_vel`` in, wheel velocity targets out, odometry back.

:class:`WheeledBase` binds the network file's ``base:`` section
(:class:`~fieldbus.core.diffdrive.DiffDriveParams`) to the process images of
the wheel joints. Call :meth:`WheeledBase.step` once per cycle, after
``exchange()``: it reads each wheel's position (and velocity) from its image
row when that row is fresh this cycle, steps the odometry, and writes the
limited wheel speeds into the rows' velocity targets (master outputs) for the
next exchange. The image is the only way out: whatever the network's output
rules do to a target, they do to the base's.

A wheel joint's target is the channel mapping 0x60FF (CiA 402 target velocity,
the drive in CSV) or else an output channel named ``velocity``; its feedback
is 0x6064 / 0x606C or input channels named ``position`` / ``velocity``, in the
map's units (rad, rad/s after scaling). A position that is an integer counter
of a declarative raw-CAN drive (``rawcan: family: frames``) wraps (seed 001's
int16 encoder count every 0.8 wheel turn): the base unwraps it, so odometry
counts every turn (a wheel must turn less than half a wrap between two fresh
readings: 0.4 turn per cycle there).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt

from fieldbus.core.diffdrive import BaseStep, DiffDrive, DiffDriveParams
from fieldbus.core.network import row_names
from fieldbus.core.pdo.image import ProcessImage
from fieldbus.core.pdo.model import DriveMap
from fieldbus.errors import FieldbusError
from fieldbus.network import CycleResult, Operational

TARGET_VELOCITY, POSITION_ACTUAL, VELOCITY_ACTUAL = 0x60FF, 0x6064, 0x606C


@dataclass(frozen=True)
class Wheel:
    """Where one wheel joint lives: its group's image, row, bus and slave (for freshness), channels."""

    joint: str
    group: str
    image: ProcessImage
    row: int
    bus: str
    slave: int  # index of its slave on the bus (BusStatus.fresh)
    target: str  # output channel (rad/s)
    position: str | None  # input channel (rad)
    velocity: str | None  # input channel (rad/s)
    wrap: float | None = None  # the position counter wraps every this many units (None: it does not)


def wrap_period(drive: DriveMap, channel: str) -> float | None:
    """The period (image units) at which an integer position counter of a declarative raw-CAN map wraps."""
    frames = drive.rawcan.frames if drive.rawcan is not None else None
    if frames is None:
        return None
    for f in frames.feedback.fields:
        if f.name == channel and f.type in ("int", "uint") and f.scale:
            return float(2**f.bits) / abs(f.scale)
    return None


def find_wheels(op: Operational, params: DiffDriveParams) -> tuple[Wheel, ...]:
    """Each wheel of ``params`` located in ``op``'s groups; a missing channel is a FieldbusError."""
    where: dict[str, tuple[str, int, str, int, DriveMap]] = {}
    for backend in op.network.backends:
        for g in backend.groups:
            for row, joint in enumerate(row_names(g.slaves)):
                k = row // g.slaves[0].map.axes
                where[joint] = (g.name, row, backend.bus.name, g.first + k, g.slaves[k].map)
    wheels = []
    for joint in params.wheel_names:
        if joint not in where:
            raise FieldbusError(f"wheel '{joint}' is not a joint of this network")
        gname, row, bus, slave, drive = where[joint]
        image = op[gname]
        target = image.layout.outputs.channel_for(TARGET_VELOCITY, "velocity")
        if target is None:
            raise FieldbusError(
                f"wheel '{joint}': its map has no velocity target (0x60FF, or an output named 'velocity')"
            )
        pos = image.layout.inputs.channel_for(POSITION_ACTUAL, "position")
        vel = image.layout.inputs.channel_for(VELOCITY_ACTUAL, "velocity")
        need = "position" if params.position_feedback else "velocity"
        if not params.open_loop and (pos if params.position_feedback else vel) is None:
            raise FieldbusError(
                f"wheel '{joint}': odometry needs its {need} (set open_loop: true to run without)"
            )
        wrap = wrap_period(drive, pos) if pos is not None else None
        wheels.append(Wheel(joint, gname, image, row, bus, slave, target, pos, vel, wrap))
    return tuple(wheels)


class WheeledBase:
    """A differential-drive base on the wheels of ``op`` (``params`` defaults to the file's ``base:``)."""

    def __init__(self, op: Operational, params: DiffDriveParams | None = None) -> None:
        params = params if params is not None else op.network.model.base
        if params is None:
            raise FieldbusError("this network file has no 'base:' section (see docs/amr.md)")
        self.params = params
        self.drive = DiffDrive(params)
        self.wheels = find_wheels(op, params)
        self._targets: list[npt.NDArray[Any]] = [w.image.outputs[w.target] for w in self.wheels]
        self._pos: list[npt.NDArray[Any] | None] = [
            w.image.inputs[w.position] if w.position else None for w in self.wheels
        ]
        self._vel: list[npt.NDArray[Any] | None] = [
            w.image.inputs[w.velocity] if w.velocity else None for w in self.wheels
        ]
        self.last: BaseStep | None = None
        self._raw: list[float] = [math.nan] * len(self.wheels)  # last fresh wrapped reading per wheel
        self._turns: list[float] = [0.0] * len(self.wheels)  # unwrapped = reading + turns

    @property
    def odometry(self) -> Any:
        """The :class:`~fieldbus.core.diffdrive.Odometry` (pose in m / rad, twist in m/s, rad/s)."""
        return self.drive.odometry

    def command(self, linear_x: float, angular_z: float, now_s: float) -> str | None:
        """A ``cmd_vel`` (m/s, rad/s) at ``now_s``; the reason it was refused (``nan``, ``inf``) or None."""
        return self.drive.command(linear_x, angular_z, now_s)

    def hold(self) -> None:
        """Drop the command: the base ramps to zero and waits for a new one."""
        self.drive.hold()

    def _feedback(self, res: CycleResult, arrays: list[npt.NDArray[Any] | None]) -> tuple[float, ...]:
        out = []
        for w, a in zip(self.wheels, arrays, strict=True):
            fresh = bool(res.bus(w.bus).fresh[w.slave])
            out.append(float(a[w.row]) if a is not None and fresh else math.nan)
        return tuple(out)

    def _unwrapped(self, positions: tuple[float, ...]) -> tuple[float, ...]:
        """Wrapping counters made continuous: each step's change taken as the shorter way round."""
        out = list(positions)
        for i, (w, x) in enumerate(zip(self.wheels, positions, strict=True)):
            if w.wrap is None or not math.isfinite(x):
                continue
            last = self._raw[i]
            if math.isfinite(last):
                jump = x - last - math.remainder(x - last, w.wrap)
                self._turns[i] -= jump
            self._raw[i] = x
            out[i] = x + self._turns[i]
        return tuple(out)

    def step(self, res: CycleResult, now_s: float, dt_s: float, *, enabled: bool = True) -> BaseStep:
        """One cycle after ``exchange()`` returned ``res``: odometry in, wheel targets out.

        ``enabled``: every wheel drive is OPERATION ENABLED. When not (or while the safe stop is
        latched) the command is dropped, the limiter restarts from rest and the targets are 0: a base
        that comes back never resumes an old command by itself.
        """
        if not enabled or res.safe_stop:
            self.drive.hold()
            self.drive.reset_speeds()
        positions = self._unwrapped(self._feedback(res, self._pos))
        step = self.drive.step(now_s, dt_s, positions, self._feedback(res, self._vel))
        speeds = step.wheel_velocity if enabled and not res.safe_stop else (0.0,) * len(self.wheels)
        for w, target, v in zip(self.wheels, self._targets, speeds, strict=True):
            target[w.row] = v
        self.last = step
        return step

    def wheel_rows(self) -> dict[str, npt.NDArray[np.intp]]:
        """Per group, the rows that are wheels (for a controller that enables only those)."""
        rows: dict[str, list[int]] = {}
        for w in self.wheels:
            rows.setdefault(w.group, []).append(w.row)
        return {g: np.array(r, dtype=np.intp) for g, r in rows.items()}
