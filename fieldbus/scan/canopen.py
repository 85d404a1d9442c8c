"""Scan a CAN bus for CANopen nodes: who answers, identity, device type and name, PDO parameters.

A node is found by its boot-up or heartbeat (0x700 + id) while the scan
listens, else by an SDO upload of 0x1000 sent to every other id 1..127 at
once (any answer, an abort too, means a node). Then every node is read by
SDO - identity 0x1018, device type 0x1000, name 0x1008, heartbeat 0x1017,
PDO communication 0x1400../0x1800.. and mapping 0x1600../0x1A00.. - with
all nodes' transfers in flight together: each node runs the project's
sans-IO SDO client (:mod:`fieldbus.core.sdo.canopen_client`), one transfer at a time
per node as CiA 301 requires. Nothing is written; no NMT command is sent.
"""

from __future__ import annotations

import struct
import time
from collections.abc import Generator
from dataclasses import dataclass, field
from typing import Any

from fieldbus.core.sdo.canopen_client import sdo_upload
from fieldbus.errors import BackendUnavailableError, BusTimeoutError, FieldbusError, SdoAbortError
from fieldbus.scan.model import Device, Identity, PdoEntry, ScannedPdo, entry_name, entry_type, mapping_entry

COB_TSDO, COB_RSDO, COB_HEARTBEAT = 0x580, 0x600, 0x700
ABORT_NO_OBJECT = 0x06020000
ABORT_TIMEOUT = 0x05040000
NMT_STATES = {0x00: "BOOT-UP", 0x04: "STOPPED", 0x05: "OPERATIONAL", 0x7F: "PRE-OPERATIONAL"}
MAX_PDOS = 512  # CiA 301: 0x1400-0x15FF / 0x1800-0x19FF
COB_INVALID = 0x80000000

Job = Generator[bytes, bytes, Any]  # yields SDO requests, is sent the answers


@dataclass
class CanopenNodeInfo(Device):
    node_id: int = 0
    seen: str = "sdo"  # "boot-up" | "heartbeat" | "sdo"
    nmt_state: str | None = None  # from its heartbeat, when one was seen
    heartbeat_ms: int | None = None


@dataclass
class CanopenScan:
    channel: str
    interface: str
    nodes: list[CanopenNodeInfo] = field(default_factory=list)


def open_bus(channel: str, interface: str, bitrate: int | None) -> Any:
    try:
        import can
    except ImportError as exc:
        raise BackendUnavailableError(
            f"scanning CANopen needs python-can ({exc}): pip install 'fieldbus[canopen]'"
        ) from None
    try:
        return can.Bus(interface=interface, channel=channel, bitrate=bitrate)
    except Exception as exc:
        raise FieldbusError(f"cannot open {interface} channel {channel}: {exc}") from exc


class SdoRunner:
    """Runs SDO jobs for many nodes at once on one python-can bus (one transfer per node in flight)."""

    def __init__(self, bus: Any, timeout_s: float) -> None:
        import can

        self._can = can
        self.bus = bus
        self.timeout_s = timeout_s
        self.heard: dict[int, tuple[str, int]] = {}  # node -> ("boot-up"/"heartbeat", state byte)

    def send(self, node: int, data: bytes) -> None:
        msg = self._can.Message(arbitration_id=COB_RSDO + node, data=data, is_extended_id=False)
        for _ in range(100):  # a socketcan queue may be full for a moment (ENOBUFS)
            try:
                self.bus.send(msg)
                return
            except self._can.CanOperationError:
                time.sleep(0.001)
        self.bus.send(msg)

    def listen(self, seconds: float) -> None:
        """Note boot-ups and heartbeats for ``seconds``."""
        end = time.monotonic() + seconds
        while (left := end - time.monotonic()) > 0:
            msg = self.bus.recv(timeout=left)
            if msg is not None:
                self._note(msg)

    def _note(self, msg: Any) -> None:
        cob = msg.arbitration_id
        if not msg.is_extended_id and COB_HEARTBEAT < cob <= COB_HEARTBEAT + 127 and len(msg.data) >= 1:
            state = msg.data[0] & 0x7F
            self.heard[cob - COB_HEARTBEAT] = ("boot-up" if state == 0 else "heartbeat", state)

    def run(self, jobs: dict[int, Job]) -> dict[int, Any]:
        """Each job's return value (or the exception that ended it), by node id."""
        results: dict[int, Any] = {}
        waiting: dict[int, tuple[bytes, float]] = {}  # node -> (request, deadline)

        def advance(node: int, step: Any) -> None:
            try:
                req = step()
            except StopIteration as stop:
                results[node] = stop.value
                waiting.pop(node, None)
                return
            except FieldbusError as exc:
                results[node] = exc
                waiting.pop(node, None)
                return
            waiting[node] = (req, time.monotonic() + self.timeout_s)
            self.send(node, req)

        for node, job in jobs.items():
            advance(node, lambda job=job: next(job))
        while waiting:
            now = time.monotonic()
            for node, (req, deadline) in list(waiting.items()):
                if deadline <= now:
                    if req[0] >> 5 in (0, 3):  # inside a segmented transfer: tell the node
                        self.send(node, b"\x80" + req[1:4] + struct.pack("<I", ABORT_TIMEOUT))
                    err = BusTimeoutError(f"node {node}: no SDO answer within {self.timeout_s * 1e3:.0f} ms")
                    advance(node, lambda job=jobs[node], err=err: job.throw(err))
            if not waiting:
                break
            msg = self.bus.recv(timeout=max(0.0, min(d for _, d in waiting.values()) - time.monotonic()))
            if msg is None or msg.is_extended_id:
                continue
            node = msg.arbitration_id - COB_TSDO
            if node in waiting and len(msg.data) == 8:
                data = bytes(msg.data)
                advance(node, lambda job=jobs[node], data=data: job.send(data))
            else:
                self._note(msg)
        return results


