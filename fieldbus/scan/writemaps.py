"""``--write-maps DIR``: drive maps and a network file from what a scan found.

One drive map per distinct device (identity and PDO mapping; the serial
number is left out so one map serves every unit), named after the device,
with the PDOs as mapped, the object names the device gave (SDO Information,
SII) or the CiA 402 / address defaults, ``profile: cia402`` when the
controlword and statusword are mapped, a ``canopen:`` section with the COB-IDs
and transmission types found. Then one network file for the bus with every
device at its position or node id. Everything is validated by loading it
back before anything is written: nothing half-written on an error.
"""

from __future__ import annotations

import re
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

from fieldbus.core.network import network_from_text
from fieldbus.core.pdo.load import drive_map_from_text
from fieldbus.core.pdo.names import CONTROLWORD, STATUSWORD, default_name
from fieldbus.errors import FieldbusError
from fieldbus.scan.model import Device, ScannedPdo

GAP_MAX_INDEX = 0x0007  # entries at 0x0000-0x0007 are gaps: the data-type "dummy" objects of CoE


@dataclass(frozen=True)
class BusSpec:
    """The bus the network file describes."""

    type: str  # "ethercat" | "canopen"
    interface: str
    can_interface: str | None = None
    bitrate: int | None = None
    cycle_time_us: int = 1000
    receive_timeout_us: int = 500
    name: str = "bus"


@dataclass(frozen=True)
class Placed:
    """A device at its place on the bus: EtherCAT position or CAN node id."""

    device: Device
    position: int
    node_id: int | None = None
    heartbeat_ms: int | None = None
    coe: bool = True


@dataclass(frozen=True)
class Written:
    network: Path
    maps: tuple[Path, ...]


def write_maps(placed: Sequence[Placed], out_dir: str | Path, bus: BusSpec, source: str) -> Written:
    """Write the maps and ``network.yaml`` into ``out_dir``; each file is validated before any is written."""
    out = Path(out_dir)
    texts: dict[str, str] = {}  # file name -> text
    key_to_file: dict[str, str] = {}
    slave_lines: list[str] = []
    used_names: set[str] = set()
    for p in placed:
        text = map_text(p, bus, source)
        key = text.split("\n", 3)[-1]  # the map without its comment lines
        if key not in key_to_file:
            stem = _stem(p.device.name or p.device.device_name or "device")
            fname = f"{stem}.yaml"
            n = 2
            while fname in texts:
                fname = f"{stem}_{n}.yaml"
                n += 1
            key_to_file[key] = fname
            texts[fname] = text
        fname = key_to_file[key]
        where = f"n{p.node_id}" if p.node_id is not None else f"p{p.position}"
        name = f"{Path(fname).stem}_{where}"
        while name in used_names:
            name += "_"
        used_names.add(name)
        node = f", node_id: {p.node_id}" if p.node_id is not None else ""
        slave_lines.append(f"      - {{name: {name}, map: {fname}{node}}}")
    for fname, text in texts.items():
        try:
            drive_map_from_text(text, str(out / fname))
        except FieldbusError as exc:
            raise FieldbusError(f"the map written for {fname} does not validate: {exc}") from exc
    net = network_text(bus, slave_lines, source)
    _check_network(net, texts, out)
    out.mkdir(parents=True, exist_ok=True)
    paths = []
    for fname, text in texts.items():
        (out / fname).write_text(text)
        paths.append(out / fname)
    net_path = out / "network.yaml"
    net_path.write_text(net)
    return Written(net_path, tuple(paths))


def _check_network(net: str, texts: dict[str, str], out: Path) -> None:
    import tempfile

    with tempfile.TemporaryDirectory(prefix="fieldbus-maps-") as tmp:
        for fname, text in texts.items():
            (Path(tmp) / fname).write_text(text)
        try:
            network_from_text(net, str(out / "network.yaml"), tmp)
        except FieldbusError as exc:
            raise FieldbusError(f"the network file written for the scan does not validate: {exc}") from exc


def network_text(bus: BusSpec, slave_lines: list[str], source: str) -> str:
    lines = [
        f"# Written by `{source}`: the devices found, in wire order (EtherCAT) or by node id (CAN).",
        f"name: {_stem(bus.name)}",
        f"cycle_time_us: {bus.cycle_time_us}",
        f"receive_timeout_us: {bus.receive_timeout_us}",
        "buses:",
        f"  - name: {_stem(bus.name)}",
        f"    type: {bus.type}",
        f"    interface: {_quote(bus.interface)}",
    ]
    if bus.type == "canopen":
        lines.append(f"    can_interface: {_quote(bus.can_interface or 'socketcan')}")
        if bus.bitrate:
            lines.append(f"    bitrate: {bus.bitrate}")
    lines.append("    slaves:")
    lines += slave_lines
    return "\n".join(lines) + "\n"


