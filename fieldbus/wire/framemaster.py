"""An EtherCAT master that speaks frames through a transport (the in-process sim backend's engine).

A transport is any ``frame -> reply`` callable (None: the frame was lost);
``sim_slaves.ethercat.EscChain.process`` is one. Every step here is real
EtherCAT: datagrams built with :mod:`fieldbus.core.ecat`, working counters
checked, SII read through the ESC's EEPROM interface, SDOs through the CoE
mailbox (SM0 master -> slave, SM1 slave -> master), SyncManagers and FMMUs
programmed as SOEM does for an LRW image (all outputs from logical 0 in wire
order, then all inputs). Station addresses are 0x1001 + position, as SOEM
assigns them.
"""

from __future__ import annotations

import struct
from collections.abc import Callable, Iterator
from dataclasses import dataclass

from fieldbus.core.al import AL_ACK, AL_ERROR, AL_INIT
from fieldbus.core.ecat import Command, Datagram, build_master_frame, decode_frame
from fieldbus.core.sdo import info as sdo_info
from fieldbus.errors import BusTimeoutError, FieldbusError, SdoAbortError, StateTransitionError

Transport = Callable[[bytes], "bytes | None"]

STATION_BASE = 0x1001

# registers written to 0 by every slave at start (SOEM's defaults): DL control (port loops, alias
# off), DL user/IRQ mask, IRQ masks, FMMUs, SyncManagers, DC activation, DC control loop inputs
DEFAULT_REGISTERS = (
    (0x0101, 1),
    (0x0103, 1),
    (0x0200, 2),
    (0x0300, 8),
    (0x0600, 48),
    (0x0800, 32),
    (0x0981, 1),
    (0x0910, 8),
    (0x0930, 2),
    (0x0934, 2),
)

# SII word addresses (ETG.1000.6 5.4) and categories
SII_VENDOR, SII_PRODUCT, SII_REVISION = 0x08, 0x0A, 0x0C
SII_MBX_OUT, SII_MBX_IN = 0x18, 0x1A
SII_CATEGORIES = 0x40
SII_CAT_STRINGS, SII_CAT_GENERAL, SII_CAT_SM, SII_CAT_END = 10, 30, 41, 0xFFFF
SII_SM_OUTPUTS, SII_SM_INPUTS = 3, 4
EEPROM_READ = 0x0100
EEPROM_BUSY = 0x8000

MBX_TYPE_COE = 0x03
COE_EMERGENCY, COE_SDO_REQUEST, COE_SDO_RESPONSE = 1, 2, 3
SDO_ABORT = 0x80
SDO_ABORT_TIMEOUT = 0x05040000  # CiA 301: SDO protocol timed out

_U16 = struct.Struct("<H")
_U32 = struct.Struct("<I")
_MBX = struct.Struct("<HHBB")  # length, address, channel/priority, type/counter
_SDO = struct.Struct("<HBHBI")  # CoE header, command, index, sub-index, data/size


@dataclass(frozen=True)
class SyncManagerInfo:
    """One SyncManager from the SII SM category: physical start, default length, control, type."""

    start: int
    length: int
    control: int
    type: int


@dataclass(frozen=True)
class SlaveInfo:
    """What the master read from one slave's SII: identity, name, mailbox and SM layout (bytes)."""

    position: int
    station: int
    vendor_id: int
    product_id: int
    revision: int
    name: str
    mbx_out: tuple[int, int]  # SM0 start, size (master -> slave)
    mbx_in: tuple[int, int]  # SM1 start, size (slave -> master)
    sms: tuple[SyncManagerInfo, ...]

    def sm(self, kind: int) -> SyncManagerInfo | None:
        return next((s for s in self.sms if s.type == kind), None)


@dataclass(frozen=True)
class Mapping:
    """Where one slave's process data sit in the logical image (bytes)."""

    station: int
    out_offset: int
    out_size: int
    in_offset: int
    in_size: int


