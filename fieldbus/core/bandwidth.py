"""Bus bandwidth: wire time per cycle, bus load and max cycle rate (pure: no I/O, no clock).

Three bus models, each a function over small frozen dataclasses:

- classic CAN and CAN FD (:func:`can_frame_bits`, :func:`can_frame_time_us`,
  :func:`can_cycle`), including worst-case bit stuffing and the CAN
  schedulability analysis of Davis, Burns, Bril and Lukkien (2007);
- EtherCAT (:func:`ethercat_frames`, :func:`ethercat_cycle`) from the frame
  layout, with per-slave forwarding delay and cable propagation.

Units are in the names: ``*_bits`` bit times, ``*_us`` microseconds,
``*_bytes`` bytes, ``*_hz`` per second. Directions are named from the
master's side: *outputs* (RxPDO, master -> drive) and *inputs* (TxPDO,
drive -> master). Every assumption and its source is in ``docs/bandwidth.md``.

:func:`bus_bandwidth` and :func:`network_bandwidth` adapt a loaded network
(any object with the attributes of :class:`BusLike`) to these models.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from typing import Any, Literal, Protocol

from fieldbus.core.canfamily import FrameTime, families
from fieldbus.core.pdo.model import CanopenConfig, DriveMap, Pdo
from fieldbus.core.rawcan import RawCanConfig
from fieldbus.errors import PdoMapError

JsonScalar = int | float | str | bool | None | tuple[int, ...]

# --------------------------------------------------------------------------- CAN

#: Bits of a classic CAN frame before the data field that are subject to stuffing
#: plus the 15-bit CRC: SOF 1, ID 11, RTR 1, IDE 1, r0 1, DLC 4, CRC 15 (standard);
#: the extended format adds SRR, IDE... : 54 (Davis et al. 2007, "g").
CAN_STUFFED_OVERHEAD_BITS = {False: 34, True: 54}
#: CRC delimiter 1, ACK slot 1, ACK delimiter 1, EOF 7 and the 3-bit interframe space.
CAN_TAIL_BITS = 13
CAN_IFS_BITS = 3
#: Classic CAN and CAN FD data lengths (ISO 11898-1:2015): FD rounds up to the next.
CAN_FD_LENGTHS = (0, 1, 2, 3, 4, 5, 6, 7, 8, 12, 16, 20, 24, 32, 48, 64)
#: CAN FD header, SOF to DLC: SOF, ID 11, RRS, IDE, FDF, res, BRS, ESI, DLC 4 (base);
#: the extended format adds SRR and the 18-bit ID extension.
CAN_FD_HEADER_BITS = {False: 22, True: 41}
#: The part of that header sent at the nominal (arbitration) rate: SOF .. BRS.
CAN_FD_ARBITRATION_BITS = {False: 17, True: 36}
#: CRC field: 4-bit stuff count (3-bit Gray code + parity) + CRC-17 (<= 16 bytes) or CRC-21.
CAN_FD_STUFF_COUNT_BITS = 4


def can_fd_length(data_bytes: int) -> int:
    """Bytes actually sent for ``data_bytes`` in a CAN FD frame (DLC rounding up to 12..64)."""
    for n in CAN_FD_LENGTHS:
        if n >= data_bytes:
            return n
    raise ValueError(f"CAN FD carries at most 64 data bytes, not {data_bytes}")


def _check_classic(data_bytes: int) -> None:
    if not 0 <= data_bytes <= 8:
        raise ValueError(f"classic CAN carries 0..8 data bytes, not {data_bytes}")


@dataclass(frozen=True)
class CanBits:
    """Length of one CAN frame in bit times, interframe space (3 bits) included.

    ``nominal_rate_bits`` are sent at the arbitration bit rate, ``data_rate_bits``
    at the data bit rate (CAN FD with BRS; 0 otherwise).
    """

    nominal_rate_bits: int
    data_rate_bits: int = 0

    @property
    def total(self) -> int:
        return self.nominal_rate_bits + self.data_rate_bits


def can_frame_split(
    data_bytes: int,
    *,
    extended: bool = False,
    fd: bool = False,
    brs: bool = False,
    worst_case: bool = True,
) -> CanBits:
    """Bit times of one data frame, split by bit rate; 3-bit interframe space included.

    Classic CAN (Davis et al. 2007, eq. 1): ``g + 8s + 13 + floor((g + 8s - 1)/4)``
    with ``g`` = 34 (11-bit ID) or 54 (29-bit ID); the stuffing term only when
    ``worst_case``. CAN FD (ISO 11898-1:2015; Linux ``include/linux/can/length.h``):
    header + rounded data + stuff count and CRC-17/21 + fixed stuff bits (one per
    4 bits of that field, always present) + 13 tail bits; dynamic stuff bits
    (``floor((header + data - 1)/4)``, SOF through data) only when ``worst_case``.
    With ``brs`` the part from after BRS to the CRC field is at the data rate.
    """
    if not fd:
        _check_classic(data_bytes)
        g = CAN_STUFFED_OVERHEAD_BITS[extended]
        stuffed = g + 8 * data_bytes
        stuff = (stuffed - 1) // 4 if worst_case else 0
        return CanBits(stuffed + CAN_TAIL_BITS + stuff)
    n = can_fd_length(data_bytes)
    header = CAN_FD_HEADER_BITS[extended]
    crc_field = CAN_FD_STUFF_COUNT_BITS + (17 if n <= 16 else 21)
    fixed_stuff = math.ceil(crc_field / 4)
    dyn_region = header + 8 * n
    dyn_stuff = (dyn_region - 1) // 4 if worst_case else 0
    total = dyn_region + crc_field + fixed_stuff + CAN_TAIL_BITS + dyn_stuff
    if not brs:
        return CanBits(total)
    arb = CAN_FD_ARBITRATION_BITS[extended]
    arb_stuff = (arb - 1) // 4 if worst_case else 0  # stuff bits falling in SOF..BRS
    nominal = arb + arb_stuff + CAN_TAIL_BITS
    return CanBits(nominal, total - nominal)


def can_frame_bits(
    data_bytes: int, *, extended: bool = False, fd: bool = False, worst_case: bool = True
) -> int:
    """Bit times of one CAN data frame on the wire, 3-bit interframe space included.

    Examples (classic, standard ID, 8 bytes): 111 nominal, 135 worst case
    (Davis et al. 2007). See :func:`can_frame_split` for the formulas.
    """
    return can_frame_split(data_bytes, extended=extended, fd=fd, worst_case=worst_case).total


def can_frame_time_us(
    data_bytes: int,
    *,
    bitrate: int,
    data_bitrate: int | None = None,
    extended: bool = False,
    fd: bool = False,
    worst_case: bool = True,
) -> float:
    """Microseconds one frame occupies the bus (interframe space included).

    ``bitrate`` is the nominal (arbitration) rate in bit/s; for CAN FD with bit
    rate switching pass ``data_bitrate``: the data phase is then timed at that rate.
    """
    brs = fd and data_bitrate is not None and data_bitrate != bitrate
    b = can_frame_split(data_bytes, extended=extended, fd=fd, brs=brs, worst_case=worst_case)
    t = b.nominal_rate_bits * 1e6 / bitrate
    if b.data_rate_bits:
        assert data_bitrate is not None
        t += b.data_rate_bits * 1e6 / data_bitrate
    return t


@dataclass(frozen=True)
class CanFrame:
    """One frame on a CAN bus.

    ``period_us`` None: sent once every cycle (SYNC, PDOs). Otherwise a
    background frame (heartbeat, EMCY budget) with that minimum inter-arrival
    time, counted as load and as interference, not in the per-cycle figures.
    ``frame_bits`` overrides the computed length (textbook models, e.g. "130 bits").
    ``after``: the label of the frame this one answers (a raw-CAN motor's reply follows its
    command): the timeline never puts it earlier, whatever its priority.
    """

    can_id: int
    data_bytes: int
    label: str = ""
    extended: bool = False
    fd: bool = False
    period_us: float | None = None
    frame_bits: int | None = None
    after: str | None = None

    @property
    def priority_key(self) -> tuple[int, int, int]:
        """Arbitration order: lower wins; a base frame beats an extended one with the same 11 bits."""
        if self.extended:
            return (self.can_id >> 18, 1, self.can_id & 0x3FFFF)
        return (self.can_id, 0, 0)


@dataclass(frozen=True)
class CanParams:
    """Per-bus CAN parameters: bit rates in bit/s; ``data_bitrate`` only for CAN FD with BRS."""

    bitrate: int = 1_000_000
    data_bitrate: int | None = None

    def frame_time_us(self, f: CanFrame, *, worst_case: bool = True) -> float:
        """Bus time of ``f`` in µs (interframe space included)."""
        if f.frame_bits is not None:
            return f.frame_bits * 1e6 / self.bitrate
        rate = self.data_bitrate if f.fd else None
        return can_frame_time_us(
            f.data_bytes,
            bitrate=self.bitrate,
            data_bitrate=rate,
            extended=f.extended,
            fd=f.fd,
            worst_case=worst_case,
        )

    def frame_bits(self, f: CanFrame, *, worst_case: bool = True) -> int:
        """Bit times of ``f`` (both phases counted as bits, whatever their rate)."""
        if f.frame_bits is not None:
            return f.frame_bits
        return can_frame_bits(f.data_bytes, extended=f.extended, fd=f.fd, worst_case=worst_case)


def can_response_times_us(
    frames: Sequence[CanFrame], params: CanParams, cycle_us: float
) -> tuple[float | None, ...]:
    """Worst-case response time (µs) of each frame, queued to bus-idle-again; None if unbounded.

    CAN schedulability analysis as revised by Davis, Burns, Bril and Lukkien
    (2007), eq. 9-14, with zero queuing jitter: blocking by the longest
    lower-priority frame, a level-m busy period, and every instance q in it:
    ``w(q) = B + q*C + sum_hp ceil((w + tau_bit)/T_k) * C_k``,
    ``R(q) = w(q) - q*T + C``. Cyclic frames have period ``cycle_us`` and are
    all queued at the same instant (the SYNC), the critical instant.
    Frame times are worst case (stuffed).
    """
    tau = 1e6 / params.bitrate
    c = [params.frame_time_us(f) for f in frames]
    t = [f.period_us if f.period_us is not None else cycle_us for f in frames]
    keys = [f.priority_key for f in frames]
    eps = 1e-9
    out: list[float | None] = []
    for m in range(len(frames)):
        hp = [k for k in range(len(frames)) if k != m and keys[k] < keys[m]]
        lp = [k for k in range(len(frames)) if k != m and keys[k] > keys[m]]
        # Equal keys (should not happen on a real bus) count as higher priority.
        hp += [k for k in range(len(frames)) if k != m and keys[k] == keys[m]]
        blocking = max((c[k] for k in lp), default=0.0)
        hep = [*hp, m]
        if sum(c[k] / t[k] for k in hep) >= 1.0:
            out.append(None)
            continue
        busy = c[m]
        for _ in range(10_000):
            nxt = blocking + sum(math.ceil(busy / t[k] - eps) * c[k] for k in hep)
            if abs(nxt - busy) < eps:
                break
            busy = nxt
        instances = max(1, math.ceil(busy / t[m] - eps))
        worst = 0.0
        for q in range(instances):
            w = blocking + q * c[m]
            for _ in range(10_000):
                nxt = blocking + q * c[m] + sum(math.ceil((w + tau) / t[k] - eps) * c[k] for k in hp)
                if abs(nxt - w) < eps:
                    break
                w = nxt
            worst = max(worst, w - q * t[m] + c[m])
        out.append(worst)
    return tuple(out)


# ---------------------------------------------------------------------- EtherCAT

ETH_PREAMBLE_SFD_BYTES = 8
ETH_HEADER_BYTES = 14
ETH_FCS_BYTES = 4
ETH_IFG_BYTES = 12
ETH_MIN_PAYLOAD_BYTES = 46  # 60 bytes header + payload, 64 with FCS
ETH_MAX_PAYLOAD_BYTES = 1500
ECAT_HEADER_BYTES = 2
ECAT_DATAGRAM_HEADER_BYTES = 10
ECAT_WKC_BYTES = 2
#: Most datagram data in one frame: 1500 - 2 - 10 - 2.
ECAT_MAX_DATAGRAM_DATA_BYTES = (
    ETH_MAX_PAYLOAD_BYTES - ECAT_HEADER_BYTES - ECAT_DATAGRAM_HEADER_BYTES - ECAT_WKC_BYTES
)
#: FRMW of the reference clock's system time (0x0910) for distributed clocks: 8 bytes data.
ECAT_DC_DATAGRAM_DATA_BYTES = 8
#: Beckhoff EK1101 technical data, "Propagation delay 1 µs typ." (100BASE-TX in and out).
DEFAULT_FORWARDING_DELAY_US = 1.0
#: Signal propagation in twisted-pair cable, ~5 ns/m (ETHERNET Powerlink "Performance").
CABLE_NS_PER_M = 5.0


def ethernet_wire_bytes(datagram_data: Sequence[int]) -> int:
    """Bytes one EtherCAT frame occupies on the wire, from its datagrams' data sizes.

    Preamble+SFD 8, Ethernet header 14, EtherCAT header 2, per datagram 10 + data + 2 (WKC),
    padding to the 46-byte minimum payload, FCS 4, interframe gap 12.
    """
    payload = ECAT_HEADER_BYTES + sum(ECAT_DATAGRAM_HEADER_BYTES + n + ECAT_WKC_BYTES for n in datagram_data)
    if payload > ETH_MAX_PAYLOAD_BYTES:
        raise ValueError(f"EtherCAT payload {payload} bytes exceeds {ETH_MAX_PAYLOAD_BYTES}")
    return (
        ETH_PREAMBLE_SFD_BYTES
        + ETH_HEADER_BYTES
        + max(payload, ETH_MIN_PAYLOAD_BYTES)
        + ETH_FCS_BYTES
        + ETH_IFG_BYTES
    )


def wire_time_us(bits: float, bitrate: float) -> float:
    """Microseconds to send ``bits`` at ``bitrate`` bit/s."""
    return bits * 1e6 / bitrate


@dataclass(frozen=True)
class EcatSlave:
    """Process data of one EtherCAT slave in bytes: ``out_bytes`` master->slave (RxPDO),
    ``in_bytes`` slave->master (TxPDO). Delays None: use the bus defaults."""

    out_bytes: int
    in_bytes: int
    name: str = ""
    forwarding_delay_us: float | None = None
    cable_m: float | None = None


@dataclass(frozen=True)
class EthercatParams:
    """EtherCAT bus parameters.

    ``mode``: ``"lrw"`` one logical read/write datagram, or ``"lrd_lwr"`` separate
    write (outputs) and read (inputs) datagrams. ``overlap``: inputs and outputs
    share the logical area (LRW only): each slave takes ``max(out, in)`` bytes
    instead of ``out + in``. ``dc``: add the distributed-clock FRMW datagram.
    ``forwarding_delay_us``: per slave, total of the frame's way in and back out.
    ``cable_m``: cable length before each slave (master->slave 1, 1->2, ...).
    """

    bitrate: float = 100e6
    mode: Literal["lrw", "lrd_lwr"] = "lrw"
    overlap: bool = False
    dc: bool = False
    forwarding_delay_us: float = DEFAULT_FORWARDING_DELAY_US
    cable_m: float = 1.0
    cable_ns_per_m: float = CABLE_NS_PER_M
    max_datagram_data_bytes: int = ECAT_MAX_DATAGRAM_DATA_BYTES


@dataclass(frozen=True)
class EcatFrame:
    """One EtherCAT frame: its datagrams as (command, data bytes), and wire bytes incl. IFG."""

    datagrams: tuple[tuple[str, int], ...]
    wire_bytes: int


def ethercat_datagrams(slaves: Sequence[EcatSlave], params: EthercatParams) -> list[tuple[str, int]]:
    """Cyclic datagrams before splitting into frames: (command, data bytes)."""
    out = sum(s.out_bytes for s in slaves)
    inp = sum(s.in_bytes for s in slaves)
    grams: list[tuple[str, int]] = []
    if params.dc:
        grams.append(("FRMW", ECAT_DC_DATAGRAM_DATA_BYTES))
    if params.mode == "lrw":
        size = sum(max(s.out_bytes, s.in_bytes) for s in slaves) if params.overlap else out + inp
        if size:
            grams.append(("LRW", size))
    else:
        if out:
            grams.append(("LWR", out))
        if inp:
            grams.append(("LRD", inp))
    return grams


def ethercat_frames(slaves: Sequence[EcatSlave], params: EthercatParams) -> tuple[EcatFrame, ...]:
    """Pack the cyclic datagrams into frames, splitting at the datagram-data limit.

    Greedy: a datagram goes into the current frame while it fits, and is split
    (any byte boundary, an optimistic assumption) across further frames otherwise.
    """
    frames: list[list[tuple[str, int]]] = [[]]
    full = ETH_MAX_PAYLOAD_BYTES - ECAT_HEADER_BYTES
    per = ECAT_DATAGRAM_HEADER_BYTES + ECAT_WKC_BYTES
    room = full
    for cmd, size in ethercat_datagrams(slaves, params):
        left = size
        while left > 0:
            space = min(room - per, params.max_datagram_data_bytes)
            if space <= 0:
                frames.append([])
                room = full
                continue
            chunk = min(left, space)
            frames[-1].append((cmd, chunk))
            room -= chunk + per
            left -= chunk
    packed = [tuple(f) for f in frames if f]
    if not packed:
        return ()
    return tuple(EcatFrame(g, ethernet_wire_bytes([n for _, n in g])) for g in packed)


# ------------------------------------------------------------------- results


@dataclass(frozen=True)
class Slot:
    """One frame in the timeline of a cycle: start and duration in µs from the cycle start."""

    label: str
    start_us: float
    duration_us: float

    def to_json(self) -> dict[str, JsonScalar]:
        return {"label": self.label, "start_us": self.start_us, "duration_us": self.duration_us}


@dataclass(frozen=True)
class BusResult:
    """Bandwidth of one bus at ``rate_hz`` cycles per second.

    ``frames_per_cycle``: cyclic frames; ``bytes_per_cycle``: process data
    bytes exchanged per cycle, outputs + inputs (for CAN: data bytes of the
    cyclic frames); ``wire_bits_per_cycle``: bit times on the wire (CAN: worst
    case with stuffing; EtherCAT: whole frames incl. preamble and IFG);
    ``wire_time_us``: bus time of one cycle's frames; ``load_percent``: share of
    the bus time used at ``rate_hz`` (background frames included);
    ``max_rate_hz``: highest cycle rate the bus sustains (None: unbounded).
    """

    name: str
    type: str
    rate_hz: float
    frames_per_cycle: int
    bytes_per_cycle: int
    wire_bits_per_cycle: float
    wire_time_us: float
    load_percent: float
    max_rate_hz: float | None
    extras: tuple[tuple[str, JsonScalar], ...] = ()
    timeline: tuple[Slot, ...] = field(default=(), repr=False)

    def extra(self, key: str) -> JsonScalar:
        """One of the bus-type specific figures (``worst_case_bits``, ``round_trip_us``...)."""
        return dict(self.extras).get(key)

    def to_json(self, *, timeline: bool = False) -> dict[str, object]:
        """JSON-ready dict; ``timeline=True`` adds the frames of one cycle (µs)."""
        d: dict[str, object] = {
            "name": self.name,
            "type": self.type,
            "rate_hz": _r(self.rate_hz),
            "frames_per_cycle": self.frames_per_cycle,
            "bytes_per_cycle": self.bytes_per_cycle,
            "wire_bits_per_cycle": _r(self.wire_bits_per_cycle),
            "wire_time_us": _r(self.wire_time_us),
            "load_percent": _r(self.load_percent),
            "max_rate_hz": None if self.max_rate_hz is None else _r(self.max_rate_hz),
        }
        for k, v in self.extras:
            d[k] = _r(v) if isinstance(v, float) else v
        if timeline:
            d["timeline"] = [s.to_json() for s in self.timeline]
        return d


def overload(b: BusResult) -> str | None:
    """Why bus ``b`` cannot run at its rate (more than 100 % of the bus time), or None when it can."""
    if b.load_percent <= 100.0:
        return None
    top = f"; it runs at most {b.max_rate_hz:.0f} Hz" if b.max_rate_hz else ""
    return (
        f"bus '{b.name}' needs {b.load_percent:.1f} % of the {b.type} bus at {b.rate_hz:.0f} Hz "
        f"({b.wire_time_us:.0f} us of frames in a {1e6 / b.rate_hz:.0f} us cycle){top}: "
        "lengthen cycle_time_us, raise the bit rate or split the bus"
    )


@dataclass(frozen=True)
class NetworkResult:
    """Every bus of a network, and the bottleneck: the bus with the lowest max cycle rate."""

    rate_hz: float
    buses: tuple[BusResult, ...]

    @property
    def bottleneck(self) -> str | None:
        limited = [b for b in self.buses if b.max_rate_hz is not None]
        if not limited:
            return None
        return min(limited, key=lambda b: (b.max_rate_hz, -b.load_percent)).name

    @property
    def overloaded(self) -> tuple[BusResult, ...]:
        """The buses over 100 % load at their rate (see :func:`overload`)."""
        return tuple(b for b in self.buses if overload(b) is not None)

    def to_json(self) -> dict[str, object]:
        return {
            "rate_hz": _r(self.rate_hz),
            "buses": [b.to_json() for b in self.buses],
            "bottleneck": self.bottleneck,
            "overloaded": [b.name for b in self.overloaded],
        }


def _r(x: float) -> float:
    return round(x, 3) if math.isfinite(x) else x


# ------------------------------------------------------------------- per-bus models


def can_cycle(
    frames: Sequence[CanFrame],
    params: CanParams,
    rate_hz: float,
    *,
    name: str = "can",
    type: str = "canopen",
) -> BusResult:
    """CAN bus figures for one cycle of ``frames`` at ``rate_hz`` (worst-case stuffing).

    Cyclic frames are queued together at the start of a cycle (the SYNC) and go
    out in priority order. Background frames (``period_us`` set) add load and
    interference. Extras: ``worst_case_bits`` and ``nominal_bits`` per cycle,
    ``worst_response_us`` of the lowest-priority cyclic frame (Davis et al. 2007)
    and ``schedulable`` (every cyclic frame done within the cycle).
    """
    cycle_us = 1e6 / rate_hz
    cyclic = [f for f in frames if f.period_us is None]
    background = [f for f in frames if f.period_us is not None]
    wire_us = sum(params.frame_time_us(f) for f in cyclic)
    bits = float(sum(params.frame_bits(f) for f in cyclic))
    nominal = sum(params.frame_bits(f, worst_case=False) for f in cyclic)
    bg_share = sum(params.frame_time_us(f) / f.period_us for f in background if f.period_us)
    load = (wire_us / cycle_us + bg_share) * 100.0
    max_rate = (1.0 - bg_share) * 1e6 / wire_us if wire_us > 0 and bg_share < 1 else None
    extras: list[tuple[str, JsonScalar]] = [
        ("bitrate", params.bitrate),
        ("data_bitrate", params.data_bitrate),
        ("worst_case_bits", int(bits)),
        ("nominal_bits", nominal),
        ("nominal_wire_time_us", sum(params.frame_time_us(f, worst_case=False) for f in cyclic)),
        ("background_load_percent", bg_share * 100.0),
    ]
    if cyclic:
        resp = can_response_times_us(frames, params, cycle_us)
        idx = [i for i, f in enumerate(frames) if f.period_us is None]
        lowest = max(idx, key=lambda i: frames[i].priority_key)
        worst = resp[lowest]
        extras.append(("worst_response_us", worst))
        extras.append(("worst_response_frame", frames[lowest].label or hex(frames[lowest].can_id)))
        cyc_resp = [resp[i] for i in idx]
        extras.append(("schedulable", all(r is not None and r <= cycle_us for r in cyc_resp)))
    timeline: list[Slot] = []
    t = 0.0
    for f in _arbitration_order(cyclic):
        d = params.frame_time_us(f)
        timeline.append(Slot(f.label or hex(f.can_id), t, d))
        t += d
    return BusResult(
        name=name,
        type=type,
        rate_hz=rate_hz,
        frames_per_cycle=len(cyclic),
        bytes_per_cycle=sum(f.data_bytes for f in cyclic),
        wire_bits_per_cycle=bits,
        wire_time_us=wire_us,
        load_percent=load,
        max_rate_hz=max_rate,
        extras=tuple(extras),
        timeline=tuple(timeline),
    )


def _arbitration_order(frames: Sequence[CanFrame]) -> list[CanFrame]:
    """The cycle's frames in the order they take the bus: each time the bus is free, the
    highest-priority frame that is ready wins; a frame with ``after`` is ready once that frame is sent."""
    pending = sorted(frames, key=lambda f: f.priority_key)
    labels = {f.label for f in frames}
    sent: set[str] = set()
    order: list[CanFrame] = []
    while pending:
        ready = next(f for f in pending if f.after is None or f.after in sent or f.after not in labels)
        pending.remove(ready)
        order.append(ready)
        sent.add(ready.label)
    return order


def ethercat_cycle(
    slaves: Sequence[EcatSlave],
    params: EthercatParams,
    rate_hz: float,
    *,
    name: str = "ethercat",
) -> BusResult:
    """EtherCAT bus figures for one cycle at ``rate_hz``.

    ``wire_time_us``: the cycle's frames back to back on the master's link
    (IFG included); ``round_trip_us`` (extra): wire time + per-slave forwarding
    delays + cable there and back, i.e. when the last frame is back at the
    master; ``max_rate_hz`` = 1 / round trip (the frame must be back before the
    next cycle). ``load_percent``: link occupancy, wire time / cycle time.
    """
    frames = ethercat_frames(slaves, params)
    wire_bytes = sum(f.wire_bytes for f in frames)
    wire_us = wire_time_us(8 * wire_bytes, params.bitrate)
    fwd = sum(
        s.forwarding_delay_us if s.forwarding_delay_us is not None else params.forwarding_delay_us
        for s in slaves
    )
    cable = sum(s.cable_m if s.cable_m is not None else params.cable_m for s in slaves)
    prop_us = 2.0 * cable * params.cable_ns_per_m / 1000.0
    rtt = wire_us + fwd + prop_us
    cycle_us = 1e6 / rate_hz
    timeline: list[Slot] = []
    t = 0.0
    for i, f in enumerate(frames):
        d = wire_time_us(8 * f.wire_bytes, params.bitrate)
        timeline.append(Slot(f"frame {i + 1}: " + "+".join(c for c, _ in f.datagrams), t, d))
        t += d
    if slaves:
        timeline.append(Slot("forwarding + cable", wire_us, fwd + prop_us))
    extras: list[tuple[str, JsonScalar]] = [
        ("bitrate", params.bitrate),
        ("mode", params.mode),
        ("overlap", params.overlap),
        ("dc", params.dc),
        ("slaves", len(slaves)),
        ("outputs_bytes", sum(s.out_bytes for s in slaves)),
        ("inputs_bytes", sum(s.in_bytes for s in slaves)),
        ("frame_bytes", tuple(f.wire_bytes for f in frames)),
        ("forwarding_us", fwd),
        ("propagation_us", prop_us),
        ("round_trip_us", rtt),
        ("fits_cycle", rtt <= cycle_us),
    ]
    return BusResult(
        name=name,
        type="ethercat",
        rate_hz=rate_hz,
        frames_per_cycle=len(frames),
        bytes_per_cycle=sum(s.out_bytes + s.in_bytes for s in slaves),
        wire_bits_per_cycle=float(8 * wire_bytes),
        wire_time_us=wire_us,
        load_percent=wire_us / cycle_us * 100.0,
        max_rate_hz=1e6 / rtt if rtt > 0 else None,
        extras=tuple(extras),
        timeline=tuple(timeline),
    )


# ------------------------------------------------------------------- adapters


class SlaveLike(Protocol):
    """What the adapters read from a network slave (``fieldbus.core.network.Slave``)."""

    @property
    def name(self) -> str: ...
    @property
    def map(self) -> DriveMap: ...
    @property
    def node_id(self) -> int | None: ...


class BusLike(Protocol):
    """What the adapters read from a network bus (``fieldbus.core.network.Bus``)."""

    @property
    def name(self) -> str: ...
    @property
    def type(self) -> str: ...
    @property
    def bitrate(self) -> int | None: ...
    @property
    def data_bitrate(self) -> int | None: ...
    @property
    def cycle_time_us(self) -> float: ...
    @property
    def slaves(self) -> Sequence[SlaveLike]: ...


class NetworkLike(Protocol):
    """What :func:`network_bandwidth` reads from a network."""

    @property
    def cycle_time_us(self) -> float: ...
    @property
    def buses(self) -> Sequence[BusLike]: ...


@dataclass(frozen=True)
class CanOptions:
    """How a CANopen / raw CAN bus is turned into frames.

    ``sync``: a SYNC (COB-ID 0x080, 0 bytes) every cycle on CANopen buses.
    ``heartbeat``: each node's heartbeat (1 byte, 0x700 + node) every
    ``heartbeat_ms`` of its map (CANopen only). ``emcy_per_s``: EMCY budget,
    8-byte frames (0x080 + node) per second per node. ``frame_bits``: force every
    frame to this many bits (textbook models).
    """

    sync: bool = True
    heartbeat: bool = True
    emcy_per_s: float = 0.0
    frame_bits: int | None = None


def pdo_bytes(pdos: Iterable[Pdo]) -> int:
    """Process-data bytes of PDOs packed in one SyncManager (EtherCAT): ceil(sum of bits / 8)."""
    return (sum(p.bits for p in pdos) + 7) // 8


def ecat_slave(slave: SlaveLike) -> EcatSlave:
    """An :class:`EcatSlave` from a network slave: outputs = RxPDOs, inputs = TxPDOs."""
    device = slave.map.bus_map  # a multi-axis map: every axis's PDOs
    return EcatSlave(pdo_bytes(device.rpdo), pdo_bytes(device.tpdo), name=slave.name)


def _default_cob(tx: bool, number: int, node: int) -> int:
    base = 0x180 if tx else 0x200
    return base + 0x100 * min(max(number - 1, 0), 3) + node


def can_frames(
    slaves: Sequence[SlaveLike], *, bus_type: str, fd_bus: bool, options: CanOptions = CanOptions()
) -> list[CanFrame]:
    """CAN frames of one cycle (and background frames) from the slaves' maps.

    RPDOs (outputs, master -> drive) and TPDOs (inputs, drive -> master), one
    frame each; COB-IDs from the map's CANopen section or the CiA 301 defaults.
    Every PDO is counted every cycle (synchronous, transmission type 1..240
    treated as 1: conservative).
    """
    frames: list[CanFrame] = []
    shared: set[tuple[int, bool]] = set()  # declarative frames already counted (several motors each)
    fb = options.frame_bits
    if bus_type == "canopen" and options.sync:
        frames.append(CanFrame(0x080, 0, "SYNC", frame_bits=fb))
    for s in slaves:
        node = s.node_id
        if node is None:
            raise PdoMapError(f"slave {s.name!r} on a CAN bus needs a node_id", file=s.map.source)
        cfg = s.map.canopen or CanopenConfig()
        fd = fd_bus or cfg.fd
        limit = 64 if fd else 8
        if s.map.rawcan is not None and s.map.rawcan.protocol is not None:  # shared frames: once per bus
            for f, once in protocol_frames(s.name, s.map.rawcan, node, fb, fd_bus):
                if not once or (f.can_id, f.extended) not in shared:
                    shared.add((f.can_id, f.extended))
                    frames.append(f)
            continue
        if s.map.rawcan is not None:  # one command frame and its reply per motor, not PDOs
            frames += _motor_frames(s.name, s.map.rawcan, node, s.map.rpdo, s.map.tpdo, fb, fd_bus)
            continue
        for tx, pdos in ((False, s.map.rpdo), (True, s.map.tpdo)):
            for pdo in pdos:
                if pdo.size > limit:
                    kind = "CAN FD" if fd else "classic CAN"
                    raise PdoMapError(
                        f"{'TxPDO' if tx else 'RxPDO'} 0x{pdo.index:04X} of slave {s.name!r} is "
                        f"{pdo.size} bytes: {kind} carries at most {limit}",
                        file=s.map.source,
                        path=f"{'tpdo' if tx else 'rpdo'}",
                    )
                cob = pdo.canopen.cob_id_for(node) if pdo.canopen else _default_cob(tx, pdo.number, node)
                label = f"{s.name} {'TPDO' if tx else 'RPDO'}{pdo.number}"
                frames.append(CanFrame(cob & 0x1FFFFFFF, pdo.size, label, cob > 0x7FF, fd, frame_bits=fb))
        if bus_type == "canopen" and options.heartbeat and cfg.heartbeat_ms > 0:
            frames.append(
                CanFrame(0x700 + node, 1, f"{s.name} heartbeat", period_us=cfg.heartbeat_ms * 1000.0)
            )
        if options.emcy_per_s > 0:
            frames.append(CanFrame(0x080 + node, 8, f"{s.name} EMCY", period_us=1e6 / options.emcy_per_s))
    return frames


def _motor_frames(
    name: str,
    cfg: RawCanConfig,
    node: int,
    rpdo: Sequence[Pdo],
    tpdo: Sequence[Pdo],
    frame_bits: int | None,
    fd: bool = False,
) -> list[CanFrame]:
    """A raw-CAN motor's command (CAN id ``command_id + node``) and the reply that follows it
    (``reply_id``, or the command's id when the map names none), as the rawcan backend sends them;
    CAN FD frames on an FD bus (the backend sends every data frame as FD there)."""
    command_id = cfg.command_id + node
    reply_id = cfg.reply_can_id(node)
    out_bytes, in_bytes, extended = sum(p.size for p in rpdo), sum(p.size for p in tpdo), False
    command = CanFrame(command_id, out_bytes, f"{name} command", extended, fd, frame_bits=frame_bits)
    reply = CanFrame(
        reply_id, in_bytes, f"{name} reply", extended, fd, frame_bits=frame_bits, after=command.label
    )
    return [command, reply]


def protocol_frames(
    name: str, cfg: RawCanConfig, node: int, frame_bits: int | None, fd: bool = False
) -> list[tuple[CanFrame, bool]]:
    """One cycle of a motor whose family runs on the protocol (:mod:`fieldbus.core.canfamily`), as its
    family reports its frames, each with whether several motors share it (then it comes once per motor,
    the same id, and is counted once)."""
    family = families()[cfg.family]
    return [(_wire_frame(t, frame_bits, fd), t.shared) for t in family.wire_frames(name, cfg.protocol, node)]


def _wire_frame(t: FrameTime, frame_bits: int | None, fd: bool) -> CanFrame:
    """A family's reported frame ``t`` (:meth:`~fieldbus.core.canfamily.CanFamily.wire_frames`) as the
    calculator's frame; ``fd``: data frames as CAN FD, a remote frame stays classic (CAN FD has none)."""
    return CanFrame(
        t.can_id,
        t.data_bytes,
        t.label,
        t.extended,
        fd and not t.remote,
        t.period_us,
        frame_bits=frame_bits,
        after=t.after,
    )


def family_frames(
    name: str,
    cfg: RawCanConfig,
    node: int,
    frame_bits: int | None = None,
    mode: str | None = None,
    fd: bool = False,
) -> list[CanFrame]:
    """One cycle of a motor of a family on the protocol as the rawcan backend runs it: its family's
    :meth:`~fieldbus.core.canfamily.CanFamily.wire_frames`, in ``mode`` for a family with modes (default:
    the map's; Damiao: the mode's command on ``node + id_offset``, 8 bytes, and its 8-byte reply on
    MST_ID). ``fd``: the data frames as CAN FD (an FD bus); a remote frame stays classic (CAN FD has none).
    """
    if cfg.protocol is None:
        raise ValueError(f"{name}: its map's family is not on the protocol (fieldbus.core.canfamily)")
    wire: Any = families()[cfg.family].wire_frames  # a family with modes takes mode=
    times = wire(name, cfg.protocol, node, mode=mode) if mode else wire(name, cfg.protocol, node)
    return [_wire_frame(t, frame_bits, fd) for t in times]


def bus_bandwidth(
    bus: BusLike,
    rate_hz: float | None = None,
    *,
    can: CanOptions = CanOptions(),
    ethercat: EthercatParams | None = None,
) -> BusResult:
    """Bandwidth of one bus of a loaded network at ``rate_hz`` (default: the bus's cycle time).

    EtherCAT: LRW unless a map disables it; DC datagram if any map sets
    ``assign_activate``. CAN: classic unless the bus has a ``data_bitrate``
    or a map says ``canopen.fd``. ``sim`` buses use no wire.
    """
    rate = rate_hz if rate_hz is not None else 1e6 / bus.cycle_time_us
    if bus.type == "ethercat":
        slaves = [ecat_slave(s) for s in bus.slaves]
        if ethercat is None:
            lrw = all(s.map.ethercat.lrw for s in bus.slaves)
            dc = any(s.map.assign_activate for s in bus.slaves)
            ethercat = EthercatParams(mode="lrw" if lrw else "lrd_lwr", dc=dc)
        return ethercat_cycle(slaves, ethercat, rate, name=bus.name)
    if bus.type in ("canopen", "rawcan"):
        bitrate = bus.bitrate or 1_000_000
        fd_bus = bus.data_bitrate is not None
        frames = can_frames(bus.slaves, bus_type=bus.type, fd_bus=fd_bus, options=can)
        params = CanParams(bitrate, bus.data_bitrate)
        return can_cycle(frames, params, rate, name=bus.name, type=bus.type)
    payload = sum(pdo_bytes(s.map.bus_map.rpdo) + pdo_bytes(s.map.bus_map.tpdo) for s in bus.slaves)
    return BusResult(bus.name, bus.type, rate, 0, payload, 0.0, 0.0, 0.0, None)


def network_bandwidth(
    network: NetworkLike,
    rate_hz: float | None = None,
    *,
    can: CanOptions = CanOptions(),
    ethercat: EthercatParams | None = None,
) -> NetworkResult:
    """Every bus of ``network`` at ``rate_hz`` (default: each bus at its own cycle time;
    the summary's ``rate_hz`` is then the network's)."""
    rate = rate_hz if rate_hz is not None else 1e6 / network.cycle_time_us
    buses = tuple(bus_bandwidth(b, rate_hz, can=can, ethercat=ethercat) for b in network.buses)
    return NetworkResult(rate, buses)
