"""A model-based test of the safety contract (docs/safety.md) under arbitrary faults.

hypothesis drives a network through random sequences of steps: exchange,
frame loss, short or corrupted working counters, power cycles, node silence,
transmit errors, bus-off, valid and invalid SDO requests from another thread,
clear_safe_stop and close. After every step the invariants are checked
against a model that knows only what the test injected and what each cycle
reported:

- S1: exchange() and close() never raise for a bus fault (only PhaseError after close);
- S2: every channel of a slave that is not fresh is bit-identical to its last accepted values;
- S3: a slave whose reply the test destroyed is never fresh;
- S4: the latch closes at safe_stop_after misses in a row or at a bus error and opens
  only after clear_safe_stop() and release_after fresh cycles; a clear during an
  outage is refused;
- S5: a malformed request raises at submit; every request's future is done by close();
- S11: a command written as NaN, +-inf or out of the map's window (rule ``bad_command``) reaches the
  wire as the model's value: NaN keeps the value sent last, inf and out-of-window values saturate to
  the window; what the drive received (the emulated ESC's SM2 memory, the CANopen node's dictionary,
  the raw-CAN frame on the bus) is never outside the window nor the wire type's extreme.

Three networks: EtherCAT on the in-process emulator (sim), CANopen and raw-CAN
MIT motors on python-can's virtual bus against the emulators in sim_slaves.
The CAN emulators run in threads, so a CAN cycle may also miss on its own
(load): the model takes any reported miss as input and checks the invariants
as implications, never a timing.

Profiles: the suite runs a fixed seed (derandomized) of a few thousand steps in
all. A long soak: ``FIELDBUS_MODEL_EXAMPLES=500 FIELDBUS_MODEL_STEPS=200 pytest
tests/integration/test_safety_model.py`` (random seeds unless
``FIELDBUS_MODEL_DERANDOMIZE=1``).
"""

from __future__ import annotations

import itertools
import json
import math
import os
import struct
import threading
from concurrent.futures import Future
from pathlib import Path
from typing import Any

import can
import pytest
from hypothesis import HealthCheck, settings
from hypothesis import strategies as st
from hypothesis.stateful import RuleBasedStateMachine, initialize, invariant, rule

import fieldbus
from fieldbus.commands.demo import DEMO_MAP
from fieldbus.core.safety import SafeStopClearError, Verdict
from fieldbus.errors import PhaseError, RequestError

MIT_MAP = Path(__file__).resolve().parents[2] / "pdo_maps" / "cubemars_ak80_9_mit.yaml"
SAFE_STOP_AFTER = 4
INT32_MAX, INT32_MIN = 2**31 - 1, -(2**31)
COUNTS_PER_RAD = 20860.7568  # DEMO_MAP's target_position factor
WINDOW_COUNTS = (-41721, 62582)  # 0x607D:01..02 written at start-up: -2 rad .. 3 rad
BAD = st.sampled_from([math.nan, math.inf, -math.inf, 1e9, -1e9, 2.5, -1.5, 0.25, 40.0, -40.0])


def windowed_demo_map(folder: Path) -> Path:
    """DEMO_MAP with the software position limit 0x607D as start-up SDOs (the output path's window)."""
    f = folder / "joint.yaml"
    f.write_text(
        DEMO_MAP.read_text().replace(
            "sdo:\n",
            "sdo:\n"
            f"  - {{index: 0x607D, sub_index: 1, type: int32, value: {WINDOW_COUNTS[0]}}}\n"
            f"  - {{index: 0x607D, sub_index: 2, type: int32, value: {WINDOW_COUNTS[1]}}}\n",
            1,
        )
    )
    return f


RELEASE_AFTER = 3
_channels = itertools.count()
_tmp = Path(os.environ.get("TMPDIR", "/tmp"))


def _profile(examples: int, steps: int) -> settings:
    return settings(
        max_examples=int(os.environ.get("FIELDBUS_MODEL_EXAMPLES", examples)),
        stateful_step_count=int(os.environ.get("FIELDBUS_MODEL_STEPS", steps)),
        derandomize=os.environ.get(
            "FIELDBUS_MODEL_DERANDOMIZE", "1" if "FIELDBUS_MODEL_EXAMPLES" not in os.environ else "0"
        )
        == "1",
        deadline=None,
        suppress_health_check=list(HealthCheck),
        database=None,
    )


