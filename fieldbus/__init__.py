"""fieldbus: EtherCAT / CANopen master and PDO mapping for robots.

Everything a controller needs is here, without knowing the package's layout::

    import fieldbus

    with fieldbus.open_network("robot.yaml") as net:
        op = net.bring_up()                  # SDO plans written and read back, then OP
        legs = op["legs"]                    # fieldbus.ProcessImage, one row per axis
        ctrl = fieldbus.Cia402Controller(legs.n_axes)
        ...
        result = op.exchange()               # one call per cycle, every bus

Directions: the API speaks from the master's side (``inputs``, ``outputs``);
drive maps speak from the drive's side (RxPDO = outputs, TxPDO = inputs).
:data:`PDO_MAPS` is the folder of drive maps shipped with the package.
"""

from pathlib import Path

from fieldbus.backends.ecat_firmware import FileTransferResult, transfer_file
from fieldbus.core.acyclic_modes import AcyclicModes
from fieldbus.core.cia402 import Cia402Controller, Goal, Homing, HomingPhase, Mode, State402
from fieldbus.core.drivefault import DriveFault
from fieldbus.core.foe import FoeError, FoeErrorCode
from fieldbus.core.network import SHIPPED_MAPS, load_network
from fieldbus.core.output_rules import OutputClamp
from fieldbus.core.pdo import DriveMap, drive_map_from_text, load_drive_map
from fieldbus.core.pdo.image import ProcessImage
from fieldbus.core.pdo.layout import layout
from fieldbus.core.profile import ProfileMove, ProfilePhase
from fieldbus.core.safety import SafeStopClearError, Verdict
from fieldbus.core.sdo import canopen_plan, coe_plan
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
from fieldbus.network import BusEvent, BusFault, BusStatus, CycleResult, FaultKind, Operational, open_network
from fieldbus.platform.loop import run_cycles
from fieldbus.platform.timing import CycleTimer
from fieldbus.version import __version__
from fieldbus.wheeled_base import WheeledBase

PDO_MAPS: Path = SHIPPED_MAPS
"""Drive maps shipped with the package (Maxon EPOS4, Elmo Gold, Synapticon, Beckhoff EL7201, ...); a
network file names one as ``map: shipped:NAME`` (e.g. ``shipped:generic_cia402``), wherever it is."""

__all__ = [
    "PDO_MAPS",
    "AcyclicModes",
    "BackendUnavailableError",
    "BusEvent",
    "BusFault",
    "BusStatus",
    "BusTimeoutError",
    "Cia402Controller",
    "CycleResult",
    "CycleTimer",
    "DriveFault",
    "DriveMap",
    "FaultKind",
    "FieldbusError",
    "FileTransferResult",
    "FoeError",
    "FoeErrorCode",
    "Goal",
    "Homing",
    "HomingPhase",
    "Mode",
    "Operational",
    "OutputClamp",
    "PdoMapError",
    "PhaseError",
    "ProcessImage",
    "ProfileMove",
    "ProfilePhase",
    "SafeStopClearError",
    "SdoAbortError",
    "SdoMismatchError",
    "State402",
    "StateTransitionError",
    "Verdict",
    "WheeledBase",
    "WorkingCounterError",
    "__version__",
    "canopen_plan",
    "coe_plan",
    "drive_map_from_text",
    "layout",
    "load_drive_map",
    "load_network",
    "open_network",
    "run_cycles",
    "transfer_file",
]