class FrameMaster:
    """Bring-up and acyclic services over a frame transport. Blocking; not for the cycle."""

    def __init__(self, transport: Transport, *, retries: int = 3, mailbox_polls: int = 200) -> None:
        self.transport = transport
        self.retries = retries
        self.mailbox_polls = mailbox_polls
        self.emergencies: list[tuple[int, int, int]] = []  # (station, error code, error register)
        self._idx = 0
        self._mbx_counter: dict[int, int] = {}

    # -- frames ---------------------------------------------------------------------------
    def txrx(self, dgs: list[Datagram]) -> tuple[Datagram, ...]:
        """Send one frame of ``dgs`` and return the datagrams as they came back (retries lost frames)."""
        self._idx = (self._idx + 1) & 0xFF
        dgs = [Datagram(d.cmd, self._idx, d.address, d.data) for d in dgs]
        frame = build_master_frame(dgs)
        for _ in range(self.retries):
            reply = self.transport(frame)
            if reply is not None:
                return decode_frame(reply).datagrams
        raise BusTimeoutError(f"no reply to {self.retries} tries of a {dgs[0].cmd.name} frame")

    def fprd(self, station: int, ado: int, n: int) -> tuple[bytes, int]:
        (d,) = self.txrx([Datagram.physical(Command.FPRD, station, ado, bytes(n))])
        return d.data, d.wkc

    def fpwr(self, station: int, ado: int, data: bytes) -> int:
        (d,) = self.txrx([Datagram.physical(Command.FPWR, station, ado, data)])
        return d.wkc

    def _fpwr_checked(self, station: int, ado: int, data: bytes, what: str) -> None:
        if self.fpwr(station, ado, data) != 1:
            raise StateTransitionError(f"station 0x{station:04X}: {what} not acknowledged (WKC 0)")

    # -- scan -------------------------------------------------------------------------------
    def scan(self) -> int:
        """Reset every slave to INIT and to default settings, as SOEM's config_init does; count them.

        Whatever an earlier master (or a fuzzer) left behind is undone before
        anything is read: DL control and port settings, interrupt masks, FMMUs,
        SyncManagers, DC activation, EEPROM access given back to the master.
        """
        self.txrx([Datagram.physical(Command.BWR, 0, 0x0120, _U16.pack(AL_INIT | AL_ACK))])
        (d,) = self.txrx([Datagram.physical(Command.BRD, 0, 0x0000, bytes(2))])
        for ado, size in DEFAULT_REGISTERS:
            self.txrx([Datagram.physical(Command.BWR, 0, ado, bytes(size))])
        self.txrx([Datagram.physical(Command.BWR, 0, 0x0120, _U16.pack(AL_INIT | AL_ACK))])
        self.txrx([Datagram.physical(Command.BWR, 0, 0x0500, b"\x02")])  # EEPROM: reset PDI access
        self.txrx([Datagram.physical(Command.BWR, 0, 0x0500, b"\x00")])  # ... and to the master
        return d.wkc

    def identify(self, found: int) -> list[SlaveInfo]:
        """Station addresses for all ``found`` slaves first, then each one's SII.

        In this order because addresses left by an earlier master may repeat:
        until every slave has its new one, a configured-address read could
        reach two slaves at once.
        """
        stations = [self.assign_station(p) for p in range(found)]
        return [self.read_sii(p, st) for p, st in enumerate(stations)]

    def assign_station(self, position: int) -> int:
        """Give the slave at ``position`` its configured station address (APWR 0x0010)."""
        station = STATION_BASE + position
        (d,) = self.txrx([Datagram.physical(Command.APWR, -position, 0x0010, _U16.pack(station))])
        if d.wkc != 1:
            raise StateTransitionError(f"position {position}: no slave took a station address")
        return station

    # -- SII ----------------------------------------------------------------------------------
    def eeprom_read(self, station: int, word: int) -> bytes:
        """8 bytes of the SII from word address ``word`` (through the ESC's EEPROM interface)."""
        cmd = _U16.pack(EEPROM_READ) + _U32.pack(word)
        self._fpwr_checked(station, 0x0502, cmd, "EEPROM read command")
        for _ in range(self.mailbox_polls):
            status, wkc = self.fprd(station, 0x0502, 2)
            if wkc == 1 and not _U16.unpack(status)[0] & EEPROM_BUSY:
                data, _ = self.fprd(station, 0x0508, 8)
                return data
        raise BusTimeoutError(f"station 0x{station:04X}: EEPROM stays busy")

    def read_sii(self, position: int, station: int) -> SlaveInfo:
        """Identity, mailbox and SyncManager layout from the slave's SII."""
        head = b"".join(self.eeprom_read(station, w) for w in range(SII_VENDOR, SII_MBX_IN + 4, 4))

        def u32(word: int) -> int:
            return int(_U32.unpack_from(head, 2 * (word - SII_VENDOR))[0])

        def u16(word: int) -> int:
            return int(_U16.unpack_from(head, 2 * (word - SII_VENDOR))[0])

        name = ""
        strings: list[str] = []
        general = b""
        sms: list[SyncManagerInfo] = []
        for kind, data in self._categories(station):
            if kind == SII_CAT_STRINGS:
                strings = sii_strings(data)
            elif kind == SII_CAT_GENERAL:
                general = data
            elif kind == SII_CAT_SM:
                for k in range(len(data) // 8):
                    start, length, ctrl, _status, _enable, sm_type = struct.unpack_from(
                        "<HHBBBB", data, 8 * k
                    )
                    sms.append(SyncManagerInfo(start, length, ctrl, sm_type))
        if len(general) > 3 and 0 < general[3] <= len(strings):
            name = strings[general[3] - 1]  # name index (1-based into the strings)
        return SlaveInfo(
            position,
            station,
            u32(SII_VENDOR),
            u32(SII_PRODUCT),
            u32(SII_REVISION),
            name,
            (u16(SII_MBX_OUT), u16(SII_MBX_OUT + 1)),
            (u16(SII_MBX_IN), u16(SII_MBX_IN + 1)),
            tuple(sms),
        )

    def _categories(self, station: int) -> Iterator[tuple[int, bytes]]:
        word = SII_CATEGORIES
        while word < 0x4000:
            kind, words = struct.unpack("<HH", self.eeprom_read(station, word)[:4])
            if kind == SII_CAT_END:
                return
            data = b"".join(self.eeprom_read(station, w) for w in range(word + 2, word + 2 + words, 4))
            yield kind, data[: 2 * words]
            word += 2 + words

    # -- AL states ------------------------------------------------------------------------------
    def setup_mailbox(self, info: SlaveInfo) -> None:
        """SM0/SM1 for the mailbox, as the SII says (needed before PRE-OP)."""
        (o_start, o_len), (i_start, i_len) = info.mbx_out, info.mbx_in
        if o_len and i_len:
            sm01 = struct.pack("<HHI", o_start, o_len, 0x00010026) + struct.pack(
                "<HHI", i_start, i_len, 0x00010022
            )
            self._fpwr_checked(info.station, 0x0800, sm01, "mailbox SyncManagers")
        self._mbx_counter[info.station] = 0

    def request_state(self, station: int, state: int) -> None:
        self._fpwr_checked(station, 0x0120, _U16.pack(state), "AL control")

    def al_status(self, station: int) -> tuple[int, int] | None:
        """(AL status, AL status code), or None when the station does not answer."""
        data, wkc = self.fprd(station, 0x0130, 6)
        if wkc != 1:
            return None
        status, _, code = struct.unpack("<HHH", data)
        return status, code

    def wait_state(
        self, stations: list[int], state: int, polls: int = 100
    ) -> dict[int, tuple[int, int] | None]:
        """Poll until every station reports ``state``; returns the ones that did not (status, code)."""
        missing: dict[int, tuple[int, int] | None] = {}
        for _ in range(polls):
            missing = {}
            for st in stations:
                got = self.al_status(st)
                if got is None or (got[0] & 0x1F) != state:
                    missing[st] = got
            if not missing or any(v is not None and v[0] & AL_ERROR for v in missing.values()):
                break
        return missing

    # -- CoE SDO (mailbox) ------------------------------------------------------------------------
    def _mailbox_send(self, info: SlaveInfo, coe: bytes) -> None:
        start, size = info.mbx_out
        if not size:
            raise FieldbusError(f"station 0x{info.station:04X} has no mailbox")
        counter = self._mbx_counter.get(info.station, 0) % 7 + 1
        self._mbx_counter[info.station] = counter
        frame = (_MBX.pack(len(coe), 0, 0, MBX_TYPE_COE | counter << 4) + coe).ljust(size, b"\0")
        for _ in range(self.mailbox_polls):
            if self.fpwr(info.station, start, frame[:size]) == 1:
                return
        raise BusTimeoutError(f"station 0x{info.station:04X}: mailbox stays full")

    def _mailbox_receive(self, info: SlaveInfo) -> bytes:
        """The next CoE answer (emergencies are recorded and skipped)."""
        start, size = info.mbx_in
        for _ in range(self.mailbox_polls):
            data, wkc = self.fprd(info.station, start, size)
            if wkc != 1:
                continue
            length, _, _, tc = _MBX.unpack_from(data)
            coe = data[_MBX.size : _MBX.size + length]
            if tc & 0x0F == MBX_TYPE_COE and len(coe) >= 2 and coe[1] >> 4 == COE_EMERGENCY:
                code, reg = struct.unpack_from("<HB", coe, 2)
                self.emergencies.append((info.station, code, reg))
                continue
            return coe
        raise BusTimeoutError(f"station 0x{info.station:04X}: no mailbox answer")

    def _sdo_exchange(self, info: SlaveInfo, request: bytes, index: int, sub: int) -> bytes:
        self._mailbox_send(info, request)
        coe = self._mailbox_receive(info)
        if len(coe) < 10:
            raise SdoAbortError(SDO_ABORT_TIMEOUT, index=index, sub_index=sub, detail="short SDO answer")
        service, cmd = coe[1] >> 4, coe[2]
        if cmd == SDO_ABORT:
            raise SdoAbortError(_U32.unpack_from(coe, 6)[0], index=index, sub_index=sub)
        if service != COE_SDO_RESPONSE:
            raise SdoAbortError(
                SDO_ABORT_TIMEOUT, index=index, sub_index=sub, detail=f"CoE service {service}"
            )
        return coe

    def sdo_download(self, info: SlaveInfo, index: int, sub: int, data: bytes) -> None:
        """Write ``data`` to ``index:sub`` (expedited up to 4 bytes, else normal in one mailbox)."""
        if len(data) <= 4:
            cmd = 0x23 | (4 - len(data)) << 2
            req = _SDO.pack(COE_SDO_REQUEST << 12, cmd, index, sub, 0)[:6] + data.ljust(4, b"\0")
        else:
            room = info.mbx_out[1] - _MBX.size - _SDO.size
            if len(data) > room:
                raise FieldbusError(f"SDO 0x{index:04X}:{sub:02X}: {len(data)} bytes exceed the mailbox")
            req = _SDO.pack(COE_SDO_REQUEST << 12, 0x21, index, sub, len(data)) + data
        self._sdo_exchange(info, req, index, sub)

    def sdo_upload(self, info: SlaveInfo, index: int, sub: int) -> bytes:
        """Read ``index:sub`` (expedited, normal or segmented answers)."""
        coe = self._sdo_exchange(info, _SDO.pack(COE_SDO_REQUEST << 12, 0x40, index, sub, 0), index, sub)
        cmd = coe[2]
        if cmd & 0x02:  # expedited
            n = 4 - ((cmd >> 2) & 0x03) if cmd & 0x01 else 4
            return bytes(coe[6 : 6 + n])
        size = _U32.unpack_from(coe, 6)[0]
        data = bytearray(coe[10:])
        toggle = 0
        while len(data) < size:
            seg = self._sdo_exchange(
                info, struct.pack("<HB", COE_SDO_REQUEST << 12, 0x60 | toggle) + bytes(7), index, sub
            )
            chunk = seg[3:]
            if seg[2] & 0x01 and len(chunk) == 7:
                chunk = chunk[: 7 - ((seg[2] >> 1) & 0x07)]
            data += chunk
            toggle ^= 0x10
            if seg[2] & 0x01:
                break
        return bytes(data[:size])

    # -- CoE SDO Information (ETG.1000.6 5.6.3) ---------------------------------------------------
    def _sdo_info(self, info: SlaveInfo, request: bytes, expect: int, index: int = 0, sub: int = 0) -> bytes:
        self._mailbox_send(info, request)
        joined = sdo_info.Reassembly(expect, index, sub)
        for _ in range(0x10000):
            data = joined.add(self._mailbox_receive(info))
            if data is not None:
                return data
        raise BusTimeoutError(f"station 0x{info.station:04X}: SDO Information answer never ends")

    def od_list(self, info: SlaveInfo, list_type: int = sdo_info.ListType.ALL) -> list[int]:
        """The indices of the slave's objects (Get OD List, all fragments)."""
        data = self._sdo_info(info, sdo_info.od_list_request(list_type), sdo_info.InfoOpcode.OD_LIST_RES)
        return sdo_info.parse_od_list(data)[1]

    def object_description(self, info: SlaveInfo, index: int) -> sdo_info.ObjectDescription:
        data = self._sdo_info(info, sdo_info.od_request(index), sdo_info.InfoOpcode.OD_RES, index)
        return sdo_info.parse_od(data)

    def entry_description(self, info: SlaveInfo, index: int, sub: int) -> sdo_info.EntryDescription:
        data = self._sdo_info(info, sdo_info.oe_request(index, sub), sdo_info.InfoOpcode.OE_RES, index, sub)
        return sdo_info.parse_oe(data)

    # -- process data ---------------------------------------------------------------------------
    def map_process_data(self, info: SlaveInfo, m: Mapping) -> None:
        """SM2/SM3 lengths and one FMMU each, as SOEM programs an LRW image."""
        f = 0
        for size, kind, offset, fmmu_type in (
            (m.out_size, SII_SM_OUTPUTS, m.out_offset, 2),
            (m.in_size, SII_SM_INPUTS, m.in_offset, 1),
        ):
            if not size:
                continue
            sm = info.sm(kind)
            if sm is None:
                raise StateTransitionError(
                    f"station 0x{m.station:04X}: SII has no SyncManager of type {kind}"
                )
            reg = 0x0810 if kind == SII_SM_OUTPUTS else 0x0818
            self._fpwr_checked(
                m.station, reg, struct.pack("<HHBBBB", sm.start, size, sm.control, 0, 1, 0), "SM"
            )
            fmmu = struct.pack("<IHBBHBBB", offset, size, 0, 7, sm.start, 0, fmmu_type, 1) + bytes(3)
            self._fpwr_checked(m.station, 0x0600 + 16 * f, fmmu, "FMMU")
            f += 1


def sii_strings(data: bytes) -> list[str]:
    """The strings of an SII STRINGS category (count, then length-prefixed latin-1 strings)."""
    from fieldbus.core.sii import strings

    return strings(data)


def layout_image(sizes: list[tuple[int, int]]) -> tuple[list[Mapping], int, int]:
    """Logical image for slaves' (out, in) byte sizes: all outputs from 0 in order, then all inputs.

    Returns the mappings (stations from :data:`STATION_BASE`), output bytes, input bytes.
    """
    out_bytes = sum(o for o, _ in sizes)
    maps = []
    o_off, i_off = 0, out_bytes
    for pos, (o, i) in enumerate(sizes):
        maps.append(Mapping(STATION_BASE + pos, o_off, o, i_off, i))
        o_off += o
        i_off += i
    return maps, out_bytes, i_off - out_bytes
