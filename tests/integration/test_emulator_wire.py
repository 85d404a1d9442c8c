"""An independent master of our own against the wire emulator: raw AF_PACKET frames over a veth pair.

Not SOEM: :class:`~fieldbus.wire.framemaster.FrameMaster` (the sim
backend's frame-level master) behind a raw socket on the master's end, whose
source MAC has the locally administered bit (0x02 in the first byte) set, as
any master may choose. A real ESC processes every EtherCAT frame reaching
port 0 whatever its MAC addresses, so the emulator must too. The other tests
send what SOEM never sends: frames padded or with bytes after the last
datagram, several frames in flight, datagrams in any order, the same frame
twice, an 802.1Q VLAN tag, a unicast destination MAC.

The raw-socket transport lives here, not in ``fieldbus.backends``: it is test
equipment (one frame at a time, blocking, no cycle timing) that no backend
uses. Receive waits are bounded (:data:`RECV_TIMEOUT_S` per try);
FrameMaster retries a lost acyclic frame as a master would, a lost cycle
frame is counted, never resent.
"""

from __future__ import annotations

import itertools
import math
import select
import socket
import struct
import time
import warnings
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass

import pytest

from fieldbus.commands.demo import DEMO_MAP
from fieldbus.core.al import AL_INIT, AL_OP, AL_PREOP, AL_SAFEOP
from fieldbus.core.ecat import BROADCAST_MAC, Command, Datagram, build_master_frame, decode_frame
from fieldbus.core.pdo.load import load_drive_map
from fieldbus.wire.framemaster import STATION_BASE, FrameMaster, Mapping, SlaveInfo, layout_image
from fieldbus.wire.packet_socket import ETH_P_ALL, bound_packet_socket
from sim_slaves.ethercat.veth import Emulator

pytestmark = [pytest.mark.veth, pytest.mark.timeout(120)]

N = 4
MASTER_MAC = bytes.fromhex("02005e000a01")  # unicast, locally administered (0x02 in the first byte)
RECV_TIMEOUT_S = 0.1  # per try (FrameMaster) or cycle: replies take 0.05-1 ms, on a loaded machine tens [s]
REPLY_WAIT_S = 1.0  # for a reply that must come, where a master would not resend [s]
QUIET_S = 0.05  # how long to listen for frames that must not come [s]
CYCLES = 2000
VLAN_TCI = 5 << 13 | 7  # priority 5, VLAN 7
ETH_P_8021Q = 0x8100
SOL_PACKET = 263
PACKET_AUXDATA = 8
PACKET_OUTGOING = 4
TP_STATUS_VLAN_VALID = 0x10
AUXDATA = struct.Struct("<IIIHHHH")  # tpacket_auxdata: status, len, snaplen, mac, net, vlan_tci, vlan_tpid
OUT = struct.Struct("<HihB")  # demo_joint outputs: controlword, target position, target torque, mode
IN = struct.Struct("<HiihB")  # inputs: statusword, position, velocity, torque, mode display
CSP = 8


def _untagged(frame: bytes) -> bytes:
    """``frame`` without its 802.1Q tag (as the kernel hands a tagged frame to a packet socket)."""
    return frame[:12] + frame[16:] if frame[12:14] == b"\x81\x00" else frame


def _tagged(frame: bytes, tci: int) -> bytes:
    """``frame`` with an 802.1Q tag (TPID 0x8100, ``tci``) after the MAC addresses."""
    return frame[:12] + struct.pack(">HH", ETH_P_8021Q, tci) + frame[12:]


