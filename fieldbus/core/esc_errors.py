"""ESC error counters and link state per slave and port, their rise, and the cable they point at.

Registers (Beckhoff ESC datasheet section II; ETG.1000.4 "DL information"),
u8 counters that stop at 0xFF:

- 0x0300 + 2p  invalid frame counter of port p (CRC error, frame too short, ...)
- 0x0301 + 2p  RX error counter of port p (physical layer: symbol errors)
- 0x0308 + p   forwarded RX error counter of port p (a frame an ESC upstream
  already found bad, so marked: counted here, but the error is not here)
- 0x030C       ECAT processing unit error counter
- 0x030D       PDI error counter
- 0x0310 + p   lost link counter of port p
- 0x0110       DL status (u16): bit 0 PDI operational (EEPROM loaded),
  bits 4-7 physical link on port 0-3, bits 8 + 2p loop closed, 9 + 2p
  communication on port p

Writing any of 0x0300-0x030B clears those twelve, 0x030C and 0x030D each
themselves, any of 0x0310-0x0313 the four lost-link counters (same source),
so one 20-byte write of zeros at 0x0300 resets them all.

The cable rule (:func:`suspect_links`), for a line where each slave's port 0
faces the master and port 1 the next slave: a frame is corrupted on one
cable; the ESC that receives it there counts an invalid frame (or RX error,
or a lost link) on that port and marks the frame, so every ESC after it counts
only a *forwarded* error. Hence an error first counted at port 0 of slave
k+1, or at port 1 of slave k, points at the cable between slave k's port 1
and slave k+1's port 0 (port 0 of slave 0: the master's cable); forwarded
counts are never the origin. Positions are 0-based in wire order.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

REG_ERRORS = 0x0300
ERRORS_SIZE = 0x14  # 0x0300-0x0313
REG_DL_STATUS = 0x0110
DL_STATUS_SIZE = 2
PORTS = 4
COUNTER_MAX = 0xFF


@dataclass(frozen=True)
class PortCounters:
    """One port's counters (counts; u8 on the ESC, saturating at 255)."""

    invalid_frame: int = 0
    rx_error: int = 0
    forwarded: int = 0
    lost_link: int = 0

    @property
    def origin(self) -> int:
        """Errors that started on this port's cable (forwarded ones did not)."""
        return self.invalid_frame + self.rx_error + self.lost_link

    @property
    def total(self) -> int:
        return self.origin + self.forwarded


@dataclass(frozen=True)
class EscErrors:
    """One slave's error counters (registers 0x0300-0x0313)."""

    ports: tuple[PortCounters, PortCounters, PortCounters, PortCounters] = (
        PortCounters(),
        PortCounters(),
        PortCounters(),
        PortCounters(),
    )
    processing_unit: int = 0
    pdi: int = 0

    @classmethod
    def from_registers(cls, raw: bytes) -> EscErrors:
        """From the 20 bytes read at 0x0300."""
        if len(raw) < ERRORS_SIZE:
            raise ValueError(f"{len(raw)} bytes read at 0x0300, {ERRORS_SIZE} needed")
        ports = tuple(
            PortCounters(raw[2 * p], raw[2 * p + 1], raw[0x08 + p], raw[0x10 + p]) for p in range(PORTS)
        )
        return cls(ports, raw[0x0C], raw[0x0D])  # type: ignore[arg-type]

    def to_registers(self) -> bytes:
        out = bytearray(ERRORS_SIZE)
        for p, c in enumerate(self.ports):
            out[2 * p], out[2 * p + 1] = min(c.invalid_frame, 255), min(c.rx_error, 255)
            out[0x08 + p], out[0x10 + p] = min(c.forwarded, 255), min(c.lost_link, 255)
        out[0x0C], out[0x0D] = min(self.processing_unit, 255), min(self.pdi, 255)
        return bytes(out)

    def since(self, before: EscErrors | None) -> EscErrors:
        """The rise since ``before`` (None: since zero). A counter lower than before was cleared: its value."""

        def d(new: int, old: int) -> int:
            return new - old if new >= old else new

        if before is None:
            return self
        ports = tuple(
            PortCounters(
                d(n.invalid_frame, o.invalid_frame),
                d(n.rx_error, o.rx_error),
                d(n.forwarded, o.forwarded),
                d(n.lost_link, o.lost_link),
            )
            for n, o in zip(self.ports, before.ports, strict=True)
        )
        return EscErrors(ports, d(self.processing_unit, before.processing_unit), d(self.pdi, before.pdi))  # type: ignore[arg-type]

    @property
    def any(self) -> bool:
        return bool(self.processing_unit or self.pdi or any(p.total for p in self.ports))

    @property
    def saturated(self) -> bool:
        """Some counter reached 255 and stopped: its rise from here on is not seen (reset them)."""
        return COUNTER_MAX in self.to_registers()


