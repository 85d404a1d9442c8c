"""EtherCAT backend on pysoem (SOEM inside).

Bring-up: ``config_init`` and an identity check against the maps; in PRE-OP
each slave's CoE SDO plan is written and read back; ``config_map`` and a size
check against our layout; SAFE-OP (each slave's SyncManager and FMMU
registers kept for recovery); OP, confirmed by the working counter.

Cycle: outputs are copied per slave from its process-image row into SOEM's IO map (pysoem exposes each
slave's area only as ``bytes``: a transient copy, nothing kept), one LRW is
sent, the reply is awaited for at most the bus's receive timeout with the GIL
released, inputs are copied back into the slaves' rows of the process images.

Recovery (like SOEM's ``ecatcheck``) is a generator advanced by the cycle one
pysoem call or one frame at a time, after a miss and while a slave is known
not to be in OP; a power-cycled slave is configured again step by step (SOEM's
``reconfig`` sequence, split), see docs/backends.md.
"""

from __future__ import annotations

import contextlib
import functools
import time
from collections import deque
from collections.abc import Generator
from typing import Any

from fieldbus.backends import soem_socket
from fieldbus.backends.base import Backend, SdoRequest
from fieldbus.backends.buslock import InterfaceLock, lock_network_card, release_all
from fieldbus.backends.sdo_exec import apply_plan, plan_transfers, retried
from fieldbus.core.al import AL_ACK, AL_ERROR, AL_INIT, AL_OP, AL_PREOP, AL_SAFEOP, al_status_name, state_name
from fieldbus.core.dc.master import HostSync, HostSyncConfig
from fieldbus.core.network import Bus
from fieldbus.core.sdo import coe_plan
from fieldbus.core.wkc import Recovery, recovery_action
from fieldbus.errors import (
    BackendUnavailableError,
    BusTimeoutError,
    FieldbusError,
    SdoAbortError,
    StateTransitionError,
)
from fieldbus.wire.pcap import EthercatCapture

try:
    import pysoem
except ImportError as exc:  # pragma: no cover - depends on the install
    raise BackendUnavailableError(
        f"the ethercat backend needs pysoem ({exc}): pip install 'fieldbus[ethercat]'"
    ) from None

STATE_TIMEOUT_US = 2_000_000
RECONFIG_TIMEOUT_US = 500
SYNC1_ACTIVATE = 0x0400  # assign_activate bit: SYNC1 generation (0x0981 bit 2)
HOST_OFFSET_FRACTION = 50  # host sends this % of a cycle after each SYNC0 (SOEM examples: 50 %)
SDO_RETRIES = 2  # an SDO without answer (not an abort) is tried this many more times
MAX_EMERGENCIES = 1000  # emergencies kept (oldest dropped)
REDUNDANT_SLACK_US = 200  # a reply handed over this long past the timeout is still in time (redundant port)
ACYCLIC_SDO_TIMEOUT_US = 3000  # SOEM's mailbox timeout for an SDO served in the cycle (default 700 ms)
PLAN_RETRY_S = 1.0  # a slave whose reconfiguration failed is tried again after this
RECOVERY_FRAME_TIMEOUT_US = 1000  # one register read/write during recovery (a lost frame costs this)
RECOVERY_FRAME_TRIES = 4  # a register write whose reply is lost or late is sent again, one try per cycle
# SOEM's mailbox timeout for one of the plan's SDOs during recovery (default 700 ms): the cycle that
# carries it waits at most this long; a transfer without answer is sent again next cycle
RECOVERY_SDO_TIMEOUT_US = 3_000
RECOVERY_SDO_TRIES = 4
STATE_POLL_STEPS = 200  # cycles a reconfigured slave may take to reach a state
SNAPSHOT_TIMEOUT_US = 20_000
SM_SNAPSHOT, FMMU_SNAPSHOT = 8, 4  # SyncManagers and FMMUs kept per slave (SOEM: EC_MAXSM, EC_MAXFMMU)
REG_FMMU0, REG_SM0 = 0x0600, 0x0800
REG_AL_CONTROL, REG_AL_STATUS, REG_EEPROM_CONFIG = 0x0120, 0x0130, 0x0500


