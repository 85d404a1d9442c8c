"""Multi-axis CiA 402 slaves: one EtherCAT device, n drives answering at +0x800 per axis.

CiA 402 gives the k-th axis ("logical device") of a device the objects of the
first at ``0x800 x k`` higher (0x6040 -> 0x6840). The drive map describes axis 1
and says how many axes there are (``axes:``, see :attr:`DriveMap.bus_map`); here
the device's object dictionary holds every axis's objects, and
:class:`MultiAxisDrive` runs one :class:`~sim_slaves.drive402.Cia402Drive` per
axis, each seeing its own objects through an :class:`AxisObjects` view that
shifts 0x6000-0x67FF by the axis's offset. The axes are the drives of one
:class:`~sim_slaves.drive_bank.DriveBank`, stepped together in one bank step.
"""

from __future__ import annotations

from fieldbus.core.pdo.model import DriveMap, is_axis_object
from sim_slaves.drive402 import Cia402Drive, DriveParams
from sim_slaves.drive_bank import DriveBank
from sim_slaves.ethercat.diaghistory import add_diag_history, record_fault
from sim_slaves.od import ObjectDictionary, is_cia402_drive


class AxisObjects:
    """The objects of one axis: 0x6000-0x67FF at ``offset`` above, every other object as it is."""

    def __init__(self, od: ObjectDictionary, offset: int) -> None:
        self.od = od
        self.offset = offset

    def _index(self, index: int) -> int:
        return index + self.offset if is_axis_object(index) else index

    def get_value(self, index: int, sub: int) -> int | float:
        return self.od.get_value(self._index(index), sub)

    def set_value(self, index: int, sub: int, value: int | float) -> None:
        self.od.set_value(self._index(index), sub, value)


def device_od(drive: DriveMap, params: DriveParams | None = None) -> ObjectDictionary:
    """The object dictionary of the device ``drive`` describes, every axis's objects included."""
    od = ObjectDictionary.from_drive_map(drive.bus_map, params)
    for k in range(1, drive.axes):
        off = drive.object_offsets[k]
        for (index, sub), e in list(od._entries.items()):
            if is_axis_object(index) and (index + off, sub) not in od._entries:
                od.add(
                    index + off,
                    sub,
                    e.dtype,
                    e.value,
                    access=e.access,
                    name=e.name,
                    mappable=e.mappable,
                    pdo_dir=e.pdo_dir,
                )
        for index, (name, code, data_type) in list(od._objects.items()):
            if is_axis_object(index) and index + off not in od._objects:
                od.describe(index + off, f"{name} (axis {k + 1})", code, data_type)
    od.fix_subindex0()
    if is_cia402_drive(drive):
        add_diag_history(od)  # ETG.1020 0x10F3: a fault writes a message (sim_slaves.ethercat.diaghistory)
    return od


class MultiAxisDrive:
    """The application of a multi-axis slave: one CiA 402 drive per axis, stepped together.

    ``state`` is axis 1's (what a one-axis probe reads), ``states`` every axis's.
    """

    def __init__(self, drives: list[Cia402Drive], offsets: tuple[int, ...]) -> None:
        if len(drives) != len(offsets):
            raise ValueError(f"{len(drives)} drives for {len(offsets)} axes")
        self.drives = drives if _one_run(drives) else _in_one_bank(drives)  # stepped together
        self.offsets = offsets
        self._od: ObjectDictionary | None = None
        self._views: list[AxisObjects] = []
        self._time_ns = 0  # local time [ns]: the sum of the steps, for the diagnosis history

    @property
    def params(self) -> DriveParams:
        return self.drives[0].params

    @property
    def state(self) -> object:
        return self.drives[0].state

    @property
    def states(self) -> list[object]:
        return [d.state for d in self.drives]

    def step(self, od: ObjectDictionary, dt_s: float) -> None:
        if od is not self._od:  # a new OD (power cycle): new views, so each drive binds again
            self._od = od
            self._views = [AxisObjects(od, off) for off in self.offsets]
        self._time_ns += round(dt_s * 1e9)
        bank, first = self.drives[0].bank, self.drives[0].slot
        before = [d.error_code for d in self.drives]
        for axis, view in enumerate(self._views):
            bank.load_inputs(first + axis, view)
        bank.step(first, first + len(self.drives), dt_s)
        for axis, (drive, view) in enumerate(zip(self.drives, self._views, strict=True)):
            bank.store_outputs(first + axis, view)
            if drive.error_code and drive.error_code != before[axis]:  # a fault began: the history gets it
                record_fault(od, drive.error_code, self._time_ns, axis)

    def inject_fault(self, code: int, *, persistent: bool = False, axis: int = 0) -> None:
        """Fault axis ``axis`` (0-based) with error code ``code`` (0x603F of that axis)."""
        self.drives[axis].inject_fault(code, persistent=persistent)

    def power_cycle(self) -> None:
        for d in self.drives:
            d.power_cycle()

    def connection_lost(self) -> None:
        for d in self.drives:
            d.connection_lost()


def _one_run(drives: list[Cia402Drive]) -> bool:
    """Are ``drives`` consecutive drives of one bank (one bank step steps them all)?"""
    first = drives[0]
    return all(d.bank is first.bank and d.slot == first.slot + k for k, d in enumerate(drives))


def _in_one_bank(drives: list[Cia402Drive]) -> list[Cia402Drive]:
    """New drives of one bank of their own, with the parameters of ``drives`` and where each stands."""
    bank = DriveBank([d.params for d in drives])
    for new, old in zip(bank.drives, drives, strict=True):
        new.place(old.position_rad)
    return bank.drives


def app_states(app: object) -> list[int]:
    """The CiA 402 state of each axis of a slave's application (-1: not a drive)."""
    states = getattr(app, "states", None)
    if states is None:
        states = [getattr(app, "state", -1)]
    return [int(s) for s in states]


def app_positions(app: object) -> list[float]:
    """Each axis's own shaft position in the drive's counts, unquantised (NaN: not a drive)."""
    drives = getattr(app, "drives", None) or [app]
    return [
        float(d.position_rad * d.counts_per_rad) if hasattr(d, "position_rad") else float("nan")
        for d in drives
    ]
