"""One slave's firmware (or file) update over FoE: INIT -> BOOTSTRAP, the transfer, back to INIT.

:func:`transfer_file` is the whole procedure on a network card (``fieldbus
firmware``, ``fieldbus.transfer_file``). Works on a pysoem ``Master`` or the in-process one
(:class:`~fieldbus.backends.ecat_inprocess.InProcessMaster`): only the
slave's AL state calls (``state`` / ``write_state`` / ``state_check``) and
single-datagram register access (``_fprd`` / ``_fpwr``) are used, so the
transfer runs through :class:`~fieldbus.backends.ecat_mailbox.SlaveMailbox`
one datagram per step - the same bounded steps as an SDO in OP - and a
caller can stop between any two steps (Ctrl-C, a progress bar, a test that
cuts the power).

BOOTSTRAP has its own mailbox: the SII's bootstrap mailbox (words
0x14/0x15 receive offset and size, 0x16/0x17 send offset and size, read
through the ESC's EEPROM interface) is written into SM0/SM1 in INIT, then
BOOT is requested (ETG.1000.6 6.4; SOEM's ``firm_update`` example does the
same). Only the updated slave leaves its state: the others keep theirs, and
a master that keeps cycling them keeps them in OP (docs/firmware.md).
"""

from __future__ import annotations

import contextlib
import struct
from collections.abc import Callable, Generator
from dataclasses import dataclass
from typing import Any

from fieldbus.backends.ecat_mailbox import MailboxLayout, SlaveMailbox
from fieldbus.core.al import AL_ACK, AL_BOOT, AL_ERROR, AL_INIT, AL_PREOP, al_status_name, state_name
from fieldbus.core.foe import FoeError, FoeTransfer
from fieldbus.errors import BusTimeoutError, FieldbusError, StateTransitionError

FRAME_TIMEOUT_US = 2000  # one datagram's wait (SOEM's EC_TIMEOUTRET): outside OP, mailbox speed
STATE_POLL_US, STATE_POLLS = 1000, 5000  # a state change: up to 5 s (a boot loader may take seconds to start)
STEPS_PER_ANSWER = 2000  # datagrams from one FoE answer to the next (polls included; BUSY: more answers)
EEPROM_POLLS = 100
SII_BOOT_MAILBOX = 0x14  # SII words 0x14-0x17: bootstrap receive offset, size; send offset, size
SII_REVISION = 0x0C
SM_CTRL_MBX_OUT, SM_CTRL_MBX_IN = 0x26, 0x22  # mailbox mode, ECAT writes / reads, PDI interrupt
REG_AL_STATUS, REG_AL_CODE = 0x0130, 0x0134
REG_EEPROM_CONFIG, REG_EEPROM_CONTROL, REG_EEPROM_DATA = 0x0500, 0x0502, 0x0508
EEPROM_READ, EEPROM_BUSY = 0x0100, 0x8000

_SM = struct.Struct("<HHBBBB")


@dataclass(frozen=True)
class Identity:
    """What a slave says it is: SII identity (vendor, product, revision) and the revision in 0x1018:03
    (None where it cannot be read: no CoE, or the slave does not reach PRE-OP)."""

    name: str
    vendor_id: int
    product_code: int
    revision: int
    od_revision: int | None

    def line(self) -> str:
        od = "?" if self.od_revision is None else f"0x{self.od_revision:08X}"
        return (
            f"{self.name} vendor 0x{self.vendor_id:08X} product 0x{self.product_code:08X} "
            f"revision 0x{self.revision:08X} (0x1018:03 {od})"
        )


class _Port:
    """A slave's registers one datagram at a time (SlaveMailbox's RegisterPort) on a pysoem-shaped slave."""

    def __init__(self, slave: Any, timeout_us: int) -> None:
        self.slave = slave
        self.timeout_us = timeout_us

    def read(self, ado: int, size: int) -> bytes | None:
        from fieldbus.backends.ecat_master import read_register  # pysoem's errors mapped there

        return read_register(self.slave, ado, size, self.timeout_us)

    def write(self, ado: int, data: bytes) -> bool:
        from fieldbus.backends.ecat_master import write_register

        return write_register(self.slave, ado, data, self.timeout_us)


