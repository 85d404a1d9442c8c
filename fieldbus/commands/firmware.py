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
import contextlib
import json
import os
import sys
from pathlib import Path
from typing import Any, TextIO

from fieldbus.commands.argtypes import integer
from fieldbus.commands.usage import add_command
from fieldbus.errors import BusTimeoutError, FieldbusError

EXAMPLES = __doc__.split("\n\n")[1].strip("\n")
CODES = [
    (0, "the file was written (or read) and the slave is back in INIT, the segment scanned again"),
    (
        1,
        "the bus cannot be opened, no such slave, BOOTSTRAP refused, an FoE error (its code and name)\n"
        "or no answer; the message says what state the slave is left in and how to recover",
    ),
]
AGAIN = "run the same command again to finish the update (docs/firmware.md)"


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
    from fieldbus.backends.buslock import lock_network_card

    with lock_network_card(args.target):  # refused while a master runs on the card
        return _update(args, name, data)


def _update(args: argparse.Namespace, name: str, data: bytes | None) -> int:
    from fieldbus.backends.ecat_firmware import FirmwareSession
    from fieldbus.backends.ecat_master import open_segment

    master = open_segment(args.target)
    try:
        session = FirmwareSession(master, args.slave)
        before = session.identity()
        _say(args, f"before: {before.line()}")
        layout = session.enter_preop() if args.preop else session.enter_bootstrap()
        mode = "PRE-OP" if args.preop else "BOOTSTRAP"
        _say(args, f"{session.where}: {mode} (mailbox {layout.out_size}/{layout.in_size} bytes)")
        t = session.foe(name, data, password=args.password)
        bar = Progress(sys.stderr, name, t.total)
        steps = session.transfer(t)
        try:
            while True:
                try:
                    next(steps)
                except StopIteration:
                    break
                bar.show(t.done, t.total)
        except KeyboardInterrupt:
            bar.end()
            raise KeyboardInterrupt(
                f"{session.where} stays in {mode}"
                + (" with an incomplete file" if data is not None else "")
                + f"; {AGAIN}"
            ) from None
        except BusTimeoutError as exc:
            bar.end()
            raise FieldbusError(
                f"{exc}; {session.where} may be left in {mode}, or without valid firmware if it lost"
                f" power: {AGAIN}"
            ) from None
        except FieldbusError as exc:
            bar.end()
            _back_to_init(session)
            raise FieldbusError(f"{exc}; {session.where} is back in INIT") from None
        bar.show(t.done, t.total)
        bar.end()
        if t.result is not None:
            args.file.write_bytes(t.result)
        session.leave_bootstrap()
    finally:
        master.close()
    master = open_segment(args.target)  # the rescan: SOEM configures the slave's mailbox again
    try:
        after = FirmwareSession(master, args.slave).identity()
    finally:
        master.close()
    _say(args, f"after:  {after.line()}")
    note = ""
    if data is not None and after.revision == before.revision:
        note = "the new firmware runs from the device's next power cycle"
        _say(args, note)
    if args.json:
        print(
            json.dumps(
                {
                    "ok": True,
                    "slave": args.slave,
                    "file": name,
                    "bytes": t.done,
                    "before": before.__dict__,
                    "after": after.__dict__,
                    "note": note,
                }
            )
        )
    return 0


def _back_to_init(session: Any) -> None:
    with contextlib.suppress(FieldbusError):  # the message names the first error; the state is then unknown
        session.leave_bootstrap()


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

    def end(self) -> None:
        if self.tty:
            self.stream.write("\n")
            self.stream.flush()
