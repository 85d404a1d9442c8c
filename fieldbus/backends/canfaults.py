"""What goes wrong on a CAN bus, counted per backend: late and extra frames, driver errors, bus-off.

The CANopen and raw-CAN backends mix in :class:`CanFaults`; the counters only
grow (since the backend was made) and the cycle reports them. A python-can
error on send or receive becomes :class:`~fieldbus.errors.BusIoError` (the
driver's error kept as ``cause``), counted in ``tx_errors`` / ``rx_errors``.

Error frames (python-can's ``is_error_frame``; socketcan delivers them unless
``ignore_rx_error_frames``) carry the error class in their 11-bit id
(``linux/can/error.h``): they are counted, ``CAN_ERR_BUSOFF`` in ``bus_off``,
and never taken for data (an error frame with class 0x082 would otherwise read
as an EMCY of node 2, or as a motor's reply).
"""

from __future__ import annotations

from typing import Any

from fieldbus.core.network import Bus
from fieldbus.errors import BusIoError

CAN_ERR_BUSOFF = 0x040  # linux/can/error.h: the controller went bus-off
CAN_ERR_RESTARTED = 0x100  # the controller was restarted after bus-off


class CanFaults:
    """Counters of one CAN bus's faults (class defaults: 0 / None until the first one)."""

    bus: Bus
    late_frames = 0  # awaited frames that came after their cycle's receive timeout (dropped, never used)
    extra_frames = 0  # awaited frames that came more than once in one cycle (the first one counts)
    tx_errors = 0  # sends the driver refused (e.g. "Transmit buffer full": no node acknowledges)
    rx_errors = 0  # receives the driver failed
    error_frames = 0  # error frames received (any class)
    bus_off = 0  # bus-off reports (error frames of class CAN_ERR_BUSOFF)
    last_error: str | None = None  # the newest of the above, or of a failing stop()/close()

    def _io_failed(self, verb: str, exc: BaseException) -> BusIoError:
        """Count a driver error on ``verb`` ("send" / "receive") and wrap it (raise the result)."""
        if verb == "send":
            self.tx_errors += 1
        else:
            self.rx_errors += 1
        b = self.bus
        where = f"{b.can_interface or 'socketcan'} channel {b.interface}"
        self.last_error = f"{verb}: {type(exc).__name__}: {exc}"
        return BusIoError(f"bus '{b.name}': cannot {verb} on {where}: {exc}", exc)

    def _error_frame(self, msg: Any) -> None:
        """An error frame came: count it (bus-off apart)."""
        self.error_frames += 1
        cls = int(msg.arbitration_id)
        if cls & CAN_ERR_BUSOFF:
            self.bus_off += 1
            self.last_error = f"bus-off (error frame class 0x{cls:03X})"
        else:
            self.last_error = f"error frame class 0x{cls:03X}"

    def _shut_failed(self, verb: str, exc: BaseException) -> None:
        """stop()/close() never raise: a failure there is kept in ``last_error``."""
        self.last_error = f"{verb}: {type(exc).__name__}: {exc}"
