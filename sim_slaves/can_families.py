"""Which emulator speaks a raw-CAN drive map's family, for the testing kit, the emulator process and the demo.

A raw-CAN map names its family in ``rawcan.family`` (:mod:`fieldbus.core.rawcan`), a family on the protocol
(:func:`fieldbus.core.canfamily.families`: ``mit``, the MIT frame alone; ``damiao``; ``cubemars``, servo or
MIT by its ``protocol``, :mod:`sim_slaves.cubemars`; ``odrive``, :mod:`sim_slaves.odrive`; ``frames``,
described in data, :mod:`sim_slaves.frames_motor`; or a third party's) whose class names its emulator. One emulator object
serves the motors of one bus, so the motors of a bus must be of one family (and, for CubeMars, of one
protocol); :func:`bus_family` refuses a mix, naming the maps.
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from importlib import import_module
from typing import Any

from fieldbus.core.canfamily import families
from fieldbus.core.pdo.model import DriveMap
from fieldbus.core.rawcan import FAMILIES
from fieldbus.platform.clock import Clock
from sim_slaves.mit_motor import MitMotorSimulator

__all__ = ["FAMILIES", "bus_family", "family_of", "simulator"]


def family_of(drive: DriveMap) -> str:
    """The emulator kind of a raw-CAN map, as its family in the table says
    (:meth:`~fieldbus.core.canfamily.CanFamily.emulator_kind`: mostly its ``rawcan.family``; one kind per
    protocol where a family's emulators differ). Raises ``ValueError`` for a map without a ``rawcan`` section."""
    cfg = drive.rawcan
    if cfg is None:
        raise ValueError(f"drive map {drive.name} has no rawcan section")
    registered = families().get(cfg.family)
    if registered is None or cfg.protocol is None:
        return cfg.family
    return registered.emulator_kind(cfg.protocol)  # the family's table says (CubeMars: per protocol)


def bus_family(drives: Iterable[DriveMap]) -> str:
    """The one family (:func:`family_of`) of every map of a bus; ``ValueError`` naming each family's
    first map when there are several (one emulator serves one family per bus)."""
    found: dict[str, str] = {}
    for d in drives:
        found.setdefault(family_of(d), d.name)
    if len(found) != 1:
        have = ", ".join(f"{family} ({name})" for family, name in found.items())
        raise ValueError(
            f"motors of {len(found)} families on one bus: {have}; one emulator serves one family"
        )
    return next(iter(found))


def simulator(
    bus: Any,
    motors: Sequence[tuple[DriveMap, int]],
    *,
    clock: Clock | None = None,
    dt_s: float | None = None,
    log: Any = None,
) -> MitMotorSimulator:
    """The emulator of ``motors`` (``[(drive_map, node_id), ...]``, one family) on python-can ``bus``, not
    started: ``.start()`` for its own thread, or ``serve`` / ``deliver`` from the caller.

    ``clock``: the time the motors read (timeouts, heartbeats, watchdogs; default the machine's);
    ``dt_s``: unused (the physics run on ``clock``, in steps of :data:`sim_slaves.mit_motor.STEP_S`).
    """
    bus_family(d for d, _ in motors)  # one family (and CubeMars protocol) per bus, else refused
    items = list(motors)
    cfg = items[0][0].rawcan if items else None
    registered = families().get(cfg.family) if cfg is not None and cfg.protocol is not None else None
    if registered is not None and registered.emulator is not None:  # a family on the protocol names its own
        module, _, attr = registered.emulator.partition(":")
        emulator: MitMotorSimulator = getattr(import_module(module), attr)(
            bus, items, dt_s=dt_s, log=log, clock=clock
        )
        return emulator
    return MitMotorSimulator(bus, items, dt_s=dt_s, log=log, clock=clock)