class FirmwareSession:
    """Slave ``position`` (0-based) of ``master``, taken through BOOTSTRAP for FoE transfers."""

    def __init__(self, master: Any, position: int, *, frame_timeout_us: int = FRAME_TIMEOUT_US) -> None:
        if not 0 <= position < len(master.slaves):
            raise FieldbusError(f"no slave at position {position}: {len(master.slaves)} slaves found")
        self.master = master
        self.position = position
        self.slave = master.slaves[position]
        self.where = f"slave {position} ({self.slave.name})"
        self.port = _Port(self.slave, frame_timeout_us)
        self.layout: MailboxLayout | None = None  # the bootstrap mailbox, once in BOOT

    # -- registers and SII ---------------------------------------------------------------------------
    def _read(self, ado: int, size: int, what: str) -> bytes:
        for _ in range(3):
            data = self.port.read(ado, size)
            if data is not None:
                return data
        raise BusTimeoutError(f"{self.where}: no answer reading {what} (register 0x{ado:04X})")

    def _write(self, ado: int, data: bytes, what: str) -> None:
        for _ in range(3):
            if self.port.write(ado, data):
                return
        raise BusTimeoutError(f"{self.where}: no answer writing {what} (register 0x{ado:04X})")

    def sii_word_pair(self, word: int) -> tuple[int, int]:
        """SII words ``word`` and ``word + 1`` through the ESC's EEPROM interface (the master owns it)."""
        self._write(REG_EEPROM_CONFIG, b"\0", "EEPROM access")
        self._write(REG_EEPROM_CONTROL, struct.pack("<HI", EEPROM_READ, word), "EEPROM read command")
        for _ in range(EEPROM_POLLS):
            status = struct.unpack("<H", self._read(REG_EEPROM_CONTROL, 2, "EEPROM status"))[0]
            if not status & EEPROM_BUSY:
                lo, hi = struct.unpack("<HH", self._read(REG_EEPROM_DATA, 4, "EEPROM data"))
                return lo, hi
        raise BusTimeoutError(f"{self.where}: EEPROM stays busy reading word 0x{word:02X}")

    def identity(self, *, od: bool = True) -> Identity:
        """The slave's identity from its SII; 0x1018:03 by SDO when ``od`` and the slave is in PRE-OP or
        above (a pysoem ``sdo_read``)."""
        words = [self.sii_word_pair(w) for w in (0x08, 0x0A, SII_REVISION)]
        vendor, product, revision = (lo | hi << 16 for lo, hi in words)
        from fieldbus.backends.ecat_master import sdo

        od_revision = None
        if od and self.al_state()[0] & 0x0F in (AL_PREOP, 0x04, 0x08):
            try:
                raw = sdo(
                    lambda: self.slave.sdo_read(0x1018, 3),
                    index=0x1018,
                    sub_index=3,
                    slave=self.where,
                    what="read",
                    tries=2,
                )
                od_revision = int.from_bytes(bytes(raw)[:4], "little")
            except FieldbusError:  # an abort or no answer: shown as unknown
                od_revision = None
        return Identity(str(self.slave.name), vendor, product, revision, od_revision)

    def al_state(self) -> tuple[int, int]:
        """(AL status, AL status code) read now."""
        raw = self._read(REG_AL_STATUS, 6, "AL status")
        status, _r, code = struct.unpack("<HHH", raw)
        return status, code

    # -- states --------------------------------------------------------------------------------------
    def request(self, state: int, polls: int = STATE_POLLS) -> None:
        """Request ``state`` of this slave only (acknowledging an error) and wait for it, at most ``polls``
        waits of 1 ms; a refusal (the error indicator) raises :class:`StateTransitionError` at once, with
        the AL status code."""
        status, code = self.al_state()
        self.slave.state = state | (AL_ACK if status & AL_ERROR else 0)
        self.slave.write_state()
        for _ in range(polls):
            self.slave.state_check(state, STATE_POLL_US)
            status, code = self.al_state()
            if status & 0x0F == state and not status & AL_ERROR:
                return
            if status & AL_ERROR:
                break
        raise StateTransitionError(
            f"{self.where}: {state_name(state)} requested, the slave shows {state_name(status)}"
            f" (AL status code 0x{code:04X} {al_status_name(code)})",
            al_status=code,
            slave=self.where,
        )

    def enter_bootstrap(self) -> MailboxLayout:
        """INIT, the bootstrap mailbox into SM0/SM1, BOOT; the bootstrap mailbox's layout."""
        self.request(AL_INIT)
        out_start, out_size = self.sii_word_pair(SII_BOOT_MAILBOX)
        in_start, in_size = self.sii_word_pair(SII_BOOT_MAILBOX + 2)
        if not out_size or not in_size or out_size == 0xFFFF or in_size == 0xFFFF:
            raise FieldbusError(f"{self.where}: its SII has no bootstrap mailbox (words 0x14-0x17): no FoE")
        sms = _SM.pack(out_start, out_size, SM_CTRL_MBX_OUT, 0, 1, 0) + _SM.pack(
            in_start, in_size, SM_CTRL_MBX_IN, 0, 1, 0
        )
        self._write(0x0800, sms, "SM0/SM1 (bootstrap mailbox)")
        self.request(AL_BOOT)
        self.layout = MailboxLayout(out_start, out_size, in_start, in_size)
        return self.layout

    def enter_preop(self) -> MailboxLayout:
        """PRE-OP with the standard mailbox (SII words 0x18-0x1B, as the scan wrote it into SM0/SM1): for
        files a device takes outside BOOTSTRAP (a configuration file); the mailbox's layout."""
        self.request(AL_PREOP)
        layout = MailboxLayout.from_sm_registers(self._read(0x0800, 16, "SM0/SM1"))
        if layout is None:
            raise FieldbusError(f"{self.where}: no mailbox in SM0/SM1: no FoE")
        self.layout = layout
        return layout

    def leave_bootstrap(self) -> None:
        """Back to INIT (a rescan configures the slave again)."""
        self.request(AL_INIT)
        self.layout = None

    # -- transfers -----------------------------------------------------------------------------------
    def transfer(
        self, t: FoeTransfer, layout: MailboxLayout | None = None
    ) -> Generator[None, None, bytes | None]:
        """Run ``t`` one datagram per step through the mailbox ``layout`` (default: the bootstrap one)."""
        lay = layout or self.layout
        if lay is None:
            raise FieldbusError(f"{self.where}: not in BOOTSTRAP (enter_bootstrap first)")
        mbx = SlaveMailbox(lay, self.port)
        try:
            return (yield from mbx.transfer(t, STEPS_PER_ANSWER, per_answer=True))
        except FoeError as exc:
            raise FoeError(exc.code, text=exc.text, file=exc.file, slave=self.where) from None

    def foe(self, name: str, data: bytes | None, *, password: int = 0) -> FoeTransfer:
        """A read (``data`` None) or write of ``name`` sized for the mailbox entered (bootstrap or standard)."""
        if self.layout is None:
            raise FieldbusError(f"{self.where}: not in BOOTSTRAP (enter_bootstrap first)")
        return FoeTransfer(
            name, data, password=password, mailbox_out=self.layout.out_size, mailbox_in=self.layout.in_size
        )


