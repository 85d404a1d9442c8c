"""Where fieldbus finds its backends: the built-in ones by name, the others by entry point.

Each bus type is declared once, here for the built-in backends and on the
class for a backend registered in the ``fieldbus.backends`` entry-point group
(name = bus ``type``): the ``open_network(**options)`` names it reads and
whether it is a CAN bus. Loading a network file asks this module which types
exist, so a bus of a registered type can be named in a file. This module
imports no backend: the core reads it; :func:`fieldbus.backends.backend_class`
imports a backend when a bus is opened.

A registered class may set ``bus_options`` (a tuple of option names; absent:
any option is passed through) and ``can_bus`` (bool, default False).
"""

from __future__ import annotations

import sys
from dataclasses import dataclass
from importlib.metadata import EntryPoint, entry_points

GROUP = "fieldbus.backends"


@dataclass(frozen=True)
class BusType:
    """A bus type: the ``open_network`` options its backend reads (None: any) and whether it is CAN."""

    name: str
    options: tuple[str, ...] | None = None
    can: bool = False


# bus type -> (module, class, the extra that provides its dependencies)
BACKENDS: dict[str, tuple[str, str, str | None]] = {
    "sim": ("fieldbus.backends.sim", "SimBackend", "ethercat"),  # the ethercat backend in process
    "ethercat": ("fieldbus.backends.ethercat", "EthercatBackend", "ethercat"),
    "canopen": ("fieldbus.backends.canopen", "CanopenBackend", "can"),
    "rawcan": ("fieldbus.backends.rawcan", "RawCanBackend", "can"),
}

# Keyword options of open_network(**options) that each built-in backend reads (fieldbus/backends/*.py).
BACKEND_OPTIONS: dict[str, tuple[str, ...]] = {
    "sim": ("chain_maps", "clock", "error_counters"),
    "ethercat": (
        "exact_timeout",
        "pcap",
        "frame_timeout_us",
        "sdo_timeout_s",
        "iomap",
        "transport",
        "clock",
        "chain_maps",
        "error_counters",
    ),
    "canopen": ("can_bus", "can_log", "sdo_timeout_s", "heartbeat_consumer_ms", "clock"),
    "rawcan": ("can_bus", "can_log", "clock"),
}

BUILT_IN: dict[str, BusType] = {
    name: BusType(name, BACKEND_OPTIONS[name], can=name in ("canopen", "rawcan")) for name in BACKENDS
}


_found: tuple[object, tuple[str, ...], dict[str, EntryPoint]] | None = None


def registered() -> dict[str, EntryPoint]:
    """The entry points of the group, by bus type (a built-in name is not taken over).

    Looked up once per import path: finding them reads the metadata of every installed
    distribution (milliseconds), and every bus of every network file loaded asks. A changed
    ``sys.path`` (or ``entry_points`` itself replaced) looks again.
    """
    global _found
    key = (entry_points, tuple(sys.path))
    if _found is None or _found[0] is not key[0] or _found[1] != key[1]:
        eps = {ep.name: ep for ep in entry_points(group=GROUP) if ep.name not in BUILT_IN}
        _found = (key[0], key[1], eps)
    return dict(_found[2])


def bus_type_names() -> tuple[str, ...]:
    """Every bus type a network file may name: the built-in ones, then the registered ones (sorted)."""
    return (*BUILT_IN, *sorted(registered()))


def bus_type(name: str) -> BusType | None:
    """The declaration of bus type ``name``, or None when no backend has it.

    A registered backend whose class cannot be loaded (a missing dependency)
    is declared as accepting any option; opening it says what is missing.
    """
    if name in BUILT_IN:
        return BUILT_IN[name]
    ep = registered().get(name)
    if ep is None:
        return None
    try:
        cls = ep.load()
    except Exception:  # a broken plugin says so when its bus opens (backend_class), not here
        return BusType(name)
    options = getattr(cls, "bus_options", None)
    return BusType(
        name,
        tuple(str(o) for o in options) if isinstance(options, tuple | list) else None,
        can=bool(getattr(cls, "can_bus", False)),
    )
