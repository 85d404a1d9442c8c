"""EtherCAT backend on pysoem (SOEM inside).

Bring-up: ``config_init`` and an identity check against the maps; in PRE-OP
each slave's CoE SDO plan is written and read back; ``config_map`` and a size
check against our layout; SAFE-OP (each slave's SyncManager and FMMU
registers kept for recovery); OP, confirmed by the working counter.

Cycle: outputs are copied from the process images into SOEM's IO map, one
copy per axis group through a view of the map that :mod:`.soem_iomap` finds
and proves at SAFE-OP (option ``iomap="bytes"``, or a layout it cannot prove:
per slave through pysoem's ``bytes`` setters and getters), one LRW is sent,
the reply is awaited for at most the bus's receive timeout with the GIL
released, inputs are copied back into the groups' receive rows the same way.

Recovery (like SOEM's ``ecatcheck``) is a generator advanced by the cycle one
datagram at a time, after a miss and while a slave is known not to be in OP; a
power-cycled slave is found again by position (SOEM's ``recover``, split: see
:mod:`.ecat_raw`) and configured again step by step (SOEM's ``reconfig``
sequence, split), see docs/backends.md.

Bounded steps: in OP no pysoem call that waits longer than one reply is made.
Each cycle sends its LRW and at most one other datagram (a recovery step or a
step of an SDO transfer, :mod:`.ecat_mailbox`), which waits at most
``frame_timeout_us`` (the bus's receive timeout, at most 1 ms by default,
below SOEM's ``EC_TIMEOUTRET``, 2 ms, so SOEM sends it once); so one ``exchange()``
waits at most the receive timeout plus that. docs/reliability.md, "Bounded steps".
"""

from __future__ import annotations

import functools
import struct
import time
from collections import deque
from collections.abc import Callable, Generator
from typing import Any

import numpy as np
import numpy.typing as npt

from fieldbus.backends import soem_iomap, soem_socket
from fieldbus.backends.base import Backend, SdoRequest
from fieldbus.backends.buslock import InterfaceLock, lock_network_card, release_all
from fieldbus.backends.ecat_mailbox import MailboxLayout, SlaveMailbox
from fieldbus.backends.ecat_master import (  # raises BackendUnavailableError without pysoem
    SoemPort,
    check_state,
    describe,
    find_slaves,
    open_card,
    pysoem,
    read_register,
    request_state,
    sdo,
    state_error,
)
from fieldbus.backends.ecat_raw import RawDatagrams
from fieldbus.backends.sdo_exec import apply_plan
from fieldbus.core import kernels
from fieldbus.core.al import AL_ACK, AL_ERROR, AL_INIT, AL_OP, AL_PREOP, AL_SAFEOP, state_name
from fieldbus.core.coe_mailbox import SdoTransfer
from fieldbus.core.dc.master import HostSync, HostSyncConfig
from fieldbus.core.ecat import Command, Datagram
from fieldbus.core.esc_errors import CounterRise, ErrorWatch, LinkChange
from fieldbus.core.network import Bus
from fieldbus.core.sdo import StepKind, coe_plan
from fieldbus.core.wkc import AL_UNREAD, Recovery, answered_slaves, recovery_action, wkc_weights
from fieldbus.errors import (
    BusTimeoutError,
    FieldbusError,
    SdoAbortError,
    SdoMismatchError,
    StateTransitionError,
)
from fieldbus.platform.clock import Clock, is_virtual
from fieldbus.wire.pcap import EthercatCapture

STATE_TIMEOUT_US = 2_000_000
RECONFIG_TIMEOUT_US = 500
SYNC1_ACTIVATE = 0x0400  # assign_activate bit: SYNC1 generation (0x0981 bit 2)
HOST_OFFSET_FRACTION = 50  # host sends this % of a cycle after each SYNC0 (SOEM examples: 50 %)
SDO_RETRIES = 2  # an SDO without answer (not an abort) is tried this many more times
MAX_EMERGENCIES = 1000  # emergencies kept (oldest dropped)
REDUNDANT_SLACK_US = 200  # a reply handed over this long past the timeout is still in time (redundant port)
# An SDO asked for in OP runs one datagram per cycle; it gets a BusTimeoutError when not complete after
# this long in cycles (cycles in which it got its datagram: none while the bus recovers). SOEM's own SDO
# timeout is 700 ms. No cycle waits for it: see the frame timeout.
ACYCLIC_SDO_TIMEOUT_US = 500_000
# One datagram beside the LRW (acyclic or recovery) waits at most the bus's receive timeout, and at most
# this by default: the acyclic budget of one exchange() (as recovery's frames before). Option
# frame_timeout_us up to SOEM's EC_TIMEOUTRET (pysoem.settings.timeouts.ret, 2 ms): SOEM sends a frame
# again when no reply came within EC_TIMEOUTRET, so below it a call is one frame.
FRAME_TIMEOUT_US = 1000
PLAN_RETRY_S = 1.0  # a slave whose reconfiguration failed is tried again after this
RECOVERY_FRAME_TRIES = 4  # a register write whose reply is lost or late is sent again, one try per cycle
RECOVERY_SDO_TIMEOUT_US = 100_000  # one of the plan's SDOs during recovery, in cycles as above
RECOVERY_SDO_TRIES = 4  # ... tried this many times when it does not complete in time
EEPROM_POLLS = 100  # cycles a found-again slave's EEPROM may stay busy for one read
PRIME_STEPS = 50  # datagrams of the upload that takes over a slave's mailbox counter (bring-up)
STATE_POLL_STEPS = 200  # cycles a reconfigured slave may take to reach a state
SNAPSHOT_TIMEOUT_US = 20_000
SNAPSHOT_TRIES = 3
SM_SNAPSHOT, FMMU_SNAPSHOT = 8, 4  # SyncManagers and FMMUs kept per slave (SOEM: EC_MAXSM, EC_MAXFMMU)
REG_FMMU0, REG_SM0 = 0x0600, 0x0800
REG_AL_CONTROL, REG_AL_STATUS, REG_EEPROM_CONFIG = 0x0120, 0x0130, 0x0500
REG_STATION, REG_EEPROM_CONTROL = 0x0010, 0x0502  # station address, alias; EEPROM control/status
EEPROM_READ, EEPROM_BUSY, EEPROM_NACK = 0x0100, 0x8000, 0x2000  # EEPROM command; status bits
SII_VENDOR, SII_PRODUCT, SII_REVISION = 0x08, 0x0A, 0x0C  # SII word addresses (identity)