@dataclass(frozen=True)
class DlStatus:
    """DL status (0x0110) decoded: PDI operational, per port link, loop closed, communication."""

    raw: int

    @property
    def pdi_operational(self) -> bool:
        return bool(self.raw & 0x0001)

    def link(self, port: int) -> bool:
        return bool(self.raw & (0x0010 << port))

    def loop_closed(self, port: int) -> bool:
        return bool(self.raw & (0x0100 << 2 * port))

    def communication(self, port: int) -> bool:
        return bool(self.raw & (0x0200 << 2 * port))

    def describe(self) -> str:
        ports = []
        for p in range(PORTS):
            if self.link(p) or self.communication(p):
                ports.append(
                    f"{p}:{'link' if self.link(p) else 'no link'}{'' if self.loop_closed(p) else ' open'}"
                )
            else:
                ports.append(f"{p}:{'closed' if self.loop_closed(p) else '-'}")
        return ("PDI ok " if self.pdi_operational else "PDI NOT operational ") + " ".join(ports)


@dataclass(frozen=True)
class Link:
    """A cable: from ``upstream``'s port ``upstream_port`` (None: the master) to ``downstream``'s port."""

    upstream: int | None
    upstream_port: int
    downstream: int | None
    downstream_port: int

    def describe(self, names: Sequence[str] | None = None) -> str:
        def who(i: int | None) -> str:
            if i is None:
                return "the master"
            return f"slave {i}" + (f" ({names[i]})" if names and i < len(names) else "")

        if self.downstream is None:
            return f"{who(self.upstream)} port {self.upstream_port} (nothing known behind it)"
        up = who(self.upstream) + ("" if self.upstream is None else f" port {self.upstream_port}")
        return f"cable between {up} and {who(self.downstream)} port {self.downstream_port}"


@dataclass(frozen=True)
class Suspect:
    """A cable and the errors that started on it (counts at its two ends)."""

    link: Link
    errors: int


def link_of(slave: int, port: int, count: int) -> Link:
    """The cable on ``port`` of ``slave`` in a line of ``count`` slaves (port 0 up, port 1 down)."""
    if port == 0:
        return Link(None if slave == 0 else slave - 1, 1, slave, 0)
    if port == 1 and slave + 1 < count:
        return Link(slave, 1, slave + 1, 0)
    return Link(slave, port, None, 0)


def suspect_links(rises: Sequence[EscErrors | None], *, minimum: int = 1) -> list[Suspect]:
    """Cables where errors started (see the module's rule), most errors first; forwarded counts ignored."""
    count = len(rises)
    found: dict[Link, int] = {}
    for i, r in enumerate(rises):
        if r is None:
            continue
        for p, c in enumerate(r.ports):
            if c.origin:
                link = link_of(i, p, count)
                found[link] = found.get(link, 0) + c.origin
    out = [Suspect(k, v) for k, v in found.items() if v >= minimum]
    out.sort(key=lambda s: (-s.errors, s.link.upstream if s.link.upstream is not None else -1))
    return out


@dataclass
class CounterRise:
    """Counters of ``slave`` rose between two reads (its ports' rises, the suspect cable if any)."""

    slave: int
    rise: EscErrors
    total: EscErrors
    suspects: list[Suspect] = field(default_factory=list)


@dataclass
class LinkChange:
    """Port ``port`` of ``slave`` gained or lost its link (DL status 0x0110)."""

    slave: int
    port: int
    up: bool


