"""``fieldbus firmware write|read ethercat IFACE --slave N FILE``: a file to or from a slave over FoE.

    fieldbus firmware write ethercat eth0 --slave 3 drive-2.1.efw
    fieldbus firmware write ethercat eth0 --slave 3 app.bin --name app.efw --password 0x1234
    fieldbus firmware read ethercat eth0 --slave 3 backup.efw --name app.efw
    fieldbus firmware write ethercat eth0 --slave 3 config.csv --preop

The slave (position, 0-based) goes INIT -> BOOTSTRAP, the file goes over
FoE with a progress bar on stderr, the slave goes back to INIT and the
segment is scanned again; its identity (SII revision, 0x1018:03) is shown
before and after. Most devices run new firmware from their next power
cycle. ``--preop``: the transfer runs in PRE-OP through the standard
mailbox instead, for files a device takes outside BOOTSTRAP (a
configuration file). An interrupted transfer (Ctrl-C, a cable, power) leaves the device
in BOOTSTRAP, or without valid firmware: run the same command again
(docs/firmware.md).
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from dataclasses import asdict
from pathlib import Path
from typing import Any, TextIO

from fieldbus.commands.argtypes import integer
from fieldbus.commands.usage import add_command
from fieldbus.errors import FieldbusError

EXAMPLES = __doc__.split("\n\n")[1].strip("\n")
CODES = [
    (0, "the file was written (or read) and the slave is back in INIT, the segment scanned again"),
    (
        1,
        "the bus cannot be opened, no such slave, BOOTSTRAP refused, an FoE error (its code and name)\n"
        "or no answer; the message says what state the slave is left in and how to recover",
    ),
]


def register(sub: Any) -> None:
    p = add_command(
        sub,
        "firmware",
        help="write or read a file (firmware) to or from an EtherCAT slave over FoE, in BOOTSTRAP",
        doc=__doc__,
        codes=CODES,
    )
    verbs = p.add_subparsers(dest="verb", metavar="VERB", required=True)
    for verb in ("write", "read"):
        what = "write a file to the slave" if verb == "write" else "read a file from the slave"
        v = add_command(
            verbs, verb, help=what, doc=f"{what[0].upper()}{what[1:]}.\n\n{EXAMPLES}", codes=CODES
        )
        v.add_argument("bus_type", choices=("ethercat",), metavar="BUS", help="ethercat")
        v.add_argument("target", metavar="IFACE", help="network card")
        v.add_argument("--slave", type=integer(0), required=True, help="slave position, 0-based")
        v.add_argument(
            "file",
            metavar="FILE",
            type=Path,
            help="the file to send" if verb == "write" else "where to save it",
        )
        v.add_argument("--name", help="the file name on the slave (default: FILE's name)")
        v.add_argument(
            "--password", type=integer(0, 0xFFFFFFFF), default=0, help="FoE password, u32 (default 0)"
        )
        v.add_argument(
            "--preop",
            action="store_true",
            help="transfer in PRE-OP (standard mailbox), not BOOTSTRAP: files a device takes there",
        )
        v.add_argument("--json", action="store_true", help="one JSON object on stdout")
        v.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    name = args.name or args.file.name
    if args.verb == "write":
        try:
            data: bytes | None = args.file.read_bytes()
        except OSError as exc:
            raise FieldbusError(f"{args.file}: cannot read it ({exc.strerror})") from None
    else:
        data = None
        parent = args.file.resolve().parent
        if not parent.is_dir() or not os.access(parent, os.W_OK):
            raise FieldbusError(f"{args.file}: its folder does not exist or cannot be written")
    from fieldbus.backends.ecat_firmware import transfer_file

    bar = Progress(sys.stderr, name, len(data) if data is not None else 0)
    try:
        res = transfer_file(
            args.target,
            args.slave,
            name,
            data,
            password=args.password,
            preop=args.preop,
            progress=bar.show,
            say=lambda line: _say(args, line),
        )
    finally:
        bar.end()
    if res.data is not None:
        args.file.write_bytes(res.data)
    note = ""
    if data is not None and res.after.revision == res.before.revision:
        note = "the new firmware runs from the device's next power cycle"
        _say(args, note)
    if args.json:
        out = {"ok": True, "slave": args.slave, "file": name, "bytes": res.size, "note": note}
        print(json.dumps({**out, "before": asdict(res.before), "after": asdict(res.after)}))
    return 0


def _say(args: argparse.Namespace, line: str) -> None:
    print(line, file=sys.stderr if args.json else sys.stdout, flush=True)


class Progress:
    """A progress bar on ``stream``: redrawn in place on a terminal, a line per quarter otherwise."""

    WIDTH = 30

    def __init__(self, stream: TextIO, name: str, total: int) -> None:
        self.stream = stream
        self.name = name
        self.tty = stream.isatty()
        self.shown = -1
        self.drawn = False

    def show(self, done: int, total: int) -> None:
        pct = 100 * done // total if total else 0
        step = pct if self.tty else pct // 25 * 25
        if step == self.shown:
            return
        self.shown = step
        fill = self.WIDTH * pct // 100
        text = f"{self.name} [{'#' * fill}{'-' * (self.WIDTH - fill)}] {pct:3d}% {done}/{total or '?'} bytes"
        self.stream.write(("\r" + text) if self.tty else text + "\n")
        self.stream.flush()
        self.drawn = True

    def end(self) -> None:
        if self.tty and self.drawn:
            self.stream.write("\n")
            self.stream.flush()