class EthercatBackend(Backend):
    """One EtherCAT segment on one network card (``interface`` in the network file).

    Options: ``exact_timeout`` (default True: SOEM's packet socket non-blocking,
    so a lost frame costs the receive timeout, not a scheduler tick; False
    keeps SOEM's blocking wait); ``frame_timeout_us`` (the acyclic budget: how
    long the one datagram beside the LRW waits; default the receive timeout,
    at most ``FRAME_TIMEOUT_US``; up to SOEM's ``EC_TIMEOUTRET``);
    ``sdo_timeout_s`` (as on canopen: an SDO in OP fails when not complete
    after this many seconds of cycles in which it ran - one datagram each -
    default ``ACYCLIC_SDO_TIMEOUT_US``).
    """

    kind = "ethercat"
    _locks: tuple[InterfaceLock, ...] = ()  # one per network card, held from open() to close()

    def __init__(self, bus: Bus, **options: object) -> None:
        super().__init__(bus, **options)
        self._init_master(bus, options)
        self._init_cycle(bus, options)
        self._init_acyclic(bus, options)
        self._init_slave_records()

    def _init_master(self, bus: Bus, options: dict[str, object]) -> None:
        """The master: pysoem's on a network card, or the emulated chain in this process (``transport``)."""
        transport = options.get("transport", "soem")  # "in-process": the emulated chain (ecat_inprocess)
        if not bus.interface and transport != "in-process":
            raise FieldbusError(f"bus '{bus.name}': an ethercat bus needs 'interface'")
        if transport not in ("soem", "in-process"):
            raise FieldbusError(
                f"bus '{bus.name}': transport {transport!r} is not one of 'soem', 'in-process'"
            )
        self.in_process = transport == "in-process"
        if self.in_process:
            from fieldbus.backends.ecat_inprocess import InProcessMaster
            from fieldbus.emulators import emulator_part

            maps = options.get(
                "chain_maps"
            )  # what the emulated slaves are, in wire order (default: the maps)
            chain_maps = list(maps) if isinstance(maps, (list, tuple)) else [s.map for s in bus.slaves]
            # the emulator reads the network file's emulator: sections (opaque to fieldbus)
            emulator_options = emulator_part("emulator_options")
            emulated = [emulator_options(s.emulator) if s.emulator else None for s in bus.slaves]
            clock = options.get("clock")  # the emulated chain's time (a virtual one: deterministic runs)
            if clock is not None and not isinstance(clock, Clock):
                raise FieldbusError(f"bus '{bus.name}': option clock is not a fieldbus.platform.clock.Clock")
            self.master: Any = InProcessMaster(
                chain_maps, drive_params=emulated if len(emulated) == len(chain_maps) else None, clock=clock
            )
        else:
            # a real segment runs on the wall clock: a wall clock is accepted (the testing kit passes the
            # network's clock to every bus), a virtual one or the emulated chain's maps are not
            clock = options.get("clock")
            if is_virtual(clock):
                raise FieldbusError(f"bus '{bus.name}': a virtual clock needs transport='in-process'")
            if options.get("chain_maps") is not None:
                raise FieldbusError(f"bus '{bus.name}': option chain_maps needs transport='in-process'")
            self.master = pysoem.Master()

    def _init_cycle(self, bus: Bus, options: dict[str, object]) -> None:
        """The cycle's state: receive timeout (ns), process-data views or copies, capture, stale frames."""
        self._slaves: list[Any] = []
        self._open = False
        self._timeout_us = bus.receive_timeout_us
        self._timeout_ns = bus.receive_timeout_us * 1000
        self._sent_ns = 0
        self._lost = False  # the last LRW's reply did not come back in time (lost or late)
        self._wkc = -1  # the last LRW's working counter in time (-1: none)
        self._host_sync: HostSync | None = None
        self._dc_correction = 0
        self.late_replies = 0  # replies that came back, but later than the receive timeout
        self._out_views: list[tuple[Any, memoryview]] = []
        self._in_views: list[tuple[Any, memoryview]] = []
        # process data through one view of SOEM's IO map (soem_iomap), per group: (destination, source)
        iomap = options.get("iomap", "view")  # "bytes": pysoem's per-slave bytes in the cycle
        if iomap not in ("view", "bytes"):
            raise FieldbusError(f"bus '{bus.name}': iomap {iomap!r} is not one of 'view', 'bytes'")
        self._iomap_view = iomap == "view"
        self._out_copies: list[tuple[npt.NDArray[np.uint8], npt.NDArray[np.uint8]]] = []
        self._in_copies: list[tuple[npt.NDArray[np.uint8], npt.NDArray[np.uint8]]] = []
        # the same copies bound once (core.kernels: one C call each where it is built)
        self._out_run: list[Callable[[], object]] = []
        # called after each reply's inputs arrived in the receive rows (the sim backend's fault hooks); None:
        # nothing (no call on the cycle's path)
        self.on_inputs: Callable[[], None] | None = None
        self._in_run: list[Callable[[], object]] = []
        self.iomap: npt.NDArray[np.uint8] | None = None  # SOEM's IO map, when soem_iomap proved where
        # exact receive timeout: SOEM's socket non-blocking (option exact_timeout, default on)
        self._exact_timeout = bool(options.get("exact_timeout", True)) and not self.in_process  # no socket
        pcap = options.get("pcap")  # every EtherCAT frame of the card, both directions, to this pcap file
        if pcap and not bus.interface:  # in process without a card: no frames on a wire to capture
            raise FieldbusError(f"bus '{bus.name}': option pcap needs a network card ('interface')")
        self.capture = EthercatCapture(str(pcap), bus.interface) if pcap and bus.interface else None
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

    def _init_acyclic(self, bus: Bus, options: dict[str, object]) -> None:
        """The acyclic budget beside the LRW: SDO tries and timeout, frame timeout (µs), error-counter reads."""
        self._sdo_tries = SDO_RETRIES + 1  # tries per blocking SDO (bring-up)
        cap = int(pysoem.settings.timeouts.ret)
        default = min(bus.receive_timeout_us, FRAME_TIMEOUT_US, cap)
        self.frame_timeout_us = int(options.get("frame_timeout_us", default))  # type: ignore[call-overload]
        # ESC error counters and DL status read in OP, one datagram in a cycle nothing else took (esc_errors)
        self.error_watch: ErrorWatch | None = None
        # True: a read in every free cycle; an integer N: in one cycle of every N (less wire time per cycle)
        every = options.get("error_counters", False)
        if isinstance(every, bool) or not isinstance(every, int) or every < 0:
            if not isinstance(every, bool):
                raise FieldbusError(
                    f"bus '{bus.name}': error_counters is True/False or cycles >= 1, not {every!r}"
                )
            every = int(every)
        self._watch_errors = every > 0
        self._watch_every = max(1, every)
        self._watch_tick = 0
        self.diag_datagrams = 0  # datagrams the error watch sent
        sdo_timeout_us = 1e6 * float(options.get("sdo_timeout_s", ACYCLIC_SDO_TIMEOUT_US / 1e6))  # type: ignore[arg-type]
        self._sdo_steps_max = max(1, int(sdo_timeout_us) // bus.cycle_time_us)  # datagrams (= cycles) per SDO
        if not 0 < self.frame_timeout_us <= cap:
            raise FieldbusError(
                f"bus '{bus.name}': frame_timeout_us {self.frame_timeout_us} out of 1..{cap} (SOEM's EC_TIMEOUTRET)"
            )

    def _init_slave_records(self) -> None:
        """Per slave, what bring-up learns and recovery needs: mailboxes, stations, SM/FMMU registers, AL."""
        # one datagram besides the LRW per cycle: set by the ports, cleared by send()
        self._frame_sent = False
        self._mailboxes: list[SlaveMailbox | None] = []  # per slave, from its SM0/SM1 registers (SAFE-OP)
        self._stations: list[tuple[int, int]] = []  # per slave: (station address, alias) as SOEM set them
        self._acyclic: tuple[SdoRequest, Generator[None, None, bytes | None]] | None = None
        self._raw: RawDatagrams | None = None  # our own frames on SOEM's socket (position addressing)
        self._retry_at = [0.0] * self.n_slaves  # monotonic s: a slave whose reconfiguration failed waits
        self._wkc_weights: list[int] | None = None
        # per slave, the AL status this recovery read last (None: no answer; AL_UNREAD: not yet)
        self.al_read: list[int | None] = [AL_UNREAD] * self.n_slaves
        self._sm_regs: list[list[tuple[int, bytes]]] = []  # per slave: (register, bytes) to write again
        self._fmmu_regs: list[list[tuple[int, bytes]]] = []
        # (slave, error code, error register) seen in SDO answers, newest last
        self.emergencies: deque[tuple[int, int, int]] = deque(maxlen=MAX_EMERGENCIES)

    # -- bring-up ----------------------------------------------------------------
    def open(self) -> None:
        """Lock the NIC(s) (:class:`~fieldbus.errors.InterfaceInUseError` when another master has one),
        open them (and find SOEM's packet socket: see :mod:`.soem_socket`), find the slaves."""
        if not self._locks and not self.in_process:
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
        open_card(
            self.master,
            self.bus.interface or "",
            self.bus.redundant_interface,
            where=f"bus '{self.bus.name}': ",
        )
        self._open = True
        self.sockets = soem_socket.packet_sockets(soem_socket.open_sockets() - before)
        ports = 2 if self.bus.redundant_interface else 1  # one packet socket per port
        if self._exact_timeout and len(self.sockets) != ports:
            raise FieldbusError(
                f"bus '{self.bus.name}': {len(self.sockets)} new packet sockets after opening "
                f"'{self.bus.interface}', SOEM opens {ports}; "
                "pass exact_timeout=False to keep SOEM's own receive wait (a lost frame then costs 4-10 ms)"
            )
        self._slaves = find_slaves(self.master)
        self._check_identity(len(self._slaves))

    def _check_identity(self, found: int) -> None:
        self.check_identities(
            [(s.name, s.man, s.id) for s in self._slaves[: max(found, 0)]],
            "(in process)" if self.in_process else f"on {self.bus.interface}",
        )

    def configure(self) -> None:
        state = check_state(self.master, pysoem.PREOP_STATE, STATE_TIMEOUT_US)
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
        self._map_iomap()
        self._configure_dc()
        state = check_state(self.master, pysoem.SAFEOP_STATE, STATE_TIMEOUT_US)
        if state != pysoem.SAFEOP_STATE:
            self._raise_state("SAFE-OP", state)
        self._snapshot_registers()
        self._prime_mailboxes()

    def _map_iomap(self) -> None:
        """One copy per axis group and direction between the images and SOEM's IO map, when
        :func:`.soem_iomap.locate` proves where it is; otherwise the per-slave ``bytes`` path stays."""
        self.iomap, self._out_copies, self._in_copies = None, [], []
        self._out_run, self._in_run = [], []
        if not self._iomap_view:
            return
        sizes = [(a.out_size, a.in_size) for a in self.areas]
        view = self.master.iomap if self.in_process else soem_iomap.locate(self.master, self._slaves, sizes)
        if view is None:
            return
        o_at, i_at = 0, self.out_bytes
        out_copies, in_copies = [], []
        for k, g in enumerate(self.groups):
            n = len(g.slaves)
            o, i = self.areas[g.first].out_size, self.areas[g.first].in_size
            # the image has a row per axis (a multi-axis slave's bytes are its axes' rows, in order)
            wire_out, rx = g.image.outputs.wire, self.rx[k]
            if (o and wire_out.size != n * o) or (i and rx.size != n * i):
                return  # a layout the rows do not tile: the per-slave path stays
            if o:
                out_copies.append((view[o_at : o_at + n * o].reshape(wire_out.shape), wire_out))
            if i:
                in_copies.append((rx, view[i_at : i_at + n * i].reshape(rx.shape)))
            o_at += n * o
            i_at += n * i
        self._out_copies, self._in_copies = out_copies, in_copies
        self._out_run = [kernels.copier(d, s) for d, s in out_copies]
        self._in_run = [kernels.copier(d, s) for d, s in in_copies]
        self.iomap = view

    def _prime_mailboxes(self) -> None:
        """Take over each slave's mailbox counter from SOEM with a harmless upload (0x1000:0, device type).

        SOEM counted 1..7 during bring-up and does not say where it stopped;
        this first request carries 0, which SOEM never sends, and every later
        one 1..7 in turn, so none can be taken for a repeat of SOEM's last. Were
        this upload's write reply lost and sent again, a slave that takes every
        0 as new would answer it twice: a read, harmless. Its outcome (an abort,
        no answer) does not matter; the counter has moved on either way.
        """
        for i, mbx in enumerate(self._mailboxes):
            if mbx is None:
                continue
            steps = self._sdo_steps(i, 0x1000, 0, None, PRIME_STEPS)
            try:
                while True:
                    next(steps)
            except (StopIteration, FieldbusError):
                pass

    def _snapshot_registers(self) -> None:
        """Keep each slave's SyncManager and FMMU registers as SOEM programmed them (SAFE-OP).

        A power-cycled slave is configured again from these (:meth:`_reconfigure`),
        step by step, instead of SOEM's ``reconfig`` - one long call. Only
        enabled entries (SM with a start address, FMMU with its activate bit);
        the SM status and PDI-control bytes are read-only and written as 0.
        """
        self._sm_regs, self._fmmu_regs = [], []
        self._mailboxes, self._stations = [], []
        for i, s in enumerate(self._slaves):
            sm = self._snapshot_read(i, REG_SM0, SM_SNAPSHOT * 8)
            fmmu = self._snapshot_read(i, REG_FMMU0, FMMU_SNAPSHOT * 16)
            station = self._snapshot_read(i, REG_STATION, 4)  # station address, alias
            self._stations.append(struct.unpack("<HH", station))
            layout = MailboxLayout.from_sm_registers(sm[:16])
            self._mailboxes.append(
                None
                if layout is None
                else SlaveMailbox(layout, SoemPort(self, s), functools.partial(self._emcy, i))
            )
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

    def _snapshot_read(self, i: int, ado: int, size: int) -> bytes:
        """``size`` bytes of slave ``i``'s registers at ``ado`` (bring-up: SOEM's waits, tried 3 times)."""
        for _ in range(SNAPSHOT_TRIES):
            data = read_register(self._slaves[i], ado, size, SNAPSHOT_TIMEOUT_US)
            if data is not None:
                return data
        raise StateTransitionError(
            f"bus '{self.bus.name}': position {i} ({self.areas[i].slave.name}) did not answer a read of "
            f"register 0x{ado:04X} in {SNAPSHOT_TRIES} tries of {SNAPSHOT_TIMEOUT_US / 1000:g} ms"
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
        """Slave ``i`` from INIT/PRE-OP back to SAFE-OP, one datagram per step.

        The sequence of SOEM's ``ecx_reconfig_slave`` (INIT, EEPROM to PDI, the
        SyncManagers, PRE-OP, the SDO plan - written, then read back, through
        :mod:`.ecat_mailbox` - SAFE-OP, the FMMUs), split so that no cycle waits
        for more than one reply. A failure (an SDO abort, a state that is not
        reached) puts the slave back to INIT (in a step of its own) and raises:
        it never runs with a mapping the network did not write.
        """
        area = self.areas[i]
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
            yield from self._plan_steps(i)
            step = "SAFE-OP request"
            yield from self._write(i, REG_AL_CONTROL, bytes([AL_SAFEOP, 0]))
            step = "waiting for SAFE-OP"
            yield from self._await_state(i, AL_SAFEOP)
            for address, data in self._fmmu_regs[i]:
                step = f"FMMU register 0x{address:04X}"
                yield from self._write(i, address, data)
        except Exception as exc:
            self._retry_at[i] = self._now_s() + PLAN_RETRY_S
            yield  # the step that failed had its datagram; the INIT request gets a step of its own
            SoemPort(self, self._slaves[i]).write(REG_AL_CONTROL, bytes([AL_INIT | AL_ACK, 0]))
            raise StateTransitionError(
                f"bus '{self.bus.name}': position {i} ({area.slave.name}) could not be configured again after "
                f"falling out of OP, left in INIT (next try in {PLAN_RETRY_S:g} s): {step}: {describe(exc)}"
            ) from exc

    def _plan_steps(self, i: int) -> Generator[None, None, int]:
        """Slave ``i``'s SDO plan through its mailbox, one datagram per step: the writes, then the read-backs.

        As :func:`~fieldbus.backends.sdo_exec.apply_plan`: the first abort or
        mismatch raises. A transfer not complete within ``RECOVERY_SDO_TIMEOUT_US``
        is made again (``RECOVERY_SDO_TRIES`` in all); transfers are idempotent.
        """
        name = self.areas[i].slave.name
        plan = coe_plan(self.areas[i].slave.map)
        transfers = 0
        for st in plan.steps:
            if st.kind is StepKind.WRITE:
                yield from self._plan_sdo(i, st.index, st.sub_index, st.data)
                transfers += 1
                yield
        for st in plan.checks:
            assert st.readback is not None
            got = yield from self._plan_sdo(i, st.index, st.sub_index, None)
            transfers += 1
            want = st.readback
            if got is None or got[: len(want)] != want or any(got[len(want) :]):
                raise SdoMismatchError(
                    index=st.index, sub_index=st.sub_index, expected=want, received=got or b"", slave=name
                )
            yield
        return transfers

    def _plan_sdo(
        self, i: int, index: int, sub: int, data: bytes | None
    ) -> Generator[None, None, bytes | None]:
        last: BusTimeoutError | None = None
        for attempt in range(RECOVERY_SDO_TRIES):
            if attempt:
                yield
            try:
                steps = max(1, RECOVERY_SDO_TIMEOUT_US // self.bus.cycle_time_us)
                return (yield from self._sdo_steps(i, index, sub, data, steps))
            except BusTimeoutError as exc:
                last = exc
        assert last is not None
        raise last

    def _sdo_steps(
        self, i: int, index: int, sub: int, data: bytes | None, max_steps: int
    ) -> Generator[None, None, bytes | None]:
        """One SDO transfer with slave ``i`` through its mailbox, one datagram per step (the last: no yield)."""
        name = self.areas[i].slave.name
        mbx = self._mailboxes[i] if i < len(self._mailboxes) else None
        if mbx is None:
            raise FieldbusError(f"bus '{self.bus.name}' slave {name}: no mailbox (no SDO access)")
        t = SdoTransfer(index, sub, data, mailbox_out=mbx.layout.out_size)
        try:
            return (yield from mbx.transfer(t, max_steps))
        except SdoAbortError as exc:
            raise SdoAbortError(exc.code, index=exc.index, sub_index=exc.sub_index, slave=name) from None
        except BusTimeoutError:
            what = "read" if data is None else "write"
            raise BusTimeoutError(
                f"bus '{self.bus.name}' slave {name}: SDO {what} 0x{index:04X}:{sub:02X} not complete in "
                f"{max_steps} cycles (one datagram per cycle)"
            ) from None

    def _emcy(self, slave: int, code: int, register: int) -> None:
        self.emergencies.append((slave, code, register))
        self.emcy_count += 1

    def _write(self, i: int, address: int, data: bytes) -> Generator[None, None, None]:
        """One register write to slave ``i``, then a step; a lost or late reply is sent again next step.

        Every register written during recovery is idempotent (AL control, EEPROM
        owner, SM and FMMU entries), so a repeat is safe, as in SOEM's own
        ``ecx_FPWRw``, which repeats a frame until its (longer) timeout.
        """
        port = SoemPort(self, self._slaves[i])
        for _ in range(RECOVERY_FRAME_TRIES):
            if port.write(address, data):
                yield
                return
            yield
        raise BusTimeoutError(
            f"register 0x{address:04X} write not acknowledged in {RECOVERY_FRAME_TRIES} tries"
        )

    def _await_state(self, i: int, state: int) -> Generator[None, None, None]:
        """Read slave ``i``'s AL status once per step until it shows ``state``; give up after a while.

        A read without answer (lost or late frame) counts as one poll that did not see it yet.
        """
        for _ in range(STATE_POLL_STEPS):
            got = self._al_status(i)
            yield  # the step ends with its datagram, whatever it showed
            if got is None:
                continue
            if got & 0x0F == state:
                return
            if got & AL_ERROR and state != AL_INIT:
                raise StateTransitionError(f"{state_name(got)} instead of {state_name(state)}")
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
        if self._watch_errors and self._slaves:
            self.error_watch = ErrorWatch(len(self._slaves))

    def _raise_state(self, target: str, lowest: int) -> None:
        names = [a.slave.name for a in self.areas]
        raise state_error(self.master, self._slaves, names, target, lowest, where=f"bus '{self.bus.name}': ")

    def slave_state(self, i: int) -> str:
        """Slave ``i``'s AL state as SOEM last read it (bring-up and recovery read it, the cycle does not)."""
        return state_name(int(self._slaves[i].state)) if i < len(self._slaves) else "-"

    # -- cycle ----------------------------------------------------------------------
    def send(self) -> None:
        """Outputs into SOEM's IO map, frames still queued from earlier cycles discarded, the LRW sent."""
        if self.iomap is not None:
            for copy in self._out_run:
                copy()
        else:
            for s, mv in self._out_views:
                s.output = bytes(mv)
        if self._exact_timeout:
            self.stale_frames += soem_socket.drain(self.sockets, self._drain_buf)
        self._frame_sent = False
        if not self.in_process:  # in-process the transport judges lateness on its own clock (receive)
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
        # in-process the transport judges lateness on its own clock (ecat_inprocess), not the wall's
        if wkc >= 0 and not self.in_process and time.perf_counter_ns() - self._sent_ns > self._late_ns:
            self.late_replies += 1
            self.late_wkc, wkc = wkc, -1
        self._wkc, self._lost = wkc, wkc < 0
        if self._host_sync is not None and wkc >= 0:
            dc = int(self.master.dc_time)
            self.dc_time_ns = dc
            self._dc_correction = self._host_sync.step(dc)
            self.dc_sync_error_ns = self._host_sync.delta_ns
        if wkc < 0:
            return None
        if self.iomap is not None:
            for copy in self._in_run:
                copy()
        else:
            for s, mv in self._in_views:
                mv[:] = s.input
        if self.on_inputs is not None:
            self.on_inputs()
        return wkc

    def slaves_answered(self, wkc: int | None) -> npt.NDArray[np.bool_] | None:
        """Which slaves processed a short LRW, from this recovery's AL readings (:func:`answered_slaves`)."""
        if self._wkc_weights is None:
            self._wkc_weights = wkc_weights([a.layout for a in self.areas])
        got = answered_slaves(wkc, self._wkc_weights, self.al_read)
        return None if got is None else np.array(got, dtype=bool)

    def dc_correction_ns(self) -> int:
        """Correction for the next deadline from the host PI (SOEM's ec_sync), ns; 0 without DC."""
        c, self._dc_correction = self._dc_correction, 0
        return c

    def _recover(self) -> Generator[None, None, bool]:
        """Recovery after a miss: :meth:`_recover_passes`, but after a lost frame not in the cycle of the loss.

        A frame that did not come back (lost, or late) says nothing about the
        slaves' states, and the cycle of the loss has already waited the
        receive timeout: no datagram goes out in it. The next cycle's LRW
        decides: its full working counter proves that every slave processed
        it in OP - what the pass's first datagram (a BRD of AL status) would
        have found - and recovery ends there without a frame of its own;
        anything else (lost again, a short WKC) starts the passes in that cycle.
        """
        if self._lost:
            yield  # the cycle of the loss: nothing sent
            if self._wkc == self.expected_wkc:
                return True
        return (yield from self._recover_passes())

    def _recover_passes(self) -> Generator[None, None, bool]:
        """SOEM's ecatcheck as steps of one datagram; passes repeat until all are in OP.

        A pass starts with one broadcast read of every slave's AL status (as
        SOEM's ``read_state`` does): all answered and all in OP ends it there,
        one datagram after a miss that left every slave in OP. Otherwise each
        slave's AL status is read on its own (one FPRD per step) rather than
        with ``read_state``, which then reads every slave one by one in one
        call - up to 5 ms for 12 slaves. Runs in the cycle's thread on purpose:
        pysoem holds the GIL in its calls, so a monitor thread would stall the
        cycle at moments nobody chose.
        """
        worked = False
        self.al_read = [AL_UNREAD] * len(self._slaves)  # this run's readings only
        while True:
            if not any(s.is_lost for s in self._slaves) and (yield from self._all_in_op()):
                self.recoveries += worked
                return True
            all_ok = True
            for i, s in enumerate(self._slaves):
                state = None if s.is_lost else self._al_status(i)
                self.al_read[i] = state
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
                    if self._now_s() < self._retry_at[i]:
                        continue  # its configuration failed a moment ago: not every cycle
                    yield from self._reconfigure(i)
                    yield from self._write(i, REG_AL_CONTROL, bytes([AL_OP, 0]))
                elif action is Recovery.RECOVER:  # silent at its address: find it by position (SOEM)
                    s.is_lost = not (yield from self._find_again(i))
                yield
            if all_ok:
                self.recoveries += worked
                return True
            worked = True

    def _now_s(self) -> float:
        """Seconds for recovery's waits: the wall clock's, in-process the transport's (maybe virtual)."""
        return self.master.clock() / 1e9 if self.in_process else time.monotonic()

    def _al_status(self, i: int) -> int | None:
        """Slave ``i``'s AL status register (one FPRD), None when it does not answer at its address."""
        raw = SoemPort(self, self._slaves[i]).read(REG_AL_STATUS, 2)
        return None if raw is None else int.from_bytes(raw, "little")

    def _raw_channel(self) -> RawDatagrams | None:
        """Our own datagrams on SOEM's socket(s), opened at first use; None without a socket."""
        if self._raw is None and self.sockets:
            self._raw = RawDatagrams(self.sockets)
        return self._raw

    def _all_in_op(self) -> Generator[None, None, bool]:
        """One BRD of AL status (0x0130): True when every slave answered and the OR of their states is OP."""
        raw = self._raw_channel()
        if raw is None:  # pragma: no cover - SOEM always opens a packet socket on Linux
            return False
        self._frame_sent = True
        d = raw.txrx(Datagram.physical(Command.BRD, 0, REG_AL_STATUS, bytes(2)), self.frame_timeout_us)
        yield
        return (
            d is not None
            and d.wkc == len(self._slaves)
            and int.from_bytes(d.data, "little") & (0x0F | AL_ERROR) == AL_OP
        )

    def _find_again(self, i: int) -> Generator[None, None, bool]:
        """SOEM's ``ecx_recover_slave`` for slave ``i`` as single datagrams (one per step); True: found.

        By position (APRD/APWR, :mod:`.ecat_raw`): its station address and
        alias; a slave that lost its address (0: power-cycled) and shows the
        same alias and, in its SII, the same vendor, product and revision as
        at bring-up gets its station address back. Position addressing
        throughout, so no temporary address is needed (SOEM uses one). Each
        datagram ends its step (:meth:`_ap`).
        """
        s = self._slaves[i]
        if self._raw_channel() is None:  # pragma: no cover - SOEM always opens a packet socket on Linux
            return bool(s.recover(timeout=RECONFIG_TIMEOUT_US) > 0)  # unbounded (documented)
        station, alias = self._stations[i]
        got = yield from self._ap(i, Command.APRD, REG_STATION, bytes(4))
        if got is None:
            return False
        now, now_alias = struct.unpack("<HH", got)
        if now == station:
            return True
        if now != 0 or now_alias != alias:
            return False  # another slave at this position, or one that kept another address: not adopted
        if (yield from self._ap(i, Command.APWR, REG_EEPROM_CONFIG, b"\x00")) is None:  # EEPROM to master
            return False
        for word, want in ((SII_VENDOR, s.man), (SII_PRODUCT, s.id), (SII_REVISION, s.rev)):
            value = yield from self._ap_eeprom(i, word)
            if value != want:
                return False
        return (yield from self._ap(i, Command.APWR, REG_STATION, struct.pack("<H", station))) is not None

    def _ap(self, i: int, cmd: Command, ado: int, data: bytes) -> Generator[None, None, bytes | None]:
        """One position-addressed datagram to slave ``i``, then a step; its data, None without WKC 1."""
        assert self._raw is not None
        self._frame_sent = True
        d = self._raw.txrx(Datagram.physical(cmd, -i, ado, data), self.frame_timeout_us)
        yield
        return d.data if d is not None and d.wkc == 1 else None

    def _ap_eeprom(self, i: int, word: int) -> Generator[None, None, int | None]:
        """Four bytes of slave ``i``'s SII from ``word``: the read command, then polls of status and data.

        One poll reads control/status, address and data (0x0502-0x050B) in one
        datagram. None when a datagram is not answered; a busy EEPROM is polled
        for ``EEPROM_POLLS`` steps, then :class:`BusTimeoutError`.
        """
        command = struct.pack("<HI", EEPROM_READ, word)
        if (yield from self._ap(i, Command.APWR, REG_EEPROM_CONTROL, command)) is None:
            return None
        for _ in range(EEPROM_POLLS):
            raw = yield from self._ap(i, Command.APRD, REG_EEPROM_CONTROL, bytes(10))
            if raw is None:
                return None
            status = int.from_bytes(raw[:2], "little")
            if status & EEPROM_NACK:
                return None
            if not status & EEPROM_BUSY:
                return int.from_bytes(raw[6:10], "little")
        raise BusTimeoutError(f"position {i}: EEPROM busy for {EEPROM_POLLS} cycles")

    # -- shut-down --------------------------------------------------------------------
    def stop(self) -> None:
        self._recovery = None
        self._acyclic = None
        if self._raw is not None:
            self._raw.close()
            self._raw = None
        if self._open and self._slaves:
            request_state(self.master, pysoem.INIT_STATE)

    def close(self) -> None:
        try:
            if self._open:
                self._open = False
                self.iomap, self._out_copies, self._in_copies = None, [], []  # not past the master's life
                self._out_run, self._in_run = [], []
                self.master.close()
        finally:
            try:
                if self.capture is not None:
                    time.sleep(0.01)  # the last replies reach the capture socket
                    self.capture.close()
            finally:
                locks, self._locks = self._locks, ()
                release_all(locks)

    def diag_step(self) -> list[CounterRise | LinkChange]:
        """One read of the error watch's rotation (counters or DL status of one slave), if this cycle's
        datagram is still free (no SDO, no recovery took it); what changed. Never raises."""
        watch = self.error_watch
        if watch is None or self._frame_sent or self.recovering:
            return []
        self._watch_tick += 1
        if self._watch_tick % self._watch_every:
            return []
        i, reg, size = watch.next_read()
        try:
            raw = SoemPort(self, self._slaves[i]).read(reg, size)
        except Exception:  # a fault of the bus: this read is missed, the cycle goes on
            raw = None
        self.diag_datagrams += 1
        return watch.feed(raw)

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
        """Advance an SDO asked for in OP by one datagram (:mod:`.ecat_mailbox`); True when finished.

        No SOEM mailbox call: the request goes into the slave's SM0, SM1 is
        polled and read, one datagram per cycle, each waiting at most
        :attr:`frame_timeout_us`. In a cycle whose datagram went to recovery it
        waits for the next. Not complete after ``sdo_timeout_s`` worth of
        cycles (datagrams): :class:`BusTimeoutError` (ask again). Never raises.
        """
        if self._frame_sent:
            return False
        try:
            if self._acyclic is None or self._acyclic[0] is not request:
                steps = self._sdo_steps(
                    request.slave, request.index, request.sub_index, request.data, self._sdo_steps_max
                )
                self._acyclic = (request, steps)
            next(self._acyclic[1])
            return False
        except StopIteration as done:
            request.finish(done.value)
        except FieldbusError as exc:
            request.finish(error=exc)
        except Exception as exc:  # a fault of ours or of the bus: that request's, not the cycle's
            request.finish(
                error=FieldbusError(f"bus '{self.bus.name}': SDO transfer failed: {describe(exc)}")
            )
        self._acyclic = None
        return True

    def _sdo(
        self, slave: int, index: int, sub_index: int, what: str, call: Any, tries: int | None = None
    ) -> Any:
        """One blocking SDO transfer (bring-up) with pysoem's errors as ours (:func:`.ecat_master.sdo`): an
        abort raises at once, no answer is tried ``SDO_RETRIES`` more times, an emergency that came instead
        of the answer is kept in :attr:`emergencies` and the transfer tried again."""
        return sdo(
            lambda: call(self._slaves[slave]),
            index=index,
            sub_index=sub_index,
            slave=self.areas[slave].slave.name,
            what=what,
            who=f"bus '{self.bus.name}' slave {self.areas[slave].slave.name}",
            tries=self._sdo_tries if tries is None else tries,
            on_emergency=functools.partial(self._emcy, slave),
        )
