"""``fieldbus validate FILE...``: check drive maps and network files, print a summary.

Exit 0 when every file is valid; 1 with ``file:line:column field: message`` on
the first error of each invalid file. A network whose bus needs more than 100 %
of its bus time at its cycle rate is invalid; what may work but is likely a
mistake (a receive timeout longer than the cycle) is a ``warning:`` line.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path
from typing import Any

from fieldbus.commands.usage import add_command
from fieldbus.core.bandwidth import network_bandwidth, overload
from fieldbus.core.diffdrive import DiffDriveParams
from fieldbus.core.network import NetworkConfig, is_network_document, parse_network
from fieldbus.core.pdo.layout import layout
from fieldbus.core.pdo.load import looks_like_drive_map, parse_drive_map, shape
from fieldbus.core.pdo.model import DriveMap
from fieldbus.core.safestop import safe_stop_plan
from fieldbus.core.yamlsrc import load_file
from fieldbus.errors import PdoMapError


def register(sub: Any) -> None:
    p = add_command(
        sub,
        "validate",
        help="check drive maps / network files and summarise their process data",
        doc=__doc__,
        codes=[
            (0, "every file is valid"),
            (1, "a file is invalid: file:line:column field: message on stderr (with --json: in the object)"),
        ],
    )
    p.add_argument("files", nargs="+", metavar="FILE", help="drive map or network YAML")
    p.add_argument("--json", action="store_true", help="one JSON object on stdout")
    p.set_defaults(func=run)


def map_summary(drive: DriveMap) -> dict[str, Any]:
    """JSON-able summary of a drive map's layout (EtherCAT bit packing)."""
    lay = layout(drive)
    out: dict[str, Any] = {
        "kind": "drive_map",
        "name": drive.name,
        "vendor_id": f"0x{drive.vendor_id:08X}",
        "product_id": f"0x{drive.product_id:08X}",
        "profile": drive.profile,
        "sdo_writes": len(drive.sdo),
        "axes": drive.axes,
        "canopen": drive.canopen is not None,
        "safe_stop": safe_stop_plan(drive, lay).describe(),
    }
    for dl in (lay.outputs, lay.inputs):
        out[dl.direction.value] = {
            "pdo": [
                {"index": f"0x{p.index:04X}", "bit_offset": p.bit_offset, "bits": p.bits} for p in dl.pdos
            ],
            "bits": dl.bits,
            "bytes": dl.size,
            "entries": [
                {
                    "name": None if e.channel.is_gap else e.name,
                    "object": e.channel.address,
                    "type": e.channel.type.name,
                    "bit_offset": e.bit_offset,
                    "bits": e.bits,
                    "unit": e.channel.unit,
                }
                for e in dl.entries
            ],
        }
    return out


def network_summary(net: NetworkConfig) -> dict[str, Any]:
    return {
        "kind": "network",
        "name": net.name,
        "cycle_time_us": net.cycle_time_us,
        "buses": [
            {
                "name": b.name,
                "type": b.type,
                "cycle_time_us": b.cycle_time_us,
                "slaves": [
                    {
                        "name": s.name,
                        "map": s.map.name,
                        "position": s.position,
                        "node_id": s.node_id,
                        "output_bytes": layout(s.map.bus_map, pdo_align=8 if b.is_can else 1).outputs.size,
                        "input_bytes": layout(s.map.bus_map, pdo_align=8 if b.is_can else 1).inputs.size,
                    }
                    for s in b.slaves
                ],
            }
            for b in net.buses
        ],
        **({"base": _base_summary(net.base)} if net.base is not None else {}),
    }


def _base_summary(base: DiffDriveParams) -> dict[str, Any]:
    def limit(v: float) -> float | None:
        return None if math.isnan(v) else v

    return {
        "left_wheel_names": list(base.left_wheel_names),
        "right_wheel_names": list(base.right_wheel_names),
        "wheel_separation": base.wheel_separation,
        "wheel_radius": base.wheel_radius,
        "max_linear": limit(base.linear.max_velocity),
        "max_angular": limit(base.angular.max_velocity),
        "cmd_vel_timeout": base.cmd_vel_timeout,
    }


