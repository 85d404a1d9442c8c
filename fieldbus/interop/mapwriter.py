"""Drive-map YAML text from imported PDO descriptions (shared by the ESI and EDS importers).

The text is written by hand (one flow mapping per channel, like the maps in
``pdo_maps/``) and validated by loading it back with
:func:`fieldbus.core.pdo.load.drive_map_from_text`.
"""

from __future__ import annotations

import json
import re
from collections.abc import Iterable
from dataclasses import dataclass, field

from fieldbus.core import datatypes
from fieldbus.core.pdo.names import CIA402_NAMES, CONTROLWORD, STATUSWORD


@dataclass
class Entry:
    """One imported PDO entry (``index`` 0 or a CiA 301 dummy object: a gap)."""

    index: int
    sub_index: int
    type: str
    name: str = ""  # the vendor's name (sanitised into the channel name)
    note: str = ""  # why the type was guessed, for the description

    @property
    def is_gap(self) -> bool:
        return self.index <= 0x0007


@dataclass
class ImportedPdo:
    """One imported PDO: mapping index, entries and its CANopen/EtherCAT details."""

    index: int
    name: str = ""
    entries: list[Entry] = field(default_factory=list)
    fixed: bool = False
    can: dict[str, int | bool] = field(default_factory=dict)  # canopen.pdo[] keys


def yaml_str(text: str) -> str:
    """``text`` as a YAML double-quoted scalar (JSON strings are YAML)."""
    return json.dumps(text, ensure_ascii=False)


def stem(text: str, fallback: str = "device") -> str:
    """A lower-case name usable as a map or channel name (``[a-z0-9_]``, not starting with a digit)."""
    s = re.sub(r"[^0-9A-Za-z]+", "_", text.strip()).strip("_").lower()
    if not s:
        s = fallback
    return s if not s[0].isdigit() else f"x{s}"


def is_cia402(pdos: Iterable[ImportedPdo]) -> bool:
    """Whether the PDOs carry the CiA 402 controlword or statusword."""
    return any(e.index in (CONTROLWORD, STATUSWORD) and e.sub_index == 0 for p in pdos for e in p.entries)


def channel_names(pdos: list[ImportedPdo]) -> list[list[str | None]]:
    """Unique channel names for one direction: CiA 402 defaults, else the vendor's name.

    A vendor name used twice (Beckhoff terminals call every entry ``Input``) is
    prefixed with its PDO's name; what still clashes gets ``_2``, ``_3``...
    """
    raw: list[list[str | None]] = []
    counts: dict[str, int] = {}
    for p in pdos:
        row: list[str | None] = []
        for e in p.entries:
            if e.is_gap:
                row.append(None)
                continue
            name = CIA402_NAMES.get((e.index, e.sub_index)) or stem(
                e.name, f"x{e.index:04x}_{e.sub_index:02x}"
            )
            row.append(name)
            counts[name] = counts.get(name, 0) + 1
        raw.append(row)
    used: set[str] = set()
    out: list[list[str | None]] = []
    for p, row in zip(pdos, raw, strict=True):
        new_row: list[str | None] = []
        for e, maybe in zip(p.entries, row, strict=True):
            if maybe is None:
                new_row.append(None)
                continue
            name = maybe
            if counts[name] > 1 and (e.index, e.sub_index) not in CIA402_NAMES and p.name:
                name = f"{stem(p.name, 'pdo')}_{name}"
            base, n = name, 2
            while name in used:
                name, n = f"{base}_{n}", n + 1
            used.add(name)
            new_row.append(name)
        out.append(new_row)
    return out


def pdo_lines(key: str, pdos: list[ImportedPdo]) -> list[str]:
    """The ``rpdo:``/``tpdo:`` block for ``pdos`` (empty when there are none)."""
    if not pdos:
        return []
    lines = [f"{key}:"]
    for p, names in zip(pdos, channel_names(pdos), strict=True):
        lines.append(f"  - index: 0x{p.index:04X}")
        if p.name:
            lines.append(f"    name: {yaml_str(p.name)}")
        if p.fixed:
            lines.append("    fixed: true")
        lines.append("    channels:")
        for e, name in zip(p.entries, names, strict=True):
            parts = [f"index: 0x{e.index:04X}", f"sub_index: {e.sub_index}", f"type: {e.type}"]
            if name is not None:
                parts.append(f"name: {name}")
                desc = (f"{e.name} ({e.note})" if e.name else e.note) if e.note else e.name
                if desc and stem(desc) != name:
                    parts.append(f"description: {yaml_str(desc)}")
            lines.append("      - {" + ", ".join(parts) + "}")
    return lines


def gap_types(bits: int) -> list[str]:
    """``bitN`` types covering a gap of ``bits`` (split at the widest ``bitN``)."""
    out = []
    while bits > 0:
        n = min(bits, datatypes.MAX_BITN)
        out.append(f"bit{n}")
        bits -= n
    return out