def scan(
    channel: str,
    interface: str = "socketcan",
    bitrate: int | None = None,
    *,
    can_bus: Any = None,
    listen_s: float = 0.3,
    probe_timeout_s: float = 0.1,
    sdo_timeout_s: float = 0.5,
    nodes: range = range(1, 128),
) -> CanopenScan:
    """Find the nodes on ``channel`` and read each one (see the module docstring)."""
    bus = can_bus if can_bus is not None else open_bus(channel, interface, bitrate)
    try:
        probe = SdoRunner(bus, probe_timeout_s)
        probe.listen(listen_s)
        asked = {n: sdo_upload(0x1000, 0) for n in nodes if n not in probe.heard}
        answered = probe.run(asked)
        found = sorted(
            {n for n in probe.heard if n in nodes}
            | {n for n, r in answered.items() if not isinstance(r, BusTimeoutError)}
        )
        reader = SdoRunner(bus, sdo_timeout_s)
        reader.heard = probe.heard
        results = reader.run({n: _read_node(n) for n in found})
    finally:
        if can_bus is None:
            bus.shutdown()
    out = CanopenScan(channel, interface)
    for n in found:
        info = results[n]
        if isinstance(info, Exception):  # the job catches per object; this is a bug guard
            info = CanopenNodeInfo(
                name=f"node{n}", identity=Identity(0, 0, 0, 0), node_id=n, errors=[str(info)]
            )
        heard = reader.heard.get(n)
        if heard is not None:
            info.seen = heard[0]
            info.nmt_state = NMT_STATES.get(heard[1], f"0x{heard[1]:02X}")
        out.nodes.append(info)
    return out


def _read_node(node: int) -> Generator[bytes, bytes, CanopenNodeInfo]:
    """One node's reads, in order; an abort or timeout on one object is noted and the rest go on."""
    errors: list[str] = []

    def u(index: int, sub: int) -> Generator[bytes, bytes, int | None]:
        raw = yield from read(index, sub)
        return None if raw is None else int.from_bytes(raw, "little")

    def read(index: int, sub: int, *, note: bool = True) -> Generator[bytes, bytes, bytes | None]:
        try:
            return (yield from sdo_upload(index, sub))
        except SdoAbortError as exc:
            if note:
                errors.append(f"node {node}: 0x{index:04X}:{sub:02X}: abort 0x{exc.code:08X} {exc.name}")
            return None
        except BusTimeoutError as exc:
            errors.append(f"0x{index:04X}:{sub:02X}: {exc}")
            return None

    ident = []
    for sub in (1, 2, 3, 4):
        ident.append((yield from u(0x1018, sub)) or 0)
    device_type = yield from u(0x1000, 0)
    name_raw = yield from read(0x1008, 0, note=False)
    name = name_raw.split(b"\0", 1)[0].decode("latin-1").strip() if name_raw else None
    heartbeat = yield from u(0x1017, 0)
    info = CanopenNodeInfo(
        name=name or f"node{node}",
        identity=Identity(*ident),
        device_type=device_type,
        device_name=name,
        errors=errors,
        node_id=node,
        heartbeat_ms=heartbeat,
    )
    for comm_base, map_base, target, tpdo in (
        (0x1400, 0x1600, info.rpdo, False),
        (0x1800, 0x1A00, info.tpdo, True),
    ):
        for k in range(MAX_PDOS):
            cob = yield from read(comm_base + k, 1, note=False)
            if cob is None:
                break  # no more PDOs (0x06020000), or the node does not say
            cob_id = int.from_bytes(cob, "little")
            pdo = ScannedPdo(map_base + k, [], cob_id=cob_id & 0x1FFFFFFF, enabled=not cob_id & COB_INVALID)
            pdo.transmission_type = yield from u(comm_base + k, 2)
            if tpdo:
                pdo.inhibit_time = yield from u(comm_base + k, 3)
                pdo.event_timer = yield from u(comm_base + k, 5)
            count = yield from u(map_base + k, 0)
            for sub in range(1, (count or 0) + 1):
                raw = yield from u(map_base + k, sub)
                if raw is None:
                    continue
                index, esub, bits = mapping_entry(raw)
                tname, source = entry_type(index, esub, bits)
                pdo.entries.append(PdoEntry(index, esub, bits, tname, entry_name(index, esub, None), source))
            target.append(pdo)
    return info
