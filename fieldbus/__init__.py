"""fieldbus: EtherCAT / CANopen master and PDO mapping for robots.

Directions: the API speaks from the master's side (``inputs``, ``outputs``);
drive maps speak from the drive's side (RxPDO = outputs, TxPDO = inputs).
"""

from fieldbus.errors import (
    BackendUnavailableError,
    BusTimeoutError,
    FieldbusError,
    PdoMapError,
    PhaseError,
    SdoAbortError,
    SdoMismatchError,
    StateTransitionError,
    WorkingCounterError,
)

__version__ = "0.1.0"

__all__ = [
    "BackendUnavailableError",
    "BusTimeoutError",
    "FieldbusError",
    "PdoMapError",
    "PhaseError",
    "SdoAbortError",
    "SdoMismatchError",
    "StateTransitionError",
    "WorkingCounterError",
    "__version__",
]
