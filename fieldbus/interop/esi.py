"""EtherCAT Slave Information (ESI, ETG.2000 XML) -> drive map.

Pure: XML bytes in, YAML text and a validated :class:`DriveMap` out. The XML is
parsed with ``defusedxml`` (entity declarations and external references are
refused, so no billion laughs and no file or network access). Every problem is
a :class:`~fieldbus.errors.PdoMapError` naming the file, the line and the
element path (``Descriptions/Devices/Device[1]/RxPdo[2]/Entry[3]/BitLen``).

What is taken from the file: identity (vendor id, product code, revision), the
device's name, the PDOs assigned by default (``Sm`` attribute) with ``Fixed``
and ``Mandatory``, alternatives chosen by the caller (their ``Exclude`` lists
drop the default PDOs they replace), entries with names, types and bit
lengths, gaps, the SyncManagers, the CoE mailbox and the DC operation modes.
"""

from __future__ import annotations

import re
import xml.etree.ElementTree as ET
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from typing import Any

from fieldbus.core import datatypes
from fieldbus.core.pdo.load import ANY_PDO_RANGE, COE_RANGES, drive_map_from_text
from fieldbus.core.pdo.model import Direction, DriveMap
from fieldbus.errors import FieldbusError, PdoMapError
from fieldbus.interop.mapwriter import Entry, ImportedPdo, gap_types, is_cia402, pdo_lines, stem, yaml_str

# ESI (IEC 61131-3 style) data type names -> fieldbus type names
_TYPES: dict[str, str] = {
    "BOOL": "bool", "BIT": "bool", "BIT1": "bool",
    "SINT": "int8", "INT": "int16", "DINT": "int32", "LINT": "int64",
    "USINT": "uint8", "UINT": "uint16", "UDINT": "uint32", "ULINT": "uint64",
    "BYTE": "uint8", "WORD": "uint16", "DWORD": "uint32", "LWORD": "uint64",
    "BITARR8": "uint8", "BITARR16": "uint16", "BITARR32": "uint32",
    "REAL": "float", "REAL32": "float", "LREAL": "double", "REAL64": "double",
    "INTEGER8": "int8", "INTEGER16": "int16", "INTEGER32": "int32", "INTEGER64": "int64",
    "UNSIGNED8": "uint8", "UNSIGNED16": "uint16", "UNSIGNED32": "uint32", "UNSIGNED64": "uint64",
    "BOOLEAN": "bool",
    # not ETG.2000 names, but written by some ESI generators (Pollen's Orbita2d file)
    "INT8": "int8", "INT16": "int16", "INT32": "int32", "INT64": "int64",
    "UINT8": "uint8", "UINT16": "uint16", "UINT32": "uint32", "UINT64": "uint64",
}  # fmt: skip
_BIT_RE = re.compile(r"^BIT([2-8])$")
_ODD_RE = re.compile(r"^(U?)INT(24|40|48|56)$")


@dataclass(frozen=True)
class EsiDevice:
    """A ``<Device>`` of an ESI file."""

    type: str  # the <Type> text, e.g. "EL1008"
    name: str  # the <Name> (English if given)
    product_code: int
    revision: int
    line: int | None

    def __str__(self) -> str:
        return f"{self.type}:0x{self.revision:08X} (product 0x{self.product_code:08X}, {self.name})"


@dataclass(frozen=True)
class EsiImport:
    """Result of :func:`import_esi`."""

    text: str  # the drive map YAML
    drive: DriveMap
    device: EsiDevice
    alternatives: tuple[str, ...]  # PDOs the file offers besides the assigned ones ("0x1601 name")
    warnings: tuple[str, ...]


class EsiDeviceChoiceError(FieldbusError):
    """The file describes several devices (or revisions) and none, or no single one, was chosen."""

    def __init__(self, message: str, devices: Sequence[EsiDevice]) -> None:
        self.devices = tuple(devices)
        super().__init__(message)


class _LineBuilder(ET.TreeBuilder):
    """TreeBuilder that remembers the source line of every element."""

    def __init__(self) -> None:
        super().__init__()
        self.lines: dict[int, int] = {}
        self.parser: Any = None

    def start(self, tag: str, attrs: dict[str, str], /) -> ET.Element:
        elem = super().start(tag, attrs)
        if self.parser is not None:
            self.lines[id(elem)] = int(self.parser.parser.CurrentLineNumber)
        return elem


