"""``fieldbus scan ethercat IFACE --errors``: every slave's ESC error counters, link state and EEPROM status.

Read by position (APRD) on SOEM's socket *before* any configuration:
SOEM's ``config_init`` clears the RX error counters (its
``ecx_set_slaves_to_default`` writes 8 zero bytes to 0x0300, "reset CRC
counters"), so a normal scan would erase the evidence. Nothing is written and
no state changes, unless ``reset`` (one BWR of 20 zero bytes at 0x0300,
which clears every counter on every slave, after reading them).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

from fieldbus.core.ecat import Command, Datagram
from fieldbus.core.esc_errors import (
    DL_STATUS_SIZE,
    ERRORS_SIZE,
    REG_DL_STATUS,
    REG_ERRORS,
    DlStatus,
    EscErrors,
    Suspect,
    suspect_links,
)
from fieldbus.errors import FieldbusError

REG_AL_STATUS, REG_EEPROM_STATUS = 0x0130, 0x0502
TIMEOUT_US = 2000
TRIES = 3


@dataclass
class SlaveErrors:
    position: int
    errors: EscErrors | None  # None: did not answer
    dl_status: DlStatus | None
    al_status: int | None
    eeprom_status: int | None


@dataclass
class ErrorScan:
    interface: str
    slaves: list[SlaveErrors]
    suspects: list[Suspect] = field(default_factory=list)
    reset: bool = False

    def as_json(self) -> dict[str, Any]:
        from fieldbus.wire.eeprom import ST_CHECKSUM, status_text

        return {
            "interface": self.interface,
            "reset": self.reset,
            "slaves": [
                {
                    "position": s.position,
                    "answered": s.errors is not None,
                    "ports": []
                    if s.errors is None
                    else [
                        {
                            "invalid_frame": p.invalid_frame,
                            "rx_error": p.rx_error,
                            "forwarded": p.forwarded,
                            "lost_link": p.lost_link,
                        }
                        for p in s.errors.ports
                    ],
                    "processing_unit": None if s.errors is None else s.errors.processing_unit,
                    "pdi": None if s.errors is None else s.errors.pdi,
                    "dl_status": None if s.dl_status is None else s.dl_status.raw,
                    "links": None if s.dl_status is None else [s.dl_status.link(p) for p in range(4)],
                    "pdi_operational": None if s.dl_status is None else s.dl_status.pdi_operational,
                    "al_status": s.al_status,
                    "eeprom_status": s.eeprom_status,
                    "eeprom": None if s.eeprom_status is None else status_text(s.eeprom_status & ~0x00FF),
                    "eeprom_checksum_error": None
                    if s.eeprom_status is None
                    else bool(s.eeprom_status & ST_CHECKSUM),
                }
                for s in self.slaves
            ],
            "suspects": [
                {
                    "link": s.link.describe(),
                    "upstream": s.link.upstream,
                    "downstream": s.link.downstream,
                    "errors": s.errors,
                }
                for s in self.suspects
            ],
        }


def read_errors(interface: str, *, reset: bool = False) -> ErrorScan:
    """Every slave's counters, DL status, AL status and EEPROM status on ``interface`` (see the module)."""
    import pysoem

    from fieldbus.backends import soem_socket
    from fieldbus.backends.buslock import lock_network_card
    from fieldbus.backends.ecat_master import open_card
    from fieldbus.backends.ecat_raw import RawDatagrams

    with lock_network_card(interface):
        master = pysoem.Master()
        before = soem_socket.open_sockets()
        open_card(master, interface)
        raw = RawDatagrams(soem_socket.packet_sockets(soem_socket.open_sockets() - before))
        try:
            count = _count(raw, interface)
            slaves = [_read(raw, p) for p in range(count)]
            if reset:
                d = _txrx(raw, Datagram.physical(Command.BWR, 0, REG_ERRORS, bytes(ERRORS_SIZE)))
                if d is None or d.wkc != count:
                    got = "no answer" if d is None else f"{d.wkc} of {count} slaves"
                    raise FieldbusError(f"'{interface}': clearing the error counters: {got}")
        finally:
            raw.close()
            master.close()
    return ErrorScan(interface, slaves, suspect_links([s.errors for s in slaves]), reset)


def _txrx(raw: Any, d: Datagram) -> Datagram | None:
    for _ in range(TRIES):
        got = raw.txrx(d, TIMEOUT_US)
        if got is not None:
            return got  # type: ignore[no-any-return]
    return None


def _count(raw: Any, interface: str) -> int:
    d = _txrx(raw, Datagram.physical(Command.BRD, 0, 0x0000, bytes(2)))
    if d is None or d.wkc == 0:
        raise FieldbusError(f"no EtherCAT slave answers on '{interface}' (is the cable in and the link up?)")
    return int(d.wkc)


def _read(raw: Any, position: int) -> SlaveErrors:
    def aprd(ado: int, size: int) -> bytes | None:
        d = _txrx(raw, Datagram.physical(Command.APRD, -position, ado, bytes(size)))
        return None if d is None or d.wkc != 1 else bytes(d.data)

    err, dl, al, ee = (
        aprd(REG_ERRORS, ERRORS_SIZE),
        aprd(REG_DL_STATUS, DL_STATUS_SIZE),
        aprd(REG_AL_STATUS, 2),
        aprd(REG_EEPROM_STATUS, 2),
    )
    return SlaveErrors(
        position,
        None if err is None else EscErrors.from_registers(err),
        None if dl is None else DlStatus(int.from_bytes(dl, "little")),
        None if al is None else int.from_bytes(al, "little"),
        None if ee is None else int.from_bytes(ee, "little"),
    )


def format_text(scan: ErrorScan) -> str:
    """One line per slave (counters per port: invalid/rx/forwarded/lost), then the suspect cables."""
    from fieldbus.core.al import state_name
    from fieldbus.wire.eeprom import status_text

    lines = [
        f"{'pos':>3}  {'port 0 inv/rx/fwd/lost':<22}  {'port 1':<14}  {'PU':>3} {'PDI':>3}  DL status / AL / EEPROM"
    ]
    for s in scan.slaves:
        if s.errors is None:
            lines.append(f"{s.position:>3}  no answer")
            continue
        p0, p1 = s.errors.ports[0], s.errors.ports[1]
        extra = [
            f"port {k}: {p.invalid_frame}/{p.rx_error}/{p.forwarded}/{p.lost_link}"
            for k, p in enumerate(s.errors.ports)
            if k >= 2 and p.total
        ]
        dl = "-" if s.dl_status is None else s.dl_status.describe()
        al = (
            "-"
            if s.al_status is None
            else state_name(s.al_status & 0x0F) + (" ERR" if s.al_status & 0x10 else "")
        )
        ee = "-" if s.eeprom_status is None else status_text(s.eeprom_status & ~0x00FF)
        lines.append(
            f"{s.position:>3}  {f'{p0.invalid_frame}/{p0.rx_error}/{p0.forwarded}/{p0.lost_link}':<22}  "
            f"{f'{p1.invalid_frame}/{p1.rx_error}/{p1.forwarded}/{p1.lost_link}':<14}  "
            f"{s.errors.processing_unit:>3} {s.errors.pdi:>3}  {dl} / {al} / EEPROM {ee}"
            + ("; " + "; ".join(extra) if extra else "")
        )
    if scan.suspects:
        for x in scan.suspects:
            lines.append(f"suspect: {x.link.describe()}: {x.errors} errors started there")
    else:
        lines.append("no errors started on any cable (forwarded counts are never the origin)")
    if scan.reset:
        lines.append("counters cleared after reading")
    return "\n".join(lines)
