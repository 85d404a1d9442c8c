"""Opening a python-can bus for a network's CAN bus (shared by the CANopen and raw-CAN backends)."""

from __future__ import annotations

from typing import Any

from fieldbus.core.network import Bus
from fieldbus.errors import FieldbusError


def open_can_bus(bus: Bus, default_interface: str = "socketcan") -> Any:
    """``can.Bus`` with the bus's interface type, channel, bit rate and ``can_options``.

    Raises :class:`FieldbusError` naming the bus when python-can refuses.
    """
    import can

    interface = bus.can_interface or default_interface
    extra: dict[str, Any] = dict(bus.can_options)
    try:
        return can.Bus(interface=interface, channel=bus.interface, bitrate=bus.bitrate, **extra)
    except Exception as exc:
        raise FieldbusError(
            f"bus '{bus.name}': cannot open {interface} channel {bus.interface}: {exc}"
        ) from exc
