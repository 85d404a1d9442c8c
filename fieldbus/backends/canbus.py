"""A CAN backend's python-can bus: opened (or handed in), logged, closed (CANopen and raw-CAN backends)."""

from __future__ import annotations

from typing import Any

from fieldbus.core.network import Bus
from fieldbus.errors import FieldbusError
from fieldbus.wire.canlog import CanLogWriter, LoggedBus


def open_can_bus(bus: Bus, default_interface: str = "socketcan") -> Any:
    """``can.Bus`` with the bus's interface type, channel, bit rate and ``can_options``.

    Raises :class:`FieldbusError` naming the bus when python-can refuses.
    """
    import can

    interface = bus.can_interface or default_interface
    extra: dict[str, Any] = dict(bus.can_options)
    if bus.data_bitrate is not None:  # CAN FD: python-can's interfaces take fd and the data-phase rate
        extra.setdefault("fd", True)
        extra.setdefault("data_bitrate", bus.data_bitrate)
    try:
        return can.Bus(interface=interface, channel=bus.interface, bitrate=bus.bitrate, **extra)
    except Exception as exc:
        raise FieldbusError(
            f"bus '{bus.name}': cannot open {interface} channel {bus.interface}: {exc}"
        ) from exc


def attach_can_bus(bus: Bus, current: Any, log: CanLogWriter | None) -> Any:
    """The bus a backend's ``open`` uses: ``current`` (handed in as ``can_bus``) or one opened here,
    wrapped to log every frame when ``log`` is given (once)."""
    port = current if current is not None else open_can_bus(bus)
    return LoggedBus(port, log) if log is not None and not isinstance(port, LoggedBus) else port


def release_can_bus(port: Any, owned: bool, log: CanLogWriter | None) -> None:
    """Shut ``port`` down if the backend opened it, and close the frame log whatever happens."""
    try:
        if port is not None and owned:
            port.shutdown()
    finally:
        if log is not None:
            log.close()
