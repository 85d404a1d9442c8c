"""SDO plans: the ordered object writes that configure a drive's PDOs and start-up values.

Pure data; a backend executes a plan outside the cycle (EtherCAT PRE-OP hook,
CANopen PRE-OPERATIONAL), then reads back every step whose ``readback`` is set
and stops bring-up on the first abort or mismatch.

CoE order (ETG.1000.6 PDO assignment / mapping, as TwinCAT's start-up list):
clear 0x1C12:00 and 0x1C13:00; per PDO clear 0x16xx/0x1Axx:00, write the
entries, write the count; write the assignment entries and counts; then the
map's own start-up SDOs.

CANopen order (CiA 301, 7.5.2.35 "PDO mapping" procedure): per PDO set the
COB-ID invalid bit (31) in 0x14xx/0x18xx:01, write transmission type (and
inhibit / event time), clear the mapping count, write the entries, write the
count, write the COB-ID with bit 31 cleared; unused PDO 1-4 are disabled
first; then the heartbeat producer time (0x1017) and the start-up SDOs.
"""

from __future__ import annotations

import enum
from dataclasses import dataclass
from functools import cache

from fieldbus.core.pdo.load import DEFAULT_COB_IDS
from fieldbus.core.pdo.model import Direction, DriveMap, Pdo
from fieldbus.errors import FieldbusError

COB_ID_INVALID = 0x80000000


class StepKind(enum.Enum):
    WRITE = "write"  # download ``data``; read back later if ``readback`` is set
    VERIFY = "verify"  # upload only; the value must equal ``readback`` (fixed PDOs)


@dataclass(frozen=True)
class SdoStep:
    """One SDO transfer of a plan. ``data`` and ``readback`` are little-endian bytes."""

    kind: StepKind
    index: int
    sub_index: int
    data: bytes
    readback: bytes | None
    why: str

    @property
    def address(self) -> str:
        return f"0x{self.index:04X}:{self.sub_index:02X}"

    def __str__(self) -> str:
        verb = "write" if self.kind is StepKind.WRITE else "check"
        return f"{verb} {self.address} = {self.data.hex() or '-'}  ({self.why})"


@dataclass(frozen=True)
class SdoPlan:
    """The ordered steps configuring one drive on one bus (``"coe"`` or ``"canopen"``)."""

    drive: str
    bus: str
    steps: tuple[SdoStep, ...]

    @property
    def writes(self) -> tuple[SdoStep, ...]:
        return tuple(s for s in self.steps if s.kind is StepKind.WRITE)

    @property
    def checks(self) -> tuple[SdoStep, ...]:
        """Steps whose final value must be read back, in plan order."""
        return tuple(s for s in self.steps if s.readback is not None)


def _u8(v: int) -> bytes:
    return v.to_bytes(1, "little")


def _u16(v: int) -> bytes:
    return v.to_bytes(2, "little")


def _u32(v: int) -> bytes:
    return v.to_bytes(4, "little")


def _w(index: int, sub: int, data: bytes, why: str, *, final: bool = True) -> SdoStep:
    return SdoStep(StepKind.WRITE, index, sub, data, data if final else None, why)


def _mapping_steps(pdo: Pdo, mapping_index: int) -> list[SdoStep]:
    """Steps that write (or, for a fixed PDO, check) one mapping object."""
    what = f"PDO 0x{pdo.index:04X}"
    if pdo.fixed:
        steps = [
            SdoStep(StepKind.VERIFY, mapping_index, i, b"", _u32(ch.mapping_value), f"{what} fixed entry {i}")
            for i, ch in enumerate(pdo.channels, start=1)
        ]
        steps.append(
            SdoStep(StepKind.VERIFY, mapping_index, 0, b"", _u8(len(pdo.channels)), f"{what} fixed count")
        )
        return steps
    steps = [_w(mapping_index, 0, _u8(0), f"{what}: clear mapping count", final=False)]
    for i, ch in enumerate(pdo.channels, start=1):
        name = "gap" if ch.is_gap else ch.name
        steps.append(_w(mapping_index, i, _u32(ch.mapping_value), f"{what} entry {i}: {ch.address} {name}"))
    steps.append(_w(mapping_index, 0, _u8(len(pdo.channels)), f"{what}: {len(pdo.channels)} entries"))
    return steps


def _startup_steps(drive: DriveMap) -> list[SdoStep]:
    return [
        _w(s.index, s.sub_index, s.data, s.description or f"start-up {s.type.name} = {s.value:g}")
        for s in drive.sdo
    ]


