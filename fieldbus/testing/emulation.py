"""Bring up emulators for a network file as it is, open the master on them, tear all down.

    with fieldbus.testing.emulate("robot.yaml") as emu:
        op = emu.op                          # brought up: SDO plans written and read back, OP
        emu.run(controller.step, cycles=2000)      # paced on emu.clock (virtual: as fast as it goes)
        emu.lose_cycles("legs", 12)          # faults by bus and slave name
        ...

EtherCAT buses run on the in-process ``sim`` backend (``ethercat="sim"``) or
on the real pysoem master over a veth pair with the emulator in a child
process (``ethercat="veth"``); CAN buses (CANopen, raw-CAN motors: each bus the
emulator of its maps' family) on an in-process bus (``can="virtual"``) or on
``fieldbus_udp`` with every CAN bus's emulator in one child process (``can="udp"``). Interfaces and channels are substituted;
the file is not touched. With every emulator in process the clock is a
:class:`~fieldbus.platform.clock.VirtualClock` unless told otherwise: the
master and the emulators run in lockstep, time passes only in the master's
waits, and a run gives the same cycles bit for bit on any machine.
"""

from __future__ import annotations

import dataclasses
import tempfile
from collections.abc import Callable, Iterator, Mapping
from contextlib import ExitStack, contextmanager
from pathlib import Path
from typing import Any

from fieldbus.core.cia402 import State402
from fieldbus.core.network import Bus, NetworkConfig, load_network, row_names
from fieldbus.errors import FieldbusError
from fieldbus.network import Network, Operational, open_network
from fieldbus.platform.clock import WALL, Clock, VirtualClock, is_virtual
from fieldbus.platform.loop import run_cycles
from fieldbus.platform.timing import CycleTimer
from fieldbus.testing.provider import (
    CAN_MODES,
    ETHERCAT_MODES,
    BusEmulator,
    EmulationContext,
    EmulationError,
    find_emulator,
)
from fieldbus.testing.trace import Trace

SAFE_STOP_NOTE = "the policy's safe_stop_after consecutive misses latch the safe stop"