class _FlakyBus(can.BusABC):  # type: ignore[misc]
    """python-can's virtual bus whose send / receive raise while told to (transmit error, bus-off)."""

    def __init__(self, channel: str) -> None:
        self._inner = can.Bus(interface="virtual", channel=channel)
        self.tx_fail = 0  # the next n sends raise
        self.off = 0  # the next n receives raise (bus-off)
        self.sent: dict[int, bytes] = {}  # CAN id -> the data of the last frame sent
        super().__init__(channel=channel)

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        if self.tx_fail > 0:
            self.tx_fail -= 1
            raise can.CanOperationError("Transmit buffer full")
        self.sent[msg.arbitration_id] = bytes(msg.data)
        self._inner.send(msg, timeout)

    def _recv_internal(self, timeout: float | None) -> tuple[can.Message | None, bool]:
        if self.off > 0:
            self.off -= 1
            raise can.CanOperationError("bus-off")
        return self._inner.recv(timeout), False

    def shutdown(self) -> None:
        self._inner.shutdown()
        super().shutdown()


class ContractMachine(RuleBasedStateMachine):
    """The model and the rules every bus shares; subclasses make the network and its fault rules."""

    def __init__(self) -> None:
        super().__init__()
        self.net: fieldbus.Network | None = None
        self.op: fieldbus.Operational | None = None
        self.closed = False
        self.futures: list[Future[bytes | None]] = []
        self.must_stale: dict[int, int] = {}  # slave index -> cycles from the next one that must be stale
        self.silent: set[int] = set()  # slaves that must be stale from the next cycle on (after grace)
        self.grace = 0
        # the latch model (S4)
        self.streak = 0
        self.ok_run = 0
        self.latched = False
        self.clear_pending = False
        self.last_ok = True
        self.accepted: list[tuple[bytes, bytes]] = []  # per slave: values row, wire row last accepted
        self.rows: list[tuple[Any, int]] = []
        self.expect: dict[int, float] = {}  # axis -> the command value the output path must send (S11)

    # the command channel the rule bad_command writes and its window (engineering units)
    target = "target_position"
    window = (WINDOW_COUNTS[0] / COUNTS_PER_RAD, WINDOW_COUNTS[1] / COUNTS_PER_RAD)

    def check_wire(self) -> None:
        """S11 on what the drives received (each bus its own oracle)."""

    # -- subclass hooks ---------------------------------------------------------------------
    def open(self) -> fieldbus.Network:
        raise NotImplementedError

    def slaves(self) -> list[str]:
        assert self.net is not None
        return [a.slave.name for a in self.net.backends[0].areas]

    @initialize()
    def bring_up(self) -> None:
        self.net = self.open()
        self.op = self.net.bring_up()
        b = self.net.backends[0]
        self.rows = [(b.groups[a.group].image.inputs, a.row) for a in b.areas]
        self.accepted = [self._row(i) for i in range(len(self.rows))]

    def _row(self, i: int) -> tuple[bytes, bytes]:
        inputs, row = self.rows[i]
        return inputs.values[row : row + 1].tobytes(), inputs.wire[row].tobytes()

    # -- the cycle and the model --------------------------------------------------------------
    @rule()
    def exchange(self) -> None:
        self._exchange()

    @rule(n=st.integers(1, 12))
    def run(self, n: int) -> None:
        for _ in range(n):
            self._exchange()

    def _exchange(self) -> None:
        assert self.op is not None
        if self.closed:
            with pytest.raises(PhaseError):
                self.op.exchange()
            return
        res = self.op.exchange()  # S1: never raises
        self._check_outputs()
        bus = res.buses[0]
        for i in range(len(self.rows)):
            if bus.fresh[i]:
                self.accepted[i] = self._row(i)
            else:  # S2: untouched, bit for bit
                assert self._row(i) == self.accepted[i], f"stale slave {i} changed"
        for i, left in list(self.must_stale.items()):  # S3
            assert not bus.fresh[i], f"slave {i} fresh in a cycle whose reply was destroyed"
            if left <= 1:
                del self.must_stale[i]
            else:
                self.must_stale[i] = left - 1
        if self.grace > 0:
            self.grace -= 1
        else:
            for i in self.silent:
                assert not bus.fresh[i], f"silent slave {i} reads fresh"
        ok = bus.verdict is Verdict.OK
        assert ok == bool(bus.fresh.all())
        if ok:
            self.streak = 0
            self.ok_run += 1
            if self.latched and self.clear_pending and self.ok_run >= RELEASE_AFTER:
                self.latched = self.clear_pending = False
        else:
            self.ok_run = 0
            self.streak += 1
            self.clear_pending = False
            if bus.verdict is Verdict.ERROR or self.streak >= SAFE_STOP_AFTER:
                self.latched = True
        self.last_ok = ok
        assert res.safe_stop == self.latched == bus.safe_stop, (res.safe_stop, self.latched, bus)

    # -- the one output path (S11) ------------------------------------------------------------------
    @rule(axis=st.integers(0, 7), value=BAD)
    def bad_command(self, axis: int, value: float) -> None:
        assert self.op is not None
        if self.closed:
            return
        out = self.op["bus"].outputs[self.target]
        axis %= len(out)
        prev = float(out[axis])  # after an exchange the image holds what was sent
        lo, hi = self.window
        want = prev if math.isnan(value) else min(hi, max(lo, value))
        out[axis] = value
        self.expect[axis] = want

    def _check_outputs(self) -> None:
        assert self.op is not None
        out = self.op["bus"].outputs[self.target]
        for axis, want in self.expect.items():
            assert float(out[axis]) == pytest.approx(want, abs=1e-9), (axis, float(out[axis]), want)
        lo, hi = self.window
        assert all(lo - 1e-9 <= float(v) <= hi + 1e-9 for v in out), list(out)
        self.check_wire()

    @rule()
    def clear(self) -> None:
        assert self.op is not None
        if self.closed:
            with pytest.raises(PhaseError):
                self.op.clear_safe_stop()
            return
        if self.latched and not self.last_ok:
            with pytest.raises(SafeStopClearError):
                self.op.clear_safe_stop()
            return
        opened = self.op.clear_safe_stop()
        if self.latched:
            self.clear_pending = True
            if self.ok_run >= RELEASE_AFTER:
                self.latched = self.clear_pending = False
        assert opened == (not self.latched)
        assert self.op.result.safe_stop == self.latched

    # -- requests from another thread (S5) ----------------------------------------------------------
    @rule(
        slave=st.integers(0, 7),
        index=st.one_of(st.integers(0x1000, 0x1018), st.integers(-3, 0x20000)),
        sub=st.one_of(st.integers(0, 4), st.integers(-2, 0x300)),
        write=st.booleans(),
    )
    def request(self, slave: int, index: int, sub: int, write: bool) -> None:
        assert self.op is not None
        names = self.slaves()
        name = names[slave % len(names)]
        valid = 0 <= index <= 0xFFFF and 0 <= sub <= 0xFF
        outcome: list[BaseException | Future[bytes | None]] = []

        def ask() -> None:
            assert self.op is not None
            try:
                if write:
                    outcome.append(self.op.submit_sdo_write("bus", name, index, sub, b"\x00\x00"))
                else:
                    outcome.append(self.op.submit_sdo_read("bus", name, index, sub))
            except BaseException as exc:
                outcome.append(exc)

        t = threading.Thread(target=ask)
        t.start()
        t.join()
        (got,) = outcome
        if self.closed:
            assert isinstance(got, PhaseError)
        elif valid:
            assert isinstance(got, Future), got
            self.futures.append(got)
        else:
            assert isinstance(got, RequestError), got

    @rule()
    def close(self) -> None:
        assert self.net is not None
        self.net.close()  # S1: never raises for a bus fault
        self.closed = True
        assert all(f.done() for f in self.futures)  # S5: nothing outlives close()
        assert self.net.last_wind_down is not None

    def teardown(self) -> None:
        if self.net is not None:
            self.net.close()
            assert all(f.done() for f in self.futures)
        self.close_emulators()

    def close_emulators(self) -> None:
        pass

    def destroyed(self, i: int, n: int) -> None:
        """Slave ``i``'s next ``n`` replies are destroyed by the test: those cycles must be stale."""
        self.must_stale[i] = max(self.must_stale.get(i, 0), n)

    @invariant()
    def stays_consistent(self) -> None:
        if self.op is not None and not self.closed:
            assert self.op.result.safe_stop == self.latched


