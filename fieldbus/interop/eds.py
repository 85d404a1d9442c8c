"""CANopen EDS / DCF -> drive map, read with canopen's own parser.

Pure: a path (or text) in, YAML text and a validated :class:`DriveMap` out.
The object dictionary comes from ``canopen.objectdictionary.import_od``; the
PDOs from the default mapping objects 0x1600-0x17FF / 0x1A00-0x1BFF and their
communication objects 0x1400-0x15FF / 0x1800-0x19FF (COB-ID, transmission
type, inhibit time, event timer); names and types from the dictionary.
A PDO whose default COB-ID is invalid (bit 31) or that maps nothing is left
out and named in the header comment.
"""

from __future__ import annotations

import io
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from fieldbus.core import datatypes
from fieldbus.core.pdo.load import DEFAULT_COB_IDS, drive_map_from_text
from fieldbus.core.pdo.model import Direction, DriveMap
from fieldbus.core.pdo.names import CIA402_TYPES
from fieldbus.errors import BackendUnavailableError, PdoMapError
from fieldbus.interop.mapwriter import Entry, ImportedPdo, is_cia402, pdo_lines, stem, yaml_str

# CiA 301 data type codes -> fieldbus type names (24/40/48/56-bit integers become bitN)
_CODES: dict[int, str] = {
    0x01: "bool", 0x02: "int8", 0x03: "int16", 0x04: "int32", 0x05: "uint8", 0x06: "uint16",
    0x07: "uint32", 0x08: "float", 0x11: "double", 0x15: "int64", 0x1B: "uint64",
}  # fmt: skip


@dataclass(frozen=True)
class EdsImport:
    """Result of :func:`import_eds`."""

    text: str
    drive: DriveMap
    skipped: tuple[str, ...]  # PDOs left out, with the reason
    warnings: tuple[str, ...]


def _canopen() -> Any:
    try:
        import canopen
    except ImportError:
        raise BackendUnavailableError(
            "fieldbus import eds reads EDS/DCF files with the canopen package: pip install 'fieldbus[interop]'"
        ) from None
    return canopen


def _value(var: Any) -> Any:
    """A variable's DCF ParameterValue, else its DefaultValue (None when neither parsed)."""
    v = getattr(var, "value", None)
    return v if v is not None else getattr(var, "default", None)


def _relative_cob(var: Any) -> int | None:
    """The COB-ID of a ``$NODEID+0x180`` style default without the node id."""
    raw = getattr(var, "value_raw", None) or getattr(var, "default_raw", None)
    if not isinstance(raw, str) or "$NODEID" not in raw.upper():
        return None
    try:
        return int(re.sub(r"\+?\$NODEID\+?", "", raw.replace(" ", "").upper()), 0)
    except ValueError:
        return None


def _sub(od: Any, index: int, sub: int) -> Any:
    try:
        obj = od[index]
    except KeyError:
        return None
    if sub == 0 and not hasattr(obj, "subindices"):
        return obj
    try:
        return obj[sub]
    except (KeyError, TypeError):
        return None


# tried in turn: vendor files in the wild are UTF-8 (with or without a BOM), else mostly Windows-1252;
# Latin-1 decodes any byte, so it ends the list
ENCODINGS = ("utf-8-sig", "cp1252", "latin-1")


def decode_vendor_text(raw: bytes) -> tuple[str, str | None]:
    """``raw`` as text: UTF-8, else Windows-1252, else Latin-1; and a note naming the fallback taken.

    The note names the first byte that is not UTF-8 by value and line, never the text around it.
    """
    try:
        return raw.decode(ENCODINGS[0]), None
    except UnicodeDecodeError as exc:
        bad = raw[exc.start]
        line = raw.count(b"\n", 0, exc.start) + 1
    for enc in ENCODINGS[1:]:
        try:
            text = raw.decode(enc)
        except UnicodeDecodeError:
            continue
        return text, f"not UTF-8 (byte 0x{bad:02X} on line {line}): read as {_ENC_NAMES[enc]}"
    raise AssertionError("latin-1 decodes every byte")  # pragma: no cover