class RawPort:
    """The master's end of the veth pair: EtherCAT frames out, frames in with their VLAN tag.

    Called with a frame, it is a :data:`~fieldbus.wire.framemaster.Transport`:
    the source MAC replaced by ``src``, a VLAN tag ``vlan`` (TCI) inserted when
    given, and the reply is the next arriving frame of the same length whose
    first datagram has the request's command and index (late replies to
    earlier frames are passed over), None after ``timeout_s`` [s]. A frame whose
    source MAC is not this port's (the locally administered bit aside, which an
    ESC sets) is no reply to it: kept in :attr:`strangers`, never returned.
    """

    def __init__(
        self,
        iface: str,
        *,
        src: bytes = MASTER_MAC,
        vlan: int | None = None,
        timeout_s: float = RECV_TIMEOUT_S,
    ) -> None:
        self.src, self.vlan, self.timeout_s = src, vlan, timeout_s
        self.iface = iface
        self.reply_tags: list[int | None] = []  # VLAN TCI of every reply the transport returned
        self.strangers: list[str] = []  # frames from another sender that reached this port (see port())
        # every protocol: only such a socket sees a VLAN tag; made without one, then bound (packet_socket)
        self.sock = bound_packet_socket(iface, ETH_P_ALL)
        self.sock.setsockopt(SOL_PACKET, PACKET_AUXDATA, 1)
        self.sock.setblocking(False)
        self.poller = select.poll()
        self.poller.register(self.sock.fileno(), select.POLLIN)

    def close(self) -> None:
        self.sock.close()

    def frame(self, dgs: Sequence[Datagram], *, dst: bytes = BROADCAST_MAC) -> bytes:
        """A master frame of ``dgs`` from this port (its source MAC, its VLAN tag if any)."""
        frame = build_master_frame(list(dgs), src=self.src, dst=dst)
        return frame if self.vlan is None else _tagged(frame, self.vlan)

    def send(self, frame: bytes) -> None:
        self.sock.send(frame)

    def recv(self, timeout_s: float) -> tuple[bytes, int | None] | None:
        """The next EtherCAT frame arriving (untagged) and the TCI of its VLAN tag; None after ``timeout_s``."""
        deadline = time.monotonic() + timeout_s
        while True:
            try:
                data, anc, _flags, addr = self.sock.recvmsg(2048, socket.CMSG_SPACE(AUXDATA.size))
            except BlockingIOError:
                left = deadline - time.monotonic()
                if left <= 0:
                    return None
                self.poller.poll(math.ceil(left * 1000))
                continue
            if addr[2] == PACKET_OUTGOING or len(data) < 16 or data[12:14] != b"\x88\xa4":
                continue
            if data[6] | 0x02 != self.src[0] | 0x02 or data[7:12] != self.src[1:]:
                self.strangers.append(_stranger(data))
                continue
            tci = None
            for level, kind, aux in anc:
                if level == SOL_PACKET and kind == PACKET_AUXDATA:
                    status, *_, vlan_tci, _tpid = AUXDATA.unpack_from(aux)
                    tci = vlan_tci if status & TP_STATUS_VLAN_VALID else None
            return data, tci

    def reply_to(self, frame: bytes, timeout_s: float) -> tuple[bytes, int | None] | None:
        """The reply to ``frame`` sent earlier (untagged) and its VLAN TCI; None after ``timeout_s`` [s]."""
        want = _untagged(frame)
        deadline = time.monotonic() + timeout_s
        while (got := self.recv(deadline - time.monotonic())) is not None:
            data = got[0]
            if len(data) == len(want) and data[16:18] == want[16:18]:
                return got
        return None

    def exchange(self, frame: bytes, timeout_s: float = REPLY_WAIT_S) -> tuple[bytes, int | None] | None:
        """Send ``frame`` and wait at most ``timeout_s`` [s] for its reply (see :meth:`reply_to`)."""
        self.send(frame)
        return self.reply_to(frame, timeout_s)

    def __call__(self, frame: bytes) -> bytes | None:
        frame = frame[:6] + self.src + frame[12:]
        got = self.exchange(frame if self.vlan is None else _tagged(frame, self.vlan), self.timeout_s)
        if got is None:
            return None
        self.reply_tags.append(got[1])
        return got[0]


def _stranger(frame: bytes) -> str:
    """A frame from another sender, in a line: its source MAC and first datagram."""
    try:
        d = decode_frame(frame).datagrams[0]
        first = f"{d.cmd.name} index {d.idx} WKC {d.wkc}"
    except Exception as exc:  # a stranger's frame need not decode
        first = f"undecodable ({exc})"
    return f"from {frame[6:12].hex(':')}: {first}"


def _datagrams(reply: tuple[bytes, int | None] | None) -> tuple[Datagram, ...]:
    assert reply is not None, "no reply"
    return decode_frame(reply[0]).datagrams


@pytest.fixture
def port(ethercat_emulator: Callable[..., Emulator]) -> Iterator[Callable[..., tuple[Emulator, RawPort]]]:
    """``port(vlan=None)``: a fresh emulated segment of N demo joints and a raw port on its master end."""
    ports: list[RawPort] = []

    def start(*, vlan: int | None = None) -> tuple[Emulator, RawPort]:
        emu = ethercat_emulator([DEMO_MAP], count=N)
        ports.append(RawPort(emu.iface, vlan=vlan))
        return emu, ports[-1]

    yield start
    for p in ports:
        p.close()
        if p.strangers:  # not this test's subject, but something sends on a veth pair not its own: say so
            warnings.warn(
                f"{len(p.strangers)} frame(s) from another sender reached {p.iface}: {p.strangers[:3]}",
                stacklevel=1,
            )