class Emulation:
    """A network on emulated slaves: the opened :class:`Network`, its :class:`Operational`, faults, a trace.

    Faults name a bus and a slave as the network file does. Each says in its
    docstring what the master should see; ``docs/testing.md`` has the table.
    A fault that has no meaning on a bus raises
    :class:`~fieldbus.testing.FaultNotSupported` naming the bus and why.
    """

    def __init__(
        self, network: Network, model: NetworkConfig, emulators: Mapping[str, BusEmulator], clock: Clock
    ):
        self.network = network
        self.model = model
        self.emulators = dict(emulators)
        self.clock = clock
        self._op: Operational | None = None
        self._trace: Trace | None = None

    # -- phases -------------------------------------------------------------------------------
    def bring_up(self) -> Operational:
        """``network.bring_up()`` (``emulate`` does it unless ``bring_up=False``); starts the trace."""
        op = self.network.bring_up()
        self._attach(op)
        return op

    def _attach(self, op: Operational) -> None:
        trace = Trace(op, self.network)
        op.add_observer(trace)  # called at the end of every exchange()
        self._op, self._trace = op, trace

    @property
    def op(self) -> Operational:
        """The network in OP (after bring-up)."""
        if self._op is None:
            raise FieldbusError("the emulated network is not brought up yet: call emu.bring_up()")
        return self._op

    @property
    def trace(self) -> Trace:
        """Every cycle since bring-up (see :class:`~fieldbus.testing.Trace`)."""
        if self._trace is None:
            raise FieldbusError("the emulated network is not brought up yet: call emu.bring_up()")
        return self._trace

    @property
    def cycle_time_us(self) -> int:
        """The network's shortest bus cycle, µs (the rate ``exchange()`` is called at)."""
        return min(b.cycle_time_us for b in self.model.buses)

    @property
    def virtual(self) -> bool:
        """True when time is virtual (passes only when the loop or the master waits)."""
        return is_virtual(self.clock)

    def run(self, step: Callable[[int], bool | None], cycles: int, **options: Any) -> CycleTimer:
        """:func:`fieldbus.run_cycles` at the network's cycle time on :attr:`clock`; ``step(k)`` calls
        ``op.exchange()`` itself, as a controller does; returning True stops early. ``options`` go to
        ``run_cycles``.

        ``k`` is the index of the cycle the step's ``exchange()`` runs, counted from bring-up and going
        on across calls: ``CycleResult.cycle`` before that exchange, the row of :attr:`trace` it fills
        (``run(step, 100)`` twice: k = 0..99, then 100..199). Before bring-up, 0..cycles-1.
        """
        op = self._op
        if op is None:
            return run_cycles(step, self.cycle_time_us, cycles, clock=self.clock, **options)
        result = op.result

        def indexed(_i: int) -> bool | None:
            return step(result.cycle)

        return run_cycles(indexed, self.cycle_time_us, cycles, clock=self.clock, **options)

    def cycles(self, n: int) -> None:
        """``n`` cycles of ``op.exchange()`` alone (outputs as they are), paced on :attr:`clock`."""
        op = self.op

        def step(_k: int) -> None:
            op.exchange()

        self.run(step, n)

    # -- looking up names ------------------------------------------------------------------------
    def _bus(self, bus: str) -> tuple[Bus, BusEmulator]:
        emu = self.emulators.get(bus)
        if emu is None:
            raise FieldbusError(f"no bus '{bus}' (have: {', '.join(self.emulators)})")
        return self.model.bus(bus), emu

    def _slave(self, bus: str, slave: str | None) -> tuple[BusEmulator, int]:
        model, emu = self._bus(bus)
        if slave is None:
            return emu, 0
        for i, s in enumerate(model.slaves):
            if s.name == slave:
                return emu, i
        raise FieldbusError(
            f"bus '{bus}' has no slave '{slave}' (have: {', '.join(s.name for s in model.slaves)})"
        )

    def drive_states(self, bus: str) -> list[State402 | None]:
        """Each slave's (each axis of a multi-axis slave's) CiA 402 state as the emulated drive itself
        has it (None: not a drive; :meth:`cia402_states` for a bus of drives, without ``None``).

        The emulator's side, not the master's: for checks that the drives really stopped.
        """
        return [State402(s) if s >= 0 else None for s in self._bus(bus)[1].drive_states()]

    def drive_positions(self, bus: str) -> list[float]:
        """Each axis's shaft position as the emulated drive's physics has it: the ground truth. The
        in-process EtherCAT emulator gives the drive's own counts (unquantised; divide by the map's
        counts per unit), an in-process raw-CAN emulator each motor's position in its map's unit (rad),
        never wrapped; elsewhere :class:`FaultNotSupported`."""
        return self._bus(bus)[1].drive_positions()

    def cia402_states(self, bus: str) -> list[State402]:
        """:meth:`drive_states` of a bus of CiA 402 drives, typed without ``None``: a slave that is not
        a CiA 402 drive raises :class:`~fieldbus.FieldbusError` naming it."""
        out: list[State402] = []
        rows = row_names(self._bus(bus)[0].slaves)  # a row per axis of a multi-axis slave
        for row, state in zip(rows, self.drive_states(bus), strict=False):
            if state is None:
                raise FieldbusError(f"bus '{bus}': '{row}' is not a CiA 402 drive")
            out.append(state)
        return out

    # -- faults ------------------------------------------------------------------------------------
    def lose_cycles(self, bus: str, cycles: int) -> None:
        """Lose the process data of the next ``cycles`` cycles of bus ``bus`` (only those: the
        frames of recovery and SDO transfers in between still pass).

        Master: each of those cycles has verdict TIMEOUT (EtherCAT, raw CAN) or SHORT/TIMEOUT
        (CANopen: no TPDO came), is not fresh and keeps the last inputs; at ``safe_stop_after``
        consecutive misses the safe stop latches. EtherCAT: the frames are dropped; CANopen:
        every node sends no TPDO for that many SYNCs; raw CAN: no motor answers that many commands.
        """
        self._check_count(cycles)
        self._bus(bus)[1].lose_cycles(cycles)

    def delay(self, bus: str, seconds: float, cycles: int = 1) -> None:
        """EtherCAT: the replies of the next ``cycles`` frames come back ``seconds`` late.

        Master: a reply later than the bus's receive timeout is a miss (TIMEOUT, inputs held);
        a shorter delay only makes ``exchange()`` that much longer (on a virtual clock: exactly).
        Over veth the runner holds back the next frames, recovery frames included.
        """
        self._check_count(cycles)
        if seconds < 0:
            raise FieldbusError(f"delay: seconds must be >= 0, got {seconds}")
        self._bus(bus)[1].delay(seconds, cycles)

    def short_wkc(self, bus: str, cycles: int = 1, *, slave: str | None = None) -> None:
        """The working counter of the next ``cycles`` cycles comes back short.

        Master: verdict SHORT, the cycle not fresh, inputs held, counted towards the safe stop.
        EtherCAT: one less than expected in the process-data datagram (``slave`` unused);
        CANopen / raw CAN: slave ``slave`` (default the first) sends nothing for that many cycles,
        so only its inputs are stale and the other slaves' stay fresh.
        """
        self._check_count(cycles)
        emu, i = self._slave(bus, slave)
        emu.short_wkc(cycles, i)

    def corrupt_inputs(self, bus: str, slave: str, cycles: int = 1) -> None:
        """Slave ``slave``'s inputs arrive with every bit inverted for ``cycles`` cycles, framing intact.

        Master: nothing the bus can tell (the working counter, COB-ID and length are right): the
        cycle is fresh and the values are wrong. Only a controller's own plausibility checks
        (a position jump, a statusword that matches no state) catch it. Not over veth.
        """
        self._check_count(cycles)
        emu, i = self._slave(bus, slave)
        emu.corrupt_inputs(i, cycles)

    def power_cycle(self, bus: str, slave: str) -> None:
        """Slave ``slave`` loses power and comes back with its defaults (mapping and SDO values lost).

        Master: EtherCAT: SHORT cycles while it is gone (its WKC share missing), then the
        backend's recovery brings it back to OP by itself (``BusStatus.recovering``, then
        ``recoveries`` + 1); its drive restarts in SWITCH ON DISABLED, so a controller must
        enable it again. CANopen: a boot-up message, then the node is configured again and
        started (``recoveries`` + 1). Raw CAN: the motor's family's power-up state, its replies go on
        (MIT: out of motor mode; Damiao: disabled, registers as at power-up; ODrive: IDLE, no error;
        CubeMars servo: running, no error); docs/testing.md, "Raw-CAN families".
        """
        emu, i = self._slave(bus, slave)
        emu.power_cycle(i)

    def firmware_power_loss(self, bus: str, slave: str, after_bytes: int) -> None:
        """EtherCAT: slave ``slave`` loses power in the middle of its next FoE write, once that has
        taken ``after_bytes`` more bytes, and comes back in INIT without valid firmware (it refuses
        PRE-OP, AL status code 0x0014, until a firmware write completes); docs/firmware.md."""
        self._check_count(after_bytes)
        emu, i = self._slave(bus, slave)
        emu.firmware_power_loss(i, after_bytes)

    def drive_fault(self, bus: str, slave: str, code: int | str, *, axis: int = 1) -> None:
        """The drive of slave ``slave`` faults with error code ``code`` (0x603F, e.g. 0x7300 sensor).

        ``axis``: which axis of a multi-axis slave (``axes:`` in its map), 1-based within the slave
        (1: the first; its error code sits in 0x603F, axis k's in 0x603F + 0x800 x (k - 1)). The
        master's ``DriveFault`` names that axis's row and ``slave_axis`` = ``axis`` - 1.

        ``code`` may be the code's CiA 301 / CiA 402 name (``"sensor error"``, see
        :func:`fieldbus.diagnosis.error_code`).

        Master: the statusword shows FAULT from the next cycle or two (the bus stays fresh), the
        error code is in 0x603F (in the inputs when the map has it, else by SDO), and an emergency
        (EMCY) with that code is sent (``backend.emergencies``). A fault reset (controlword bit 7)
        clears it. Raw CAN: ``code`` is the family's own (Damiao error nibble 0x8..0xE, ODrive axis
        error bits, CubeMars error code 1..6); the motor lets go, its replies carry the code and the
        master reports one named ``MotorFaultEvent`` in ``CycleResult.events``. Not on MIT motors of
        family ``mit`` (no error code).
        """
        if isinstance(code, str):
            from fieldbus.core.diagnosis import error_code

            code = error_code(code)
        top = 0xFFFF_FFFF if self._bus(bus)[0].type == "rawcan" else 0xFFFF
        if not 0 < code <= top:
            raise FieldbusError(f"drive_fault: error code must be 0x1..{top:#x}, got {code:#x}")
        emu, i = self._slave(bus, slave)
        axes = self._bus(bus)[0].slaves[i].map.axes
        if not 1 <= axis <= axes:
            raise FieldbusError(f"drive_fault: slave '{slave}' has axes 1..{axes}, got axis={axis}")
        emu.drive_fault(i, code, axis - 1)

    def silence(self, bus: str, slave: str, silent: bool = True) -> None:
        """CAN: slave ``slave`` stops (``silent=False``: resumes) sending; it still listens.

        Master: its inputs stale and held every cycle (SHORT), the others fresh; CANopen also
        reports its heartbeat lost after the consumer time. When it resumes it is fresh again
        (a CANopen node that was never reset needs no reconfiguration).
        """
        emu, i = self._slave(bus, slave)
        emu.silence(i, silent)

    def bit_errors(self, bus: str, between: tuple[str, str], rate: float = 0.02, *, seed: int = 0) -> None:
        """EtherCAT: bit errors on the cable between two neighbouring slaves (wire order), until cleared.

        Each pass of a frame over that cable is corrupted with probability ``rate`` (seeded): the frame
        is lost (SHORT/missed cycles as a real CRC error gives), the ESC that receives it there counts
        an invalid frame on that port, the ESCs after it a forwarded error. With the bus option
        ``error_counters`` the master names that cable in ``esc_errors`` events (docs/diagnostics.md).
        """
        upstream = self._cable(bus, between)
        if not 0.0 <= rate <= 1.0:
            raise FieldbusError(f"rate {rate} is outside 0..1")
        self._bus(bus)[1].bit_errors(upstream, rate, seed)

    def flap_link(self, bus: str, between: tuple[str, str]) -> None:
        """EtherCAT: the cable between two neighbouring slaves loses its link for a moment (one frame
        lost; both ends count a lost link)."""
        self._bus(bus)[1].flap_link(self._cable(bus, between))

    def _cable(self, bus: str, between: tuple[str, str]) -> int:
        _, a = self._slave(bus, between[0])
        _, b = self._slave(bus, between[1])
        if abs(a - b) != 1:
            raise FieldbusError(
                f"bus '{bus}': {between[0]} and {between[1]} are not neighbours (positions {a} and {b})"
            )
        return min(a, b)

    def error_frames(self, bus: str, count: int = 1) -> None:
        """CAN: ``count`` error frames on the bus.

        Master: nothing: error frames carry no data and are not counted as frames of any node;
        the cycle stays fresh (a real controller retransmits the corrupted frame).
        """
        self._check_count(count)
        self._bus(bus)[1].error_frames(count)

    def bus_off(self, bus: str, slave: str, off: bool = True) -> None:
        """CAN: slave ``slave``'s controller goes bus-off (neither sends nor receives); ``off=False``:
        it recovers and, as CiA 301 says, boots again.

        Master: its inputs stale (SHORT) while off, heartbeat lost; on return a boot-up, then it
        is configured again and started (CANopen), or answers again (raw CAN).
        """
        emu, i = self._slave(bus, slave)
        emu.bus_off(i, off)

    def sdo_abort(
        self, bus: str, slave: str, index: int, sub_index: int | None = None, *, code: int = 0x06090030
    ) -> None:
        """Every SDO access to ``index:sub_index`` (None: any sub-index) of slave ``slave`` aborts with
        ``code`` (default 0x06090030, value range exceeded) until :meth:`clear_faults`.

        Master: bring-up fails with :class:`fieldbus.SdoAbortError` naming the slave, object and code
        (no drive enabled); in OP the transfer's future fails with it; a recovery after a power
        cycle fails and is retried (``BusStatus.recovery_error``). Not on raw CAN.
        """
        emu, i = self._slave(bus, slave)
        emu.sdo_abort(i, index, sub_index, code)

    def slow_sdo(self, bus: str, slave: str, cycles: int) -> None:
        """Slave ``slave``'s SDO server serves each request ``cycles`` cycles (SYNCs) late, with its
        objects as they are then, until :meth:`clear_faults` (or ``cycles=0``). CANopen only.

        Master: acyclic transfers to it take that much longer (the SDO client's timeout still bounds
        them). A drive fault's error code (0x603F, read by SDO when the map does not map it) is read
        that late: a controller that resets the fault before the read is served lets the drive clear
        the code first, and the ``DriveFault`` comes with code 0 - what ``hold_reset`` (see
        ``Operational.fault_code_pending``) prevents.
        """
        if cycles < 0:
            raise FieldbusError(f"slow_sdo: cycles must be >= 0, got {cycles}")
        emu, i = self._slave(bus, slave)
        emu.slow_sdo(i, cycles)

    def clear_faults(self, bus: str) -> None:
        """Undo every pending or lasting injection on bus ``bus`` (not a power cycle already done)."""
        self._bus(bus)[1].clear_faults()

    def recover_motor(self, bus: str, slave: str) -> bool:
        """Raw CAN: the master clears motor ``slave``'s fault and enables it again by its family's own
        sequence (``backend.recover``, between cycles); True when the motor is enabled again.

        Its set-points are seeded from where it is (position as read, speed and torque 0, the gains
        kept): it holds there until the controller writes its targets again.
        """
        model, _ = self._bus(bus)
        if model.type != "rawcan":
            raise FieldbusError(
                f"recover_motor: bus '{bus}' is {model.type}, not rawcan (CiA 402: fault reset)"
            )
        self._slave(bus, slave)  # a known name, or the error naming the bus's slaves
        backend: Any = self.op.network.backend(bus)
        return bool(backend.recover(slave))

    @staticmethod
    def _check_count(n: int) -> None:
        if n < 1:
            raise FieldbusError(f"a fault needs a count >= 1, got {n}")


