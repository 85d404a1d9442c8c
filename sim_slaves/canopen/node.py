"""One emulated CANopen device (CiA 301 + CiA 402), sans-IO: CAN frames in, CAN frames out.

The object dictionary comes from the drive map (:mod:`sim_slaves.od`) plus
the CiA 301 communication objects: 0x1005 SYNC COB-ID, 0x1017 producer
heartbeat time, 0x1400-0x1403 / 0x1800-0x1803 PDO communication (COB-ID with
bit 31 = PDO not valid, transmission type, inhibit time, event timer) and
0x1600-0x1603 / 0x1A00-0x1A03 PDO mapping. PDO mapping can only change in
PRE-OPERATIONAL with the PDO invalid, as CiA 301 says, and a valid PDO's
CAN-ID cannot change (0x06090030); what is mapped is what is sent and received
(the PDO layout is rebuilt when the mapping or a communication object changes).

Directions from the master's side: RPDOs (0x1400/0x1600) carry master
outputs to the drive, TPDOs (0x1800/0x1A00) master inputs from it.

Transmission types (CiA 301 7.2.2): a received synchronous RPDO (0-240) takes
effect at the next SYNC, an asynchronous one (254/255) at once. At each SYNC
the drive model steps, then TPDOs go out: type 1-240 every n-th SYNC since
the node entered OPERATIONAL, type 0 (acyclic synchronous) when its data
changed, type 254/255 (event driven) when its data changed and the inhibit
time has passed, and on its event timer (:meth:`CanopenNode.timers`).
"""

from __future__ import annotations

import struct
from dataclasses import dataclass
from enum import IntEnum
from typing import Protocol

from fieldbus.core import datatypes
from fieldbus.core.pdo.model import Channel, DriveMap
from fieldbus.errors import SdoAbortError
from sim_slaves.ethercat.axes import device_od
from sim_slaves.od import Access, CommState, Entry, ObjectDictionary

U8 = datatypes.lookup("uint8")
U16 = datatypes.lookup("uint16")
U32 = datatypes.lookup("uint32")
assert U8 is not None and U16 is not None and U32 is not None

COB_NMT, COB_SYNC, COB_EMCY, COB_TSDO, COB_RSDO, COB_HEARTBEAT = 0x000, 0x080, 0x080, 0x580, 0x600, 0x700
RPDO_COB = (0x200, 0x300, 0x400, 0x500)
TPDO_COB = (0x180, 0x280, 0x380, 0x480)
INVALID = 0x80000000
CAN_ID_MASK = 0x1FFFFFFF
ABORT_TOGGLE = 0x05030000
ABORT_COMMAND = 0x05040001
ABORT_LENGTH = 0x06070010
ABORT_VALUE_RANGE = 0x06090030
ABORT_STATE = 0x08000022
ABORT_GENERAL = 0x08000000
COMM_AREA = range(0x1000, 0x2000)  # restored by NMT reset communication
PDO_OBJECTS = range(0x1400, 0x1C00)  # communication and mapping objects of PDOs

Frame = tuple[int, bytes]  # (11-bit COB-ID, data)
ERROR_FIELD, ERROR_FIELD_DEPTH = 0x1003, 8  # CiA 301 pre-defined error field: the last 8 errors


class NmtState(IntEnum):
    """NMT states and their heartbeat byte (CiA 301)."""

    BOOTUP = 0x00
    STOPPED = 0x04
    OPERATIONAL = 0x05
    PRE_OPERATIONAL = 0x7F


_COMM = {
    NmtState.PRE_OPERATIONAL: CommState.PRE_OPERATIONAL,
    NmtState.OPERATIONAL: CommState.OPERATIONAL,
    NmtState.STOPPED: CommState.INIT,
    NmtState.BOOTUP: CommState.INIT,
}

# byte-aligned types packed with struct (the fast path); others bit by bit
_STRUCT_CODE = {
    ("int", 8): "b",
    ("uint", 8): "B",
    ("int", 16): "h",
    ("uint", 16): "H",
    ("int", 32): "i",
    ("uint", 32): "I",
    ("int", 64): "q",
    ("uint", 64): "Q",
    ("float", 32): "f",
    ("float", 64): "d",
}