# -- bring-up and the cycle, as an independent master does them --


@dataclass
class Bus:
    """Slaves in OP: the logical image (outputs from 0, then inputs) and the LRW's expected WKC."""

    port: RawPort
    master: FrameMaster
    infos: list[SlaveInfo]
    maps: list[Mapping]
    out_bytes: int
    in_bytes: int

    @property
    def expected_wkc(self) -> int:
        return sum((2 if m.out_size else 0) + (1 if m.in_size else 0) for m in self.maps)

    @property
    def safe_op_wkc(self) -> int:
        """In SAFE-OP the output SyncManagers take no writes: only the reads count."""
        return sum(1 if m.in_size else 0 for m in self.maps)

    def lrw_datagram(self, outputs: bytes, idx: int) -> Datagram:
        return Datagram(Command.LRW, idx, 0, outputs + bytes(self.in_bytes))

    def cycle(self, outputs: bytes, idx: int) -> tuple[bytes, int] | None:
        """One LRW over the image: (inputs, WKC), None when the frame was lost."""
        got = self.port.exchange(self.port.frame([self.lrw_datagram(outputs, idx)]), self.port.timeout_s)
        if got is None:
            return None
        (d,) = decode_frame(got[0]).datagrams
        return d.data[self.out_bytes :], d.wkc


def _pdo_bytes(master: FrameMaster, info: SlaveInfo, assign: int) -> int:
    """Bytes of the PDOs assigned in ``assign`` (0x1C12 outputs / 0x1C13 inputs), read over CoE."""
    bits = 0
    for k in range(1, master.sdo_upload(info, assign, 0)[0] + 1):
        pdo = struct.unpack("<H", master.sdo_upload(info, assign, k))[0]
        for e in range(1, master.sdo_upload(info, pdo, 0)[0] + 1):
            bits += struct.unpack("<I", master.sdo_upload(info, pdo, e))[0] & 0xFF
    return (bits + 7) // 8


def _go(master: FrameMaster, stations: list[int], state: int) -> None:
    for st in stations:
        master.request_state(st, state)
    missing = master.wait_state(stations, state)
    assert not missing, {f"0x{st:04X}": got for st, got in missing.items()}


def _controlword(status: int) -> int:
    """CiA 402 enable sequence: fault reset, shutdown, switch on, enable operation."""
    if status & 0x08:
        return 0x80
    if status & 0x4F == 0x40:
        return 0x06
    if status & 0x6F == 0x21:
        return 0x07
    return 0x0F


def _outputs(inputs: bytes, n: int) -> bytes:
    """Every drive: the next controlword of the enable sequence, CSP, target = actual position."""
    out = b""
    for i in range(n):
        status, pos, _vel, _torque, _mode = IN.unpack_from(inputs, i * IN.size)
        out += OUT.pack(_controlword(status), pos, 0, CSP)
    return out


