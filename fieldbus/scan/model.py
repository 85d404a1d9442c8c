"""What a bus scan found: devices, identities and PDO mappings as the devices report them. Plain data.

Both scans (EtherCAT, CANopen) fill these; ``--json`` prints them with
:func:`as_json`, ``--write-maps`` turns them into drive maps
(:mod:`fieldbus.scan.writemaps`).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from typing import Any

from fieldbus.core import datatypes
from fieldbus.core.pdo.names import CIA402_TYPES, default_name
from fieldbus.core.sdo.info import TYPE_NAMES

_BY_BITS = {1: "bool", 8: "uint8", 16: "uint16", 32: "uint32", 64: "uint64"}


@dataclass
class Identity:
    vendor_id: int
    product_id: int
    revision: int
    serial: int


@dataclass
class PdoEntry:
    """One mapped object. ``type``/``name``: from the device (SDO Information, SII), else a guess."""

    index: int
    sub_index: int
    bits: int
    type: str
    name: str
    source: str = "guess"  # "sdo-info" | "sii" | "cia402" | "guess"


@dataclass
class ScannedPdo:
    """One PDO as the device has it mapped; CANopen communication parameters when on CAN."""

    index: int
    entries: list[PdoEntry]
    cob_id: int | None = None
    enabled: bool | None = None
    transmission_type: int | None = None
    inhibit_time: int | None = None
    event_timer: int | None = None
    fixed: bool = False  # EtherCAT: SDO Information says its mapping object is read-only


@dataclass
class Device:
    """The part of a scanned device that makes a drive map."""

    name: str
    identity: Identity
    rpdo: list[ScannedPdo] = field(default_factory=list)  # master outputs
    tpdo: list[ScannedPdo] = field(default_factory=list)  # master inputs
    device_type: int | None = None
    device_name: str | None = None
    errors: list[str] = field(default_factory=list)  # what could not be read, with the reason
    # EtherCAT: the device's PDO assignment (0x1C12/0x1C13) is read-only (SDO Information), or it names a
    # PDO outside ETG.1000.6's ranges: a map written for it says ethercat.pdo_assign: false
    assign_fixed: bool = False


def entry_type(index: int, sub: int, bits: int, coe_code: int | None = None) -> tuple[str, str]:
    """(type name, source) of a mapped entry: the device's CoE data type, CiA 402, else by bit length."""
    if coe_code is not None:
        name = TYPE_NAMES.get(coe_code)
        dt = datatypes.lookup(name) if name else None
        if dt is not None and dt.bits == bits:
            return dt.name, "sdo-info"
    known = CIA402_TYPES.get((index, sub))
    kdt = datatypes.lookup(known) if known else None
    if kdt is not None and kdt.bits == bits:
        return kdt.name, "cia402"
    return _BY_BITS.get(bits, f"bit{bits}"), "guess"


def entry_name(index: int, sub: int, device_name: str | None) -> str:
    """A channel name: the device's (made an identifier), else the CiA 402 / address default."""
    if device_name:
        ident = "".join(c if c.isalnum() else "_" for c in device_name.strip().lower()).strip("_")
        while "__" in ident:
            ident = ident.replace("__", "_")
        if ident and not ident[0].isdigit():
            return ident
    return default_name(index, sub)


def mapping_entry(raw: int) -> tuple[int, int, int]:
    """(index, sub-index, bits) of a 32-bit PDO mapping value."""
    return raw >> 16, (raw >> 8) & 0xFF, raw & 0xFF


def as_json(obj: Any) -> Any:
    """Dataclasses as dicts (for ``--json``)."""
    if dataclasses.is_dataclass(obj) and not isinstance(obj, type):
        return {f.name: as_json(getattr(obj, f.name)) for f in dataclasses.fields(obj)}
    if isinstance(obj, list | tuple):
        return [as_json(v) for v in obj]
    return obj
