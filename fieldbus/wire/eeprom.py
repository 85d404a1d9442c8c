"""The SII EEPROM through one ESC's EEPROM interface (registers 0x0500-0x050F), as a real ESC requires.

Registers (Beckhoff ESC datasheet section II): 0x0500 EEPROM configuration
(bit 0: offered to the PDI; the master takes it by writing 0), 0x0502
control/status (bit 0 write enable, self-clearing; bit 6: reads return 8
bytes, else 4; bits 8-10 command: 0 NOP (clears the error bits), 1 read, 2
write, 4 reload; bit 11 checksum error, 12 EEPROM not loaded, 13 missing
acknowledge / invalid command, 14 write without write enable, 15 busy),
0x0504 address (u32, in words), 0x0508 data (4 or 8 bytes read, 2 written).

Write sequence as SOEM's ``ecx_writeeepromFP`` (ethercatmain.c): wait until
not busy; error bits set -> write NOP to clear them; the word into 0x0508;
then {0x0201 (write + enable), address, 0} into 0x0502; wait until not busy;
a missing acknowledge is tried again (3 times). Every word written here is
read back and compared.

``read(ado, n)`` / ``write(ado, data)`` are one addressed datagram each
(pysoem's ``slave._fprd`` / ``_fpwr``, or the in-process master's): None /
False when the slave did not answer.
"""

from __future__ import annotations

import struct
from collections.abc import Callable

from fieldbus.errors import BusTimeoutError, FieldbusError

REG_EEPROM_CONFIG, REG_EEPROM_CONTROL, REG_EEPROM_ADDRESS, REG_EEPROM_DATA = 0x0500, 0x0502, 0x0504, 0x0508
CMD_NOP, CMD_READ, CMD_WRITE_ENABLED, CMD_RELOAD = 0x0000, 0x0100, 0x0201, 0x0400
ST_READ8 = 0x0040
ST_CHECKSUM, ST_NOT_LOADED, ST_NACK, ST_WRITE_ENABLE, ST_BUSY = 0x0800, 0x1000, 0x2000, 0x4000, 0x8000
ST_ERRORS = ST_NACK | ST_WRITE_ENABLE  # command errors (checksum / not loaded are the load's)
BUSY_POLLS = 200  # status reads a command may stay busy (a real write takes ~5 ms; one read ~0.1 ms)
NACK_TRIES = 3

Read = Callable[[int, int], "bytes | None"]
Write = Callable[[int, bytes], bool]


class EepromError(FieldbusError):
    """The EEPROM interface refused or failed a command (which, where, the status bits)."""


class EepromVerifyError(EepromError):
    """A word written reads back another value."""


def status_text(status: int) -> str:
    """The status bits of 0x0502 in words."""
    names = [
        (ST_CHECKSUM, "checksum error in the ESC configuration area"),
        (ST_NOT_LOADED, "EEPROM not loaded"),
        (ST_NACK, "missing acknowledge or invalid command"),
        (ST_WRITE_ENABLE, "write without write enable"),
        (ST_BUSY, "busy"),
    ]
    found = [text for bit, text in names if status & bit]
    return ", ".join(found) if found else "ok"


