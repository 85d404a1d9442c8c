"""Where fieldbus finds the emulators: the entry-point group ``fieldbus.emulator_parts``.

``fieldbus`` never imports ``sim_slaves`` (docs/architecture.md): the ``sim``
backend, the demos and the soak ask for the emulator pieces they need by name,
and the ``sim_slaves`` package registers them in its distribution's entry
points. Without ``sim_slaves`` installed, fieldbus still imports and runs on
real buses; asking for an emulator then gives :class:`EmulatorsUnavailable`.

Parts: ``ethercat_chain`` (an in-process ESC chain from drive maps),
``ethercat_control`` (fault and status commands on a chain), ``veth_segment``
(emulated EtherCAT slaves on a veth pair, in their own process),
``canopen_simulator``, ``canopen_control``, ``mit_simulator`` (CAN emulators on
a python-can bus), ``can_motor_simulator`` (the emulator of a raw-CAN map's family), ``emulator_options`` (validates a network file's ``emulator:``
section, :class:`~fieldbus.core.emulator_opts.EmulatorSection`, and returns the
drive options it gives; see :func:`emulator_options_check`).
"""

from __future__ import annotations

from collections.abc import Callable
from functools import cache
from importlib.metadata import entry_points
from typing import Any

from fieldbus.errors import BackendUnavailableError

GROUP = "fieldbus.emulator_parts"


class EmulatorsUnavailable(BackendUnavailableError):
    """An emulator part was asked for and none is registered (``sim_slaves`` not installed)."""


@cache
def emulator_part(name: str) -> Any:
    """The emulator part ``name`` (see the module), loaded from its entry point."""
    found = [ep for ep in entry_points(group=GROUP) if ep.name == name]
    if not found:
        raise EmulatorsUnavailable(
            f"no emulator part '{name}' is registered (entry points '{GROUP}'): the emulators ship in the "
            "fieldbus distribution as the sim_slaves package; reinstall it (pip install 'fieldbus[all]')"
        )
    try:
        return found[0].load()
    except ImportError as exc:
        raise EmulatorsUnavailable(
            f"the emulator part '{name}' needs the Python package '{exc.name}': pip install 'fieldbus[all]'"
        ) from None


def emulator_options_check() -> Callable[[Any], Any] | None:
    """The emulators' check of a network file's ``emulator:`` section (raises a located error on a bad
    option); None when no emulator is installed: the section is then accepted and ignored."""
    try:
        check: Callable[[Any], Any] = emulator_part("emulator_options")
    except EmulatorsUnavailable:
        return None
    return check