@cache
def coe_plan(drive: DriveMap) -> SdoPlan:
    """The CoE (EtherCAT) plan: PDO assignment and mapping, then start-up SDOs.

    Computed once per map (maps and plans are frozen): a recovery that configures a
    power-cycled slave again reuses it.

    With ``ethercat.pdo_assign: false`` the assignment is the device's own and
    is not written; each PDO's mapping is still written (or, ``fixed``, verified).

    Empty for a map with ``ethercat.coe: false`` but start-up SDOs (mapping
    then comes from the SII).
    """
    drive = drive.bus_map  # a multi-axis map: every axis's PDOs and start-up SDOs
    if not drive.ethercat.coe:
        if drive.sdo:
            raise FieldbusError(f"{drive.name}: start-up SDOs need CoE, but ethercat.coe is false")
        return SdoPlan(drive.name, "coe", ())
    steps: list[SdoStep] = []
    assigns = (drive.rpdo or drive.tpdo) and drive.ethercat.pdo_assign  # False: the device's is fixed
    if assigns:
        steps.append(_w(0x1C12, 0, _u8(0), "clear RxPDO assignment (SM2, outputs)", final=False))
        steps.append(_w(0x1C13, 0, _u8(0), "clear TxPDO assignment (SM3, inputs)", final=False))
    for pdo in (*drive.rpdo, *drive.tpdo):
        steps.extend(_mapping_steps(pdo, pdo.index))
    if assigns:
        for assign, pdos in ((0x1C12, drive.rpdo), (0x1C13, drive.tpdo)):
            for i, pdo in enumerate(pdos, start=1):
                steps.append(_w(assign, i, _u16(pdo.index), f"assign PDO 0x{pdo.index:04X}"))
            steps.append(_w(assign, 0, _u8(len(pdos)), f"{len(pdos)} PDOs assigned"))
    steps.extend(_startup_steps(drive))
    return SdoPlan(drive.name, "coe", tuple(steps))


def canopen_plan(drive: DriveMap, node_id: int) -> SdoPlan:
    """The CANopen plan for ``drive`` at ``node_id`` (1..127), per CiA 301."""
    drive = drive.bus_map  # a multi-axis map: every axis's PDOs (their own COB-IDs) and start-up SDOs
    if drive.canopen is None:
        raise FieldbusError(f"{drive.name} ({drive.source}) has no 'canopen' section")
    if not 1 <= node_id <= 127:
        raise FieldbusError(f"node id {node_id} out of range 1..127")
    steps: list[SdoStep] = []
    for direction, comm_base in ((Direction.OUTPUTS, 0x1400), (Direction.INPUTS, 0x1800)):
        pdos = drive.pdos(direction)
        used = {p.number for p in pdos}
        if drive.canopen.disable_unused_pdos:
            for number, cob in enumerate(DEFAULT_COB_IDS[direction], start=1):
                if number not in used:
                    kind = direction.yaml_key.upper()
                    steps.append(
                        _w(
                            comm_base + number - 1,
                            1,
                            _u32(COB_ID_INVALID | (cob + node_id)),
                            f"disable unused {kind}{number}",
                        )
                    )
    for direction, comm_base in ((Direction.OUTPUTS, 0x1400), (Direction.INPUTS, 0x1800)):
        for pdo in drive.pdos(direction):
            assert pdo.canopen is not None  # the loader fills it when 'canopen' is present
            comm = comm_base + pdo.number - 1
            cob = pdo.canopen.cob_id_for(node_id)
            label = f"{direction.yaml_key.upper()}{pdo.number}"
            steps.append(
                _w(comm, 1, _u32(COB_ID_INVALID | cob), f"{label}: COB-ID invalid while mapping", final=False)
            )
            steps.append(_w(comm, 2, _u8(pdo.canopen.transmission_type), f"{label}: transmission type"))
            if direction is Direction.INPUTS:
                steps.append(_w(comm, 3, _u16(pdo.canopen.inhibit_time), f"{label}: inhibit time (100 us)"))
            if direction is Direction.INPUTS or pdo.canopen.event_timer:
                steps.append(_w(comm, 5, _u16(pdo.canopen.event_timer), f"{label}: event timer (ms)"))
            steps.extend(_mapping_steps(pdo, pdo.index))
            steps.append(_w(comm, 1, _u32(cob), f"{label}: COB-ID 0x{cob:03X} valid"))
    steps.append(_w(0x1017, 0, _u16(drive.canopen.heartbeat_ms), "producer heartbeat time (ms)"))
    steps.extend(_startup_steps(drive))
    return SdoPlan(drive.name, "canopen", tuple(steps))