def check(path: str) -> dict[str, Any]:
    """Validate one file; raises :class:`PdoMapError`."""
    doc = load_file(path)
    if is_network_document(doc.data):
        net = parse_network(doc, base=Path(path).parent, default_name=Path(path).stem)
        for i, bus in enumerate(network_bandwidth(net).buses):
            why = overload(bus)
            if why is not None:
                raise doc.error(("buses", i), why)
        return {**network_summary(net), "warnings": list(net.warnings)}
    if not looks_like_drive_map(doc.data):
        raise doc.error(
            (),
            f"neither a drive map nor a network file: its top level is {shape(doc.data)}, with none of "
            "vendor_id, product_id, rpdo, tpdo, rawcan, buses (its content is not shown)",
        )
    return map_summary(parse_drive_map(doc, default_name=Path(path).stem))


def _print_map(path: str, s: dict[str, Any]) -> None:
    print(f"{path}: drive map '{s['name']}' vendor {s['vendor_id']} product {s['product_id']} OK")
    for direction, pdo_kind in (("outputs", "RxPDO"), ("inputs", "TxPDO")):
        d = s[direction]
        print(f"  {direction} ({pdo_kind}, master {'->' if direction == 'outputs' else '<-'} drive): "
              f"{d['bytes']} bytes ({d['bits']} bits) in {len(d['pdo'])} PDO")  # fmt: skip
        for e in d["entries"]:
            name = e["name"] or "(gap)"
            unit = f" [{e['unit']}]" if e["unit"] else ""
            print(f"    bit {e['bit_offset']:4d} +{e['bits']:<2d} {e['object']} {e['type']:<7} {name}{unit}")
    print(f"  safe stop: {s['safe_stop']}")


def _print_network(path: str, s: dict[str, Any]) -> None:
    print(f"{path}: network '{s['name']}' OK, {len(s['buses'])} bus(es)")
    for b in s["buses"]:
        print(f"  {b['name']} ({b['type']}, {b['cycle_time_us']} us): {len(b['slaves'])} slaves")
        for sl in b["slaves"]:
            where = f"node {sl['node_id']}" if sl["node_id"] is not None else f"pos {sl['position']}"
            print(
                f"    {where:>8} {sl['name']:<16} {sl['map']:<24} out {sl['output_bytes']} B, in {sl['input_bytes']} B"
            )
    if "base" in s:
        w = s["base"]

        def lim(v: float | None, unit: str) -> str:
            return "no limit" if v is None else f"{v:g} {unit}"

        print(
            f"  base: left {', '.join(w['left_wheel_names'])} / right {', '.join(w['right_wheel_names'])}, "
            f"separation {w['wheel_separation']:g} m, radius {w['wheel_radius']:g} m, "
            f"linear {lim(w['max_linear'], 'm/s')}, angular {lim(w['max_angular'], 'rad/s')}, "
            f"cmd_vel timeout {w['cmd_vel_timeout']:g} s"
        )


def run(args: argparse.Namespace) -> int:
    results: list[dict[str, Any]] = []
    failed = 0
    for path in args.files:
        try:
            summary = check(path)
            results.append({"file": path, "ok": True, **summary})
            if not args.json:
                for warning in summary.get("warnings", ()):
                    print(f"warning: {warning}", file=sys.stderr)
                (_print_network if summary["kind"] == "network" else _print_map)(path, summary)
        except PdoMapError as exc:
            failed += 1
            results.append(
                {
                    "file": path,
                    "ok": False,
                    "error": {
                        "message": exc.message,
                        "file": exc.file,
                        "line": exc.line,
                        "column": exc.column,
                        "path": exc.path,
                        "text": str(exc),
                    },
                }
            )
            if not args.json:
                print(f"error: {exc}", file=sys.stderr)
    if args.json:
        print(json.dumps({"ok": failed == 0, "files": results}))
    return 1 if failed else 0