def bring_up(port: RawPort, n: int = N) -> Bus:
    """Scan, SII, mailbox, PRE-OP, sizes from the CoE PDO assignment, SM/FMMU, SAFE-OP, OP."""
    drive = load_drive_map(DEMO_MAP)
    master = FrameMaster(port)
    assert master.scan() == n
    infos = master.identify(n)
    for info in infos:
        assert (info.vendor_id, info.product_id, info.name) == (drive.vendor_id, drive.product_id, drive.name)
        master.setup_mailbox(info)
    stations = [info.station for info in infos]
    _go(master, stations, AL_PREOP)
    sizes = [(_pdo_bytes(master, info, 0x1C12), _pdo_bytes(master, info, 0x1C13)) for info in infos]
    expected = (sum(p.bits for p in drive.rpdo) // 8, sum(p.bits for p in drive.tpdo) // 8)
    assert sizes == [expected] * n == [(OUT.size, IN.size)] * n
    maps, out_bytes, in_bytes = layout_image(sizes)
    for info, m in zip(infos, maps, strict=True):
        master.map_process_data(info, m)
        # the process-data watchdog (0x0420, in units of the default 100 us divider) at its longest, 6.5 s,
        # as a master may configure it: these tests judge the wire, and a loaded machine that stalls this
        # process or the emulator past the default 100 ms would take the slaves to SAFE-OP mid-test
        assert master.fpwr(info.station, 0x0420, struct.pack("<H", 0xFFFF)) == 1
    _go(master, stations, AL_SAFEOP)
    for st, (o, i) in zip(stations, sizes, strict=True):  # what the ESCs took as SM2/SM3 lengths
        assert master.fprd(st, 0x0812, 2) == (struct.pack("<H", o), 1)
        assert master.fprd(st, 0x081A, 2) == (struct.pack("<H", i), 1)
    bus = Bus(port, master, infos, maps, out_bytes, in_bytes)
    inputs = bytes(in_bytes)
    for k in range(3):  # valid outputs before OP (SAFE-OP: inputs only count)
        got = bus.cycle(_outputs(inputs, n), k)
        assert got is not None and got[1] == bus.safe_op_wkc
        inputs = got[0]
    for st in stations:
        master.request_state(st, AL_OP)
    for k in range(200):
        got = bus.cycle(_outputs(inputs, n), k & 0x7F)
        if got is not None:
            inputs = got[0]
        if not master.wait_state(stations, AL_OP, 1):
            break
    else:
        _go(master, stations, AL_OP)  # fails with the states
    return bus


def run_cycles(bus: Bus, cycles: int) -> tuple[int, int, bytes]:
    """``cycles`` LRWs enabling the drives: (wrong WKCs, lost frames, last inputs)."""
    wrong = lost = 0
    inputs = bytes(bus.in_bytes)
    n = len(bus.maps)
    for k in range(cycles):
        got = bus.cycle(_outputs(inputs, n), 0x80 | k & 0x7F)
        if got is None:
            lost += 1
            continue
        inputs, wkc = got
        wrong += wkc != bus.expected_wkc
    return wrong, lost, inputs


def _operation_enabled(inputs: bytes, n: int) -> list[bool]:
    return [IN.unpack_from(inputs, i * IN.size)[0] & 0x6F == 0x27 for i in range(n)]


# -- tests --


def test_master_with_locally_administered_mac_brings_slaves_to_op(
    port: Callable[..., tuple[Emulator, RawPort]],
) -> None:
    """The runner used to skip frames whose source MAC had the locally administered bit: no slave found."""
    emu, p = port()
    assert p.src[0] & 0x02
    bus = bring_up(p)
    assert (bus.out_bytes, bus.in_bytes) == (N * OUT.size, N * IN.size)
    assert bus.expected_wkc == 3 * N
    wrong, lost, inputs = run_cycles(bus, CYCLES)
    assert wrong == 0, f"{wrong} of {CYCLES} cycles with a WKC other than {bus.expected_wkc}"
    assert lost <= CYCLES // 200, f"{lost} of {CYCLES} cycle frames unanswered within {RECV_TIMEOUT_S} s"
    assert all(_operation_enabled(inputs, N)), inputs.hex()
    status = emu.command(cmd="status")
    assert status["states"] == [AL_OP] * N and status["al_status_codes"] == [0] * N


@pytest.mark.parametrize(
    "trailer",
    [
        pytest.param(bytes(60 - 30), id="padded-to-60"),
        pytest.param(bytes(range(1, 101)), id="100-trailing-bytes"),
        pytest.param(b"\x01\x01\x05\x10\x00\x00" + bytes(10), id="16-byte-trailer"),
    ],
)
def test_bytes_after_the_last_datagram_are_returned_unchanged(
    port: Callable[..., tuple[Emulator, RawPort]], trailer: bytes
) -> None:
    """EtherCAT length shorter than the Ethernet payload: the datagrams processed, the rest passes through."""
    _emu, p = port()
    frame = p.frame([Datagram.physical(Command.BRD, 0, 0x0130, bytes(2), idx=0x31)])
    assert len(frame) == 30
    got = p.exchange(frame + trailer)
    assert got is not None
    reply, _ = got
    assert len(reply) == len(frame) + len(trailer)
    assert reply[30:] == trailer
    assert reply[14:16] == frame[14:16]  # EtherCAT header (length 14) as sent
    (d,) = decode_frame(reply).datagrams
    assert (d.idx, d.wkc, d.data, d.adp) == (0x31, N, struct.pack("<H", AL_INIT), N)
    # two datagrams, padded: both answered, padding untouched
    two = p.frame(
        [
            Datagram.physical(Command.BRD, 0, 0x0000, bytes(1), idx=0x32),
            Datagram.physical(Command.APRD, 0, 0x0130, bytes(2), idx=0x33),
        ]
    )
    got = p.exchange(two.ljust(60, b"\xee"))
    assert got is not None and len(got[0]) == 60 and got[0][len(two) :] == b"\xee" * (60 - len(two))
    assert [d.wkc for d in decode_frame(got[0]).datagrams] == [N, 1]


def test_several_frames_in_flight_are_all_answered_in_order(
    port: Callable[..., tuple[Emulator, RawPort]],
) -> None:
    """Three frames (station addresses, then a count) sent before any reply is read; then a burst of 16."""
    emu, p = port()
    before = emu.command(cmd="status")["frames"]
    frames = [
        p.frame([Datagram.physical(Command.APWR, 0, 0x0010, struct.pack("<H", 0x2001), idx=0x61)]),
        p.frame([Datagram.physical(Command.APWR, -1 & 0xFFFF, 0x0010, struct.pack("<H", 0x2002), idx=0x62)]),
        p.frame([Datagram.physical(Command.BRD, 0, 0x0000, bytes(2), idx=0x63)]),
    ]
    for f in frames:
        p.send(f)
    replies = [p.recv(REPLY_WAIT_S) for _ in frames]
    dgs = [_datagrams(r)[0] for r in replies]
    assert [(d.idx, d.wkc) for d in dgs] == [(0x61, 1), (0x62, 1), (0x63, N)], p.strangers
    assert p.recv(QUIET_S) is None  # one reply per frame: nothing comes back twice
    (d,) = _datagrams(p.exchange(p.frame([Datagram.physical(Command.FPRD, 0x2002, 0x0010, bytes(2))])))
    assert (d.wkc, d.data) == (1, struct.pack("<H", 0x2002))

    burst = [p.frame([Datagram.physical(Command.BRD, 0, 0x0130, bytes(2), idx=0x70 + k)]) for k in range(16)]
    for f in burst:
        p.send(f)
    got = [_datagrams(p.recv(REPLY_WAIT_S))[0] for _ in burst]
    assert [(d.idx, d.wkc) for d in got] == [(0x70 + k, N) for k in range(16)]
    assert p.recv(QUIET_S) is None
    assert emu.command(cmd="status")["frames"] - before == len(frames) + 1 + len(burst)


def test_a_frame_from_another_sender_is_no_reply(port: Callable[..., tuple[Emulator, RawPort]]) -> None:
    """A frame sent on the emulator's end by another socket reaches the master's end unprocessed (the
    emulator ignores what is sent on its own interface): the port keeps it as a stranger, names its sender
    and first datagram, and still takes the emulator's reply to its own frame."""
    emu, p = port()
    other = bound_packet_socket(emu.peer, ETH_P_ALL)
    try:
        stray = build_master_frame(
            [Datagram.physical(Command.BWR, 0, 0x0120, bytes(2), idx=2)], src=bytes(6 * [1])
        )
        other.send(stray)
        (d,) = _datagrams(
            p.exchange(p.frame([Datagram.physical(Command.BRD, 0, 0x0000, bytes(2), idx=0x31)]))
        )
        assert (d.idx, d.wkc) == (0x31, N)
        assert p.recv(QUIET_S) is None
    finally:
        other.close()
    assert p.strangers == ["from 01:01:01:01:01:01: BWR index 2 WKC 0"]
    p.strangers.clear()  # seen and judged here: no warning for it


def test_datagrams_in_any_order_within_a_frame(port: Callable[..., tuple[Emulator, RawPort]]) -> None:
    """A NOP, an FPRD, a BRD and an APRD around the cycle's LRW, in all 120 orders: every one answered."""
    _emu, p = port()
    bus = bring_up(p)
    first = bus.cycle(_outputs(bytes(bus.in_bytes), N), 1)
    assert first is not None
    outputs = _outputs(first[0], N)
    second = STATION_BASE + 1
    parts = {
        "NOP": (Datagram(Command.NOP, 0, 0, b"\x5a\xa5"), (0, b"\x5a\xa5")),
        "FPRD": (Datagram.physical(Command.FPRD, second, 0x0130, bytes(2)), (1, struct.pack("<H", AL_OP))),
        "BRD": (Datagram.physical(Command.BRD, 0, 0x0130, bytes(2)), (N, struct.pack("<H", AL_OP))),
        "APRD": (
            Datagram.physical(Command.APRD, -3 & 0xFFFF, 0x0010, bytes(2)),
            (1, struct.pack("<H", 0x1004)),
        ),
        "LRW": (bus.lrw_datagram(outputs, 0), (bus.expected_wkc, None)),
    }
    for k, order in enumerate(itertools.permutations(parts)):
        dgs = [Datagram(parts[name][0].cmd, k, parts[name][0].address, parts[name][0].data) for name in order]
        got = _datagrams(p.exchange(p.frame(dgs)))
        assert [d.cmd.name for d in got] == list(order)
        for name, d in zip(order, got, strict=True):
            wkc, data = parts[name][1]
            assert d.wkc == wkc, (order, name, d)
            if data is not None:
                assert d.data == data, (order, name, d)
            else:  # the inputs filled in, the outputs passed on unchanged
                assert d.data[: bus.out_bytes] == outputs, (order, name)
                assert d.data[bus.out_bytes :] != bytes(bus.in_bytes), (order, name)


def test_a_repeated_frame_is_processed_again(port: Callable[..., tuple[Emulator, RawPort]]) -> None:
    """Same index resent (a master's retry): the ESCs keep no history, each copy is processed and answered."""
    emu, p = port()
    bus = bring_up(p)
    outputs = _outputs(bytes(bus.in_bytes), N)
    before = emu.command(cmd="status")["frames"]
    lrw = p.frame([bus.lrw_datagram(outputs, 0x42)])
    fprd = p.frame([Datagram.physical(Command.FPRD, STATION_BASE, 0x0130, bytes(6), idx=0x43)])
    request_op = p.frame(
        [Datagram.physical(Command.FPWR, STATION_BASE, 0x0120, struct.pack("<H", AL_OP), idx=0x44)]
    )
    for f in (lrw, lrw, fprd, fprd, request_op, request_op):
        p.send(f)
    got = [_datagrams(p.recv(REPLY_WAIT_S))[0] for _ in range(6)]
    assert [(d.idx, d.wkc) for d in got] == [
        (0x42, 12),
        (0x42, 12),
        (0x43, 1),
        (0x43, 1),
        (0x44, 1),
        (0x44, 1),
    ]
    assert got[2].data == got[3].data == struct.pack("<HHH", AL_OP, 0, 0)
    assert p.recv(QUIET_S) is None
    assert emu.command(cmd="status")["frames"] - before == 6
    assert emu.command(cmd="status")["states"] == [AL_OP] * N


def test_vlan_tagged_frames_are_processed_and_keep_their_tag(
    port: Callable[..., tuple[Emulator, RawPort]],
) -> None:
    """ESCs process 802.1Q-tagged EtherCAT frames, ignore the tag's contents and return it unchanged."""
    _emu, p = port(vlan=VLAN_TCI)
    frame = p.frame([Datagram.physical(Command.BRD, 0, 0x0000, bytes(2), idx=0x21)])
    assert frame[12:18] == struct.pack(">HH", ETH_P_8021Q, VLAN_TCI) + b"\x88\xa4"
    got = p.exchange(frame)
    assert got is not None
    reply, tci = got
    assert tci == VLAN_TCI, "the reply lost its VLAN tag"
    assert len(reply) + 4 == len(frame)  # the kernel took the tag out of the data
    assert reply[6] == MASTER_MAC[0] and reply[7:12] == MASTER_MAC[1:]
    assert _datagrams(got)[0].wkc == N
    bus = bring_up(p)  # the whole bring-up and the cycle tagged
    wrong, lost, inputs = run_cycles(bus, 200)
    assert wrong == 0 and lost <= 2, (wrong, lost)
    assert all(_operation_enabled(inputs, N))
    assert p.reply_tags and set(p.reply_tags) == {VLAN_TCI}


def test_any_destination_mac_is_processed(port: Callable[..., tuple[Emulator, RawPort]]) -> None:
    """ESCs do not evaluate MAC addresses: unicast to some other station is answered like a broadcast."""
    _emu, p = port()
    for dst in (bytes.fromhex("02aabbccddee"), bytes.fromhex("001122334455"), BROADCAST_MAC):
        frame = p.frame([Datagram.physical(Command.BRD, 0, 0x0130, bytes(2), idx=0x11)], dst=dst)
        got = p.exchange(frame)
        assert got is not None, dst.hex()
        assert got[0][:6] == dst
        assert _datagrams(got)[0].wkc == N
