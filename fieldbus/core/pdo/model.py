"""Validated drive-map model: frozen dataclasses, no I/O.

Direction naming: in YAML and here, ``rpdo`` / ``tpdo`` are named from the
*drive's* side (RxPDO = the drive receives = master outputs; TxPDO = the drive
transmits = master inputs). The process-image API names them from the master's
side: ``outputs`` (RxPDO) and ``inputs`` (TxPDO).
"""

from __future__ import annotations

import enum
from dataclasses import dataclass, field, replace
from functools import cached_property
from typing import TYPE_CHECKING

from fieldbus.core.datatypes import DataType

if TYPE_CHECKING:
    from fieldbus.core.rawcan_config import RawCanConfig


class Direction(enum.Enum):
    """PDO direction, named from the master's side (see module docstring)."""

    OUTPUTS = "outputs"  # RxPDO: master -> drive
    INPUTS = "inputs"  # TxPDO: drive -> master

    @property
    def yaml_key(self) -> str:
        return "rpdo" if self is Direction.OUTPUTS else "tpdo"


@dataclass(frozen=True)
class Channel:
    """One PDO entry (one mapped object, or a gap).

    ``factor``/``offset`` follow ethercat_driver_ros2 in both directions:
    inputs ``value = factor * raw + offset``; outputs ``raw = factor * value + offset``.
    ``default`` is a *raw* value written to outputs until the user writes one
    (``None``: 0). ``mask`` is the single bit a ``bool`` occupies in its byte.
    ``safe_value`` (outputs only) is what the safe stop writes, in the units the
    process image shows (engineering units when scaled), see :mod:`fieldbus.core.safestop`.
    """

    index: int
    sub_index: int
    type: DataType
    name: str
    interface: str | None = None
    unit: str | None = None
    default: float | None = None
    mask: int | None = None
    factor: float = 1.0
    offset: float = 0.0
    scaled: bool = False
    description: str = ""
    safe_value: float | None = None  # outputs: written by the safe stop (image units), None: holds

    @property
    def is_gap(self) -> bool:
        """Padding entry (index 0, or a CiA 301 dummy object 0x0001..0x0007)."""
        return self.index <= 0x0007

    @property
    def bits(self) -> int:
        return self.type.bits

    @property
    def mapping_value(self) -> int:
        """The 32-bit value of this entry in a 0x16xx/0x1Axx mapping object."""
        return (self.index << 16) | (self.sub_index << 8) | self.bits

    @property
    def address(self) -> str:
        return f"0x{self.index:04X}:{self.sub_index:02X}"


@dataclass(frozen=True)
class CanopenPdo:
    """CANopen communication parameters of one PDO (0x14xx / 0x18xx).

    ``cob_id`` is relative: the node id is added unless ``cob_id_absolute``.
    ``inhibit_time`` is in units of 100 us, ``event_timer`` in ms (CiA 301).
    """

    cob_id: int
    transmission_type: int = 1
    inhibit_time: int = 0
    event_timer: int = 0
    cob_id_absolute: bool = False

    def cob_id_for(self, node_id: int) -> int:
        return self.cob_id if self.cob_id_absolute else self.cob_id + node_id


@dataclass(frozen=True)
class Pdo:
    """One PDO: its mapping object index (0x16xx RxPDO / 0x1Axx TxPDO) and entries.

    ``fixed``: the drive's mapping is read-only; bring-up verifies it instead of
    writing it.
    """

    index: int
    channels: tuple[Channel, ...]
    fixed: bool = False
    canopen: CanopenPdo | None = None

    @property
    def bits(self) -> int:
        return sum(c.bits for c in self.channels)

    @property
    def size(self) -> int:
        """Bytes when this PDO travels alone (one CAN frame)."""
        return (self.bits + 7) // 8

    @property
    def number(self) -> int:
        """1-based CANopen PDO number (0x1600 -> RPDO1, 0x1A03 -> TPDO4)."""
        return (self.index & 0x1FF) + 1


@dataclass(frozen=True)
class SdoWrite:
    """A start-up SDO write from the map (applied in PRE-OP, before the cycle)."""

    index: int
    sub_index: int
    type: DataType
    value: float
    description: str = ""

    @property
    def data(self) -> bytes:
        return self.type.encode(self.value)