class _Doc:
    """A parsed ESI with element lines and paths for error messages."""

    def __init__(self, data: bytes, file: str) -> None:
        import defusedxml.ElementTree as DET
        from defusedxml import DefusedXmlException

        self.file = file
        builder = _LineBuilder()
        parser = DET.DefusedXMLParser(
            target=builder, forbid_dtd=False, forbid_entities=True, forbid_external=True
        )
        builder.parser = parser
        try:
            parser.feed(data)
            root = parser.close()
        except DefusedXmlException as exc:
            line = int(parser.parser.CurrentLineNumber)
            name, sysid = getattr(exc, "name", None), getattr(exc, "sysid", None)
            what = (
                f"external entity '{name}' ({sysid})"
                if sysid
                else f"entity declaration '{name}'"
                if name
                else type(exc).__name__
            )
            raise PdoMapError(
                f"refused: {what}; entity expansion and external entities are not allowed in an ESI file",
                file=file,
                line=line,
            ) from None
        except ET.ParseError as exc:
            line, col = exc.position
            raise PdoMapError(
                f"not well-formed XML: {exc.msg}", file=file, line=line, column=col + 1
            ) from None
        self.root: ET.Element = root
        self.lines = builder.lines
        self.paths: dict[int, str] = {}
        self._index(root, "")
        if _local(root.tag) != "EtherCATInfo":
            raise self.err(
                root, f"the root element is <{_local(root.tag)}>, not <EtherCATInfo>: not an ESI file"
            )

    def _index(self, elem: ET.Element, path: str) -> None:
        self.paths[id(elem)] = path
        counts: dict[str, int] = {}
        for child in elem:
            tag = _local(child.tag)
            counts[tag] = counts.get(tag, 0) + 1
            self._index(child, f"{path}/{tag}[{counts[tag]}]" if path else f"{tag}[{counts[tag]}]")

    def err(self, elem: ET.Element, message: str, field: str = "") -> PdoMapError:
        path = self.paths.get(id(elem), "")
        path = re.sub(r"\[1\](?=/|$)", "", path)  # Device[1]/Sm[1] -> Device/Sm; keeps [n] for n > 1
        if field:
            path = f"{path}/{field}" if path else field
        return PdoMapError(message, file=self.file, line=self.lines.get(id(elem)), path=path)

    def int_text(self, elem: ET.Element, field: str) -> int:
        """The integer in child ``field`` (``#x1A00`` or decimal); error if missing."""
        child = _child(elem, field)
        if child is None:
            raise self.err(elem, f"missing <{field}>")
        return self.number(child, child.text)

    def number(self, elem: ET.Element, text: str | None, field: str = "") -> int:
        value = parse_int(text)
        if value is None:
            raise self.err(elem, f"expected a number (decimal or #x hex), got {text!r}", field)
        return value


def parse_int(text: str | None) -> int | None:
    """ESI integer: ``#x1A00`` (hex), ``0x1A00`` or decimal; None when it is neither."""
    if text is None:
        return None
    t = text.strip()
    try:
        if t[:2].lower() in ("#x", "0x"):
            return int(t[2:], 16)
        return int(t, 10)
    except ValueError:
        return None


def _local(tag: str) -> str:
    return tag.rsplit("}", 1)[-1]


def _child(elem: ET.Element, name: str) -> ET.Element | None:
    for c in elem:
        if _local(c.tag) == name:
            return c
    return None


def _children(elem: ET.Element, name: str) -> Iterator[ET.Element]:
    return (c for c in elem if _local(c.tag) == name)


def _text(elem: ET.Element | None) -> str:
    return (elem.text or "").strip() if elem is not None else ""


def _name(elem: ET.Element) -> str:
    """The English ``<Name>`` of ``elem`` (LcId 1033), else the first one."""
    names = list(_children(elem, "Name"))
    for n in names:
        if n.get("LcId") == "1033":
            return _text(n)
    return _text(names[0]) if names else ""


