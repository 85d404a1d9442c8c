"""Scan an EtherCAT segment with pysoem: every slave's identity, state, SII, topology and PDO mapping.

SOEM's ``config_init`` counts the slaves, gives them station addresses,
reads their SII and requests PRE-OP (so a running network is interrupted:
scan a bus nobody is cycling). Then, per slave: registers (station address,
alias, ESC features, DL status, AL status and code), the SII (serial, mailbox
protocols, CoE details, strings, SyncManagers, PDO categories) through the
EEPROM interface, and the PDO mapping as the slave has it: by SDO
(0x1C12/0x1C13, then each 0x16xx/0x1Axx) when it speaks CoE, else from the
SII PDO categories. Object names and data types come from the SDO
Information service when the slave offers it.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass, field
from typing import Any

from fieldbus.core.al import AL_ERROR, al_status_name, state_name
from fieldbus.core.pdo.load import COE_RANGES
from fieldbus.core.pdo.model import Direction
from fieldbus.core.sdo.info import ACCESS_WRITE_PREOP
from fieldbus.core.sii import (
    CAT_END,
    CAT_GENERAL,
    CAT_RXPDO,
    CAT_SM,
    CAT_STRINGS,
    CAT_TXPDO,
    MAILBOX_PROTOCOLS,
    SM_TYPES,
)
from fieldbus.core.sii import WORD_ALIAS as SII_ALIAS
from fieldbus.core.sii import WORD_CATEGORIES as SII_CATEGORIES
from fieldbus.core.sii import WORD_PROTOCOLS as SII_PROTOCOLS
from fieldbus.core.sii import WORD_SERIAL as SII_SERIAL
from fieldbus.errors import FieldbusError
from fieldbus.scan.model import Device, Identity, PdoEntry, ScannedPdo, entry_name, entry_type, mapping_entry

COE_DETAIL_NAMES = {
    0x01: "SDO",
    0x02: "SDO info",
    0x04: "PDO assign",
    0x08: "PDO config",
    0x20: "complete access",
}
REG_STATION, REG_ALIAS, REG_FEATURES, REG_DL_STATUS, REG_AL_STATUS = 0x0010, 0x0012, 0x0008, 0x0110, 0x0130
FEATURE_DC = 0x0004
RXPDO_ASSIGN, TXPDO_ASSIGN = 0x1C12, 0x1C13


@dataclass
class SyncManagerSii:
    index: int
    start: int
    length: int
    control: int
    enable: int
    type: str


@dataclass
class EthercatSlave(Device):
    """One slave as the scan found it (positions 0-based in wire order, as in network files)."""

    position: int = 0
    configured_address: int = 0
    alias: int = 0
    state: str = ""
    al_status_code: int = 0
    al_status: str = ""
    mailbox_protocols: list[str] = field(default_factory=list)
    coe_details: list[str] = field(default_factory=list)
    sdo_info: bool = False
    dc: bool = False
    parent: int | None = None  # position of the slave it hangs off; None: the master
    open_ports: list[int] = field(default_factory=list)
    sync_managers: list[SyncManagerSii] = field(default_factory=list)
    mapping_source: str = "none"  # "coe" | "sii" | "none"


@dataclass
class EthercatScan:
    interface: str
    slaves: list[EthercatSlave]


def sdo_read(s: Any, position: int, index: int, sub: int) -> bytes:
    """One SDO upload from slave ``s`` at ``position`` through the EtherCAT adapter (its error mapping)."""
    from fieldbus.backends import ecat_master

    who = f"slave {position} ({s.name})"
    return bytes(
        ecat_master.sdo(lambda: s.sdo_read(index, sub), index=index, sub_index=sub, slave=who, what="read")
    )


def scan(interface: str, *, sdo_information: bool = True) -> EthercatScan:
    """Scan the segment on ``interface`` (see the module docstring); refused while a master runs on it."""
    from fieldbus.backends.buslock import lock_network_card
    from fieldbus.backends.ecat_master import open_segment

    with lock_network_card(interface):  # a scan knocks a running master's slaves out of OP
        master = open_segment(interface)
        try:
            slaves = [_slave(s, i, sdo_information) for i, s in enumerate(master.slaves)]
        finally:
            master.close()
    _topology(slaves)
    return EthercatScan(interface, slaves)


class _Sii:
    """The SII through pysoem's EEPROM reads (4 bytes a read, cached)."""

    def __init__(self, slave: Any) -> None:
        self.slave = slave
        self._words: dict[int, int] = {}

    def word(self, w: int) -> int:
        if w not in self._words:
            raw = bytes(self.slave.eeprom_read(w & ~1))
            self._words[w & ~1], self._words[(w & ~1) + 1] = struct.unpack("<HH", raw[:4])
        return self._words[w]

    def u32(self, w: int) -> int:
        return self.word(w) | self.word(w + 1) << 16

    def read(self, w: int, nbytes: int) -> bytes:
        return b"".join(struct.pack("<H", self.word(w + k)) for k in range((nbytes + 1) // 2))[:nbytes]

    def categories(self) -> dict[int, bytes]:
        out: dict[int, bytes] = {}
        w = SII_CATEGORIES
        while w < 0x4000:
            kind = self.word(w)
            if kind in (CAT_END, 0xFFFF):
                break
            words = self.word(w + 1)
            if kind in (CAT_STRINGS, CAT_GENERAL, CAT_SM, CAT_TXPDO, CAT_RXPDO):
                out.setdefault(kind, self.read(w + 2, 2 * words))
            w += 2 + words
        return out


def _strings(data: bytes) -> list[str]:
    from fieldbus.wire.framemaster import sii_strings

    return sii_strings(data)


def _slave(s: Any, position: int, use_info: bool) -> EthercatSlave:
    sii = _Sii(s)
    errors: list[str] = []
    station = _reg(s, REG_STATION, 2, errors)
    alias = _reg(s, REG_ALIAS, 2, errors)
    features = _reg(s, REG_FEATURES, 2, errors)
    dl_status = _reg(s, REG_DL_STATUS, 2, errors)
    al = _reg(s, REG_AL_STATUS, 6, errors, full=True)
    al_state, al_code = (al & 0xFFFF, al >> 32) if al is not None else (int(s.state), int(s.al_status))
    protocols = sii.word(SII_PROTOCOLS)
    cats = sii.categories()
    strings = _strings(cats.get(CAT_STRINGS, b""))
    general = cats.get(CAT_GENERAL, b"")
    coe_details = general[5] if len(general) > 5 else 0
    out = EthercatSlave(
        name=s.name,
        identity=Identity(int(s.man), int(s.id), int(s.rev), sii.u32(SII_SERIAL)),
        errors=errors,
        position=position,
        configured_address=station if station is not None else 0,
        alias=alias if alias is not None else sii.word(SII_ALIAS),
        state=state_name(al_state),
        al_status_code=al_code,
        al_status=al_status_name(al_code) if al_code or al_state & AL_ERROR else "no error",
        mailbox_protocols=[n for bit, n in MAILBOX_PROTOCOLS.items() if protocols & bit],
        coe_details=[n for bit, n in COE_DETAIL_NAMES.items() if coe_details & bit],
        sdo_info=bool(protocols & 0x04 and coe_details & 0x02),
        dc=bool(features is not None and features & FEATURE_DC),
        open_ports=[p for p in range(4) if dl_status is not None and dl_status >> (9 + 2 * p) & 1],
        sync_managers=_sync_managers(cats.get(CAT_SM, b"")),
    )
    if protocols & 0x04:
        _coe(s, out, use_info and out.sdo_info)
    else:
        out.rpdo = _sii_pdos(cats.get(CAT_RXPDO, b""), strings)
        out.tpdo = _sii_pdos(cats.get(CAT_TXPDO, b""), strings)
        out.mapping_source = "sii" if out.rpdo or out.tpdo else "none"
    return out


def _reg(s: Any, address: int, n: int, errors: list[str], *, full: bool = False) -> int | None:
    from fieldbus.backends.ecat_master import read_register

    raw = read_register(s, address, n)
    if raw is None:
        errors.append(f"register 0x{address:04X}: no answer")
        return None
    return int.from_bytes(raw, "little") if full or n <= 4 else int.from_bytes(raw[:4], "little")


def _sync_managers(data: bytes) -> list[SyncManagerSii]:
    out = []
    for k in range(len(data) // 8):
        start, length, control, _status, enable, kind = struct.unpack_from("<HHBBBB", data, 8 * k)
        out.append(SyncManagerSii(k, start, length, control, enable, SM_TYPES.get(kind, f"type {kind}")))
    return out


def _sii_pdos(data: bytes, strings: list[str]) -> list[ScannedPdo]:
    """PDOs of an SII TxPDO/RxPDO category: 8-byte PDO header, 8-byte entries (ETG.2010)."""
    pdos: list[ScannedPdo] = []
    pos = 0
    while pos + 8 <= len(data):
        index, n, _sm, _dc, _name, _flags = struct.unpack_from("<HBBBBH", data, pos)
        pos += 8
        entries = []
        for _ in range(n):
            if pos + 8 > len(data):
                break
            eidx, esub, ename, etype, ebits, _ef = struct.unpack_from("<HBBBBH", data, pos)
            pos += 8
            tname, source = entry_type(eidx, esub, ebits, etype or None)
            text = strings[ename - 1] if 0 < ename <= len(strings) else None
            entries.append(
                PdoEntry(eidx, esub, ebits, tname, entry_name(eidx, esub, text), "sii" if etype else source)
            )
        pdos.append(ScannedPdo(index, entries))
    return pdos


def _coe(s: Any, out: EthercatSlave, use_info: bool) -> None:
    def read(index: int, sub: int) -> bytes:
        return sdo_read(s, out.position, index, sub)

    def u(index: int, sub: int) -> int:
        return int.from_bytes(read(index, sub), "little")

    try:
        serial = u(0x1018, 4)
        out.identity.serial = serial or out.identity.serial
    except FieldbusError as exc:
        out.errors.append(str(exc))
    for what, call in (
        ("device_type", lambda: u(0x1000, 0)),
        ("device_name", lambda: c_string(read(0x1008, 0))),
    ):
        try:
            setattr(out, what, call())
        except FieldbusError as exc:
            out.errors.append(str(exc))
    try:
        for assign, target in ((RXPDO_ASSIGN, out.rpdo), (TXPDO_ASSIGN, out.tpdo)):
            for k in range(1, u(assign, 0) + 1):
                pdo = u(assign, k)
                raws = [u(pdo, e) for e in range(1, u(pdo, 0) + 1)]
                target.append(
                    ScannedPdo(
                        pdo, [PdoEntry(*mapping_entry(r), *entry_type(*mapping_entry(r)), "") for r in raws]
                    )
                )
        out.mapping_source = "coe"
    except FieldbusError as exc:
        out.errors.append(f"PDO mapping: {exc}")
        out.rpdo, out.tpdo = [], []
        return
    wanted = {(e.index, e.sub_index) for p in out.rpdo + out.tpdo for e in p.entries}
    config = {(RXPDO_ASSIGN, 0), (TXPDO_ASSIGN, 0)} | {(p.index, 0) for p in out.rpdo + out.tpdo}
    described = _describe(s, wanted | config, out) if use_info else {}
    for p in out.rpdo + out.tpdo:
        for e in p.entries:
            code, name, _ = described.get((e.index, e.sub_index), (None, None, None))
            e.type, e.source = entry_type(e.index, e.sub_index, e.bits, code)
            e.name = entry_name(e.index, e.sub_index, name)

    def read_only(key: tuple[int, int]) -> bool:
        access = described.get(key, (None, None, None))[2]
        return access is not None and not access & ACCESS_WRITE_PREOP

    for p in out.rpdo + out.tpdo:
        p.fixed = read_only((p.index, 0))
    outside = any(
        not lo <= p.index <= hi
        for (lo, hi), pdos in (
            (COE_RANGES[Direction.OUTPUTS], out.rpdo),
            (COE_RANGES[Direction.INPUTS], out.tpdo),
        )
        for p in pdos
    )
    out.assign_fixed = outside or read_only((RXPDO_ASSIGN, 0)) or read_only((TXPDO_ASSIGN, 0))


def _describe(
    s: Any, wanted: set[tuple[int, int]], out: EthercatSlave
) -> dict[tuple[int, int], tuple[int, str, int | None]]:
    """(CoE data type, name, access bits or None) of objects from SDO Information (pysoem's ``slave.od``)."""
    from fieldbus.backends.ecat_master import object_dictionary

    if not out.sdo_info or not wanted:
        return {}
    indices = {i for i, _ in wanted if i > 0x0007}
    found: dict[tuple[int, int], tuple[int, str, int | None]] = {}
    try:
        for obj, entries in object_dictionary(s, indices):
            if not entries:
                found[(obj.index, 0)] = (int(obj.data_type), c_string(obj.name), None)
                continue
            for sub, e in enumerate(entries):
                if (obj.index, sub) in wanted:
                    found[(obj.index, sub)] = (int(e.data_type), c_string(e.name), int(e.obj_access))
    except FieldbusError as exc:
        out.errors.append(str(exc))
    return found


def c_string(raw: Any) -> str:
    data = raw if isinstance(raw, bytes) else str(raw).encode("latin-1", "replace")
    return data.split(b"\0", 1)[0].decode("latin-1").strip()


def _topology(slaves: list[EthercatSlave]) -> None:
    """Parents from the open-port counts, walking back as SOEM does (a line: the previous slave)."""
    for i, s in enumerate(slaves):
        h = 0
        s.parent = None
        for j in range(i - 1, -1, -1):
            ports = len(slaves[j].open_ports)
            h += {1: -1, 3: 1, 4: 2}.get(ports, 0)
            if h >= 0:
                s.parent = j
                break