class EthercatBackend(Backend):
    """One EtherCAT segment on one network card (``interface`` in the network file).

    Options: ``exact_timeout`` (default True: SOEM's packet socket non-blocking,
    so a lost frame costs the receive timeout, not a scheduler tick; False
    keeps SOEM's blocking wait).
    """

    kind = "ethercat"
    _locks: tuple[InterfaceLock, ...] = ()  # one per network card, held from open() to close()

    def __init__(self, bus: Bus, **options: object) -> None:
        super().__init__(bus, **options)
        if not bus.interface:
            raise FieldbusError(f"bus '{bus.name}': an ethercat bus needs 'interface'")
        self.master: Any = pysoem.Master()
        self._slaves: list[Any] = []
        self._open = False
        self._timeout_us = bus.receive_timeout_us
        self._timeout_ns = bus.receive_timeout_us * 1000
        self._sent_ns = 0
        self._host_sync: HostSync | None = None
        self._dc_correction = 0
        self.late_replies = 0  # replies that came back, but later than the receive timeout
        self._out_views: list[tuple[Any, memoryview]] = []
        self._in_views: list[tuple[Any, memoryview]] = []
        # exact receive timeout: SOEM's socket non-blocking (option exact_timeout, default on)
        self._exact_timeout = bool(options.get("exact_timeout", True))
        pcap = options.get("pcap")  # every EtherCAT frame of the card, both directions, to this pcap file
        self.capture = EthercatCapture(str(pcap), bus.interface) if pcap else None
        # With a redundant port and the ring open (a cable cut: the usual reason to have one), SOEM
        # waits for both ports until its timer ends, so a good reply is handed over at the timeout,
        # a few µs past it. The non-blocking socket still ends that wait at SOEM's timer; the slack
        # only keeps such a reply from being judged late.
        if bus.redundant_interface and self._exact_timeout:
            self._late_ns = self._timeout_ns + REDUNDANT_SLACK_US * 1000
        else:
            self._late_ns = self._timeout_ns
        self.sockets: list[int] = []  # SOEM's AF_PACKET socket(s), found at open()
        # A reply later than its timeout must not be taken for a later frame's: SOEM matches replies by
        # frame index only (16 of them), so a frame still queued when a cycle starts is discarded.
        self.stale_frames = 0
        self._drain_buf = [bytearray(soem_socket.MAX_FRAME)]
        self._sdo_tries = SDO_RETRIES + 1  # tries per SDO (1 during recovery: no cycle waits for retries)
        self._retry_at = [0.0] * self.n_slaves  # monotonic s: a slave whose reconfiguration failed waits
        self._sm_regs: list[list[tuple[int, bytes]]] = []  # per slave: (register, bytes) to write again
        self._fmmu_regs: list[list[tuple[int, bytes]]] = []
        # (slave, error code, error register) seen in SDO answers, newest last
        self.emergencies: deque[tuple[int, int, int]] = deque(maxlen=MAX_EMERGENCIES)

    # -- bring-up ----------------------------------------------------------------
    def open(self) -> None:
        """Lock the NIC(s) (:class:`~fieldbus.errors.InterfaceInUseError` when another master has one),
        open them (and find SOEM's packet socket: see :mod:`.soem_socket`), find the slaves."""
        if not self._locks:
            locks: list[InterfaceLock] = []
            try:
                for card in (self.bus.interface, self.bus.redundant_interface):
                    if card:
                        locks.append(lock_network_card(card))
            except BaseException:
                release_all(locks)
                raise
            self._locks = tuple(locks)
        if self.capture is not None:
            self.capture.start()
        before = soem_socket.open_sockets()
        try:
            self.master.open(self.bus.interface, self.bus.redundant_interface)
        except Exception as exc:
            cards = " and ".join(f"'{p}'" for p in (self.bus.interface, self.bus.redundant_interface) if p)
            raise FieldbusError(
                f"bus '{self.bus.name}': cannot open interface {cards} ({exc}); "
                "raw sockets need root (or CAP_NET_RAW) and the link must be up"
            ) from exc
        self._open = True
        self.sockets = soem_socket.packet_sockets(soem_socket.open_sockets() - before)
        ports = 2 if self.bus.redundant_interface else 1  # one packet socket per port
        if self._exact_timeout and len(self.sockets) != ports:
            raise FieldbusError(
                f"bus '{self.bus.name}': {len(self.sockets)} new packet sockets after opening "
                f"'{self.bus.interface}', SOEM opens {ports}; "
                "pass exact_timeout=False to keep SOEM's own receive wait (a lost frame then costs 4-10 ms)"
            )
        found = self.master.config_init()
        self._slaves = list(self.master.slaves) if found > 0 else []
        self._check_identity(found)

    def _check_identity(self, found: int) -> None:
        self.check_identities(
            [(s.name, s.man, s.id) for s in self._slaves[: max(found, 0)]], f"on {self.bus.interface}"
        )

    def configure(self) -> None:
        state = self.master.state_check(pysoem.PREOP_STATE, STATE_TIMEOUT_US)
        if state != pysoem.PREOP_STATE:
            self._raise_state("PRE-OP", state)
        for i, area in enumerate(self.areas):
            plan = coe_plan(area.slave.map)
            if plan.steps:
                apply_plan(plan, *self.plan_io(i), slave=area.slave.name)

    def safe_op(self) -> None:
        try:
            self.master.config_map()
        except pysoem.ConfigMapError as exc:
            raise StateTransitionError(
                f"bus '{self.bus.name}': SOEM could not map process data: {exc}"
            ) from None
        problems = []
        for i, (area, s) in enumerate(zip(self.areas, self._slaves, strict=True)):
            out_len, in_len = len(s.output), len(s.input)
            if (out_len, in_len) != (area.out_size, area.in_size):
                problems.append(
                    f"  position {i} ({area.slave.name}): SOEM mapped {out_len} output / {in_len} input bytes, "
                    f"the map implies {area.out_size} / {area.in_size}"
                )
        if problems:
            raise StateTransitionError(
                f"bus '{self.bus.name}': process data sizes differ from the maps:\n" + "\n".join(problems)
            )
        if self.master.expected_wkc != self.expected_wkc:
            raise StateTransitionError(
                f"bus '{self.bus.name}': SOEM expects WKC {self.master.expected_wkc}, our layout {self.expected_wkc}"
            )
        self._out_views = [
            (s, self.out_row(i).data) for i, s in enumerate(self._slaves) if self.areas[i].out_size
        ]
        self._in_views = [
            (s, self.in_row(i).data) for i, s in enumerate(self._slaves) if self.areas[i].in_size
        ]
        self._configure_dc()
        state = self.master.state_check(pysoem.SAFEOP_STATE, STATE_TIMEOUT_US)
        if state != pysoem.SAFEOP_STATE:
            self._raise_state("SAFE-OP", state)
        self._snapshot_registers()

    def _snapshot_registers(self) -> None:
        """Keep each slave's SyncManager and FMMU registers as SOEM programmed them (SAFE-OP).

        A power-cycled slave is configured again from these (:meth:`_reconfigure`),
        step by step, instead of SOEM's ``reconfig`` - one long call. Only
        enabled entries (SM with a start address, FMMU with its activate bit);
        the SM status and PDI-control bytes are read-only and written as 0.
        """
        self._sm_regs, self._fmmu_regs = [], []
        for s in self._slaves:
            sm = s._fprd(REG_SM0, SM_SNAPSHOT * 8, SNAPSHOT_TIMEOUT_US)
            fmmu = s._fprd(REG_FMMU0, FMMU_SNAPSHOT * 16, SNAPSHOT_TIMEOUT_US)
            self._sm_regs.append(
                [
                    (REG_SM0 + 8 * k, sm[8 * k : 8 * k + 5] + b"\0" + sm[8 * k + 6 : 8 * k + 7] + b"\0")
                    for k in range(SM_SNAPSHOT)
                    if sm[8 * k : 8 * k + 2] != b"\0\0"
                ]
            )
            self._fmmu_regs.append(
                [
                    (REG_FMMU0 + 16 * k, fmmu[16 * k : 16 * k + 16])
                    for k in range(FMMU_SNAPSHOT)
                    if fmmu[16 * k + 12] & 1
                ]
            )

    def _configure_dc(self) -> None:
        """DC for maps with ``assign_activate``: ``config_dc``, then SYNC0 (and SYNC1) per slave.

        SYNC0 cycle = the bus cycle; shift and SYNC1 from the map's ``ethercat``
        section. The host loop then follows DC time (:meth:`dc_correction_ns`).
        """
        dc_slaves = [i for i, a in enumerate(self.areas) if a.slave.map.assign_activate]
        if not dc_slaves:
            return
        if not self.master.config_dc():
            names = ", ".join(self.areas[i].slave.name for i in dc_slaves)
            raise StateTransitionError(
                f"bus '{self.bus.name}': maps ask for DC ({names}) but no slave has DC"
            )
        cycle_ns = self.bus.cycle_time_us * 1000
        for i in dc_slaves:
            m = self.areas[i].slave.map
            sync1 = m.ethercat.sync1_cycle_ns if m.assign_activate & SYNC1_ACTIVATE else None
            self._slaves[i].dc_sync(True, cycle_ns, m.ethercat.sync0_shift_ns, sync1)
        self._host_sync = HostSync(
            HostSyncConfig(cycle_ns=cycle_ns, offset_ns=HOST_OFFSET_FRACTION * cycle_ns // 100)
        )

    def _reconfigure(self, i: int) -> Generator[None, None, None]:
        """Slave ``i`` from INIT/PRE-OP back to SAFE-OP, one frame or one SDO per step.

        The sequence of SOEM's ``ecx_reconfig_slave`` (INIT, EEPROM to PDI, the
        SyncManagers, PRE-OP, the SDO plan - written, then read back - SAFE-OP,
        the FMMUs), split so that no cycle waits for more than one of them. A
        failure (an SDO abort, a state that is not reached) puts the slave back
        to INIT and raises: it never runs with a mapping the network did not write.
        """
        s, area = self._slaves[i], self.areas[i]
        t = RECOVERY_FRAME_TIMEOUT_US
        step = "INIT request"
        try:
            yield from self._write(i, REG_AL_CONTROL, bytes([AL_INIT | AL_ACK, 0]))
            step = "waiting for INIT"
            yield from self._await_state(i, AL_INIT)
            step = "EEPROM to PDI"
            yield from self._write(i, REG_EEPROM_CONFIG, b"\x01")  # EEPROM to PDI, as SOEM does
            for address, data in self._sm_regs[i]:
                step = f"SyncManager register 0x{address:04X}"
                yield from self._write(i, address, data)
            step = "PRE-OP request"
            yield from self._write(i, REG_AL_CONTROL, bytes([AL_PREOP, 0]))
            step = "waiting for PRE-OP"
            yield from self._await_state(i, AL_PREOP)
            step = "SDO plan"
            m = self.master
            saved = m.sdo_read_timeout, m.sdo_write_timeout, self._sdo_tries
            m.sdo_read_timeout = m.sdo_write_timeout = RECOVERY_SDO_TIMEOUT_US
            self._sdo_tries = 1
            try:
                yield from plan_transfers(
                    coe_plan(area.slave.map),
                    *self.plan_io(i),
                    slave=area.slave.name,
                    tries=RECOVERY_SDO_TRIES,
                )
            finally:
                m.sdo_read_timeout, m.sdo_write_timeout, self._sdo_tries = saved
            step = "SAFE-OP request"
            yield from self._write(i, REG_AL_CONTROL, bytes([AL_SAFEOP, 0]))
            step = "waiting for SAFE-OP"
            yield from self._await_state(i, AL_SAFEOP)
            for address, data in self._fmmu_regs[i]:
                step = f"FMMU register 0x{address:04X}"
                yield from self._write(i, address, data)
        except Exception as exc:
            self._retry_at[i] = time.monotonic() + PLAN_RETRY_S
            with contextlib.suppress(Exception):
                s._fpwr(REG_AL_CONTROL, bytes([AL_INIT | AL_ACK, 0]), t)
            raise StateTransitionError(
                f"bus '{self.bus.name}': position {i} ({area.slave.name}) could not be configured again after "
                f"falling out of OP, left in INIT (next try in {PLAN_RETRY_S:g} s): {step}: {_describe(exc)}"
            ) from exc

    def _write(self, i: int, address: int, data: bytes) -> Generator[None, None, None]:
        """One register write to slave ``i``, then a step; a lost or late reply is sent again next step.

        Every register written during recovery is idempotent (AL control, EEPROM
        owner, SM and FMMU entries), so a repeat is safe, as in SOEM's own
        ``ecx_FPWRw``, which repeats a frame until its (longer) timeout.
        """
        fpwr = functools.partial(self._slaves[i]._fpwr, address, data, RECOVERY_FRAME_TIMEOUT_US)
        yield from retried(fpwr, RECOVERY_FRAME_TRIES, (pysoem.WkcError, pysoem.PacketError))
        yield

    def _await_state(self, i: int, state: int) -> Generator[None, None, None]:
        """Read slave ``i``'s AL status once per step until it shows ``state``; give up after a while.

        A read without answer (lost or late frame) counts as one poll that did not see it yet.
        """
        for _ in range(STATE_POLL_STEPS):
            got = self._al_status(i)
            if got is None:
                yield
                continue
            if got & 0x0F == state:
                return
            if got & AL_ERROR and state != AL_INIT:
                raise StateTransitionError(f"{state_name(got)} instead of {state_name(state)}")
            yield
        raise BusTimeoutError(f"did not reach {state_name(state)} within {STATE_POLL_STEPS} cycles")

    def op(self) -> None:
        """OP, confirmed by the working counter. From here on SOEM's socket is non-blocking (exact_timeout).

        Bring-up keeps SOEM's blocking wait: its many state, SII and mailbox
        exchanges then tolerate a slow answer (the wait is at least a tick),
        where the cycle wants the timeout to be exact.
        """
        if self._exact_timeout:
            for fd in self.sockets:
                soem_socket.set_nonblocking(fd)
        for _ in range(3):  # valid outputs before OP, so no watchdog trips on the way
            self.send()
            self.receive()
        self.master.state = pysoem.OP_STATE
        self.master.write_state()
        for _ in range(200):
            self.send()
            self.receive()
            if self.master.state_check(pysoem.OP_STATE, 10_000) == pysoem.OP_STATE:
                break
        else:
            self._raise_state("OP", self.master.read_state())
        self._confirm_wkc()

    def _raise_state(self, target: str, lowest: int) -> None:
        self.master.read_state()
        lines = []
        first_code: int | None = None
        for i, s in enumerate(self._slaves):
            if (s.state & 0x0F) != {"PRE-OP": 2, "SAFE-OP": 4, "OP": 8}[target] or s.state & AL_ERROR:
                code = s.al_status
                first_code = code if first_code is None else first_code
                lines.append(
                    f"  position {i} ({self.areas[i].slave.name if i < len(self.areas) else '?'}): "
                    f"{state_name(s.state)}, AL status code 0x{code:04X} {al_status_name(code)}"
                )
        raise StateTransitionError(
            f"bus '{self.bus.name}': not all slaves reached {target} (lowest {state_name(lowest)}):\n"
            + "\n".join(lines),
            al_status=first_code,
        )

    def slave_state(self, i: int) -> str:
        """Slave ``i``'s AL state as SOEM last read it (bring-up and recovery read it, the cycle does not)."""
        return state_name(int(self._slaves[i].state)) if i < len(self._slaves) else "-"

    # -- cycle ----------------------------------------------------------------------
    def send(self) -> None:
        """Outputs into SOEM's IO map, frames still queued from earlier cycles discarded, the LRW sent."""
        for s, mv in self._out_views:
            s.output = bytes(mv)
        if self._exact_timeout:
            self.stale_frames += soem_socket.drain(self.sockets, self._drain_buf)
        self._sent_ns = time.perf_counter_ns()
        self.master.send_processdata(release_gil=True)

    def receive(self) -> int | None:
        """The LRW's WKC, or None when no reply came back within the receive timeout.

        With SOEM's socket non-blocking (:mod:`.soem_socket`, the default) the
        wait ends at the timeout: measured on a dropped frame with a 500 µs
        timeout, p50 503 µs, max 537 µs (blocking: p50 5.1 ms, max 8.7 ms).
        A reply that still arrives later than the timeout after the send is
        judged here as a miss (counted in :attr:`late_replies`), inputs held.
        """
        wkc: int = self.master.receive_processdata(self._timeout_us, release_gil=True)
        self.late_wkc = None
        if wkc >= 0 and time.perf_counter_ns() - self._sent_ns > self._late_ns:
            self.late_replies += 1
            self.late_wkc, wkc = wkc, -1
        if self._host_sync is not None and wkc >= 0:
            dc = int(self.master.dc_time)
            self.dc_time_ns = dc
            self._dc_correction = self._host_sync.step(dc)
            self.dc_sync_error_ns = self._host_sync.delta_ns
        if wkc < 0:
            return None
        for s, mv in self._in_views:
            mv[:] = s.input
        return wkc

    def dc_correction_ns(self) -> int:
        """Correction for the next deadline from the host PI (SOEM's ec_sync), ns; 0 without DC."""
        c, self._dc_correction = self._dc_correction, 0
        return c

    def _recover(self) -> Generator[None, None, bool]:
        """SOEM's ecatcheck as steps of one frame (or one pysoem call); passes repeat until all are in OP.

        Each slave's AL status is read on its own (one FPRD per step) rather
        than with SOEM's ``read_state``, which reads every slave one by one
        when they differ - up to 5 ms for 12 slaves in one call. Runs in the
        cycle's thread on purpose: pysoem holds the GIL in its calls, so a
        monitor thread would stall the cycle at moments nobody chose.
        """
        worked = False
        while True:
            all_ok = True
            for i, s in enumerate(self._slaves):
                state = None if s.is_lost else self._al_status(i)
                yield
                action = recovery_action(state)
                if action is Recovery.NONE:
                    continue
                all_ok = False
                if action is Recovery.ACK_ERROR:
                    yield from self._write(i, REG_AL_CONTROL, bytes([AL_SAFEOP | AL_ACK, 0]))
                elif action is Recovery.REQUEST_OP:
                    yield from self._write(i, REG_AL_CONTROL, bytes([AL_OP, 0]))
                elif action is Recovery.RECONFIGURE:  # INIT/PRE-OP after a power cycle
                    if time.monotonic() < self._retry_at[i]:
                        continue  # its configuration failed a moment ago: not every cycle
                    yield from self._reconfigure(i)
                    yield from self._write(i, REG_AL_CONTROL, bytes([AL_OP, 0]))
                elif action is Recovery.RECOVER:  # silent at its address: find it by position (SOEM)
                    s.is_lost = s.recover(timeout=RECONFIG_TIMEOUT_US) <= 0
                yield
            if all_ok:
                self.recoveries += worked
                return True
            worked = True

    def _al_status(self, i: int) -> int | None:
        """Slave ``i``'s AL status register (one FPRD), None when it does not answer at its address."""
        try:
            raw = self._slaves[i]._fprd(REG_AL_STATUS, 2, RECOVERY_FRAME_TIMEOUT_US)
        except (pysoem.WkcError, pysoem.PacketError):
            return None
        return int.from_bytes(raw, "little")

    # -- shut-down --------------------------------------------------------------------
    def stop(self) -> None:
        self._recovery = None
        if self._open and self._slaves:
            self.master.state = pysoem.INIT_STATE
            self.master.write_state()

    def close(self) -> None:
        try:
            if self._open:
                self._open = False
                self.master.close()
        finally:
            try:
                if self.capture is not None:
                    time.sleep(0.01)  # the last replies reach the capture socket
                    self.capture.close()
            finally:
                locks, self._locks = self._locks, ()
                release_all(locks)

    # -- acyclic ------------------------------------------------------------------------
    def sdo_read(self, slave: int, index: int, sub_index: int) -> bytes:
        return self._sdo_read_sized(slave, index, sub_index, 0)

    def read_for_plan(self, slave: int, index: int, sub_index: int, size: int) -> bytes:
        return self._sdo_read_sized(slave, index, sub_index, size)

    def _sdo_read_sized(
        self, slave: int, index: int, sub_index: int, size: int, tries: int | None = None
    ) -> bytes:
        data: bytes = self._sdo(
            slave,
            index,
            sub_index,
            "read",
            lambda s: s.sdo_read(index, sub_index, size, release_gil=True),
            tries,
        )
        return data

    def sdo_write(self, slave: int, index: int, sub_index: int, data: bytes) -> None:
        self._sdo(
            slave, index, sub_index, "write", lambda s: s.sdo_write(index, sub_index, data, release_gil=True)
        )

    def acyclic_step(self, request: SdoRequest) -> bool:
        """An SDO asked for in OP, run in the cycle thread with SOEM's mailbox timeout cut to
        ``ACYCLIC_SDO_TIMEOUT_US`` and no retry, so it holds the cycle at most about that long.

        A drive slower than that to answer gets a :class:`BusTimeoutError` (ask again).
        """
        m = self.master
        saved = m.sdo_read_timeout, m.sdo_write_timeout
        m.sdo_read_timeout = m.sdo_write_timeout = ACYCLIC_SDO_TIMEOUT_US
        try:
            if request.data is None:
                request.finish(
                    self._sdo_read_sized(request.slave, request.index, request.sub_index, 0, tries=1)
                )
            else:
                data = request.data
                self._sdo(
                    request.slave,
                    request.index,
                    request.sub_index,
                    "write",
                    lambda s: s.sdo_write(request.index, request.sub_index, data, release_gil=True),
                    tries=1,
                )
                request.finish(None)
        except FieldbusError as exc:
            request.finish(error=exc)
        finally:
            m.sdo_read_timeout, m.sdo_write_timeout = saved
        return True

    def _sdo(
        self, slave: int, index: int, sub_index: int, what: str, call: Any, tries: int | None = None
    ) -> Any:
        """One SDO transfer with pysoem's errors turned into ours.

        An abort raises :class:`SdoAbortError` at once. No answer (pysoem
        ``WkcError``, a mailbox or packet error) is retried ``SDO_RETRIES``
        times - SDO transfers here are idempotent - then raised as
        :class:`BusTimeoutError`. An emergency that arrives in the mailbox
        instead of the answer is kept in :attr:`emergencies` and the transfer
        retried.
        """
        name = self.areas[slave].slave.name
        last = ""
        tries = self._sdo_tries if tries is None else tries
        for _ in range(tries):
            try:
                return call(self._slaves[slave])
            except pysoem.SdoError as exc:
                raise SdoAbortError(exc.abort_code, index=index, sub_index=sub_index, slave=name) from None
            except pysoem.Emergency as exc:
                self.emergencies.append((slave, exc.error_code, exc.error_reg))
                self.emcy_count += 1
                last = f"emergency 0x{exc.error_code:04X}"
            except (pysoem.WkcError, pysoem.MailboxError, pysoem.PacketError) as exc:
                last = f"{type(exc).__name__}: {getattr(exc, 'message', None) or exc}"
        raise BusTimeoutError(
            f"bus '{self.bus.name}' slave {name}: no answer to SDO {what} 0x{index:04X}:{sub_index:02X} "
            f"after {tries} {'try' if tries == 1 else 'tries'} ({last})"
        )


def _describe(exc: BaseException) -> str:
    """An exception as a reason: its message, or its type when it has none (pysoem's WkcError)."""
    text = str(exc)
    return (
        f"{type(exc).__name__}: {text}"
        if text
        else f"{type(exc).__name__} (no answer at the slave's address)"
    )
