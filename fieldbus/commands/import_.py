"""``fieldbus import esi|eds FILE``: a drive map from a vendor's device description.

``import esi FILE.xml [--device PRODUCT[:REVISION]] [--alternative PDO ...]
[--dc-mode NAME] [-o OUT.yaml] [--json]`` reads an EtherCAT ESI file;
``import eds FILE.eds|FILE.dcf [--node-id N] [-o OUT.yaml] [--json]`` a CANopen
EDS or DCF (with the canopen package). The map is validated before it is
printed or written. Exit 0 on success, 1 on an error, 2 when an ESI file
describes several devices and ``--device`` does not pick one (the devices are
listed).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

from fieldbus.commands.validate import map_summary
from fieldbus.errors import BackendUnavailableError, FieldbusError


def register(sub: Any) -> None:
    p: argparse.ArgumentParser = sub.add_parser(
        "import", help="a drive map from a vendor file: EtherCAT ESI (XML) or CANopen EDS/DCF"
    )
    kinds = p.add_subparsers(dest="kind", metavar="KIND", required=True)
    esi = kinds.add_parser("esi", help="EtherCAT Slave Information XML")
    esi.add_argument("file", metavar="FILE.xml")
    esi.add_argument("--device", metavar="PRODUCT[:REVISION]", help="type name or product code, and revision")
    esi.add_argument(
        "--alternative", action="append", default=[], metavar="PDO",
        help="assign this PDO (index or name) instead of the defaults it excludes; repeatable",
    )  # fmt: skip
    esi.add_argument(
        "--dc-mode", metavar="NAME", help="DC operation mode for assign_activate ('none': free run)"
    )
    eds = kinds.add_parser("eds", help="CANopen EDS or DCF")
    eds.add_argument("file", metavar="FILE.eds|FILE.dcf")
    eds.add_argument("--node-id", type=int, metavar="N", help="node id for $NODEID (a DCF names its own)")
    for q in (esi, eds):
        q.add_argument("-o", "--output", metavar="OUT.yaml", help="write the map here (default: stdout)")
        q.add_argument("--json", action="store_true", help="one JSON object on stdout")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from fieldbus.interop import esi as esi_mod

    try:
        if args.kind == "esi":
            r = esi_mod.import_esi_file(
                args.file, device=args.device, alternatives=args.alternative, dc_mode=args.dc_mode
            )
            text, drive, warnings = r.text, r.drive, r.warnings
            extra: dict[str, Any] = {
                "device": {
                    "type": r.device.type,
                    "name": r.device.name,
                    "product_code": f"0x{r.device.product_code:08X}",
                    "revision": f"0x{r.device.revision:08X}",
                },
                "alternatives": list(r.alternatives),
            }
        else:
            from fieldbus.interop.eds import import_eds

            e = import_eds(args.file, node_id=args.node_id)
            text, drive, warnings = e.text, e.drive, e.warnings
            extra = {"skipped": list(e.skipped)}
    except esi_mod.EsiDeviceChoiceError as exc:
        if args.json:
            devices = [
                {"type": d.type, "name": d.name, "product_code": f"0x{d.product_code:08X}",
                 "revision": f"0x{d.revision:08X}", "line": d.line}
                for d in exc.devices
            ]  # fmt: skip
            print(json.dumps({"ok": False, "error": str(exc), "devices": devices}))
        else:
            print(f"error: {exc}", file=sys.stderr)
        return 2
    except BackendUnavailableError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 1
    except FieldbusError:
        raise
    if args.output:
        Path(args.output).write_text(text)
    if args.json:
        out = {"ok": True, "file": args.file, "output": args.output, "warnings": list(warnings), **extra}
        out["map"] = map_summary(drive)
        if not args.output:
            out["yaml"] = text
        print(json.dumps(out))
    elif args.output:
        print(
            f"{args.output}: drive map '{drive.name}' vendor 0x{drive.vendor_id:08X} product 0x{drive.product_id:08X}"
        )
        for w in warnings:
            print(f"warning: {w}", file=sys.stderr)
    else:
        sys.stdout.write(text)
    return 0
