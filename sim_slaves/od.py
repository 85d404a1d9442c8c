"""A CiA 301 / ETG.1000.6 object dictionary for emulated drives, built from a drive map.

Shared by the EtherCAT (CoE) emulator and, later, the CANopen emulator.
Two faces:

- the *bus* face :meth:`ObjectDictionary.read` / :meth:`ObjectDictionary.write`
  works on little-endian bytes, checks access, lengths and the communication
  state, and raises :class:`~fieldbus.errors.SdoAbortError` with a CiA 301
  abort code;
- the *application* face :meth:`get_value` / :meth:`set_value` (the
  ``ObjectStore`` protocol of :mod:`sim_slaves.drive402`) works on numbers and
  never checks access: it is how the drive model and the process data reach
  the objects. A missing object raises ``KeyError``.

PDO mapping objects (0x16xx RxPDO = master outputs, 0x1Axx TxPDO = master
inputs) and PDO assignment (0x1C12 outputs, 0x1C13 inputs) are writable in
PRE-OPERATIONAL only (abort 0x08000022 otherwise); sub-index 0 must be 0
before entries are changed (abort 0x06010003). Every accepted write to them
bumps :attr:`ObjectDictionary.mapping_version`, so the owner re-lays out its
process data.
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import IntEnum
from typing import TYPE_CHECKING

from fieldbus.core import datatypes
from fieldbus.core.datatypes import DataType
from fieldbus.core.pdo.model import Channel, DriveMap, Pdo
from fieldbus.core.pdo.names import CIA402_NAMES
from fieldbus.errors import SdoAbortError

if TYPE_CHECKING:
    from sim_slaves.drive402 import DriveParams

U8 = datatypes.lookup("uint8")
U16 = datatypes.lookup("uint16")
U32 = datatypes.lookup("uint32")
assert U8 is not None and U16 is not None and U32 is not None

# CiA 301 abort codes used here.
ABORT_UNSUPPORTED = 0x06010000
ABORT_READ_ONLY = 0x06010002
ABORT_SI0_NOT_ZERO = 0x06010003
ABORT_NO_OBJECT = 0x06020000
ABORT_NOT_MAPPABLE = 0x06040041
ABORT_PDO_TOO_LONG = 0x06040042
ABORT_LENGTH = 0x06070010
ABORT_TOO_LONG = 0x06070012
ABORT_TOO_SHORT = 0x06070013
ABORT_NO_SUBINDEX = 0x06090011
ABORT_VALUE_RANGE = 0x06090030
ABORT_VALUE_HIGH = 0x06090031
ABORT_STATE = 0x08000022

RXPDO_MAP = range(0x1600, 0x1800)  # master outputs
TXPDO_MAP = range(0x1A00, 0x1C00)  # master inputs
RXPDO_ASSIGN = 0x1C12
TXPDO_ASSIGN = 0x1C13
SM_COMM_TYPE = 0x1C00
MAX_PDO_BITS = 8 * 256  # longest PDO this emulator accepts
MAPPING_CAPACITY = 16  # entries per mapping object
ASSIGN_CAPACITY = 8  # PDOs per assignment object
DEVICE_TYPE_402 = 0x00020192  # CiA 402 servo drive


class CommState(IntEnum):
    """Communication state of the device, for access rules (EtherCAT AL / CANopen NMT)."""

    INIT = 1
    PRE_OPERATIONAL = 2
    SAFE_OPERATIONAL = 4
    OPERATIONAL = 8


class Access(IntEnum):
    RO = 1
    RW = 3
    CONST = 5


class ObjectCode(IntEnum):
    """CiA 301 / ETG.1000.6 object codes (SDO Information)."""

    VAR = 7
    ARRAY = 8
    RECORD = 9


# PDO mapping directions of an entry (ETG.1000.6 object access bits 6 and 7).
PDO_RX = 0x40  # mappable into an RxPDO (master output)
PDO_TX = 0x80  # mappable into a TxPDO (master input)


@dataclass
class Entry:
    """One sub-index. ``dtype`` None: a visible string held as bytes in ``value``."""

    dtype: DataType | None
    value: int | float | bytes
    access: Access = Access.RW
    name: str = ""
    mappable: bool = False
    pdo_dir: int = 0  # PDO_RX | PDO_TX: which PDOs may map it (SDO Information)

    @property
    def size(self) -> int:
        """Bytes of the value on the bus."""
        if self.dtype is None:
            assert isinstance(self.value, bytes)
            return len(self.value)
        return max(1, (self.dtype.bits + 7) // 8)

    def encode(self) -> bytes:
        if self.dtype is None:
            assert isinstance(self.value, bytes)
            return self.value
        assert not isinstance(self.value, bytes)
        return self.dtype.encode(self.value)


# a writable VISIBLE_STRING every emulated device has (manufacturer area), for long downloads
USER_LABEL = 0x2100

# CiA 402 objects: type name and a fallback default (sim_slaves.drive402 supplies better ones).
CIA402_TYPES: dict[int, str] = {
    0x603F: "uint16",  # error code
    0x6040: "uint16",  # controlword (master output)
    0x6041: "uint16",  # statusword (master input)
    0x605A: "int16",  # quick stop option
    0x605E: "int16",  # fault reaction option
    0x6060: "int8",  # modes of operation (master output)
    0x6061: "int8",  # modes of operation display (master input)
    0x6064: "int32",  # position actual [counts]
    0x6065: "uint32",  # following error window [counts]
    0x6066: "uint16",  # following error timeout [ms]
    0x6067: "uint32",  # position window [counts]
    0x606C: "int32",  # velocity actual [counts/s]
    0x606D: "uint16",  # velocity window [counts/s]
    0x6071: "int16",  # target torque [per mille]
    0x6072: "uint16",  # max torque [per mille]
    0x6076: "uint32",  # motor rated torque [mN·m]
    0x6077: "int16",  # torque actual [per mille]
    0x607A: "int32",  # target position [counts]
    0x6080: "uint32",  # max motor speed [rpm]
    0x6085: "uint32",  # quick stop deceleration [acceleration units]
    0x60F4: "int32",  # following error actual [counts]
    0x60FF: "int32",  # target velocity [counts/s]
    0x6502: "uint32",  # supported drive modes
    # every object of the modes 0x6502 advertises, as a real drive has them whatever the master writes
    0x606F: "uint16",  # PV: velocity threshold [velocity units]
    0x607C: "int32",  # HM: home offset [counts]
    0x6081: "uint32",  # PP: profile velocity [velocity units]
    0x6083: "uint32",  # PP/PV: profile acceleration [acceleration units]
    0x6084: "uint32",  # PP/PV: profile deceleration [acceleration units]
    0x6086: "int16",  # PP/PV: motion profile type (0 linear ramp, the only one emulated)
    0x6098: "int8",  # HM: homing method
    0x609A: "uint32",  # HM: homing acceleration [acceleration units]
    0x60F2: "uint16",  # PP: positioning option code
}
# CiA 402 arrays of two sub-indices: type, object name, sub-index names (values: sim_slaves.drive402)
CIA402_RECORDS: dict[int, tuple[str, str, tuple[str, str]]] = {
    0x607D: ("int32", "Software position limit", ("Min position limit", "Max position limit")),
    0x608F: ("uint32", "Position encoder resolution", ("Encoder increments", "Motor revolutions")),
    0x6091: ("uint32", "Gear ratio", ("Motor revolutions", "Shaft revolutions")),
    0x6099: ("uint32", "Homing speeds", ("Speed during search for switch", "Speed during search for zero")),
}
# names of the mode objects CIA402_NAMES (channel names) leaves out
MODE_OBJECT_NAMES = {
    0x606F: "velocity_threshold",
    0x607C: "home_offset",
    0x6081: "profile_velocity",
    0x6083: "profile_acceleration",
    0x6084: "profile_deceleration",
    0x6086: "motion_profile_type",
    0x6098: "homing_method",
    0x609A: "homing_acceleration",
    0x60F2: "positioning_option_code",
}
NOT_MAPPABLE_402 = frozenset(
    {0x6076, 0x6080, 0x6502, 0x6086, 0x609A, 0x606F}
)  # configuration objects: SDO only
SUPPORTED_MODES_HM_CSP_CSV_CST = 0x000003A5  # 0x6502 bits 0, 2 (PP, PV), 5 (homing), 7, 8, 9 (CSP, CSV, CST)
CIA402_OUTPUTS = frozenset(  # RxPDO-mappable
    {0x6040, 0x6060, 0x6071, 0x6072, 0x607A, 0x60FF, 0x607C, 0x6081, 0x6083, 0x6084, 0x6098, 0x60F2}
)
IDENTITY_NAMES = ("Vendor ID", "Product code", "Revision number", "Serial number")
DEFTYPE_PDO_MAPPING = 0x0021  # CiA 301 structured types (SDO Information data type of records)
DEFTYPE_IDENTITY = 0x0023


class ObjectDictionary:
    """Objects by (index, sub-index); see the module docstring for the two faces."""

    def __init__(self) -> None:
        self._entries: dict[tuple[int, int], Entry] = {}
        self._subs: dict[int, list[int]] = {}
        self._aborts: dict[tuple[int, int | None], int] = {}
        self._objects: dict[int, tuple[str, ObjectCode | None, int | None]] = {}
        self.mapping_version = 0

    # -- building --

    def add(
        self,
        index: int,
        sub: int,
        dtype: DataType | None,
        value: int | float | bytes = 0,
        *,
        access: Access = Access.RW,
        name: str = "",
        mappable: bool = False,
        pdo_dir: int = 0,
    ) -> None:
        """Add (or replace) one sub-index."""
        if (index, sub) not in self._entries:
            subs = self._subs.setdefault(index, [])
            subs.append(sub)
            subs.sort()
        self._entries[(index, sub)] = Entry(dtype, value, access, name, mappable, pdo_dir)

    def describe(
        self, index: int, name: str, code: ObjectCode | None = None, data_type: int | None = None
    ) -> None:
        """Name an object (SDO Information); ``code``/``data_type`` override what its entries imply."""
        self._objects[index] = (name, code, data_type)

    def object_name(self, index: int) -> str:
        """The object's name: as described, else its sub-index 0 name, else its address."""
        if index in self._objects:
            return self._objects[index][0]
        e = self._entries.get((index, 0))
        if self.object_code(index) is ObjectCode.VAR and e is not None and e.name:
            return e.name
        return f"0x{index:04X}"

    def object_code(self, index: int) -> ObjectCode:
        """VAR for a lone sub-index 0, else RECORD (unless described otherwise)."""
        code = self._objects.get(index, ("", None, None))[1]
        if code is not None:
            return code
        return ObjectCode.VAR if self._subs.get(index) == [0] else ObjectCode.RECORD

    def object_data_type(self, index: int) -> int:
        """CoE data type code of the object: a VAR's type, an ARRAY's element type, else as described."""
        described = self._objects.get(index, ("", None, None))[2]
        if described is not None:
            return described
        subs = self._subs.get(index, [])
        key = (index, 0) if self.object_code(index) is ObjectCode.VAR or len(subs) < 2 else (index, subs[1])
        return entry_type_code(self._entries[key])

    def add_string(self, index: int, text: str, name: str = "") -> None:
        self.add(index, 0, None, text.encode(), access=Access.CONST, name=name)

    def fix_subindex0(self) -> None:
        """Give every object with sub-indices > 0 and no sub-index 0 an RO sub-index 0 = highest sub."""
        for index, subs in list(self._subs.items()):
            if 0 not in subs:
                self.add(index, 0, U8, max(subs), access=Access.RO, name="Highest sub-index supported")

    # -- queries --

    def __contains__(self, key: object) -> bool:
        return key in self._entries

    def has(self, index: int, sub: int = 0) -> bool:
        return (index, sub) in self._entries

    def indices(self) -> list[int]:
        return sorted(self._subs)

    def subindices(self, index: int) -> list[int]:
        return list(self._subs.get(index, ()))

    def entry(self, index: int, sub: int) -> Entry:
        """The entry, or :class:`SdoAbortError` 0x06020000 / 0x06090011."""
        e = self._entries.get((index, sub))
        if e is None:
            code = ABORT_NO_SUBINDEX if index in self._subs else ABORT_NO_OBJECT
            raise SdoAbortError(code, index=index, sub_index=sub)
        return e

    # -- application face (ObjectStore protocol) --

    def get_value(self, index: int, sub: int) -> int | float:
        """Numeric value of ``index:sub`` (``KeyError`` if missing; strings are not numbers)."""
        v = self._entries[(index, sub)].value
        if isinstance(v, bytes):
            raise KeyError((index, sub))
        return v

    def set_value(self, index: int, sub: int, value: int | float) -> None:
        """Set a numeric value without access checks (``KeyError`` if missing)."""
        self._entries[(index, sub)].value = value

    # -- fault injection --

    def inject_abort(self, index: int, sub: int | None, code: int) -> None:
        """Answer every SDO access to ``index:sub`` (``sub`` None: any sub-index) with ``code``."""
        self._aborts[(index, sub)] = code

    def clear_aborts(self) -> None:
        self._aborts.clear()

    def _injected(self, index: int, sub: int) -> None:
        if self._aborts:
            code = self._aborts.get((index, sub), self._aborts.get((index, None)))
            if code is not None:
                raise SdoAbortError(code, index=index, sub_index=sub, detail="injected")

    # -- bus face --

    def read(self, index: int, sub: int) -> bytes:
        """Little-endian bytes of ``index:sub`` (SDO upload)."""
        self._injected(index, sub)
        return self.entry(index, sub).encode()

    def write(self, index: int, sub: int, data: bytes, *, state: CommState) -> None:
        """SDO download of ``data`` into ``index:sub`` in communication state ``state``."""
        self._injected(index, sub)
        e = self.entry(index, sub)
        if e.access is not Access.RW:
            raise SdoAbortError(ABORT_READ_ONLY, index=index, sub_index=sub)
        if e.dtype is None:
            e.value = bytes(data)
            return
        if len(data) > e.size:
            raise SdoAbortError(ABORT_TOO_LONG, index=index, sub_index=sub)
        if len(data) < e.size:
            raise SdoAbortError(ABORT_TOO_SHORT, index=index, sub_index=sub)
        value = e.dtype.decode(bytes(data))
        if _is_mapping(index):
            self._check_mapping_write(index, sub, int(value), state)
            e.value = value
            self.mapping_version += 1
            return
        e.value = value

    def _check_mapping_write(self, index: int, sub: int, value: int, state: CommState) -> None:
        if state is not CommState.PRE_OPERATIONAL:
            raise SdoAbortError(ABORT_STATE, index=index, sub_index=sub, detail="PDO mapping outside PRE-OP")
        count = int(self.get_value(index, 0))
        if sub > 0:
            if count != 0:
                raise SdoAbortError(ABORT_SI0_NOT_ZERO, index=index, sub_index=sub)
            if index in (RXPDO_ASSIGN, TXPDO_ASSIGN) and value != 0:
                allowed = RXPDO_MAP if index == RXPDO_ASSIGN else TXPDO_MAP
                if value not in allowed or not self.has(value, 0):
                    raise SdoAbortError(ABORT_VALUE_RANGE, index=index, sub_index=sub)
            return
        capacity = max(self._subs[index])
        if value > capacity:
            raise SdoAbortError(ABORT_VALUE_HIGH, index=index, sub_index=sub)
        if index in (RXPDO_ASSIGN, TXPDO_ASSIGN):
            for s in range(1, value + 1):
                pdo = int(self.get_value(index, s))
                if not self.has(pdo, 0):
                    raise SdoAbortError(ABORT_VALUE_RANGE, index=index, sub_index=0)
            return
        bits = 0
        for s in range(1, value + 1):
            raw = int(self.get_value(index, s))
            bits += self._mapped_channel(index, raw).bits
        if bits > MAX_PDO_BITS:
            raise SdoAbortError(ABORT_PDO_TOO_LONG, index=index, sub_index=0)

    def _mapped_channel(self, mapping: int, raw: int) -> Channel:
        """The channel a 32-bit mapping entry names (gaps: index 0 or a dummy type 1..7)."""
        obj, sub, bits = raw >> 16, (raw >> 8) & 0xFF, raw & 0xFF
        if bits == 0:
            raise SdoAbortError(ABORT_NOT_MAPPABLE, index=mapping, sub_index=0, detail="zero bit length")
        if obj <= 0x0007:
            gap = datatypes.lookup(f"bit{bits}")
            assert gap is not None
            return Channel(obj, sub, gap, f"gap_{bits}")
        e = self._entries.get((obj, sub))
        if e is None or not e.mappable or e.dtype is None or e.dtype.bits != bits:
            raise SdoAbortError(
                ABORT_NOT_MAPPABLE, index=mapping, sub_index=0, detail=f"0x{obj:04X}:{sub:02X}/{bits}"
            )
        return Channel(obj, sub, e.dtype, e.name or f"0x{obj:04X}_{sub:02X}")

    # -- PDO mapping as a model --

    def pdo(self, mapping: int) -> Pdo:
        """The PDO described by mapping object ``mapping`` (0x16xx / 0x1Axx) as it stands."""
        count = int(self.get_value(mapping, 0))
        chans = tuple(
            self._mapped_channel(mapping, int(self.get_value(mapping, s))) for s in range(1, count + 1)
        )
        return Pdo(mapping, chans)

    def assigned_pdos(self, assign: int) -> tuple[Pdo, ...]:
        """The PDOs assigned by 0x1C12 (outputs) or 0x1C13 (inputs), in order."""
        count = int(self.get_value(assign, 0))
        return tuple(self.pdo(int(self.get_value(assign, s))) for s in range(1, count + 1))

    # -- from a drive map --

    @classmethod
    def from_drive_map(cls, drive: DriveMap, params: DriveParams | None = None) -> ObjectDictionary:
        """The OD of an emulated device described by ``drive``.

        Holds 0x1000 device type, 0x1008 name, 0x1018 identity, 0x1C00 SM
        communication types, 0x1C12/0x1C13 assignment, the map's 0x16xx/0x1Axx
        mapping objects, every mapped object with its type, the start-up SDO
        objects, and the CiA 402 objects for ``profile: cia402`` maps (or maps
        that map 0x6040) -- every object of every mode 0x6502 advertises (PP, PV, HM, CSP, CSV, CST),
        whether or not the map has a ``homing:`` or ``motion_profile:`` section -- at the values of the
        drive ``params`` describe
        (default: the drive the map implies, :func:`sim_slaves.drive_config.drive_params`):
        units (0x608F, 0x6091), rated torque (0x6076), limits (0x6072, 0x607D,
        0x6080), quick stop (0x605A, 0x6085), windows.
        """
        od = cls()
        is402 = is_cia402_drive(drive)
        od._add_device(drive, is402)
        if is402:
            od._add_cia402(drive, params)
        od._add_mapped(drive)
        od._add_assignment(drive)
        od.fix_subindex0()
        return od

    def _add_device(self, drive: DriveMap, is402: bool) -> None:
        """0x1000 device type, 0x1001, 0x1008 name, the user label, 0x1018 identity, 0x1C00 SM types."""
        self.add(0x1000, 0, U32, DEVICE_TYPE_402 if is402 else 0, access=Access.RO, name="Device type")
        self.add(0x1001, 0, U8, 0, access=Access.RO, name="Error register")
        self.add_string(0x1008, drive.name, "Manufacturer device name")
        self.add(USER_LABEL, 0, None, b"", access=Access.RW, name="User label")
        ident = (
            drive.vendor_id,
            drive.product_id,
            drive.revision or drive.ethercat.revision,
            drive.ethercat.serial,
        )
        self.describe(0x1018, "Identity object", ObjectCode.RECORD, DEFTYPE_IDENTITY)
        for sub, (v, n) in enumerate(zip(ident, IDENTITY_NAMES, strict=True), start=1):
            self.add(0x1018, sub, U32, v, access=Access.RO, name=n)
        self.add(0x1018, 0, U8, 4, access=Access.RO, name="Highest sub-index supported")
        self.describe(SM_COMM_TYPE, "Sync manager communication type", ObjectCode.ARRAY, 0x0005)
        self.add(SM_COMM_TYPE, 0, U8, 4, access=Access.RO, name="Highest sub-index supported")
        for sub, v in enumerate((1, 2, 3, 4), start=1):
            self.add(SM_COMM_TYPE, sub, U8, v, access=Access.RO, name=f"Communication type SM{sub - 1}")

    def _add_cia402(self, drive: DriveMap, params: DriveParams | None) -> None:
        """Every CiA 402 object of every mode 0x6502 advertises, at the values ``params`` describe."""
        defaults = _cia402_defaults(drive, params)
        for index, tname in CIA402_TYPES.items():
            dt = datatypes.lookup(tname)
            assert dt is not None
            value = SUPPORTED_MODES_HM_CSP_CSV_CST if index == 0x6502 else defaults.get((index, 0), 0)
            mappable = index not in NOT_MAPPABLE_402
            self.add(
                index,
                0,
                dt,
                value,
                name=CIA402_NAMES.get((index, 0)) or MODE_OBJECT_NAMES.get(index, f"0x{index:04X}"),
                mappable=mappable,
                pdo_dir=0 if not mappable else (PDO_RX if index in CIA402_OUTPUTS else PDO_TX),
            )
        for index, (tname, name, subs) in CIA402_RECORDS.items():
            dt = datatypes.lookup(tname)
            assert dt is not None
            self.describe(index, name, ObjectCode.ARRAY)
            for sub, sub_name in enumerate(subs, start=1):
                self.add(index, sub, dt, defaults.get((index, sub), 0), name=sub_name)

    def _add_mapped(self, drive: DriveMap) -> None:
        """The start-up SDO objects and every mapped object with its type and PDO direction(s)."""
        for sdo in drive.sdo:
            if not self.has(sdo.index, sdo.sub_index):
                self.add(sdo.index, sdo.sub_index, sdo.type, 0, name=sdo.description)
        for direction, pdos in ((PDO_RX, drive.rpdo), (PDO_TX, drive.tpdo)):
            for pdo in pdos:
                for ch in pdo.channels:
                    if ch.is_gap:
                        continue
                    old = self._entries.get((ch.index, ch.sub_index))
                    keep = old is not None and old.dtype == ch.type
                    self.add(
                        ch.index,
                        ch.sub_index,
                        ch.type,
                        old.value if old and keep else 0,
                        name=ch.name,
                        mappable=True,
                        pdo_dir=direction | (old.pdo_dir if old and keep else 0),
                    )
                    if ch.sub_index and ch.index not in self._objects:
                        self.describe(ch.index, ch.name)

    def _add_assignment(self, drive: DriveMap) -> None:
        """0x1C12/0x1C13 assignment and the 0x16xx/0x1Axx mapping objects (read-only where fixed)."""
        # a fixed assignment (ethercat.pdo_assign: false) and a fixed PDO's mapping are read-only
        assign_access = Access.RW if drive.ethercat.pdo_assign else Access.RO
        for assign, pdos in ((RXPDO_ASSIGN, drive.rpdo), (TXPDO_ASSIGN, drive.tpdo)):
            kind = "RxPDO" if assign == RXPDO_ASSIGN else "TxPDO"
            self.describe(assign, f"{kind} assign", ObjectCode.ARRAY, 0x0006)
            self.add(assign, 0, U8, len(pdos), access=assign_access, name="Highest sub-index supported")
            for sub in range(1, max(ASSIGN_CAPACITY, len(pdos)) + 1):
                self.add(
                    assign,
                    sub,
                    U16,
                    pdos[sub - 1].index if sub <= len(pdos) else 0,
                    access=assign_access,
                    name=f"SubIndex {sub:03d}",
                )
            for pdo in pdos:
                access = Access.RO if pdo.fixed else Access.RW
                self.describe(
                    pdo.index, f"{kind} mapping {pdo.number}", ObjectCode.RECORD, DEFTYPE_PDO_MAPPING
                )
                self.add(
                    pdo.index, 0, U8, len(pdo.channels), access=access, name="Highest sub-index supported"
                )
                for sub in range(1, max(MAPPING_CAPACITY, len(pdo.channels)) + 1):
                    raw = pdo.channels[sub - 1].mapping_value if sub <= len(pdo.channels) else 0
                    self.add(pdo.index, sub, U32, raw, access=access, name=f"SubIndex {sub:03d}")


def is_cia402_drive(drive: DriveMap) -> bool:
    """An emulated device is a CiA 402 drive for ``profile: cia402`` maps and maps that map the controlword."""
    return drive.profile == "cia402" or any(c.index == 0x6040 for p in drive.rpdo for c in p.channels)


def entry_type_code(e: Entry) -> int:
    """CoE data type code of an entry (VISIBLE_STRING 0x0009 for strings)."""
    return 0x0009 if e.dtype is None else (e.dtype.coe_code or _BIT_CODES.get(e.dtype.bits, 0))


_BIT_CODES = {n: 0x002F + n for n in range(1, 9)}  # BIT1 = 0x0030 .. BIT8 = 0x0037


def _is_mapping(index: int) -> bool:
    return index in RXPDO_MAP or index in TXPDO_MAP or index in (RXPDO_ASSIGN, TXPDO_ASSIGN)


def _cia402_defaults(drive: DriveMap, params: DriveParams | None) -> dict[tuple[int, int], int | float]:
    try:
        from sim_slaves.drive402 import default_objects
        from sim_slaves.drive_config import drive_params
    except ImportError:  # the drive model is optional for the OD
        return {}
    return dict(default_objects(params or drive_params(drive)))