def _devices(doc: _Doc) -> list[tuple[EsiDevice, ET.Element]]:
    out = []
    desc = _child(doc.root, "Descriptions")
    devices = _child(desc, "Devices") if desc is not None else None
    for dev in _children(devices, "Device") if devices is not None else ():
        t = _child(dev, "Type")
        if t is None:
            raise doc.err(dev, "missing <Type> (product code and revision)")
        pc = doc.number(t, t.get("ProductCode"), "@ProductCode")
        rev = t.get("RevisionNo")
        revision = 0 if rev is None else doc.number(t, rev, "@RevisionNo")
        out.append((EsiDevice(_text(t), _name(dev), pc, revision, doc.lines.get(id(dev))), dev))
    if not out:
        raise doc.err(doc.root, "no <Device> under Descriptions/Devices")
    return out


def list_devices(data: bytes | str, file: str = "<string>") -> tuple[EsiDevice, ...]:
    """The devices an ESI file describes, in file order."""
    doc = _Doc(data.encode() if isinstance(data, str) else data, file)
    return tuple(d for d, _ in _devices(doc))


def _pick(
    doc: _Doc, devices: list[tuple[EsiDevice, ET.Element]], want: str | None
) -> tuple[EsiDevice, ET.Element]:
    listing = "\n".join(f"  {d}" for d, _ in devices)
    if want is None:
        if len(devices) == 1:
            return devices[0]
        raise EsiDeviceChoiceError(
            f"{doc.file} describes {len(devices)} devices; choose one with --device PRODUCT[:REVISION]:\n{listing}",
            [d for d, _ in devices],
        )
    product, _, rev_text = want.partition(":")
    code = parse_int(product)
    revision = parse_int(rev_text) if rev_text else None
    if rev_text and revision is None:
        raise EsiDeviceChoiceError(
            f"--device {want}: revision {rev_text!r} is not a number; the devices are:\n{listing}",
            [d for d, _ in devices],
        )
    hits = [
        (d, e)
        for d, e in devices
        if (d.type.lower() == product.strip().lower() or (code is not None and d.product_code == code))
        and (revision is None or d.revision == revision)
    ]
    if len(hits) == 1:
        return hits[0]
    if not hits:
        raise EsiDeviceChoiceError(
            f"--device {want} matches no device of {doc.file}; the devices are:\n{listing}",
            [d for d, _ in devices],
        )
    sub = "\n".join(f"  {d}" for d, _ in hits)
    raise EsiDeviceChoiceError(
        f"--device {want} matches {len(hits)} revisions; add :REVISION, one of:\n{sub}", [d for d, _ in hits]
    )


@dataclass
class _Pdo:
    elem: ET.Element
    rx: bool
    index: int
    name: str
    sm: int | None
    fixed: bool
    mandatory: bool
    excludes: tuple[int, ...]


def _bool_attr(doc: _Doc, elem: ET.Element, attr: str) -> bool:
    v = elem.get(attr)
    if v is None:
        return False
    if v.strip().lower() in ("1", "true"):
        return True
    if v.strip().lower() in ("0", "false"):
        return False
    raise doc.err(elem, f"expected 0/1/true/false, got {v!r}", f"@{attr}")


def _pdos(doc: _Doc, dev: ET.Element) -> list[_Pdo]:
    out = []
    for tag, rx in (("RxPdo", True), ("TxPdo", False)):
        for p in _children(dev, tag):
            sm = p.get("Sm")
            out.append(
                _Pdo(
                    elem=p,
                    rx=rx,
                    index=doc.int_text(p, "Index"),
                    name=_name(p),
                    sm=None if sm is None else doc.number(p, sm, "@Sm"),
                    fixed=_bool_attr(doc, p, "Fixed"),
                    mandatory=_bool_attr(doc, p, "Mandatory"),
                    excludes=tuple(doc.number(x, x.text) for x in _children(p, "Exclude")),
                )
            )
    return out