_ENC_NAMES = {"cp1252": "Windows-1252 (cp1252)", "latin-1": "Latin-1 (ISO 8859-1)"}


def import_eds(source: str | Path, *, text: str | None = None, node_id: int | None = None) -> EdsImport:
    """Build a drive map (with a ``canopen:`` section) from an EDS or DCF file.

    ``source`` is the path (its suffix, ``.eds`` or ``.dcf``, tells the format);
    with ``text`` the file is not read and ``source`` only names it. ``node_id``
    resolves ``$NODEID`` (a DCF's ``[DeviceComissioning] NodeID`` otherwise).
    """
    canopen = _canopen()
    file = str(source)
    if not file.lower().endswith((".eds", ".dcf")):
        raise PdoMapError("expected an .eds or .dcf file", file=file)
    warnings: list[str] = []
    od = _object_dictionary(canopen, file, text, node_id, warnings)
    if node_id is None:
        node_id = getattr(od, "node_id", None)
    skipped: list[str] = []
    rx = _pdos(od, Direction.OUTPUTS, node_id, file, skipped, warnings)
    tx = _pdos(od, Direction.INPUTS, node_id, file, skipped, warnings)
    vendor, product, revision = _identity(od, file, warnings)
    info = od.device_information
    title = info.product_name or Path(file).stem
    lines = [
        f"# Imported by `fieldbus import eds` from {Path(file).name}"
        + (f" for node {node_id}" if node_id else "")
        + ": the default PDO mapping of the EDS.",
        "# Add scaling (factor, offset, unit) and start-up SDOs by hand; check with fieldbus validate.",
        *(f"# not imported: {s}" for s in skipped),
        *(f"# warning: {w}" for w in warnings),
        f"name: {stem(title, 'device')}",
        f"description: {yaml_str(' '.join(x for x in (info.vendor_name, info.product_name) if x))}",
        f"vendor_id: 0x{vendor:08X}",
        f"product_id: 0x{product:08X}",
        f"revision: 0x{revision:08X}",
    ]
    has_cw = any(e.index == 0x6040 and e.sub_index == 0 for p in rx for e in p.entries)
    has_sw = any(e.index == 0x6041 and e.sub_index == 0 for p in tx for e in p.entries)
    if is_cia402(rx + tx) and has_cw and has_sw:
        lines.append("profile: cia402")
    lines += pdo_lines("rpdo", rx)
    lines += pdo_lines("tpdo", tx)
    lines += _canopen_lines(od, rx + tx)
    text_out = "\n".join(lines) + "\n"
    try:
        drive = drive_map_from_text(text_out, f"{stem(title, 'device')}.yaml")
    except PdoMapError as exc:
        raise PdoMapError(f"the drive map imported from it does not validate: {exc}", file=file) from exc
    return EdsImport(text_out, drive, tuple(skipped), tuple(warnings))


def _object_dictionary(
    canopen: Any, file: str, text: str | None, node_id: int | None, warnings: list[str]
) -> Any:
    """canopen's object dictionary of the EDS/DCF ``file`` (``text``: its contents, not read again)."""
    if text is None:
        try:
            data = Path(file).read_bytes()
        except OSError as exc:
            raise PdoMapError(f"cannot read: {exc.strerror}", file=file) from None
        text, note = decode_vendor_text(data)
        if note:
            warnings.append(note)
    try:
        fp = io.StringIO(text)
        fp.name = file
        return canopen.objectdictionary.import_od(fp, node_id)
    except Exception as exc:  # configparser / canopen errors: name them, never quote the file (not a map yet)
        raise PdoMapError(
            f"canopen could not read this EDS/DCF ({type(exc).__name__}): not an EDS/DCF file, "
            "or one with a syntax error",
            file=file,
        ) from None