@dataclass(frozen=True)
class OutputLimit:
    """A map's ``limits:`` entry for one output channel, in the units the image shows (None: not given).

    ``min``/``max``: the window (a value outside saturates to it); ``max_step``: the largest change per
    cycle; ``max_rate``: the largest change per second (``max_rate`` x the bus cycle time per cycle).
    """

    channel: str
    min: float | None = None
    max: float | None = None
    max_step: float | None = None
    max_rate: float | None = None


@dataclass(frozen=True)
class HomingConfig:
    """A drive map's ``homing:`` section (CiA 402-2 homing mode); bring-up writes it as start-up SDOs.

    ``method`` 0x6098, ``offset`` 0x607C [position units], ``speed_switch``/``speed_zero`` 0x6099:01/02
    [velocity units], ``acceleration`` 0x609A [acceleration units]; ``timeout_ms`` bounds the procedure.
    """

    method: int
    offset: int = 0
    speed_switch: int = 0
    speed_zero: int = 0
    acceleration: int = 0
    timeout_ms: int = 30_000


@dataclass(frozen=True)
class MotionProfileConfig:
    """A drive map's ``motion_profile:`` section (CiA 402-2 profile position/velocity modes, PP/PV);
    bring-up writes it as start-up SDOs.

    ``velocity`` 0x6081 profile velocity [velocity units], ``acceleration``/``deceleration``
    0x6083/0x6084 [acceleration units]; ``timeout_ms`` bounds one move (:class:`fieldbus.ProfileMove`).
    None: not written (the drive keeps its own value).
    """

    velocity: int | None = None
    acceleration: int | None = None
    deceleration: int | None = None
    timeout_ms: int = 30_000


@dataclass(frozen=True)
class SyncManager:
    """An EtherCAT SyncManager as in ethercat_driver_ros2's ``sm`` list."""

    index: int
    type: str  # "output" | "input"
    pdo: str | None = None  # "rpdo" | "tpdo" | None
    watchdog: bool = False
    start: int | None = None
    size: int | None = None


@dataclass(frozen=True)
class DcMode:
    """One DC operation mode of an ESI ``<Dc><OpMode>`` (times in ns).

    A ``*_factor`` is the ESI's ``Factor`` attribute: SYNC0 as a multiple of the
    bus cycle, SYNC1 as a multiple of the SYNC0 cycle; the ``*_cycle_ns`` value
    applies when the factor is 0.
    """

    name: str
    description: str = ""
    assign_activate: int = 0
    sync0_cycle_factor: int = 0
    sync0_cycle_ns: int = 0
    sync0_shift_ns: int = 0
    sync1_cycle_factor: int = 0
    sync1_cycle_ns: int = 0
    sync1_shift_ns: int = 0


@dataclass(frozen=True)
class EthercatConfig:
    """EtherCAT specifics. Times in ns; mailbox sizes in bytes."""

    coe: bool = True
    lrw: bool = True
    mailbox_size: int = 128
    sync0_shift_ns: int = 0
    sync1_cycle_ns: int = 0
    revision: int = 0
    serial: int = 0
    dc_modes: tuple[DcMode, ...] = ()  # the device's DC operation modes (from its ESI); informational
    # False: the device's PDO assignment (0x1C12/0x1C13) is fixed (ESI CoE@PdoAssign not true); bring-up
    # never writes it, and PDO indexes anywhere in 0x1600-0x1BFF are taken as the device names them
    pdo_assign: bool = True
    # True: the device keeps an ETG.1020 diagnosis history (0x10F3); after a drive fault the network reads its
    # newest messages and reports them in the DriveFault event (fieldbus.diagnosis)
    diagnosis_history: bool = False


@dataclass(frozen=True)
class CanopenConfig:
    """CANopen specifics. ``fd``: CAN FD frames (PDOs up to 64 bytes)."""

    fd: bool = False
    heartbeat_ms: int = 100
    disable_unused_pdos: bool = True


