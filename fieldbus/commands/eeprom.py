"""``fieldbus eeprom read|write|alias|decode``: an EtherCAT slave's SII EEPROM on a live segment.

    fieldbus eeprom read eth0 3 -o drive3.bin
    fieldbus eeprom decode drive3.bin
    fieldbus eeprom alias eth0 3 1001
    fieldbus eeprom word eth0 3 0x0E 12345
    fieldbus eeprom write eth0 3 repaired.bin

SLAVE is the 0-based position in wire order (as ``fieldbus scan`` lists it).
The EEPROM goes through the slave's EEPROM interface (registers
0x0500-0x050F) as a real ESC requires: the master takes it from the PDI,
waits while busy, clears error bits, writes one word with write enable, and
every word written is read back. ``write`` recomputes the checksum of the
configuration area (CRC-8 over words 0-6, in word 7) and refuses an image
for another vendor or product unless --force; ``word`` writes one word (in
the configuration area, words 0-6, the checksum too). ``alias`` writes word 4 (the
configured station alias) and the checksum; the ESC takes the alias into
register 0x0012 at its next power-up, not before. ``decode`` reads an image
file (raw bytes, as SOEM's eepromtool and IgH's ``ethercat sii_read`` save
them) without a bus. Scan a bus nobody is cycling: SOEM's configuration
takes the slaves back to PRE-OP. docs/eeprom.md says what can go wrong and
how to recover.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any

from fieldbus.commands.argtypes import integer
from fieldbus.commands.usage import FAILED, add_command
from fieldbus.errors import FieldbusError

CODES = [
    (0, "the image was read (saved, decoded), or written and every word read back as written"),
    (
        1,
        "the interface cannot be opened, no slave at that position, the image file is malformed or for\n"
        "another device (without --force), or the EEPROM interface refused a command",
    ),
    (FAILED, "a word written reads back another value (the EEPROM may be write-protected or worn)"),
]
TIMEOUT_US = 20_000  # one register access of a tool (SOEM's EEPROM calls wait as long)


def register(sub: Any) -> None:
    p = add_command(
        sub,
        "eeprom",
        help="read, decode or write an EtherCAT slave's SII EEPROM; set its station alias",
        doc=__doc__,
        codes=CODES,
    )
    acts = p.add_subparsers(dest="action", metavar="ACTION", required=True)
    r = add_command(
        acts, "read", help="read a slave's whole image (save it with -o)", doc=__doc__, codes=CODES
    )
    _target(r)
    r.add_argument("-o", "--output", metavar="FILE", help="save the image (raw bytes) here")
    r.add_argument("--json", action="store_true", help="the decoded image as one JSON object")
    r.set_defaults(func=run_read)
    d = add_command(acts, "decode", help="decode an image file (no bus)", doc=__doc__, codes=CODES)
    d.add_argument("file", metavar="FILE", help="an SII image (raw bytes)")
    d.add_argument("--json", action="store_true", help="one JSON object on stdout")
    d.set_defaults(func=run_decode)
    w = add_command(
        acts, "write", help="write an image (checksum recomputed, read back)", doc=__doc__, codes=CODES
    )
    _target(w)
    w.add_argument("file", metavar="FILE", help="the image to write (raw bytes)")
    w.add_argument("--force", action="store_true", help="write an image whose vendor/product differ")
    w.add_argument("--all-words", action="store_true", help="write every word, not only those that differ")
    w.set_defaults(func=run_write)
    o = add_command(
        acts, "word", help="write one word (configuration area: checksum too)", doc=__doc__, codes=CODES
    )
    _target(o)
    o.add_argument("word", metavar="ADDR", type=integer(0, 0xFFFF), help="word address (0x... too)")
    o.add_argument("value", metavar="VALUE", type=integer(0, 0xFFFF), help="0..65535 (0x... too)")
    o.set_defaults(func=run_word)
    a = add_command(acts, "alias", help="set the configured station alias (word 4)", doc=__doc__, codes=CODES)
    _target(a)
    a.add_argument("alias", metavar="ALIAS", type=integer(0, 0xFFFF), help="0..65535 (0x... too)")
    a.set_defaults(func=run_alias)


def _target(p: argparse.ArgumentParser) -> None:
    p.add_argument("interface", metavar="IFACE", help="network card, e.g. eth0")
    p.add_argument("slave", metavar="SLAVE", type=integer(0, 65534), help="0-based position in wire order")


class _Session:
    """A tool's pysoem master on the card (locked), and one slave's EEPROM port."""

    def __init__(self, interface: str, position: int) -> None:
        from fieldbus.backends.buslock import lock_network_card
        from fieldbus.backends.ecat_master import open_segment, read_register, write_register
        from fieldbus.wire.eeprom import EepromPort

        self._lock = lock_network_card(interface)
        self._lock.__enter__()
        try:
            self.master = open_segment(interface)
        except BaseException:
            self._lock.__exit__(None, None, None)
            raise
        n = len(self.master.slaves)
        if not 0 <= position < n:
            self.close()
            raise FieldbusError(f"'{interface}': no slave at position {position} ({n} found: 0..{n - 1})")
        s = self.slave = self.master.slaves[position]
        self.identity = (int(s.man), int(s.id))
        self.port = EepromPort(
            lambda ado, size: read_register(s, ado, size, TIMEOUT_US),
            lambda ado, data: write_register(s, ado, data, TIMEOUT_US),
            who=f"'{interface}' slave {position} ({s.name})",
        )
        self.port.take()

    def close(self) -> None:
        try:
            self.master.close()
        finally:
            self._lock.__exit__(None, None, None)


def _load(path: str) -> bytes:
    from fieldbus.core.sii import SiiFormatError, decode

    try:
        data = Path(path).read_bytes()
    except OSError as exc:
        raise FieldbusError(f"{path}: cannot be read ({exc.strerror})") from None
    try:
        decode(data)
    except SiiFormatError as exc:
        raise FieldbusError(f"{path}: {exc}") from None
    return data


def _show(image: bytes, as_json: bool, extra: dict[str, Any] | None = None) -> None:
    from fieldbus.core.sii import decode, format_text

    c = decode(image)
    if as_json:
        print(json.dumps({**c.as_dict(), **(extra or {})}))
    else:
        print(format_text(c))


def run_decode(args: argparse.Namespace) -> int:
    _show(_load(args.file), args.json)
    return 0


def run_read(args: argparse.Namespace) -> int:
    from fieldbus.core.sii import SiiFormatError

    s = _Session(args.interface, args.slave)
    try:
        image = s.port.read_image()
    finally:
        s.close()
    if args.output:
        try:
            Path(args.output).write_bytes(image)
        except OSError as exc:
            raise FieldbusError(f"{args.output}: cannot be written ({exc.strerror})") from None
    try:
        _show(image, args.json, {"file": args.output} if args.output else None)
    except SiiFormatError as exc:
        raise FieldbusError(f"slave {args.slave}: its image is malformed: {exc} (saved as read)") from None
    return 0


def _write(args: argparse.Namespace, make: Any) -> int:
    """Read the slave's image, build the new one from it (``make(old, identity)``), write what differs."""
    from fieldbus.wire.eeprom import EepromVerifyError

    s = _Session(args.interface, args.slave)
    try:
        old = s.port.read_image()
        new = make(old, s.identity)
        try:
            written = s.port.write_image(new, old=None if getattr(args, "all_words", False) else old)
        except EepromVerifyError as exc:
            print(f"fieldbus eeprom: {exc}")
            return FAILED
    finally:
        s.close()
    print(
        f"slave {args.slave}: {written} words written and read back; the ESC loads the configuration "
        "area (alias, checksum) at its next power-up"
    )
    return 0