def _pdos(
    od: Any, direction: Direction, node_id: int | None, file: str, skipped: list[str], warnings: list[str]
) -> list[ImportedPdo]:
    """The default PDOs of one direction (RPDOs: outputs, mapping 0x1600+; TPDOs: inputs, 0x1A00+)."""
    map_base, comm_base = (0x1600, 0x1400) if direction is Direction.OUTPUTS else (0x1A00, 0x1800)
    kind = "RPDO" if direction is Direction.OUTPUTS else "TPDO"
    out: list[ImportedPdo] = []
    for n in range(512):
        if map_base + n not in od:
            continue
        label = f"{kind}{n + 1} (0x{map_base + n:04X})"
        entries = _mapped_entries(od, map_base + n, label, file, warnings)
        if not entries:
            skipped.append(f"{label}: maps nothing")
            continue
        can = _communication(od, direction, n, comm_base + n, node_id, label, skipped)
        if can is None:
            continue
        name_obj = od.get(map_base + n) if hasattr(od, "get") else None
        out.append(ImportedPdo(map_base + n, getattr(name_obj, "name", "") or "", entries, can=can))
    return out


def _mapped_entries(od: Any, index: int, label: str, file: str, warnings: list[str]) -> list[Entry]:
    """The entries the mapping object ``index`` maps, padded to whole bytes; ``[]``: it maps nothing."""
    count_var = _sub(od, index, 0)
    count = _value(count_var) if count_var is not None else 0
    if not count:
        return []
    entries: list[Entry] = []
    for s in range(1, int(count) + 1):
        v = _sub(od, index, s)
        raw = _value(v) if v is not None else None
        if raw is None:
            raise PdoMapError(
                f"{label} maps {count} entries but sub-index {s} has no value", file=file,
                path=f"[{index:X}sub{s:X}]",
            )  # fmt: skip
        entries.append(_entry(od, int(raw), label, warnings))
    bits = sum(int(e.type[3:]) if e.type.startswith("bit") else _bits(e.type) for e in entries)
    if bits % 8:
        pad = 8 - bits % 8
        warnings.append(f"{label} maps {bits} bits; padded to whole bytes with a bit{pad} gap")
        entries.append(Entry(0, 0, f"bit{pad}"))
    return entries


def _communication(
    od: Any, direction: Direction, n: int, comm: int, node_id: int | None, label: str, skipped: list[str]
) -> dict[str, int | bool] | None:
    """PDO ``n``'s communication parameters (object ``comm``) for the map's ``canopen.pdo`` entry;
    None (and why, in ``skipped``): the PDO is invalid by default, or has no COB-ID to use."""
    cob_var = _sub(od, comm, 1)
    can: dict[str, int | bool] = {}
    if cob_var is not None:
        cob_rel = _relative_cob(cob_var)
        cob_val = _value(cob_var)
        invalid = next((int(v) for v in (cob_val, cob_rel) if v is not None and int(v) & 0x80000000), None)
        if invalid is not None:  # absolute, resolved, or $NODEID+0x80000380 without a node id
            shown = f"0x{invalid:08X}" if cob_val is not None else f"$NODEID+0x{invalid:08X}"
            skipped.append(f"{label}: COB-ID {shown} is invalid (bit 31) by default")
            return None
        if cob_rel is not None:
            can["cob_id"] = cob_rel & 0x7FF
        elif cob_val is not None:
            cob = int(cob_val) & 0x7FF
            defaults = DEFAULT_COB_IDS[direction]
            if node_id and n < 4 and cob - node_id == defaults[n]:
                can["cob_id"] = defaults[n]
            else:
                can["cob_id"], can["cob_id_absolute"] = cob, True
    for key, sub in (("transmission_type", 2), ("inhibit_time", 3), ("event_timer", 5)):
        var = _sub(od, comm, sub)
        val = _value(var) if var is not None else None
        if val is not None and (key == "transmission_type" or direction is Direction.INPUTS or val):
            can[key] = int(val)
    if "cob_id" not in can and n >= 4:
        skipped.append(f"{label}: no COB-ID in 0x{comm:04X}")
        return None
    return can