def _assign(doc: _Doc, dev: ET.Element, pdos: list[_Pdo], alternatives: Sequence[str]) -> list[_Pdo]:
    """The default assignment (PDOs with ``Sm``), changed by the chosen alternatives."""
    chosen = [p for p in pdos if p.sm is not None]
    for alt in alternatives:
        code = parse_int(alt)
        hits = [
            p for p in pdos if (code is not None and p.index == code) or p.name.lower() == alt.strip().lower()
        ]
        if not hits:
            offered = ", ".join(f"0x{p.index:04X} {p.name}" for p in pdos if p not in chosen) or "none"
            raise doc.err(dev, f"--alternative {alt}: no such PDO in this device (alternatives: {offered})")
        if len(hits) > 1:
            raise doc.err(dev, f"--alternative {alt}: {len(hits)} PDOs match; give the index")
        alt_pdo = hits[0]
        if alt_pdo in chosen:
            continue
        same_dir = [p for p in chosen if p.rx == alt_pdo.rx]
        out_going = [p for p in chosen if p.index in alt_pdo.excludes or alt_pdo.index in p.excludes]
        for p in out_going:
            if p.mandatory:
                raise doc.err(
                    alt_pdo.elem,
                    f"--alternative 0x{alt_pdo.index:04X} excludes 0x{p.index:04X} ({p.name}), which is mandatory",
                )
        chosen = [p for p in chosen if p not in out_going]
        if alt_pdo.sm is None:
            default_sm = next((p.sm for p in same_dir if p.sm is not None), 2 if alt_pdo.rx else 3)
            alt_pdo.sm = default_sm
        chosen.append(alt_pdo)
    # keep file order within each direction
    order = {id(p): i for i, p in enumerate(pdos)}
    return sorted(chosen, key=lambda p: order[id(p)])


def _entry_type(doc: _Doc, e: ET.Element, bits: int, warnings: list[str], where: str) -> tuple[str, str]:
    """(fieldbus type, note) for an entry of ``bits`` bits with ESI ``<DataType>``."""
    dt_elem = _child(e, "DataType")
    esi = _text(dt_elem).upper()
    name = _TYPES.get(esi)
    if name is None:
        m = _BIT_RE.match(esi)
        if m:
            name = f"bit{m.group(1)}"
    note = ""
    if name is None:
        m = _ODD_RE.match(esi)
        if not esi:
            if bits > datatypes.MAX_BITN:
                raise doc.err(
                    e, f"{bits}-bit entry without <DataType>; at most {datatypes.MAX_BITN} bits", "BitLen"
                )
            name, note = f"bit{bits}", "no DataType in the ESI"
        elif m:
            name = f"bit{bits}"
            note = f"ESI type {esi}" + (", signed: read as unsigned bits" if not m.group(1) else "")
        elif bits <= datatypes.MAX_BITN:
            name, note = f"bit{bits}", f"ESI type {esi} has no fieldbus type"
            warnings.append(f"{where}: ESI type {esi} mapped to {name}")
        else:
            raise doc.err(
                dt_elem if dt_elem is not None else e, f"ESI type {esi!r} of {bits} bits has no fieldbus type"
            )
    dt = datatypes.lookup(name)
    assert dt is not None
    if dt.bits != bits:
        if bits > datatypes.MAX_BITN:
            raise doc.err(e, f"BitLen {bits} does not match {esi} ({dt.bits} bits)", "BitLen")
        warnings.append(f"{where}: {esi} is {dt.bits} bits but BitLen says {bits}; imported as bit{bits}")
        name, note = f"bit{bits}", f"ESI type {esi} with BitLen {bits}"
    return name, note


def _entries(doc: _Doc, p: _Pdo, warnings: list[str]) -> list[Entry]:
    out: list[Entry] = []
    for e in _children(p.elem, "Entry"):
        index = doc.int_text(e, "Index")
        sub_elem = _child(e, "SubIndex")
        sub = 0 if sub_elem is None else doc.number(sub_elem, sub_elem.text)
        bits = doc.int_text(e, "BitLen")
        if not 0 <= index <= 0xFFFF:
            raise doc.err(e, f"0x{index:X} is not an object index", "Index")
        if not 0 <= sub <= 0xFF:
            raise doc.err(e, f"{sub} is not a sub-index 0..255", "SubIndex")
        if bits < 1:
            raise doc.err(e, f"BitLen {bits}: an entry has at least 1 bit", "BitLen")
        if index == 0:
            out += [Entry(0, 0, t) for t in gap_types(bits)]
            continue
        where = f"0x{p.index:04X} entry 0x{index:04X}:{sub:02X}"
        type_name, note = _entry_type(doc, e, bits, warnings, where)
        if index <= 0x0007:
            warnings.append(
                f"{where}: a CiA 301 dummy object; imported as a gap (no field in the process image)"
            )
        out.append(Entry(index, sub if index > 0x0007 else 0, type_name, _name(e), note))
    return out