def _load(network: str | Path | NetworkConfig) -> tuple[NetworkConfig, Path | None]:
    if isinstance(network, NetworkConfig):
        src = Path(network.source)
        return network, src if src.is_file() else None
    return load_network(network), Path(network)


@contextmanager
def emulate(
    network: str | Path | NetworkConfig,
    *,
    ethercat: str = "sim",
    can: str = "virtual",
    clock: Clock | None = None,
    receive_timeout_us: int | None = None,
    bring_up: bool = True,
    workdir: str | Path | None = None,
    bus_options: Mapping[str, Mapping[str, object]] | None = None,
) -> Iterator[Emulation]:
    """Emulators for every bus of ``network`` (a file, or a loaded one), the master opened on them.

    ``ethercat``: ``"sim"`` (in process, no root) or ``"veth"`` (pysoem over a veth pair,
    the emulator in a child process; needs root). ``can``: ``"virtual"`` (in process) or
    ``"udp"`` (``fieldbus_udp``, the emulator in a child process; no fault injection).
    ``clock``: default a :class:`~fieldbus.platform.clock.VirtualClock` when every emulator
    is in process, else the wall clock; a virtual clock with a child process is refused.
    ``receive_timeout_us`` replaces every bus's (a veth or UDP segment on a loaded machine
    needs a few ms). ``bus_options``: more backend options per bus name. Everything started
    is stopped on exit, also when the body or the bring-up raises; a machine that refuses
    (no root, no veth) raises :class:`~fieldbus.testing.EmulationUnavailable`.
    """
    if ethercat not in ETHERCAT_MODES:
        raise EmulationError(f"ethercat must be one of {', '.join(ETHERCAT_MODES)}, got {ethercat!r}")
    if can not in CAN_MODES:
        raise EmulationError(f"can must be one of {', '.join(CAN_MODES)}, got {can!r}")
    model, source = _load(network)
    types = {("ethercat" if b.type == "sim" else b.type) for b in model.buses}
    in_process = not ("ethercat" in types and ethercat == "veth") and not (
        types & {"canopen", "rawcan"} and can == "udp"
    )
    if clock is None:
        clock = VirtualClock() if in_process else WALL
    elif is_virtual(clock) and not in_process:
        raise EmulationError(
            "a virtual clock needs every emulator in this process: veth and udp emulators run in "
            "real time in a child process (use ethercat='sim', can='virtual', or no clock)"
        )
    unknown = sorted(set(bus_options or {}) - {b.name for b in model.buses})
    if unknown:
        raise EmulationError(f"bus_options name no bus of the network: {', '.join(unknown)}")
    with ExitStack() as cleanup:
        if workdir is None:
            workdir = cleanup.enter_context(tempfile.TemporaryDirectory(prefix="fieldbus-testing-"))
        context = EmulationContext(
            clock=clock,
            ethercat=ethercat,
            can=can,
            workdir=Path(workdir),
            source=source,
            cleanup=cleanup,
            virtual=is_virtual(clock),
        )
        emulators: dict[str, BusEmulator] = {}
        buses = []
        options: dict[str, dict[str, object]] = {}
        for bus in model.buses:
            start = find_emulator("ethercat" if bus.type == "sim" else bus.type)
            emu = start(context, bus)
            cleanup.callback(emu.close)
            emulators[bus.name] = emu
            changes = emu.bus_changes()
            if receive_timeout_us is not None:
                changes["receive_timeout_us"] = int(receive_timeout_us)
            buses.append(dataclasses.replace(bus, **changes))
            options[bus.name] = {
                **emu.backend_options(),
                **dict((bus_options or {}).get(bus.name, {})),
            }
        emulated = dataclasses.replace(model, buses=tuple(buses))
        # the clock paces the close wind-down and goes to every backend that reads one (sim, CAN)
        net = open_network(emulated, bus_options=options, clock=clock)
        cleanup.callback(net.close)
        for bus in model.buses:
            emulators[bus.name].attach(net.backend(bus.name))
        emulation = Emulation(net, emulated, emulators, clock)
        if bring_up:
            emulation.bring_up()
        yield emulation