# -- EtherCAT on the in-process emulator ------------------------------------------------------------


class SimMachine(ContractMachine):
    def open(self) -> fieldbus.Network:
        d = _tmp / f"fb-model-{os.getpid()}-{next(_channels)}"
        d.mkdir(parents=True, exist_ok=True)
        f = d / "net.yaml"
        f.write_text(
            f"cycle_time_us: 1000\nreceive_timeout_us: 5000\nsafe_stop_after: {SAFE_STOP_AFTER}\nbuses:\n"
            f"  - {{name: bus, type: ethercat, interface: sim0,"
            f" slaves: [{{name: 'j{{i}}', map: {json.dumps(str(windowed_demo_map(d)))}, count: 3}}]}}\n"
        )
        net = fieldbus.open_network(f, backend="sim", release_after=RELEASE_AFTER)
        b = net.backends[0]
        self.chain: Any = b.chain  # type: ignore[attr-defined]
        self.send_fail = 0
        self.recv_fail = 0
        real_send, real_receive = b.send, b.receive

        def send() -> None:
            if self.send_fail > 0:
                self.send_fail -= 1
                raise OSError(105, "No buffer space available")
            real_send()

        def receive() -> int | None:
            if self.recv_fail > 0:
                self.recv_fail -= 1
                raise OSError(100, "Network is down")
            return real_receive()

        b.send = send  # type: ignore[method-assign]
        b.receive = receive  # type: ignore[method-assign]
        return net

    def _all(self, n: int) -> None:
        for i in range(3):
            self.destroyed(i, n)

    def check_wire(self) -> None:
        """The target each emulated ESC holds in its SM2 memory (controlword u16, int32 target)."""
        for esc in self.chain.slaves:
            start, length = esc.sm[2][0], esc.sm[2][1]
            if int(esc.state) != 0x08 or length < 6:  # power-cycled and not back in OP: no outputs mapped
                continue
            got = struct.unpack_from("<Hi", esc.mem, start)[1]
            assert WINDOW_COUNTS[0] <= got <= WINDOW_COUNTS[1], got  # never INT32_MAX / INT32_MIN
        assert self.op is not None
        img = self.op["bus"].outputs
        for axis, want in self.expect.items():  # the master's encoded row: rint(value x factor)
            assert struct.unpack_from("<i", bytes(img.wire[axis]), 2)[0] == round(want * COUNTS_PER_RAD)

    @rule(n=st.integers(1, 8))
    def lose_frames(self, n: int) -> None:
        self.chain.drop_frames(n, process_data=True)
        self._all(n)

    @rule(n=st.integers(1, 6), delta=st.sampled_from([-1, -2, 1]))
    def bad_working_counter(self, n: int, delta: int) -> None:  # short, or corrupted (too big)
        self.chain.corrupt_wkc(delta, n)
        self._all(n)

    @rule(slave=st.integers(0, 2))
    def power_cycle(self, slave: int) -> None:
        self.chain.power_cycle(slave)
        self._all(1)

    @rule(n=st.integers(1, 3))
    def transmit_error(self, n: int) -> None:
        self.send_fail = n
        self._all(n)

    @rule(n=st.integers(1, 3))
    def bus_off(self, n: int) -> None:
        self.recv_fail = n
        self._all(n)