def _sm_lines(doc: _Doc, dev: ET.Element, assigned: list[_Pdo]) -> list[str]:
    lines = []
    for i, sm in enumerate(_children(dev, "Sm")):
        kind_text = _text(sm)
        ctrl = parse_int(sm.get("ControlByte"))
        if kind_text in ("MBoxOut", "Outputs"):
            kind = "output"
        elif kind_text in ("MBoxIn", "Inputs"):
            kind = "input"
        elif ctrl is not None:
            kind = "output" if ctrl & 0x04 else "input"
        else:
            raise doc.err(sm, f"SyncManager {i}: neither MBoxOut/MBoxIn/Outputs/Inputs nor a ControlByte")
        parts = [f"index: {i}", f"type: {kind}"]
        carries = {("rpdo" if p.rx else "tpdo") for p in assigned if p.sm == i}
        if len(carries) == 1:
            parts.append(f"pdo: {carries.pop()}")
        if ctrl is not None and ctrl & 0x40:
            parts.append("watchdog: enable")
        start = parse_int(sm.get("StartAddress"))
        size = parse_int(sm.get("DefaultSize"))
        if start is not None and 0 <= start <= 0xFFFF:
            parts.append(f"start: 0x{start:04X}")
        if size is not None and 0 <= size <= 0xFFFF:
            parts.append(f"size: {size}")
        comment = f"  # {kind_text}" if kind_text else ""
        lines.append("  - {" + ", ".join(parts) + "}" + comment)
    return ["sm:", *lines] if lines else []


@dataclass
class _Dc:
    name: str
    desc: str
    values: dict[str, int]


def _dc_modes(doc: _Doc, dev: ET.Element) -> list[_Dc]:
    dc = _child(dev, "Dc")
    out: list[_Dc] = []
    if dc is None:
        return out
    for i, op in enumerate(_children(dc, "OpMode")):
        v: dict[str, int] = {}
        aa = _child(op, "AssignActivate")
        v["assign_activate"] = doc.number(aa, aa.text) if aa is not None else 0
        for tag, key in (
            ("CycleTimeSync0", "sync0"),
            ("ShiftTimeSync0", "sync0_shift_ns"),
            ("CycleTimeSync1", "sync1"),
            ("ShiftTimeSync1", "sync1_shift_ns"),
        ):
            el = _child(op, tag)
            if el is None:
                continue
            value = doc.number(el, el.text)
            if key.endswith("_ns"):
                v[key] = value
            else:
                factor = el.get("Factor")
                v[f"{key}_cycle_factor"] = 0 if factor is None else doc.number(el, factor, "@Factor")
                v[f"{key}_cycle_ns"] = value
        if not 0 <= v["assign_activate"] <= 0xFFFF:
            raise doc.err(
                aa if aa is not None else op, f"AssignActivate 0x{v['assign_activate']:X} is not 16 bits"
            )
        name = _text(_child(op, "Name")) or f"mode{i + 1}"
        out.append(_Dc(name, _text(_child(op, "Desc")), v))
    return out


