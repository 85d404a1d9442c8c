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
import logging
import re
import sys
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from pathlib import Path
from typing import Any

from fieldbus.commands.argtypes import NODE_ID
from fieldbus.commands.outputs import OutputError, check_file
from fieldbus.commands.usage import add_command
from fieldbus.commands.validate import map_summary

CODES = [
    (0, "the map was printed or written (warnings, if any, on stderr, alike ones once with a count)"),
    (
        1,
        "the file cannot be read or is not a device description, the map does not validate, or -o\ncannot be written",
    ),
]
ESI_CODES = [*CODES, (2, "the ESI file describes several devices and --device picks none (they are listed)")]


def register(sub: Any) -> None:
    p = add_command(
        sub,
        "import",
        help="a drive map from a vendor file: EtherCAT ESI (XML) or CANopen EDS/DCF",
        doc=__doc__,
        codes=ESI_CODES,
    )
    kinds = p.add_subparsers(dest="kind", metavar="KIND", required=True)
    esi = add_command(kinds, "esi", help="EtherCAT Slave Information XML", doc=ESI_DOC, codes=ESI_CODES)
    esi.add_argument("file", metavar="FILE.xml", help="the vendor's ESI file")
    esi.add_argument("--device", metavar="PRODUCT[:REVISION]", help="type name or product code, and revision")
    esi.add_argument(
        "--alternative", action="append", default=[], metavar="PDO",
        help="assign this PDO (index or name) instead of the defaults it excludes; repeatable",
    )  # fmt: skip
    esi.add_argument(
        "--dc-mode", metavar="NAME", help="DC operation mode for assign_activate ('none': free run)"
    )
    eds = add_command(kinds, "eds", help="CANopen EDS or DCF", doc=EDS_DOC, codes=CODES)
    eds.add_argument("file", metavar="FILE.eds|FILE.dcf", help="the vendor's EDS, or a DCF")
    eds.add_argument(
        "--node-id", type=NODE_ID, metavar="N", help="node id for $NODEID, 1..127 (a DCF names its own)"
    )
    for q in (esi, eds):
        q.add_argument("-o", "--output", metavar="OUT.yaml", help="write the map here (default: stdout)")
        q.add_argument("--json", action="store_true", help="one JSON object on stdout")
    p.set_defaults(func=run)


ESI_DOC = "A drive map from an EtherCAT Slave Information (ESI) XML file; validated before it is printed or written."
EDS_DOC = "A drive map from a CANopen EDS or DCF file (read with the canopen package); validated before it is printed."


def summarise(warnings: Sequence[str]) -> list[str]:
    """Warnings that differ only in their numbers (object, entry) once each, with how many more there are."""
    groups: dict[str, list[str]] = {}
    for w in warnings:
        groups.setdefault(re.sub(r"0x[0-9A-Fa-f]+(?::[0-9A-Fa-f]+)?|\b\d+\b", "#", w), []).append(w)
    out = []
    for alike in groups.values():
        first, last = alike[0], alike[-1]
        if len(alike) == 1:
            out.append(first)
            continue
        head, _, tail = last.rpartition(": ")
        upto = f", up to {head}" if head and first.endswith(f": {tail}") else ""
        out.append(f"{first} [and {len(alike) - 1} more alike{upto}]")
    return out


@contextmanager
def canopen_warnings(into: list[str], path: str) -> Iterator[None]:
    """What the canopen package logs (WARNING and up) while it reads ``path``: into ``into``, prefixed."""

    class Collect(logging.Handler):
        def emit(self, record: logging.LogRecord) -> None:
            into.append(f"canopen, reading {path}: {record.getMessage()}")

    log = logging.getLogger("canopen")
    handler, propagate = Collect(logging.WARNING), log.propagate
    log.addHandler(handler)
    log.propagate = False  # not also to the root logger (python's last-resort line without a prefix)
    try:
        yield
    finally:
        log.removeHandler(handler)
        log.propagate = propagate


def run(args: argparse.Namespace) -> int:
    from fieldbus.interop import esi as esi_mod

    check_file(args.output, "-o")
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

            logged: list[str] = []
            with canopen_warnings(logged, args.file):
                e = import_eds(args.file, node_id=args.node_id)
            text, drive, warnings = e.text, e.drive, (*logged, *e.warnings)
            extra = {"skipped": list(e.skipped)}
    except esi_mod.EsiDeviceChoiceError as exc:
        if args.json:
            devices = [
                {"type": d.type, "name": d.name, "product_code": f"0x{d.product_code:08X}",
                 "revision": f"0x{d.revision:08X}", "line": d.line}
                for d in exc.devices
            ]  # fmt: skip
            print(json.dumps({"ok": False, "error": str(exc), "exit": 2, "devices": devices}))
        else:
            print(f"error: {exc}", file=sys.stderr)
        return 2
    if args.output:
        try:
            Path(args.output).write_text(text)
        except OSError as exc:
            raise OutputError(f"-o {args.output}: {exc.strerror or exc}") from None
    if args.json:
        out = {"ok": True, "file": args.file, "output": args.output, "warnings": list(warnings), **extra}
        out["map"] = map_summary(drive)
        if not args.output:
            out["yaml"] = text
        print(json.dumps(out))
        return 0
    if args.output:
        print(
            f"{args.output}: drive map '{drive.name}' vendor 0x{drive.vendor_id:08X} product 0x{drive.product_id:08X}"
        )
    else:
        sys.stdout.write(text)
    for w in summarise(warnings):
        print(f"warning: {w}", file=sys.stderr)
    return 0