class ErrorWatch:
    """Read every slave's counters and DL status acyclically, one datagram per step, rotating over slaves.

    :meth:`next_read` names the one read for this step: (slave, register,
    bytes); the caller reads it (one FPRD) and hands the answer (None: no
    answer) to :meth:`feed`, which returns what changed. A slave's counters
    and DL status take two steps; all ``n`` slaves 2n steps. The first read of
    a slave is its baseline (no rise reported). Pure: no I/O, no clock.
    """

    def __init__(self, count: int) -> None:
        self.count = count
        self.step = 0
        self.reads = 0
        self.missed = 0
        self.errors: list[EscErrors | None] = [None] * count  # counters as last read
        self.baseline: list[EscErrors | None] = [None] * count  # as first read (or after a reset)
        self.dl: list[DlStatus | None] = [None] * count

    def next_read(self) -> tuple[int, int, int]:
        i, kind = divmod(self.step % (2 * self.count), 2)
        return (i, REG_ERRORS, ERRORS_SIZE) if kind == 0 else (i, REG_DL_STATUS, DL_STATUS_SIZE)

    def feed(self, raw: bytes | None) -> list[CounterRise | LinkChange]:
        i, reg, size = self.next_read()
        self.step += 1
        self.reads += 1
        if raw is None or len(raw) < size:  # no answer, or a short one: this read is missed, nothing judged
            self.missed += 1
            return []
        if reg == REG_DL_STATUS:
            return self._dl(i, DlStatus(int.from_bytes(raw[:2], "little")))
        now = EscErrors.from_registers(raw)
        before = self.errors[i]
        self.errors[i] = now
        if before is None:
            self.baseline[i] = now
            return []
        rise = now.since(before)
        if not rise.any:
            return []
        rises: list[EscErrors | None] = [None] * self.count
        rises[i] = rise
        return [CounterRise(i, rise, now, suspect_links(rises))]

    def _dl(self, i: int, st: DlStatus) -> list[CounterRise | LinkChange]:
        before, self.dl[i] = self.dl[i], st
        if before is None:
            return []
        return [LinkChange(i, p, st.link(p)) for p in range(PORTS) if st.link(p) != before.link(p)]

    def since_baseline(self) -> list[EscErrors | None]:
        """Each slave's rise since its first read (None: not read yet)."""
        return [None if e is None else e.since(b) for e, b in zip(self.errors, self.baseline, strict=True)]

    def suspects(self) -> list[Suspect]:
        """Cables where errors started since the baseline (all slaves' counters together)."""
        return suspect_links(self.since_baseline())

    def summary(self, names: Sequence[str]) -> dict[str, str]:
        """For diagnostics: "suspect_link" (the cable with most errors, if any) and "NAME/esc_errors" per
        slave whose counters rose since its baseline ("p0 inv/rx/fwd/lost ...")."""
        out: dict[str, str] = {}
        found = self.suspects()
        if found:
            out["suspect_link"] = f"{found[0].link.describe(names)} ({found[0].errors} errors)"
        for i, rise in enumerate(self.since_baseline()):
            text = format_rise(rise)
            if text not in (None, "0"):
                out[f"{names[i] if i < len(names) else i}/esc_errors"] = str(text)
        return out


def format_rise(rise: EscErrors | None) -> str | None:
    """A slave's counters as "p0 inv/rx/fwd/lost ..." for the ports with any ("0": none; None: not read)."""
    if rise is None:
        return None
    parts = [
        f"p{k} {c.invalid_frame}/{c.rx_error}/{c.forwarded}/{c.lost_link}"
        for k, c in enumerate(rise.ports)
        if c.total
    ]
    return " ".join(parts) or "0"


def describe_change(change: CounterRise | LinkChange, names: Sequence[str] | None = None) -> tuple[str, str]:
    """(event kind, detail) of a change: "esc_errors" (what rose where, the suspect cable), "link_down"/"link_up"."""

    def who(i: int) -> str:
        return f"slave {i}" + (f" ({names[i]})" if names and i < len(names) else "")

    if isinstance(change, LinkChange):
        return ("link_up" if change.up else "link_down"), f"{who(change.slave)} port {change.port}"
    parts = []
    for p, c in enumerate(change.rise.ports):
        got = [
            f"+{n} {what}"
            for n, what in (
                (c.invalid_frame, "invalid frames"),
                (c.rx_error, "RX errors"),
                (c.forwarded, "forwarded errors"),
                (c.lost_link, "lost links"),
            )
            if n
        ]
        if got:
            parts.append(f"port {p}: {', '.join(got)}")
    if change.rise.processing_unit:
        parts.append(f"+{change.rise.processing_unit} processing unit errors")
    if change.rise.pdi:
        parts.append(f"+{change.rise.pdi} PDI errors")
    detail = f"{who(change.slave)} {'; '.join(parts)}"
    if change.suspects:
        detail += f"; suspect: {change.suspects[0].link.describe(names)}"
    if change.total.saturated:
        detail += "; a counter stopped at 255 (reset them)"
    return "esc_errors", detail