def import_esi(
    data: bytes | str,
    file: str = "<string>",
    *,
    device: str | None = None,
    alternatives: Sequence[str] = (),
    dc_mode: str | None = None,
) -> EsiImport:
    """Build a drive map for one device of an ESI file.

    ``device``: ``PRODUCT[:REVISION]`` (the ``<Type>`` text or the product code)
    when the file has several; ``alternatives``: PDO indexes or names to assign
    instead of the defaults they exclude; ``dc_mode``: the DC operation mode
    whose AssignActivate the map uses (default: the first with a non-zero one;
    ``"none"``: 0, free run). Raises :class:`PdoMapError` or
    :class:`EsiDeviceChoiceError`.
    """
    doc = _Doc(data.encode() if isinstance(data, str) else data, file)
    vendor = _child(doc.root, "Vendor")
    if vendor is None:
        raise doc.err(doc.root, "missing <Vendor>")
    vendor_id = doc.int_text(vendor, "Id")
    vendor_name = _name(vendor)
    dev_info, dev = _pick(doc, _devices(doc), device)
    warnings: list[str] = []

    mailbox = _child(dev, "Mailbox")
    coe_elem = None if mailbox is None else _child(mailbox, "CoE")
    coe = coe_elem is not None
    # ETG.2000: the master downloads the assignment (0x1C1x) only with PdoAssign, the mapping only with
    # PdoConfig (both default false); otherwise the device's own is used (and a mapping is verified)
    fixed_assign = coe_elem is not None and not _bool_attr(doc, coe_elem, "PdoAssign")
    fixed_config = coe_elem is not None and not _bool_attr(doc, coe_elem, "PdoConfig")
    all_pdos = _pdos(doc, dev)
    _check_pdo_indexes(doc, all_pdos, fixed_assign, warnings)
    if fixed_assign and alternatives:
        raise doc.err(
            dev if coe_elem is None else coe_elem,
            "--alternative: the device's PDO assignment is fixed (CoE@PdoAssign is not true)",
        )
    assigned = _assign(doc, dev, all_pdos, alternatives)
    rx, tx = _imported(doc, assigned, fixed_config, warnings)
    others = tuple(f"0x{p.index:04X} {p.name}".strip() for p in all_pdos if p not in assigned)
    modes = _dc_modes(doc, dev)
    chosen_dc = _chosen_dc(doc, dev, modes, dc_mode)
    name = stem(dev_info.type or dev_info.name, "device")
    lines = [
        *_header(file, dev_info, alternatives, others, warnings),
        f"name: {name}",
        f"description: {yaml_str(' '.join(x for x in (vendor_name, dev_info.name) if x))}",
        f"vendor_id: 0x{vendor_id:08X}",
        f"product_id: 0x{dev_info.product_code:08X}",
        f"revision: 0x{dev_info.revision:08X}",
    ]
    if (
        is_cia402(rx + tx)
        and any(e.index == 0x6040 for p in rx for e in p.entries)
        and any(e.index == 0x6041 for p in tx for e in p.entries)
    ):
        lines.append("profile: cia402")
    if chosen_dc is not None and chosen_dc.values["assign_activate"]:
        lines.append(
            f"assign_activate: 0x{chosen_dc.values['assign_activate']:04X}  # DC mode {chosen_dc.name}"
        )
    lines += pdo_lines("rpdo", rx)
    lines += pdo_lines("tpdo", tx)
    lines += _sm_lines(doc, dev, assigned)
    lines += ["ethercat:", *_ethercat_lines(dev, coe, fixed_assign, chosen_dc, modes)]
    text = "\n".join(lines) + "\n"
    out_name = f"{name}.yaml"
    try:
        drive = drive_map_from_text(text, out_name)
    except PdoMapError as exc:
        raise PdoMapError(
            f"the drive map imported for {dev_info.type} does not validate: {exc}",
            file=file,
            line=dev_info.line,
        ) from exc
    return EsiImport(text, drive, dev_info, others, tuple(warnings))


def _imported(
    doc: _Doc, assigned: list[_Pdo], fixed_config: bool, warnings: list[str]
) -> tuple[list[ImportedPdo], list[ImportedPdo]]:
    """The assigned PDOs with their entries: RxPDOs (outputs), TxPDOs (inputs)."""
    imported: dict[bool, list[ImportedPdo]] = {True: [], False: []}
    for p in assigned:
        entries = _entries(doc, p, warnings)
        imported[p.rx].append(ImportedPdo(p.index, p.name, entries, fixed=p.fixed or fixed_config))
    return imported[True], imported[False]


def _header(
    file: str, dev_info: EsiDevice, alternatives: Sequence[str], others: tuple[str, ...], warnings: list[str]
) -> list[str]:
    """The imported map's comment lines: where it comes from, the PDOs not assigned, the warnings."""
    header = [
        f"# Imported by `fieldbus import esi` from {_basename(file)}: {dev_info.type}, revision 0x{dev_info.revision:08X}.",
        "# The PDOs are the device's default assignment"
        + (f" with the alternatives {', '.join(alternatives)}" if alternatives else "")
        + "; add scaling (factor, offset, unit) and start-up SDOs by hand.",
    ]
    if others:
        header.append(f"# Not assigned (fieldbus import esi --alternative INDEX): {'; '.join(others)}")
    header += [f"# warning: {w}" for w in warnings]
    return header