def _identity(od: Any, file: str, warnings: list[str]) -> tuple[int, int, int]:
    """Vendor id, product code and revision: 0x1018:01..03, else ``[DeviceInfo]``."""
    info = od.device_information
    ident = [_value(_sub(od, 0x1018, s)) if _sub(od, 0x1018, s) is not None else None for s in (1, 2, 3)]
    vendor = ident[0] if ident[0] is not None else info.vendor_number
    product = ident[1] if ident[1] is not None else info.product_number
    revision = ident[2] if ident[2] is not None else info.revision_number
    if vendor is None:
        raise PdoMapError("no vendor id (0x1018:01 or [DeviceInfo] VendorNumber)", file=file)
    if product is None:
        warnings.append("no product code (0x1018:02 or [DeviceInfo] ProductNumber): product_id 0")
        product = 0
    return int(vendor), int(product), int(revision or 0)


def _canopen_lines(od: Any, pdos: list[ImportedPdo]) -> list[str]:
    """The map's ``canopen:`` section: the heartbeat (0x1017) and each PDO's communication parameters."""
    lines = ["canopen:"]
    hb = _sub(od, 0x1017, 0)
    hb_val = _value(hb) if hb is not None else None
    if hb_val is not None and 0 <= int(hb_val) <= 0xFFFF:
        lines.append(f"  heartbeat_ms: {int(hb_val)}")
    comm = [p for p in pdos if p.can]
    if comm:
        lines.append("  pdo:")
        for p in comm:
            parts = [f"index: 0x{p.index:04X}"]
            for key, val in p.can.items():
                if key == "cob_id":
                    parts.append(f"cob_id: 0x{int(val):03X}")
                elif key == "cob_id_absolute":
                    parts.append("cob_id_absolute: true")
                else:
                    parts.append(f"{key}: {int(val)}")
            lines.append("    - {" + ", ".join(parts) + "}")
    return lines


def _bits(type_name: str) -> int:
    dt = datatypes.lookup(type_name)
    assert dt is not None
    return dt.bits


def _entry(od: Any, raw: int, label: str, warnings: list[str]) -> Entry:
    index, sub, bits = raw >> 16, (raw >> 8) & 0xFF, raw & 0xFF
    if bits == 0:
        raise PdoMapError(f"{label}: mapping entry 0x{raw:08X} has length 0")
    if index <= 0x0007:  # CiA 301 dummy object: a gap
        return Entry(index, sub if index else 0, f"bit{bits}")
    var = _sub(od, index, sub)
    name = getattr(var, "name", "") if var is not None else ""
    parent = getattr(var, "parent", None) if var is not None else None
    if parent is not None and getattr(parent, "name", None):
        name = f"{parent.name} {name}".strip()
    type_name = _CODES.get(getattr(var, "data_type", -1) or -1) if var is not None else None
    note = ""
    if var is None and CIA402_TYPES.get((index, sub)) and _bits(CIA402_TYPES[(index, sub)]) == bits:
        type_name, note = CIA402_TYPES[(index, sub)], "object not in the EDS; CiA 402 type"
    elif var is None:
        type_name = f"uint{bits}" if bits in (8, 16, 32, 64) else f"bit{bits}"
        note = "object not in the EDS"
        warnings.append(
            f"{label}: 0x{index:04X}:{sub:02X} is not in the object dictionary; typed from its length"
        )
    elif type_name is None or datatypes.lookup(type_name) is None:
        type_name, note = f"bit{bits}", f"data type 0x{var.data_type:04X}"
    dt = datatypes.lookup(type_name)
    if dt is None or dt.bits != bits:
        warnings.append(f"{label}: 0x{index:04X}:{sub:02X} is {type_name} but mapped with {bits} bits")
        type_name, note = f"bit{bits}", f"{type_name} mapped with {bits} bits"
    return Entry(index, sub, type_name, name, note)
