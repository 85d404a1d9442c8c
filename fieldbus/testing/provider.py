"""What an emulator of one bus offers the testing kit, and how the kit finds one.

Emulators are found through the ``fieldbus.emulators`` entry-point group: the
name is a bus type (``ethercat``, ``canopen``, ``rawcan``), the value a
function ``start(context, bus) -> BusEmulator``. The ``sim_slaves`` package
that ships with fieldbus registers all three; fieldbus itself imports none of
them. Every fault hook here raises :class:`FaultNotSupported` unless an
emulator overrides it; slaves are given by index on their bus.
"""

from __future__ import annotations

from contextlib import ExitStack
from dataclasses import dataclass, field
from importlib.metadata import entry_points
from pathlib import Path
from typing import TYPE_CHECKING, Any, Protocol

from fieldbus.core.network import Bus
from fieldbus.errors import FieldbusError
from fieldbus.platform.clock import Clock

if TYPE_CHECKING:
    from fieldbus.backends.base import Backend

GROUP = "fieldbus.emulators"
ETHERCAT_MODES = ("sim", "veth")
CAN_MODES = ("virtual", "udp")


class EmulationError(FieldbusError):
    """An emulated network could not be brought up (the message says which bus and why)."""


class EmulationUnavailable(EmulationError):
    """This machine refuses what the emulator needs (root, a veth pair, an extra): a test should skip."""


class FaultNotSupported(EmulationError):
    """This fault has no meaning on this bus, or this emulator cannot inject it (the message says which)."""


@dataclass
class EmulationContext:
    """What an emulator gets to start: the clock, the modes asked for, a folder, and where to clean up."""

    clock: Clock
    ethercat: str  # "sim" (in process) or "veth" (the wire runner in a child process)
    can: str  # "virtual" (in process) or "udp" (a child process on fieldbus_udp)
    workdir: Path
    source: Path | None  # the network file (the veth runner reads it again), None for a model only
    cleanup: ExitStack
    virtual: bool  # the clock is virtual: in-process emulators run in lockstep with the master
    extra: dict[str, Any] = field(default_factory=dict)


class BusEmulator:
    """The emulator of one bus. Subclasses override what their bus can do."""

    def __init__(self, bus: Bus) -> None:
        self.bus = bus

    # -- bring-up -------------------------------------------------------------------------
    def bus_changes(self) -> dict[str, Any]:
        """Fields of the bus to replace before the master opens it (``interface``, ``type``...)."""
        return {}

    def backend_options(self) -> dict[str, Any]:
        """Options for this bus's backend (``can_bus``, ``clock``...)."""
        return {}

    def attach(self, backend: Backend) -> None:
        """The master's backend of this bus exists (the sim backend holds its emulated chain)."""

    def close(self) -> None:
        """Stop everything this emulator started (threads, processes, links); called once, also on failure."""

    # -- what the emulated slaves say ---------------------------------------------------------
    def drive_states(self) -> list[int]:
        """Every slave's CiA 402 state as the emulated drive has it (``State402`` value, -1: no drive)."""
        raise self._unsupported("drive_states")

    def drive_positions(self) -> list[float]:
        """Every axis's shaft position as the emulated drive's physics has it, in its counts, unquantised."""
        raise self._unsupported("drive_positions")

    # -- faults (slave: index on the bus) -------------------------------------------------------
    def lose_cycles(self, cycles: int) -> None:
        raise self._unsupported("lose_cycles")

    def delay(self, seconds: float, cycles: int) -> None:
        raise self._unsupported("delay")

    def short_wkc(self, cycles: int, slave: int) -> None:
        raise self._unsupported("short_wkc")

    def corrupt_inputs(self, slave: int, cycles: int) -> None:
        raise self._unsupported("corrupt_inputs")

    def power_cycle(self, slave: int) -> None:
        raise self._unsupported("power_cycle")

    def firmware_power_loss(self, slave: int, after_bytes: int) -> None:
        """``slave`` loses power once an FoE write has taken ``after_bytes`` more bytes (then comes back)."""
        raise self._unsupported("firmware_power_loss")

    def slow_sdo(self, slave: int, cycles: int) -> None:
        """``slave``'s SDO server serves each request ``cycles`` cycles late (0: at once again)."""
        raise self._unsupported("slow_sdo")

    def drive_fault(self, slave: int, code: int, axis: int = 0) -> None:
        """Fault ``slave``'s drive (``axis``: 0-based axis of a multi-axis slave) with error code ``code``."""
        raise self._unsupported("drive_fault")

    def silence(self, slave: int, silent: bool) -> None:
        raise self._unsupported("silence")

    def error_frames(self, count: int) -> None:
        raise self._unsupported("error_frames")

    def bus_off(self, slave: int, off: bool) -> None:
        raise self._unsupported("bus_off")

    def sdo_abort(self, slave: int, index: int, sub_index: int | None, code: int) -> None:
        raise self._unsupported("sdo_abort")

    def bit_errors(self, upstream: int, rate: float, seed: int) -> None:
        """Bit errors on the cable behind slave ``upstream`` (its port 1, the next slave's port 0)."""
        raise self._unsupported("bit_errors")

    def flap_link(self, upstream: int) -> None:
        raise self._unsupported("flap_link")

    def clear_faults(self) -> None:
        raise self._unsupported("clear_faults")

    def _unsupported(self, what: str, why: str = "") -> FaultNotSupported:
        return FaultNotSupported(
            f"bus '{self.bus.name}' ({self.bus.type}, {type(self).__name__}): {what} is not available"
            + (f": {why}" if why else "")
        )


class EmulatorStarter(Protocol):
    def __call__(self, context: EmulationContext, bus: Bus) -> BusEmulator: ...


def find_emulator(bus_type: str) -> EmulatorStarter:
    """The registered emulator of a bus type (entry-point group ``fieldbus.emulators``)."""
    found = [ep for ep in entry_points(group=GROUP) if ep.name == bus_type]
    if not found:
        have = sorted({ep.name for ep in entry_points(group=GROUP)})
        raise EmulationUnavailable(
            f"no emulator registered for bus type '{bus_type}' (entry points '{GROUP}': "
            f"{', '.join(have) or 'none'}; is fieldbus installed with its emulators?)"
        )
    try:
        starter: EmulatorStarter = found[0].load()
    except ImportError as exc:
        raise EmulationUnavailable(
            f"the {bus_type} emulator needs the Python package '{exc.name}': pip install 'fieldbus[all]'"
        ) from None
    return starter