@dataclass(frozen=True)
class DriveMap:
    """A validated drive map: identity, PDOs, start-up SDOs, bus specifics."""

    name: str
    vendor_id: int
    product_id: int
    rpdo: tuple[Pdo, ...] = ()
    tpdo: tuple[Pdo, ...] = ()
    sdo: tuple[SdoWrite, ...] = ()
    sm: tuple[SyncManager, ...] = ()
    description: str = ""
    revision: int = 0
    profile: str | None = None
    assign_activate: int = 0
    auto_fault_reset: bool = False
    ethercat: EthercatConfig = field(default_factory=EthercatConfig)
    canopen: CanopenConfig | None = None
    rawcan: RawCanConfig | None = None  # raw-CAN motor frames (MIT mode); see fieldbus.core.rawcan
    homing: HomingConfig | None = None  # its SDOs are in ``sdo`` too (appended, in 0x6098..0x609A order)
    motion_profile: MotionProfileConfig | None = None  # its SDOs are in ``sdo`` too (0x6081, 0x6083, 0x6084)
    source: str = "<string>"
    # multi-axis devices (``axes:``): rpdo/tpdo/sdo above describe axis 1; axis k adds object_offsets[k] to
    # its CiA 402 objects (0x6000-0x67FF) and pdo_offsets[k] to its PDO indexes; see :attr:`bus_map`
    object_offsets: tuple[int, ...] = (0,)
    pdo_offsets: tuple[int, ...] = (0,)
    # CANopen communication parameters of axes 2..n's PDO copies, by their mapping index (0x1602 -> ...)
    axis_canopen: tuple[tuple[int, CanopenPdo], ...] = ()
    # the output path's limits (fieldbus.core.output_rules): the map's own; ``limits: off`` drops the defaults
    limits: tuple[OutputLimit, ...] = ()
    limits_off: bool = False

    @property
    def axes(self) -> int:
        """CiA 402 axes (logical devices) of one slave: rows of the group's image per slave."""
        return len(self.object_offsets)

    def axis_index(self, index: int, axis: int) -> int:
        """The object ``index`` of axis 1 as axis ``axis`` (0-based) names it (0x603F -> 0x683F for axis 1)."""
        return index + self.object_offsets[axis] if is_axis_object(index) else index

    @cached_property
    def bus_map(self) -> DriveMap:
        """The whole device as the bus sees it: every axis's PDOs (axis order) and start-up SDOs.

        Itself for a one-axis map. Axis k's channels are named ``<name>_axis<k+1>`` (k >= 1).
        """
        if self.axes == 1:
            return self
        return _expand_axes(self)

    def pdos(self, direction: Direction) -> tuple[Pdo, ...]:
        return self.rpdo if direction is Direction.OUTPUTS else self.tpdo

    def channels(self, direction: Direction) -> tuple[Channel, ...]:
        """Non-gap channels of a direction, in wire order."""
        return tuple(c for p in self.pdos(direction) for c in p.channels if not c.is_gap)

    def find(self, direction: Direction, index: int, sub_index: int = 0) -> Channel | None:
        """The channel mapping object ``index:sub_index`` in ``direction``, if any."""
        for c in self.channels(direction):
            if c.index == index and c.sub_index == sub_index:
                return c
        return None


AXIS_OBJECTS = (0x6000, 0x67FF)  # CiA 402 objects of the first logical device (axis); the next at +0x800


def is_axis_object(index: int) -> bool:
    """An object of a CiA 402 axis (0x6000-0x67FF): repeated per axis in a multi-axis device."""
    return AXIS_OBJECTS[0] <= index <= AXIS_OBJECTS[1]


def _expand_axes(drive: DriveMap) -> DriveMap:
    """:attr:`DriveMap.bus_map` of a multi-axis map."""

    copies = dict(drive.axis_canopen)

    def pdos(group: tuple[Pdo, ...]) -> tuple[Pdo, ...]:
        out = []
        for k, pdo_off in enumerate(drive.pdo_offsets):
            for p in group:
                chans = tuple(
                    c
                    if k == 0 or c.is_gap
                    else replace(c, index=drive.axis_index(c.index, k), name=f"{c.name}_axis{k + 1}")
                    for c in p.channels
                )
                index = p.index + pdo_off
                out.append(replace(p, index=index, channels=chans, canopen=copies.get(index, p.canopen)))
        return tuple(out)

    sdos = list(drive.sdo)
    for k in range(1, drive.axes):
        sdos += [replace(s, index=drive.axis_index(s.index, k)) for s in drive.sdo if is_axis_object(s.index)]
    return replace(
        drive,
        rpdo=pdos(drive.rpdo),
        tpdo=pdos(drive.tpdo),
        sdo=tuple(sdos),
        object_offsets=(0,),
        pdo_offsets=(0,),
        axis_canopen=(),
    )