class App(Protocol):
    def step(self, od: ObjectDictionary, dt_s: float) -> None: ...


class _Codec:
    """Packs / unpacks one PDO's mapped objects straight from / into their OD entries."""

    def __init__(self, od: ObjectDictionary, channels: tuple[Channel, ...]) -> None:
        self.channels = channels
        self.entries: list[Entry] = []
        self.floats: list[bool] = []
        fmt = "<"
        fast = True
        for ch in channels:
            if ch.is_gap:
                if ch.bits % 8:
                    fast = False
                fmt += f"{ch.bits // 8}x"
                continue
            self.entries.append(od.entry(ch.index, ch.sub_index))
            self.floats.append(ch.type.is_float)
            code = _STRUCT_CODE.get((ch.type.kind, ch.type.bits))
            if code is None:
                fast = False
            fmt += code or "x"
        self.bits = sum(ch.bits for ch in channels)
        self.size = (self.bits + 7) // 8
        self.struct = struct.Struct(fmt) if fast else None
        self.all_int = not any(self.floats)

    def pack(self) -> bytes:
        st = self.struct
        if st is not None:
            if self.all_int:
                return st.pack(*[int(e.value) for e in self.entries])
            return st.pack(
                *[
                    float(e.value) if f else int(e.value)
                    for e, f in zip(self.entries, self.floats, strict=True)
                ]
            )
        raw = 0
        bit = 0
        k = 0
        for ch in self.channels:
            bits = ch.bits
            if not ch.is_gap:
                value = self.entries[k].value
                k += 1
                assert not isinstance(value, bytes)
                enc = ch.type.encode(value)
                raw |= (int.from_bytes(enc, "little") & ((1 << bits) - 1)) << bit
            bit += bits
        return raw.to_bytes(self.size, "little")

    def unpack(self, data: bytes) -> None:
        """Write ``data`` into the mapped objects (a frame of another length is ignored, as CiA 301 allows)."""
        if len(data) < self.size:
            return
        st = self.struct
        if st is not None:
            for e, v in zip(self.entries, st.unpack_from(data), strict=True):
                e.value = v
            return
        raw = int.from_bytes(data, "little")
        bit = 0
        k = 0
        for ch in self.channels:
            bits = ch.bits
            if not ch.is_gap:
                value = (raw >> bit) & ((1 << bits) - 1)
                self.entries[k].value = ch.type.decode(value.to_bytes((bits + 7) // 8, "little"))
                k += 1
            bit += bits


@dataclass
class _PdoRuntime:
    number: int  # 1..4
    cob_id: int
    transmission_type: int
    codec: _Codec
    inhibit_s: float = 0.0
    event_s: float = 0.0
    last: bytes | None = None  # data last sent (TPDO)
    last_t: float = float("-inf")  # when (s, the caller's clock)


@dataclass
class _Segmented:
    index: int
    sub: int
    data: bytearray
    toggle: int
    size: int = -1  # indicated size of a download; -1: not indicated


def add_communication_objects(od: ObjectDictionary, drive: DriveMap, node_id: int) -> None:
    """The CiA 301 communication objects of a node at ``node_id`` (COB-IDs of the predefined set).

    PDOs the map does not have are not valid (COB-ID bit 31 set) and asynchronous (255).
    """
    od.add(0x1005, 0, U32, COB_SYNC, name="COB-ID SYNC")
    od.add(ERROR_FIELD, 0, U8, 0, name="number of errors")  # pre-defined error field, newest at sub 1
    for sub in range(1, ERROR_FIELD_DEPTH + 1):
        od.add(ERROR_FIELD, sub, U32, 0, access=Access.RO, name=f"standard error field {sub}")
    hb = drive.canopen.heartbeat_ms if drive.canopen is not None else 0
    od.add(0x1017, 0, U16, hb, name="producer heartbeat time")
    drive = drive.bus_map  # a multi-axis drive: every axis's PDOs
    for direction, comm_base, map_base, cobs, pdos in (
        ("rpdo", 0x1400, 0x1600, RPDO_COB, drive.rpdo),
        ("tpdo", 0x1800, 0x1A00, TPDO_COB, drive.tpdo),
    ):
        by_number = {p.number: p for p in pdos}
        for n in range(1, max([4, *by_number]) + 1):
            comm, mapping = comm_base + n - 1, map_base + n - 1
            pdo = by_number.get(n)
            if n > 4:  # past the pre-defined connection set: the map's own COB-ID, else none
                if pdo is None or pdo.canopen is None:
                    continue
                cob = pdo.canopen.cob_id_for(node_id)
            else:
                cob = cobs[n - 1] + node_id if pdo is not None else INVALID | (cobs[n - 1] + node_id)
            od.add(comm, 1, U32, cob, name=f"{direction}{n} COB-ID")
            od.add(comm, 2, U8, 255 if pdo is None else 1, name=f"{direction}{n} transmission type")
            if direction == "tpdo":
                od.add(comm, 3, U16, 0, name="inhibit time")
                od.add(comm, 5, U16, 0, name="event timer")
            od.add(comm, 0, U8, 5 if direction == "tpdo" else 2, access=Access.RO)
            if not od.has(mapping, 0):
                od.add(mapping, 0, U8, 0, name="PDO mapping")
                for sub in range(1, 9):
                    od.add(mapping, sub, U32, 0)


def _fresh_od(drive: DriveMap, node_id: int) -> ObjectDictionary:
    # a multi-axis drive: every axis's objects at +0x800 per axis (sim_slaves.ethercat.axes)
    od = ObjectDictionary.from_drive_map(drive) if drive.axes == 1 else device_od(drive)
    add_communication_objects(od, drive, node_id)
    return od


class CanopenNode:
    """A CiA 301 device with a CiA 402 drive behind (when the map is a CiA 402 map)."""

    def __init__(self, drive: DriveMap, node_id: int, app: App | None = None) -> None:
        if not 1 <= node_id <= 127:
            raise ValueError(f"node id {node_id} out of range 1..127")
        self.drive = drive
        self.node_id = node_id
        self.od = _fresh_od(drive, node_id)
        self.app = app
        self.state = NmtState.BOOTUP
        self.sync_count = 0  # SYNCs since the node entered OPERATIONAL
        self._rpdos: dict[int, _PdoRuntime] = {}
        self._tpdos: list[_PdoRuntime] = []
        self._timed: list[_PdoRuntime] = []  # event-driven TPDOs with an event timer
        self._pending: dict[int, bytes] = {}  # RPDO COB-ID -> data, applied at the next SYNC
        self._pdo_dirty = True  # PDO objects changed: rebuild the runtime before the next PDO
        self._mapping_seen = -1
        self._seg: _Segmented | None = None
        # fault hooks
        self.drop_tpdos = 0
        self.heartbeat_silent = False
        self.bus_off = False
        self.received_rpdos = 0
        self.sent_tpdos = 0

    # -- NMT ------------------------------------------------------------------------------
    def boot(self) -> list[Frame]:
        """Power-on: INITIALISING -> boot-up message -> PRE-OPERATIONAL."""
        self.state = NmtState.PRE_OPERATIONAL
        self._seg = None
        self._pending.clear()
        self._pdo_dirty = True
        return [(COB_HEARTBEAT + self.node_id, b"\x00")]

    def nmt(self, command: int) -> list[Frame]:
        """NMT command (CiA 301): 1 start, 2 stop, 0x80 pre-operational, 0x81 reset node, 0x82 reset comm."""
        was_operational = self.state == NmtState.OPERATIONAL
        if command == 0x01:
            if not was_operational:
                self.sync_count = 0
            self.state = NmtState.OPERATIONAL
        elif command == 0x02:
            self.state = NmtState.STOPPED
        elif command == 0x80:
            self.state = NmtState.PRE_OPERATIONAL
        elif command in (0x81, 0x82):
            if was_operational:
                self._connection_lost()
            fresh = _fresh_od(self.drive, self.node_id)
            if command == 0x81:  # reset node: every object back to its power-on value
                self.od = fresh
                reset = getattr(self.app, "power_cycle", None)
                if callable(reset):
                    reset()
            else:  # reset communication: 0x1000-0x1FFF only
                for index in fresh.indices():
                    if index in COMM_AREA:
                        for sub in fresh.subindices(index):
                            self.od.entry(index, sub).value = fresh.entry(index, sub).value
            return self.boot()
        if was_operational and self.state != NmtState.OPERATIONAL:
            self._connection_lost()
        return []

    def _connection_lost(self) -> None:
        lost = getattr(self.app, "connection_lost", None)
        if callable(lost):
            lost()  # CiA 402: the drive stops itself when it leaves OPERATIONAL

    def heartbeat(self) -> Frame | None:
        if self.heartbeat_silent or self.bus_off:
            return None
        return (COB_HEARTBEAT + self.node_id, bytes([int(self.state)]))

    @property
    def heartbeat_ms(self) -> int:
        return int(self.od.get_value(0x1017, 0))

    def emergency(self, code: int, register: int = 0, data: bytes = b"") -> Frame:
        """An EMCY frame (0x80 + node id): u16 error code, u8 error register, 5 bytes manufacturer data."""
        self.od.set_value(0x1001, 0, register)
        if code:  # an error (0x0000 is "error reset"): into 0x1003, newest at sub 1, the oldest drops off
            od = self.od
            count = min(int(od.get_value(ERROR_FIELD, 0)) + 1, ERROR_FIELD_DEPTH)
            for sub in range(count, 1, -1):
                od.set_value(ERROR_FIELD, sub, od.get_value(ERROR_FIELD, sub - 1))
            info = int.from_bytes(data[:2].ljust(2, b"\0"), "little")  # manufacturer data -> additional info
            od.set_value(ERROR_FIELD, 1, (info << 16) | code)
            od.set_value(ERROR_FIELD, 0, count)
        return (COB_EMCY + self.node_id, struct.pack("<HB", code, register) + data[:5].ljust(5, b"\0"))

    # -- SDO server (CiA 301 7.2.4) -----------------------------------------------------------
    def sdo(self, req: bytes) -> Frame | None:
        """Answer one SDO request (0x600 + id) with a response (0x580 + id)."""
        if len(req) != 8 or self.state == NmtState.STOPPED:
            return None
        cmd = req[0]
        ccs = cmd >> 5
        index, sub = req[1] | req[2] << 8, req[3]
        try:
            if ccs == 1:
                out = self._download_initiate(cmd, index, sub, req)
            elif ccs == 0:
                out = self._download_segment(cmd, req)
            elif ccs == 2:
                out = self._upload_initiate(index, sub)
            elif ccs == 3:
                out = self._upload_segment(cmd)
            elif ccs == 4:  # abort from the client: drop the transfer, no answer
                self._seg = None
                return None
            else:
                raise SdoAbortError(ABORT_COMMAND, index=index, sub_index=sub)
        except SdoAbortError as exc:
            self._seg = None
            ai, asub = (exc.index, exc.sub_index) if exc.index else (index, sub)
            out = struct.pack("<BHBI", 0x80, ai, asub, exc.code)
        return (COB_TSDO + self.node_id, out)

    def _write(self, index: int, sub: int, data: bytes) -> None:
        if index in PDO_OBJECTS:
            if 0x1600 <= index < 0x1800 or 0x1A00 <= index < 0x1C00:
                comm = index - 0x200  # 0x16xx -> 0x14xx, 0x1Axx -> 0x18xx
                if self.od.has(comm, 1) and not int(self.od.get_value(comm, 1)) & INVALID:
                    raise SdoAbortError(
                        ABORT_STATE,
                        index=index,
                        sub_index=sub,
                        detail="PDO valid: set its COB-ID bit 31 first",
                    )
            elif sub == 1 and len(data) == 4 and self.od.has(index, 1):
                old = int(self.od.get_value(index, 1))
                new = int.from_bytes(data, "little")
                if not (old | new) & INVALID and (old ^ new) & CAN_ID_MASK:
                    raise SdoAbortError(
                        ABORT_VALUE_RANGE, index=index, sub_index=sub, detail="CAN-ID of a valid PDO"
                    )
            self.od.write(index, sub, data, state=_COMM[self.state])
            self._pdo_dirty = True
            return
        self.od.write(index, sub, data, state=_COMM[self.state])

    def _download_initiate(self, cmd: int, index: int, sub: int, req: bytes) -> bytes:
        self._seg = None
        if cmd & 0x02:  # expedited
            n = 4 - ((cmd >> 2) & 0x03) if cmd & 0x01 else 4
            self._write(index, sub, req[4 : 4 + n])
        else:
            self.od.entry(index, sub)  # abort now for a missing object
            size = struct.unpack_from("<I", req, 4)[0] if cmd & 0x01 else -1
            self._seg = _Segmented(index, sub, bytearray(), 0, size)
        return struct.pack("<BHBI", 0x60, index, sub, 0)

    def _download_segment(self, cmd: int, req: bytes) -> bytes:
        seg = self._seg
        if seg is None:
            raise SdoAbortError(ABORT_COMMAND, index=0, sub_index=0, detail="no download in progress")
        if cmd & 0x10 != seg.toggle:
            raise SdoAbortError(ABORT_TOGGLE, index=seg.index, sub_index=seg.sub)
        seg.data += req[1 : 8 - ((cmd >> 1) & 0x07)]
        if seg.size >= 0 and len(seg.data) > seg.size:
            raise SdoAbortError(
                ABORT_LENGTH, index=seg.index, sub_index=seg.sub, detail="more than indicated"
            )
        seg.toggle ^= 0x10
        if cmd & 0x01:  # last segment
            self._seg = None
            if seg.size >= 0 and len(seg.data) != seg.size:
                raise SdoAbortError(
                    ABORT_LENGTH, index=seg.index, sub_index=seg.sub, detail="less than indicated"
                )
            self._write(seg.index, seg.sub, bytes(seg.data))
        return bytes([0x20 | (cmd & 0x10)]) + bytes(7)

    def _upload_initiate(self, index: int, sub: int) -> bytes:
        self._seg = None
        data = self.od.read(index, sub)
        if 1 <= len(data) <= 4:  # expedited carries 1-4 bytes; 0 bytes: segmented, size 0, one empty segment
            return struct.pack("<BHB", 0x43 | (4 - len(data)) << 2, index, sub) + data.ljust(4, b"\0")
        self._seg = _Segmented(index, sub, bytearray(data), 0)
        return struct.pack("<BHBI", 0x41, index, sub, len(data))

    def _upload_segment(self, cmd: int) -> bytes:
        seg = self._seg
        if seg is None:
            raise SdoAbortError(ABORT_COMMAND, index=0, sub_index=0, detail="no upload in progress")
        if cmd & 0x10 != seg.toggle:
            raise SdoAbortError(ABORT_TOGGLE, index=seg.index, sub_index=seg.sub)
        chunk, seg.data = bytes(seg.data[:7]), seg.data[7:]
        last = not seg.data
        head = seg.toggle | (7 - len(chunk)) << 1 | (0x01 if last else 0)
        seg.toggle ^= 0x10
        if last:
            self._seg = None
        return bytes([head]) + chunk.ljust(7, b"\0")

    # -- PDOs -----------------------------------------------------------------------------
    def _refresh_pdos(self) -> None:
        od = self.od
        if not self._pdo_dirty and od.mapping_version == self._mapping_seen:
            return
        self._pdo_dirty = False
        self._mapping_seen = od.mapping_version
        self._rpdos, self._tpdos, self._timed = {}, [], []
        for n in range(1, 5):
            for comm, mapping, is_rx in ((0x13FF + n, 0x15FF + n, True), (0x17FF + n, 0x19FF + n, False)):
                cob = int(od.get_value(comm, 1))
                if cob & INVALID:
                    continue
                rt = _PdoRuntime(
                    n, cob & 0x7FF, int(od.get_value(comm, 2)), _Codec(od, od.pdo(mapping).channels)
                )
                if is_rx:
                    self._rpdos[rt.cob_id] = rt
                    continue
                rt.inhibit_s = int(od.get_value(comm, 3)) * 100e-6
                rt.event_s = int(od.get_value(comm, 5)) * 1e-3
                self._tpdos.append(rt)
                if rt.transmission_type >= 254 and rt.event_s > 0:
                    self._timed.append(rt)

    def rpdo_cob_ids(self) -> set[int]:
        self._refresh_pdos()
        return set(self._rpdos)

    def tpdo_sizes(self) -> dict[int, int]:
        """Valid TPDOs as they are mapped now: COB-ID -> data bytes."""
        self._refresh_pdos()
        return {rt.cob_id: rt.codec.size for rt in self._tpdos}

    def rpdo(self, cob_id: int, data: bytes) -> None:
        """An RPDO arrived (master outputs); synchronous ones take effect at the next SYNC."""
        if self.state != NmtState.OPERATIONAL or self.bus_off:
            return
        self._refresh_pdos()
        rt = self._rpdos.get(cob_id)
        if rt is None:
            return
        self.received_rpdos += 1
        if rt.transmission_type <= 240:
            self._pending[cob_id] = data
        else:
            rt.codec.unpack(data)

    def sync(self, dt_s: float, now: float = 0.0) -> list[Frame]:
        """A SYNC: apply synchronous RPDOs, step the drive, send due TPDOs (in OPERATIONAL).

        ``now``: the caller's clock in seconds (inhibit time and event timer of event-driven TPDOs).
        """
        if not self.sync_inputs():
            return []
        if self.app is not None:
            self.app.step(self.od, dt_s)
        return self.sync_outputs(now)

    def sync_inputs(self) -> bool:
        """First half of :meth:`sync`: apply the synchronous RPDOs; False when the node does not take part."""
        if self.bus_off or self.state != NmtState.OPERATIONAL:
            return False
        self._refresh_pdos()
        self.sync_count += 1
        if self._pending:
            for cob, data in self._pending.items():
                rt = self._rpdos.get(cob)
                if rt is not None:
                    rt.codec.unpack(data)
            self._pending.clear()
        return True

    def sync_outputs(self, now: float) -> list[Frame]:
        """Second half of :meth:`sync`, after the drive stepped: the TPDOs due on this SYNC."""
        out: list[Frame] = []
        for rt in self._tpdos:
            t = rt.transmission_type
            if 1 <= t <= 240:
                if self.sync_count % t:
                    continue
                data = rt.codec.pack()
            elif t == 0 or t >= 254:
                data = rt.codec.pack()
                if data == rt.last or (t >= 254 and now - rt.last_t < rt.inhibit_s):
                    continue
            else:  # 241-251 reserved, 252/253 RTR only: never on SYNC
                continue
            self._send_tpdo(rt, data, now, out)
        return out

    def timers(self, now: float) -> list[Frame]:
        """Event-driven TPDOs (254/255) whose event timer expired at ``now`` (s)."""
        if not self._timed or self.bus_off or self.state != NmtState.OPERATIONAL:
            return []
        out: list[Frame] = []
        for rt in self._timed:
            if now - rt.last_t >= rt.event_s:
                self._send_tpdo(rt, rt.codec.pack(), now, out)
        return out

    def _send_tpdo(self, rt: _PdoRuntime, data: bytes, now: float, out: list[Frame]) -> None:
        rt.last, rt.last_t = data, now
        if self.drop_tpdos:
            self.drop_tpdos -= 1
            return
        out.append((rt.cob_id, data))
        self.sent_tpdos += 1