def map_text(p: Placed, bus: BusSpec, source: str) -> str:
    """One drive map (YAML) for ``p.device``; the first three lines are comments."""
    d = p.device
    where = f"node {p.node_id}" if p.node_id is not None else f"slave {p.position}"
    lines = [
        f"# Written by `{source}` from {where} ({d.name}): the PDO mapping as the device reported it.",
        "# Add scaling (factor, offset, unit), defaults and start-up SDOs by hand; check with fieldbus validate.",
        "# Serial number left out: one map serves every unit of this device.",
        f"name: {_stem(d.name or d.device_name or 'device')}",
        f"vendor_id: 0x{d.identity.vendor_id:08X}",
        f"product_id: 0x{d.identity.product_id:08X}",
        f"revision: 0x{d.identity.revision:08X}",
    ]
    outputs = {e.index for pdo in d.rpdo for e in pdo.entries}
    inputs = {e.index for pdo in d.tpdo for e in pdo.entries}
    if CONTROLWORD in outputs and STATUSWORD in inputs:  # what the CiA 402 profile of a map needs
        lines.append("profile: cia402")
    can = bus.type == "canopen"
    for key, pdos in (("rpdo", d.rpdo), ("tpdo", d.tpdo)):
        used = [pdo for pdo in pdos if pdo.entries and (not can or pdo.enabled is not False)]
        if not used:
            continue
        lines.append(f"{key}:")
        names: set[str] = set()
        for pdo in used:
            lines.append(f"  - index: 0x{pdo.index:04X}")
            if pdo.fixed and not can:
                lines.append("    fixed: true  # its mapping object is read-only: verified, never written")
            lines.append("    channels:")
            for e in pdo.entries:
                if e.index <= GAP_MAX_INDEX:  # padding (ETG.1000.6 dummy entries): no name, units or default
                    sub = e.sub_index if e.index else 0  # a 0x0000 gap has sub-index 0 whatever was read
                    lines.append(f"      - {{index: 0x{e.index:04X}, sub_index: {sub}, type: bit{e.bits}}}")
                    continue
                name = e.name or default_name(e.index, e.sub_index)
                base, n = name, 2
                while name in names:
                    name, n = f"{base}_{n}", n + 1
                names.add(name)
                lines.append(
                    f"      - {{index: 0x{e.index:04X}, sub_index: {e.sub_index}, type: {e.type}, name: {name}}}"
                )
    if not p.coe and not can:
        lines.append("ethercat: {coe: false}")
    elif d.assign_fixed and not can:
        lines.append(
            "ethercat: {pdo_assign: false}  # the device's own PDO assignment (read-only or off-range)"
        )
    if can:
        lines.append("canopen:")
        if p.heartbeat_ms is not None:
            lines.append(f"  heartbeat_ms: {p.heartbeat_ms}")
        pdo_lines = [_can_pdo(pdo, p.node_id or 0) for pdo in d.rpdo + d.tpdo if pdo.entries and pdo.enabled]
        if pdo_lines:
            lines.append("  pdo:")
            lines += pdo_lines
    return "\n".join(lines) + "\n"


def _can_pdo(pdo: ScannedPdo, node_id: int) -> str:
    cob = (pdo.cob_id or 0) & 0x7FF
    parts = [f"index: 0x{pdo.index:04X}"]
    if cob and (cob & 0x7F) == node_id:
        parts.append(f"cob_id: 0x{cob - node_id:03X}")
    elif cob:
        parts += [f"cob_id: 0x{cob:03X}", "cob_id_absolute: true"]
    for key in ("transmission_type", "inhibit_time", "event_timer"):
        v = getattr(pdo, key)
        if v is not None:
            parts.append(f"{key}: {v}")
    return "    - {" + ", ".join(parts) + "}"


def _stem(name: str) -> str:
    s = re.sub(r"[^0-9A-Za-z_]+", "_", name.strip()).strip("_").lower()
    return s if s and not s[0].isdigit() else f"d_{s}"


def _quote(s: str) -> str:
    return (
        s
        if re.fullmatch(r"[0-9A-Za-z_./-]+", s) and not s[0].isdigit()
        else '"' + s.replace('"', '\\"') + '"'
    )