def run_write(args: argparse.Namespace) -> int:
    from fieldbus.core.sii import check_identity, with_checksum

    image = _load(args.file)

    def make(old: bytes, identity: tuple[int, int]) -> bytes:
        check_identity(image, *identity, force=args.force)
        return with_checksum(image)

    return _write(args, make)


def run_alias(args: argparse.Namespace) -> int:
    from fieldbus.core.sii import with_alias

    return _write(args, lambda old, _identity: with_alias(old, args.alias))


def run_word(args: argparse.Namespace) -> int:
    from fieldbus.core.sii import CONFIG_BYTES, WORD_CHECKSUM, with_checksum
    from fieldbus.wire.eeprom import EepromVerifyError

    s = _Session(args.interface, args.slave)
    try:
        try:
            s.port.write_word(args.word, args.value)
            written = 1
            if 2 * args.word + 2 <= CONFIG_BYTES:  # the configuration area: its checksum follows
                head = s.port.read_words(0, 8)
                fixed = with_checksum(head + bytes(0x80 - len(head)))[: 2 * WORD_CHECKSUM + 2]
                s.port.write_word(WORD_CHECKSUM, int.from_bytes(fixed[-2:], "little"))
                written = 2
        except EepromVerifyError as exc:
            print(f"fieldbus eeprom: {exc}")
            return FAILED
    finally:
        s.close()
    print(f"slave {args.slave}: {written} word(s) written and read back")
    return 0