SimMachine.TestCase.settings = _profile(examples=40, steps=60)
test_safety_contract_on_sim = SimMachine.TestCase


# -- raw-CAN MIT motors on python-can's virtual bus -----------------------------------------------------


class RawCanMachine(ContractMachine):
    target = "position"
    window = (-12.5, 12.5)  # the MIT frame's position field, min..max

    def check_wire(self) -> None:
        """The MIT command frames on the bus (p16 big-endian over min..max) equal what the rules sent."""
        lo, hi = self.window
        sent, self.flaky.sent = self.flaky.sent, {}  # the frames of this exchange only
        for axis, want in self.expect.items():
            data = sent.get(1 + axis)
            if data is None or len(data) != 8 or data[:7] == b"\xff" * 7:  # none, or enter / exit / zero
                continue
            got = int.from_bytes(data[:2], "big") / 0xFFFF * (hi - lo) + lo
            assert got == pytest.approx(want, abs=(hi - lo) / 0xFFFF), (axis, got, want)

    def open(self) -> fieldbus.Network:
        from sim_slaves.mit_motor import MitMotorSimulator

        channel = f"fb-model-mit-{os.getpid()}-{next(_channels)}"
        d = _tmp / channel
        d.mkdir(parents=True, exist_ok=True)
        f = d / "net.yaml"
        f.write_text(
            f"cycle_time_us: 2000\nreceive_timeout_us: 20000\nsafe_stop_after: {SAFE_STOP_AFTER}\nbuses:\n"
            f"  - {{name: bus, type: rawcan, interface: {channel}, can_interface: virtual,\n"
            f"     slaves: [{{name: 'm{{i}}', map: {json.dumps(str(MIT_MAP))}, node_id: 1, count: 2}}]}}\n"
        )
        drive = fieldbus.load_drive_map(MIT_MAP)
        self.sim_bus = can.Bus(interface="virtual", channel=channel)
        self.sim = MitMotorSimulator(self.sim_bus, [(drive, n) for n in (1, 2)], dt_s=0.002)
        self.sim.__enter__()
        self.flaky = _FlakyBus(channel)
        return fieldbus.open_network(
            f, bus_options={"bus": {"can_bus": self.flaky}}, release_after=RELEASE_AFTER
        )

    @rule(node=st.integers(1, 2), n=st.integers(1, 5))
    def drop_replies(self, node: int, n: int) -> None:
        self.sim.drop_replies(node, n)  # in flight on a loaded machine: only S2 is checked for these

    @rule(node=st.integers(1, 2), quiet=st.booleans())
    def silence(self, node: int, quiet: bool) -> None:
        self.sim.silence(node, quiet)
        if quiet:
            self.silent.add(node - 1)
            self.grace = 2  # a reply already on the virtual bus may still arrive
        else:
            self.silent.discard(node - 1)

    @rule(n=st.integers(1, 3))
    def transmit_error(self, n: int) -> None:
        self.flaky.tx_fail = n
        self.destroyed(0, 1)
        self.destroyed(1, 1)

    @rule(n=st.integers(1, 3))
    def bus_off(self, n: int) -> None:
        self.flaky.off = n

    def close_emulators(self) -> None:
        self.sim.__exit__(None, None, None)
        self.sim_bus.shutdown()
        self.flaky.shutdown()