def run_steps(steps: Generator[None, None, bytes | None]) -> bytes | None:
    """Run a transfer's steps to the end (outside OP: nothing else waits for the bus)."""
    while True:
        try:
            next(steps)
        except StopIteration as done:
            result: bytes | None = done.value
            return result


AGAIN = "run the same command again to finish the update (docs/firmware.md)"
# after the transfer, the rescan waits this long for the segment to answer (a device may restart) [s]
RESCAN_S = 5.0


@dataclass(frozen=True)
class FileTransferResult:
    """What :func:`transfer_file` did: the slave's identity before and after, the bytes moved and, for
    a read, the file."""

    before: Identity
    after: Identity
    size: int
    data: bytes | None


def transfer_file(
    interface: str,
    slave: int,
    name: str,
    data: bytes | None,
    *,
    password: int = 0,
    preop: bool = False,
    progress: Callable[[int, int], None] | None = None,
    say: Callable[[str], None] | None = None,
) -> FileTransferResult:
    """Write ``data`` (or read, ``data`` None) as file ``name`` on slave ``slave`` (0-based) of the
    segment on ``interface``, over FoE: INIT -> BOOTSTRAP (``preop``: PRE-OP, the standard
    mailbox), the transfer, INIT, a rescan (:mod:`fieldbus.backends.ecat_firmware`).

    ``progress(done, total)`` after each datagram (a read's total is 0 until the end); ``say``
    gets the steps as lines. Takes the card (refused while a master runs on it) and every slave
    out of OP. Errors name the slave's state and the recovery: :class:`FoeError` (the slave is
    back in INIT), :class:`BusTimeoutError` (it may be left in BOOTSTRAP, or without valid
    firmware), KeyboardInterrupt (it stays in BOOTSTRAP); docs/firmware.md.
    """
    from fieldbus.backends.buslock import lock_network_card
    from fieldbus.backends.ecat_master import open_segment

    tell = say or (lambda _line: None)
    with lock_network_card(interface):
        master = open_segment(interface)
        try:
            session = FirmwareSession(master, slave)
            before = session.identity()
            tell(f"before: {before.line()}")
            layout = session.enter_preop() if preop else session.enter_bootstrap()
            mode = "PRE-OP" if preop else "BOOTSTRAP"
            tell(f"{session.where}: {mode} (mailbox {layout.out_size}/{layout.in_size} bytes)")
            t = session.foe(name, data, password=password)
            steps = session.transfer(t)
            try:
                while True:
                    try:
                        next(steps)
                    except StopIteration:
                        break
                    if progress is not None:
                        progress(t.done, t.total)
            except KeyboardInterrupt:
                incomplete = " with an incomplete file" if data is not None else ""
                raise KeyboardInterrupt(f"{session.where} stays in {mode}{incomplete}; {AGAIN}") from None
            except BusTimeoutError as exc:
                raise BusTimeoutError(
                    f"{exc}; {session.where} may be left in {mode}, or without valid firmware if it"
                    f" lost power: {AGAIN}"
                ) from None
            except FoeError as exc:
                with contextlib.suppress(FieldbusError):  # the error names the first fault
                    session.leave_bootstrap()
                raise FoeError(
                    exc.code, text=exc.text, file=exc.file, slave=f"{exc.slave} (back in INIT)"
                ) from None
            try:  # the file is whole: a Ctrl-C from here on still says where the device is
                if progress is not None:
                    progress(t.done, t.total)
                session.leave_bootstrap()
            except KeyboardInterrupt:
                raise KeyboardInterrupt(
                    f"{session.where}: the file was transferred whole, the device may stay in {mode}; {AGAIN}"
                ) from None
        finally:
            master.close()
        master = open_segment(interface, wait_s=RESCAN_S)  # the rescan: SOEM configures the mailbox again
        try:
            after = FirmwareSession(master, slave).identity()
        except KeyboardInterrupt:
            raise KeyboardInterrupt(
                f"{session.where}: the update is complete; interrupted while reading its identity back"
            ) from None
        finally:
            master.close()
    tell(f"after:  {after.line()}")
    return FileTransferResult(before, after, t.done, t.result)