def _check_pdo_indexes(doc: _Doc, pdos: list[_Pdo], fixed_assign: bool, warnings: list[str]) -> None:
    """Every PDO index within ETG.1000.6's range of its direction; outside it only where the device's
    assignment is fixed (kept, with a warning), else :class:`PdoMapError` naming the line."""
    any_lo, any_hi = ANY_PDO_RANGE
    for p in pdos:
        lo, hi = COE_RANGES[Direction.OUTPUTS if p.rx else Direction.INPUTS]
        if not lo <= p.index <= hi:
            kind = "RxPdo" if p.rx else "TxPdo"
            if not (fixed_assign and any_lo <= p.index <= any_hi):
                raise doc.err(
                    p.elem, f"{kind} index 0x{p.index:04X} is outside 0x{lo:04X}-0x{hi:04X}", "Index"
                )
            warnings.append(
                f"line {doc.lines.get(id(p.elem))}: {kind} index 0x{p.index:04X} is outside ETG.1000.6's "
                f"0x{lo:04X}-0x{hi:04X}; kept as the device names it (its PDO assignment is fixed)"
            )


def _chosen_dc(doc: _Doc, dev: ET.Element, modes: list[_Dc], dc_mode: str | None) -> _Dc | None:
    """The DC mode named ``dc_mode`` (None: the first with a non-zero AssignActivate; ``"none"``: none)."""
    if dc_mode is None:
        return next((m for m in modes if m.values["assign_activate"]), None)
    if dc_mode.lower() == "none":
        return None
    chosen = next((m for m in modes if m.name.lower() == dc_mode.lower()), None)
    if chosen is None:
        offered = ", ".join(m.name for m in modes) or "none (the device has no <Dc>)"
        raise doc.err(dev, f"--dc-mode {dc_mode}: no such DC mode; the device has {offered}")
    return chosen


def _ethercat_lines(
    dev: ET.Element, coe: bool, fixed_assign: bool, chosen_dc: _Dc | None, modes: list[_Dc]
) -> list[str]:
    """The lines of the map's ``ethercat:`` section: CoE, a fixed assignment, the mailbox size (the
    MBoxOut sync manager's default size), the chosen DC mode's shifts, every DC mode of the device."""
    mbx_size = None
    for sm in _children(dev, "Sm"):
        if _text(sm) == "MBoxOut":
            mbx_size = parse_int(sm.get("DefaultSize"))
    eth = [f"  coe: {'true' if coe else 'false'}"]
    if fixed_assign:
        eth.append("  pdo_assign: false  # CoE@PdoAssign is not true: the device's own assignment is used")
    if coe and mbx_size is not None and 32 <= mbx_size <= 1486:
        eth.append(f"  mailbox_size: {mbx_size}")
    if chosen_dc is not None:
        shift0 = chosen_dc.values.get("sync0_shift_ns", 0)
        if shift0 and -(2**31) <= shift0 < 2**31:
            eth.append(f"  sync0_shift_ns: {shift0}")
        if not chosen_dc.values.get("sync1_cycle_factor", 0) and chosen_dc.values.get("sync1_cycle_ns", 0):
            eth.append(f"  sync1_cycle_ns: {chosen_dc.values['sync1_cycle_ns']}")
    if modes:
        eth.append("  dc_modes:")
        for m in modes:
            parts = [f"name: {yaml_str(m.name)}"]
            if m.desc:
                parts.append(f"description: {yaml_str(m.desc)}")
            parts.append(f"assign_activate: 0x{m.values['assign_activate']:04X}")
            for key in (
                "sync0_cycle_factor", "sync0_cycle_ns", "sync0_shift_ns",
                "sync1_cycle_factor", "sync1_cycle_ns", "sync1_shift_ns",
            ):  # fmt: skip
                if m.values.get(key):
                    parts.append(f"{key}: {m.values[key]}")
            eth.append("    - {" + ", ".join(parts) + "}")
    return eth


def import_esi_file(path: str, **kwargs: Any) -> EsiImport:
    """:func:`import_esi` on the file at ``path``."""
    try:
        with open(path, "rb") as f:
            data = f.read()
    except OSError as exc:
        raise PdoMapError(f"cannot read: {exc.strerror}", file=path) from None
    return import_esi(data, path, **kwargs)


def _basename(file: str) -> str:
    return re.split(r"[\\/]", file)[-1]