RawCanMachine.TestCase.settings = _profile(examples=8, steps=40)
test_safety_contract_on_rawcan = RawCanMachine.TestCase


# -- CANopen on python-can's virtual bus ----------------------------------------------------------------


class CanopenMachine(ContractMachine):
    def open(self) -> fieldbus.Network:
        from sim_slaves.canopen import CanopenSimulator

        channel = f"fb-model-co-{os.getpid()}-{next(_channels)}"
        d = _tmp / channel
        d.mkdir(parents=True, exist_ok=True)
        f = d / "net.yaml"
        f.write_text(
            f"cycle_time_us: 5000\nreceive_timeout_us: 20000\nsafe_stop_after: {SAFE_STOP_AFTER}\nbuses:\n"
            f"  - {{name: bus, type: canopen, interface: {channel}, can_interface: virtual,\n"
            f"     slaves: [{{name: 'n{{i}}', map: {json.dumps(str(windowed_demo_map(d)))}, node_id: 1, count: 2}}]}}\n"
        )
        drive = fieldbus.load_drive_map(windowed_demo_map(d))
        self.sim_bus = can.Bus(interface="virtual", channel=channel)
        self.sim = CanopenSimulator(self.sim_bus, [(drive, n) for n in (1, 2)], dt_s=0.005)
        self.sim.__enter__()
        self.flaky = _FlakyBus(channel)
        return fieldbus.open_network(
            f, bus_options={"bus": {"can_bus": self.flaky}}, release_after=RELEASE_AFTER
        )

    def check_wire(self) -> None:
        """The target each emulated node holds in its dictionary (written by its RPDO)."""
        for node in (1, 2):
            got = int(self.sim.node(node).od.get_value(0x607A, 0))
            assert WINDOW_COUNTS[0] <= got <= WINDOW_COUNTS[1], (node, got)

    @rule(node=st.integers(1, 2), n=st.integers(1, 5))
    def drop_tpdos(self, node: int, n: int) -> None:
        self.sim.drop_tpdos(node, n)  # in flight on a loaded machine: only S2 is checked for these

    @rule(node=st.integers(1, 2), off=st.booleans())
    def node_bus_off(self, node: int, off: bool) -> None:
        self.sim.bus_off(node, off)
        if off:
            self.silent.add(node - 1)
            self.grace = 2
        else:
            self.silent.discard(node - 1)

    @rule(node=st.integers(1, 2))
    def power_cycle(self, node: int) -> None:
        self.sim.power_cycle(node)

    @rule(n=st.integers(1, 3))
    def transmit_error(self, n: int) -> None:
        self.flaky.tx_fail = n

    def close_emulators(self) -> None:
        self.sim.__exit__(None, None, None)
        self.sim_bus.shutdown()
        self.flaky.shutdown()


CanopenMachine.TestCase.settings = _profile(examples=8, steps=40)
test_safety_contract_on_canopen = CanopenMachine.TestCase