class EepromPort:
    """One slave's SII through its EEPROM interface (see the module)."""

    def __init__(self, read: Read, write: Write, *, who: str = "slave") -> None:
        self._read = read
        self._write = write
        self.who = who
        self.datagrams = 0

    def _rd(self, ado: int, n: int) -> bytes:
        self.datagrams += 1
        got = self._read(ado, n)
        if got is None:
            raise BusTimeoutError(f"{self.who}: no answer reading 0x{ado:04X}")
        return bytes(got)

    def _wr(self, ado: int, data: bytes) -> None:
        self.datagrams += 1
        if not self._write(ado, data):
            raise BusTimeoutError(f"{self.who}: no answer writing 0x{ado:04X}")

    def take(self) -> None:
        """The master takes the EEPROM from the PDI (0x0500 = 0)."""
        self._wr(REG_EEPROM_CONFIG, b"\x00")

    def status(self) -> int:
        return int.from_bytes(self._rd(REG_EEPROM_CONTROL, 2), "little")

    def wait_idle(self) -> int:
        """The status once not busy (:class:`BusTimeoutError` after ``BUSY_POLLS`` reads)."""
        for _ in range(BUSY_POLLS):
            st = self.status()
            if not st & ST_BUSY:
                return st
        raise BusTimeoutError(f"{self.who}: EEPROM interface busy for {BUSY_POLLS} status reads")

    def _clear_errors(self, st: int) -> None:
        if st & ST_ERRORS:
            self._wr(REG_EEPROM_CONTROL, struct.pack("<H", CMD_NOP))

    def read_block(self, word: int) -> bytes:
        """4 or 8 bytes from word address ``word`` (as the ESC offers: status bit 6)."""
        st = self.wait_idle()
        self._clear_errors(st)
        self._wr(REG_EEPROM_CONTROL, struct.pack("<HI", CMD_READ, word))
        st = self.wait_idle()
        if st & ST_NACK:
            raise EepromError(f"{self.who}: EEPROM read of word 0x{word:04X} failed: {status_text(st)}")
        return self._rd(REG_EEPROM_DATA, 8 if st & ST_READ8 else 4)

    def read_words(self, word: int, count: int) -> bytes:
        """``count`` words from word address ``word``."""
        out = bytearray()
        while len(out) < 2 * count:
            out += self.read_block(word + len(out) // 2)
        return bytes(out[: 2 * count])

    def read_image(self, *, max_words: int = 0x10000) -> bytes:
        """The image up to the end of its categories (type 0xFFFF), then to a multiple of 8 bytes.

        Bounded by the EEPROM's size as word 0x3E gives it ((Kbit + 1) x 64 words): a damaged
        category length stops there instead of reading 64 K words."""
        head = self.read_words(0, 0x40)
        size_words = (int.from_bytes(head[0x7C:0x7E], "little") + 1) * 64
        max_words = min(max_words, size_words)
        words = bytearray(head)
        addr = 0x40
        while addr + 2 <= max_words:
            kind, n = struct.unpack("<HH", self.read_words(addr, 2))
            if kind == 0xFFFF:
                words += struct.pack("<H", kind)
                break
            n = min(n, max_words - addr - 2)
            words += struct.pack("<HH", kind, n) + self.read_words(addr + 2, n)
            addr += 2 + n
        words += b"\xff" * (-len(words) % 8)
        return bytes(words)

    def write_word(self, word: int, value: int) -> None:
        """One word written (SOEM's sequence, see the module) and read back; :class:`EepromError` if not."""
        data = struct.pack("<H", value & 0xFFFF)
        for _ in range(NACK_TRIES):
            st = self.wait_idle()
            self._clear_errors(st)
            self._wr(REG_EEPROM_DATA, data)
            self._wr(REG_EEPROM_CONTROL, struct.pack("<HI", CMD_WRITE_ENABLED, word))
            st = self.wait_idle()
            if st & ST_NACK:
                continue
            if st & ST_WRITE_ENABLE:
                raise EepromError(f"{self.who}: EEPROM write of word 0x{word:04X} refused: {status_text(st)}")
            break
        else:
            raise EepromError(
                f"{self.who}: EEPROM write of word 0x{word:04X} not acknowledged {NACK_TRIES} times"
            )
        back = self.read_words(word, 1)
        if back != data:
            raise EepromVerifyError(
                f"{self.who}: word 0x{word:04X} reads back 0x{int.from_bytes(back, 'little'):04X} "
                f"after writing 0x{value & 0xFFFF:04X}"
            )

    def write_image(self, image: bytes, *, old: bytes | None = None) -> int:
        """Write ``image`` word by word (only words that differ from ``old`` when given); returns words written.

        The configuration area (words 0-7) goes last, so an interrupted write
        leaves the old checksum over the old area rather than a new area with
        a half-written rest.
        """
        order = [w for w in range(8, len(image) // 2)] + list(range(8))
        written = 0
        for w in order:
            new = image[2 * w : 2 * w + 2]
            if old is not None and old[2 * w : 2 * w + 2] == new:
                continue
            self.write_word(w, int.from_bytes(new, "little"))
            written += 1
        return written
