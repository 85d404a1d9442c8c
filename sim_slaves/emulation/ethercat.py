"""EtherCAT buses for :mod:`fieldbus.testing`: the chain inside the sim backend, or the runner over veth."""

from __future__ import annotations

from typing import Any

from fieldbus.core.network import Bus
from fieldbus.testing.provider import BusEmulator, EmulationContext, EmulationError, EmulationUnavailable
from sim_slaves.ethercat.axes import app_positions, app_states

CAN_ONLY = "a CAN fault (an EtherCAT slave has no controller of its own to go bus-off or send error frames)"
RET_TIMEOUT_US = 20_000
NOT_ALONE = "an EtherCAT slave on the line cannot go quiet alone: use power_cycle or lose_cycles"


def start(context: EmulationContext, bus: Bus) -> BusEmulator:
    """The emulator of EtherCAT bus ``bus`` as ``context.ethercat`` says (``sim`` or ``veth``)."""
    if context.ethercat == "veth" and bus.type != "sim":
        return VethBus(context, bus)
    return SimChainBus(bus)


class SimChainBus(BusEmulator):
    """The chain the ``sim`` backend builds from the bus's maps and ``emulator:`` options (in process)."""

    def __init__(self, bus: Bus) -> None:
        super().__init__(bus)
        self.backend: Any = None

    def bus_changes(self) -> dict[str, Any]:
        return {"type": "sim"}

    def attach(self, backend: Any) -> None:
        self.backend = backend

    @property
    def chain(self) -> Any:
        if self.backend is None:
            raise EmulationError(f"bus '{self.bus.name}': the network is not open yet")
        return self.backend.chain

    def drive_states(self) -> list[int]:
        return [st for s in self.chain.slaves for st in app_states(s.app)]  # each axis of a multi-axis slave

    def drive_positions(self) -> list[float]:
        return [p for s in self.chain.slaves for p in app_positions(s.app)]

    def lose_cycles(self, cycles: int) -> None:
        self.chain.drop_frames(cycles, process_data=True)

    def delay(self, seconds: float, cycles: int) -> None:
        self.backend.delay_cycles(seconds, cycles)

    def short_wkc(self, cycles: int, slave: int) -> None:
        self.chain.corrupt_wkc(-1, cycles)

    def corrupt_inputs(self, slave: int, cycles: int) -> None:
        self.backend.corrupt_inputs(slave, cycles)

    def power_cycle(self, slave: int) -> None:
        self.chain.power_cycle(slave)

    def firmware_power_loss(self, slave: int, after_bytes: int) -> None:
        self.chain.cut_power_during_foe(slave, after_bytes)

    def drive_fault(self, slave: int, code: int, axis: int = 0) -> None:
        app = self.chain.slaves[slave].app
        if not hasattr(app, "inject_fault"):
            raise self._unsupported("drive_fault", f"slave {slave} is not a CiA 402 drive")
        if axis:
            app.inject_fault(code, axis=axis)  # a MultiAxisDrive (the map's axes were checked)
        else:
            app.inject_fault(code)
        self.chain.emergency(slave, code, 0x01)

    def silence(self, slave: int, silent: bool) -> None:
        raise self._unsupported("silence", NOT_ALONE)

    def error_frames(self, count: int) -> None:
        raise self._unsupported("error_frames", CAN_ONLY)

    def bus_off(self, slave: int, off: bool) -> None:
        raise self._unsupported("bus_off", CAN_ONLY)

    def sdo_abort(self, slave: int, index: int, sub_index: int | None, code: int) -> None:
        self.chain.abort_sdo(slave, index, sub_index, code)

    def bit_errors(self, upstream: int, rate: float, seed: int) -> None:
        self.chain.bit_errors(upstream, rate, seed=seed)

    def flap_link(self, upstream: int) -> None:
        self.chain.flap_link(upstream)

    def clear_faults(self) -> None:
        self.chain.clear_faults()
        self.backend.clear_injections()


class VethBus(BusEmulator):
    """The wire runner (``python -m sim_slaves.ethercat``) on one end of a veth pair, pysoem on the other."""

    def __init__(self, context: EmulationContext, bus: Bus) -> None:
        super().__init__(bus)
        if context.source is None:
            raise EmulationError(
                f"bus '{bus.name}': over veth the emulator reads the network file: give its path"
            )
        try:
            import pysoem
        except ImportError:
            raise EmulationUnavailable(
                "EtherCAT over veth needs pysoem: pip install 'fieldbus[ethercat]'"
            ) from None
        from sim_slaves.ethercat.veth import VethUnavailable, emulated_segment

        try:
            self.emu = context.cleanup.enter_context(
                emulated_segment([], workdir=context.workdir, network=context.source, bus=bus.name)
            )
        except VethUnavailable as exc:
            raise EmulationUnavailable(str(exc)) from None
        # SOEM's frame round trip may take 20 ms instead of 2 (a user-space emulator on a shared
        # machine); process-wide, so put back when the emulation ends
        timeouts = pysoem.settings.timeouts
        old = timeouts.ret
        timeouts.ret = max(old, RET_TIMEOUT_US)
        context.cleanup.callback(setattr, timeouts, "ret", old)

    def bus_changes(self) -> dict[str, Any]:
        return {"interface": self.emu.iface, "redundant_interface": None}

    def _command(self, **msg: Any) -> dict[str, Any]:
        answer = self.emu.command(**msg)
        if not answer.get("ok"):
            raise EmulationError(f"bus '{self.bus.name}': the emulator refused {msg}: {answer.get('error')}")
        return answer

    def drive_states(self) -> list[int]:
        return [int(s) for s in self._command(cmd="status")["drive_states"]]

    def lose_cycles(self, cycles: int) -> None:
        self._command(cmd="drop", count=cycles, pd=True)

    def delay(self, seconds: float, cycles: int) -> None:
        self._command(cmd="delay", seconds=seconds, count=cycles)

    def short_wkc(self, cycles: int, slave: int) -> None:
        self._command(cmd="corrupt_wkc", delta=-1, count=cycles)

    def corrupt_inputs(self, slave: int, cycles: int) -> None:
        raise self._unsupported("corrupt_inputs", "the wire runner has no such hook: use ethercat='sim'")

    def power_cycle(self, slave: int) -> None:
        self._command(cmd="power_cycle", slave=slave)

    def firmware_power_loss(self, slave: int, after_bytes: int) -> None:
        self._command(cmd="foe_power_loss", slave=slave, after_bytes=after_bytes)

    def drive_fault(self, slave: int, code: int, axis: int = 0) -> None:
        self._command(cmd="drive_fault", slave=slave, code=code, axis=axis)

    def silence(self, slave: int, silent: bool) -> None:
        raise self._unsupported("silence", NOT_ALONE)

    def error_frames(self, count: int) -> None:
        raise self._unsupported("error_frames", CAN_ONLY)

    def bus_off(self, slave: int, off: bool) -> None:
        raise self._unsupported("bus_off", CAN_ONLY)

    def sdo_abort(self, slave: int, index: int, sub_index: int | None, code: int) -> None:
        self._command(cmd="abort_sdo", slave=slave, index=index, sub=sub_index, code=code)

    def bit_errors(self, upstream: int, rate: float, seed: int) -> None:
        self._command(cmd="bit_errors", slave=upstream, rate=rate, seed=seed)

    def flap_link(self, upstream: int) -> None:
        self._command(cmd="flap_link", slave=upstream)

    def clear_faults(self) -> None:
        self._command(cmd="clear")
