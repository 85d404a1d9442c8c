"""An emulated slave's FoE server (file access over EtherCAT, mailbox type 4) and its file store.

Files by name: a name ending in ``.efw`` is firmware - written and read in
BOOTSTRAP only (else FoE error 0x8008, bootstrap only), checked when its
last packet arrives (:func:`fieldbus.core.firmware_image.image_revision`; a
damaged image: 0x800B, program error) and reported as the revision
(0x1018:03, SII word 0x0C) from the next power cycle on. Other files
(a configuration, as Synapticon drives take over FoE) are written and read
outside BOOTSTRAP only (0x8009, not bootstrap). A wrong password: 0x800A
(no rights); an unknown file: 0x8001; more than the store holds: 0x8003;
a DATA out of sequence: 0x8005; a message out of place: 0x8004.

A firmware write that starts erases the old image: until one completes,
the device has no valid firmware and refuses to leave INIT for PRE-OP
(AL status code 0x0014) after a power cycle - it stays updatable in
BOOTSTRAP, as a device with a boot loader does. The store outlives power
cycles (:class:`FirmwareStore`); the transfer in progress does not.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

from fieldbus.core.coe_mailbox import MailboxProtocolError
from fieldbus.core.firmware_image import image_revision
from fieldbus.core.foe import (
    FOE_OVERHEAD,
    FoeErrorCode,
    FoeOpCode,
    decode_foe,
    encode_busy,
    encode_error,
    encode_foe,
)

FIRMWARE_SUFFIX = ".efw"
DEFAULT_CAPACITY = 4 << 20  # bytes one file may hold


def is_firmware(name: str) -> bool:
    return name.lower().endswith(FIRMWARE_SUFFIX)


@dataclass
class FirmwareStore:
    """A device's files and firmware state, kept over power cycles.

    ``active_revision``: the revision the running firmware reports (None:
    the drive map's); ``staged_revision``: an image written completely,
    taken at the next power cycle; ``valid``: False from the start of a
    firmware write until one completes intact.
    """

    password: int = 0
    capacity: int = DEFAULT_CAPACITY
    files: dict[str, bytes] = field(default_factory=dict)
    active_revision: int | None = None
    staged_revision: int | None = None
    valid: bool = True
    writes: int = 0  # firmware writes completed intact
    busy_answers: int = 0  # fault hook: answer the next DATA packets with BUSY
    cut_after: int | None = None  # fault hook: power lost once a write has taken this many more bytes
    on_power_loss: Callable[[], None] | None = None  # called then (the chain power-cycles the slave)

    def power_on(self) -> int | None:
        """A power cycle: a staged image becomes the running one; the revision to report (None: the map's)."""
        if self.staged_revision is not None:
            self.active_revision, self.staged_revision = self.staged_revision, None
        return self.active_revision

    def status(self) -> dict[str, object]:
        return {
            "active_revision": self.active_revision,
            "staged_revision": self.staged_revision,
            "valid": self.valid,
            "writes": self.writes,
            "files": {k: len(v) for k, v in self.files.items()},
        }


class FoeServer:
    """The FoE side of one slave's mailbox: requests in, answers out (FoE payloads, no mailbox header).

    ``size_out`` / ``size_in``: the mailboxes in use (standard or bootstrap),
    set by the ESC on each state change; a DATA carries 12 bytes less.
    """

    def __init__(self, store: FirmwareStore) -> None:
        self.store = store
        self.size_out = 0
        self.size_in = 0
        self.reset()

    def reset(self) -> None:
        """No transfer in progress (INIT, BOOT entered, power on)."""
        self._name = ""
        self._writing = False
        self._reading: bytes | None = None
        self._packet = 0  # write: the packet expected next; read: the packet sent last
        self._offset = 0  # read: bytes sent before the packet in flight
        self._buf = bytearray()

    def answers(self, payload: bytes, boot: bool) -> list[bytes]:
        """The answers to one FoE request (none to a read's final ACK or an ERR from the master)."""
        try:
            msg = decode_foe(payload)
        except MailboxProtocolError:
            return [self._fail(FoeErrorCode.ILLEGAL, "short FoE message")]
        op = msg.op
        if op in (FoeOpCode.WRQ, FoeOpCode.RRQ):
            self.reset()
            name = msg.data.split(b"\0", 1)[0].decode("latin-1")
            refused = self._refuse(name, msg.value, boot, write=op == FoeOpCode.WRQ)
            if refused is not None:
                return [self._fail(*refused)]
            self._name = name
            if op == FoeOpCode.RRQ:
                self._reading = self.store.files[name]
                return [self._next_data()]
            self._writing = True
            self._packet = 1
            if is_firmware(name):
                self.store.valid = False  # the old image is erased
                self.store.staged_revision = None
            return [encode_foe(FoeOpCode.ACK, 0)]
        if op == FoeOpCode.DATA and self._writing:
            return [self._data(msg.value, msg.data)]
        if op == FoeOpCode.ACK and self._reading is not None:
            if msg.value != self._packet:
                return [self._fail(FoeErrorCode.PACKET_NUMBER, f"ACK {msg.value}, sent {self._packet}")]
            last = self._offset + self._room_in() > len(self._reading)
            self._offset += self._room_in()
            if last:
                self.reset()
                return []
            return [self._next_data()]
        if op == FoeOpCode.ERR:
            self.reset()
            return []
        return [self._fail(FoeErrorCode.ILLEGAL, f"op code {op} out of place")]

    def _refuse(self, name: str, password: int, boot: bool, *, write: bool) -> tuple[int, str] | None:
        if not name:
            return FoeErrorCode.NOT_FOUND, "no file name"
        if password != self.store.password:
            return FoeErrorCode.NO_RIGHTS, "wrong password"
        if is_firmware(name) and not boot:
            return FoeErrorCode.BOOTSTRAP_ONLY, "firmware in BOOTSTRAP only"
        if not is_firmware(name) and boot:
            return FoeErrorCode.NOT_BOOTSTRAP, "not in BOOTSTRAP"
        if not write and name not in self.store.files:
            return FoeErrorCode.NOT_FOUND, name
        return None

    def _room_in(self) -> int:
        return self.size_in - FOE_OVERHEAD

    def _next_data(self) -> bytes:
        assert self._reading is not None
        self._packet += 1
        chunk = self._reading[self._offset : self._offset + self._room_in()]
        return encode_foe(FoeOpCode.DATA, self._packet, chunk)

    def _data(self, packet: int, data: bytes) -> bytes:
        store = self.store
        if packet != self._packet:
            return self._fail(FoeErrorCode.PACKET_NUMBER, f"DATA {packet}, expected {self._packet}")
        if store.busy_answers > 0:
            store.busy_answers -= 1
            return encode_busy(len(self._buf) >> 10, 0)
        if len(self._buf) + len(data) > store.capacity:
            return self._fail(FoeErrorCode.DISK_FULL, f"more than {store.capacity} bytes")
        self._buf += data
        self._packet += 1
        if store.cut_after is not None:
            store.cut_after -= len(data)
            if store.cut_after <= 0 and store.on_power_loss is not None:
                store.cut_after = None
                store.on_power_loss()
        if len(data) >= self.size_out - FOE_OVERHEAD:
            return encode_foe(FoeOpCode.ACK, packet)
        name, image = self._name, bytes(self._buf)
        self.reset()
        if is_firmware(name):
            revision = image_revision(image)
            if revision is None:
                return encode_error(FoeErrorCode.PROGRAM_ERROR, "image check failed")
            store.staged_revision, store.valid = revision, True
            store.writes += 1
        store.files[name] = image
        return encode_foe(FoeOpCode.ACK, packet)

    def _fail(self, code: int, text: str) -> bytes:
        self.reset()
        return encode_error(code, text)
