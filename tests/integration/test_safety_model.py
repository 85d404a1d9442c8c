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

import atexit
import itertools
import json
import math
import os
import shutil
import struct
import tempfile
import threading
from concurrent.futures import Future
from pathlib import Path
from typing import Any

import can
import pytest
import yaml
from hypothesis import HealthCheck, settings
from hypothesis import strategies as st
from hypothesis.stateful import RuleBasedStateMachine, initialize, invariant, precondition, rule

import fieldbus
from fieldbus.commands.demo import DEMO_MAP
from fieldbus.core.acyclic_modes import AcyclicModes
from fieldbus.core.cia402 import Cia402Controller, Goal, Mode, State402
from fieldbus.core.safety import SafeStopClearError, Verdict
from fieldbus.errors import PhaseError, RequestError
from fieldbus.platform.clock import VirtualClock

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
# one folder per test process for the machines' network files, removed when the process ends
_tmp = Path(tempfile.mkdtemp(prefix="fb-model-"))
atexit.register(shutil.rmtree, _tmp, True)


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
        self.corrupt_must = 0  # cycles whose working counter is corrupted (a new injection replaces it)
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
        self.sent: dict[int, float] = {}  # axis -> the command value the last exchange sent

    # the command channel the rule bad_command writes and its window (engineering units)
    target = "target_position"
    window: tuple[float, float] | None = (
        WINDOW_COUNTS[0] / COUNTS_PER_RAD,
        WINDOW_COUNTS[1] / COUNTS_PER_RAD,
    )

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
        if self.corrupt_must > 0:  # S3
            assert not bus.fresh.any(), "a slave fresh in a cycle whose working counter was corrupted"
            self.corrupt_must -= 1
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
        if self.closed or self.window is None:
            return
        out = self.op["bus"].outputs[self.target]
        axis %= len(out)
        # what was sent last (after an exchange the image holds it; a second write before the next
        # exchange replaces the first, whose value was never sent)
        prev = self.sent[axis] if axis in self.sent else float(out[axis])
        lo, hi = self.window
        want = prev if math.isnan(value) else min(hi, max(lo, value))
        out[axis] = value
        self.expect[axis] = want

    def _check_outputs(self) -> None:
        assert self.op is not None
        if self.window is None:  # a machine of its own map, without the output path's window
            return
        out = self.op["bus"].outputs[self.target]
        for axis, want in self.expect.items():
            assert float(out[axis]) == pytest.approx(want, abs=1e-9), (axis, float(out[axis]), want)
        lo, hi = self.window
        assert all(lo - 1e-9 <= float(v) <= hi + 1e-9 for v in out), list(out)
        self.sent = {axis: float(v) for axis, v in enumerate(out)}
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
        return self.open_sim(DEMO_MAP)

    def open_sim(self, drive_map: Path, **options: Any) -> fieldbus.Network:
        d = _tmp / f"fb-model-{os.getpid()}-{next(_channels)}"
        d.mkdir(parents=True, exist_ok=True)
        # the demo map with the output path's window (0x607D), or the caller's own map as it is
        chosen = windowed_demo_map(d) if drive_map == DEMO_MAP else drive_map
        f = d / "net.yaml"
        f.write_text(
            f"cycle_time_us: 1000\nreceive_timeout_us: 5000\nsafe_stop_after: {SAFE_STOP_AFTER}\nbuses:\n"
            f"  - {{name: bus, type: ethercat, interface: sim0,"
            f" slaves: [{{name: 'j{{i}}', map: {json.dumps(str(chosen))}, count: 3}}]}}\n"
        )
        net = fieldbus.open_network(f, backend="sim", release_after=RELEASE_AFTER, **options)
        b = net.backends[0]
        self.chain: Any = b.chain  # type: ignore[attr-defined]
        self.send_fail = 0
        self.recv_fail = 0
        self.on_receive: Any = None  # called after every receive (a probe of the drives)
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
            got = real_receive()
            if self.on_receive is not None:
                self.on_receive()
            return got

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
        self.chain.corrupt_wkc(delta, n)  # replaces a pending corruption (frame losses add up)
        self.corrupt_must = n

    @rule(slave=st.integers(0, 2))
    def power_cycle(self, slave: int) -> None:
        self.chain.power_cycle(slave)
        self._all(1)

    @rule(n=st.integers(1, 3))
    def transmit_error(self, n: int) -> None:
        self.send_fail += n  # adds up, as frame losses do (the model keeps the longest)
        self._all(n)

    @rule(n=st.integers(1, 3))
    def bus_off(self, n: int) -> None:
        self.recv_fail += n
        self._all(n)


SimMachine.TestCase.settings = _profile(examples=40, steps=60)
test_safety_contract_on_sim = SimMachine.TestCase


# -- S11 and S6 under a controller: transitions and closes on the in-process emulator -------------------


def _csv_map_without_modes() -> Path:
    """The demo joint with target_velocity (0x60FF) in its RxPDOs, 0x6060/0x6061 only by SDO."""
    f = _tmp / f"fb-model-{os.getpid()}-csv-no-modes.yaml"
    if not f.exists():
        doc = yaml.safe_load(Path(DEMO_MAP).read_text())
        for section in ("rpdo", "tpdo"):
            for pdo in doc[section]:
                pdo["channels"] = [c for c in pdo["channels"] if c["index"] not in (0x6060, 0x6061)]
        doc["rpdo"][1]["channels"].append(
            {"index": 0x60FF, "sub_index": 0, "type": "int32", "factor": 20860.7568, "unit": "rad/s"}
        )
        doc["name"] = "joint_csv_no_modes"
        f.write_text(yaml.safe_dump(doc, sort_keys=False))
    return f


class _HookClock(VirtualClock):
    """Virtual time (the drives' and the wind-down's); runs ``hook`` on its ``at``-th sleep."""

    def __init__(self) -> None:
        super().__init__()
        self.sleeps = 0
        self.at = -1
        self.hook: Any = None

    def sleep(self, seconds: float) -> None:
        self.sleeps += 1
        if self.sleeps == self.at and self.hook is not None:
            self.hook()
        super().sleep(seconds)


TOL_RAD_S = 1.0  # what a drive may still gain after the transition cycle (its own response), rad/s
STILL_RAD_S = 0.05  # at rest, rad/s
SETTLE_CYCLES = 200  # enabled in CSP/CSV with no command for this long: at rest
POWER_OFF_RAD_S = 0.5  # a drive's own |velocity| when the close takes its power: stopped, not coasting


class TransitionMachine(SimMachine):
    """Three drives in CSP/CSV/CST by SDO (AcyclicModes) under a Cia402Controller, plus the S11 model.

    S11, no transition starts motion: a command counts from its write until the next cycle in which
    step_image seeds the axis (a transition); from then until the next write the drive's own
    |velocity| never exceeds what it had at the transition (+ TOL_RAD_S over its first 5 cycles),
    and once it has been enabled in CSP or CSV for SETTLE_CYCLES it is at rest. S6 on the close
    rules: every drive powered when the close began is stopped when its power goes off, except a
    power-cycled one (no power to stop) - a short working counter, a power cycle, a second close.
    """

    N = 3
    window = None  # its map is not the demo map with a 0x607D window: bad_command is the other machines'

    def open(self) -> fieldbus.Network:
        self.clock = _HookClock()
        self.ctrl = Cia402Controller(self.N, mode=Mode.CSP)
        self.ctrl.set_goal(Goal.ENABLE)
        self.armed = [False] * self.N
        self.ceiling = [TOL_RAD_S] * self.N
        self.settling = [0] * self.N
        self.calm = [0] * self.N
        self.cycles_run = 0
        self.transitions_done = 0  # transitions the rule made (not skipped for an axis it could not enable)
        return self.open_sim(_csv_map_without_modes(), clock=self.clock)

    @initialize()
    def bring_up(self) -> None:
        super().bring_up()
        assert self.op is not None
        self.img = self.op["bus"]
        self.modes = AcyclicModes.for_group(self.op, "bus")
        self.drives = [s.app for s in self.chain.slaves]

    def _exchange(self) -> None:
        self.clock.advance(1_000_000)
        self.cycles_run += 1
        super()._exchange()
        if self.closed:
            return
        self.ctrl.step_image(self.img, modes=self.modes)
        for i, d in enumerate(self.drives):
            v = abs(d.velocity_rad_s)
            if self.ctrl.seeded[i]:
                if self.armed[i]:
                    self.armed[i], self.ceiling[i], self.settling[i] = False, v + TOL_RAD_S, 5
                elif self.settling[i] > 0:
                    self.ceiling[i] = max(self.ceiling[i], v + TOL_RAD_S)
                    self.settling[i] -= 1
            if self.armed[i]:
                self.calm[i] = 0
                continue
            assert v <= self.ceiling[i], (
                f"S11: drive {i} at {v:.2f} rad/s after a transition, no command since (was {self.ceiling[i]:.2f})"
            )
            steady = self.ctrl.state[i] == State402.OPERATION_ENABLED and not self.ctrl.seeded[i]
            steady = steady and int(self.modes.display[i]) in (Mode.CSP, Mode.CSV)
            self.calm[i] = self.calm[i] + 1 if steady else 0
            if self.calm[i] >= SETTLE_CYCLES:
                assert v <= STILL_RAD_S, (
                    f"S11: drive {i} moves at {v:.2f} rad/s, no command since a transition"
                )
        fresh = self.op is not None and self.op.result.fresh  # the controller sees the drives as they are
        for i, d in enumerate(self.drives):  # enabled in a mode nobody read: the drive's own 0x6061 says
            if (
                fresh
                and self.ctrl.reached[i]
                and self.ctrl.goal[i] == Goal.ENABLE
                and not self.ctrl.seeded[i]
            ):
                assert d.mode_display == self.ctrl.mode_request[i], (
                    f"S11: axis {i} enabled as {Mode(int(self.modes.display[i])).name}, the drive is in "
                    f"{Mode(d.mode_display).name}"
                )

    # -- the user ---------------------------------------------------------------------------------
    @rule(axis=st.integers(0, N - 1), x=st.floats(-1.0, 1.0), cycles=st.integers(0, 300))
    def command(self, axis: int, x: float, cycles: int) -> None:
        """Write a target in the axis's mode (only while it is enabled, not in a transition), run on."""
        self._command(axis, x)
        for _ in range(cycles):
            self._exchange()

    def _command(self, axis: int, x: float) -> None:
        if self.closed or self.ctrl.seeded[axis] or self.ctrl.state[axis] != State402.OPERATION_ENABLED:
            return
        mode = int(self.modes.display[axis])
        out, inp = self.img.outputs, self.img.inputs
        if mode == Mode.CSP:
            out["target_position"][axis] = inp["position_actual_value"][axis] + 0.05 * x
        elif mode == Mode.CSV:
            out["target_velocity"][axis] = 3.0 * x
        elif mode == Mode.CST:
            out["target_torque"][axis] = 0.1 * x
        else:
            return
        self.armed[axis] = True

    @rule(axis=st.integers(0, N - 1), mode=st.sampled_from([Mode.CSP, Mode.CSV, Mode.CST]))
    def request_mode(self, axis: int, mode: Mode) -> None:
        self.ctrl.request_mode(mode, axis)

    @rule(enable=st.booleans())
    def goal(self, enable: bool) -> None:
        self.ctrl.set_goal(Goal.ENABLE if enable else Goal.DISABLE)

    def _run(self, n: int) -> None:
        for _ in range(n):
            self._exchange()

    def _back(self, limit: int = 3000) -> None:
        """Cycles until the bus is fresh again, then clear the safe stop until it opens."""
        for k in range(limit):  # a fault injected just now shows only from the next cycles
            back = self.last_ok and self.op is not None and not self.op.result.buses[0].recovering
            if self.closed or (back and k > SAFE_STOP_AFTER + 2):
                break
            self._exchange()
        for _ in range(2 * RELEASE_AFTER + 2):
            if self.closed or not self.latched:
                break
            if self.last_ok:
                self.clear()
            self._exchange()

    @rule(
        kind=st.sampled_from(["reenable", "switch", "safe_stop", "power_cycle", "fault"]),
        axis=st.integers(0, N - 1),
        mode=st.sampled_from([Mode.CSP, Mode.CSV, Mode.CST]),
        then=st.sampled_from([Mode.CSP, Mode.CSV, Mode.CST]),
        x=st.floats(0.3, 1.0) | st.floats(-1.0, -0.3),
    )
    def transition(self, kind: str, axis: int, mode: Mode, then: Mode, x: float) -> None:
        """The axis enabled in ``mode`` (the bus brought back first), a command and motion, one transition
        (``then``: the mode a switch goes to), then SETTLE_CYCLES and more with no command."""
        if self.closed:
            return
        self._back()
        self.ctrl.set_goal(Goal.ENABLE, axis)
        self.ctrl.request_mode(mode, axis)
        for _ in range(600):
            if self.closed or (self.ctrl.reached[axis] and self.modes.display[axis] == mode):
                break
            self._exchange()
        else:
            return  # not enabled in time (a fault rule's leftovers): nothing to transition from
        self._command(axis, x)
        self.transitions_done += 1
        self._run(150)
        if kind == "reenable":
            self.ctrl.set_goal(Goal.DISABLE, axis)
            self._run(30)
            self.ctrl.set_goal(Goal.ENABLE, axis)
        elif kind == "switch":
            self.ctrl.request_mode(then, axis)
        elif kind == "safe_stop":
            self.lose_frames(SAFE_STOP_AFTER + 1)
            self._back()
        elif kind == "power_cycle":
            self.power_cycle(axis)
            self._back()
        else:
            self.drives[axis].inject_fault(0x8611)  # the controller resets it and enables again
        self._run(SETTLE_CYCLES + 150)

    # -- closes under faults (S6), each after a while of transitions -------------------------------------
    def ready_to_close(self) -> bool:
        return self.cycles_run >= 300

    @precondition(ready_to_close)
    @rule()
    def close(self) -> None:
        super().close()

    def _close_watched(self, spared: set[int], before: Any = None) -> None:
        """close() with every drive's |velocity| taken when its power goes (first seen unpowered)."""
        if self.closed:
            return
        self.chain.clear_faults()
        self.must_stale.clear()
        self.corrupt_must = 0
        self.send_fail = self.recv_fail = 0
        powered = (State402.OPERATION_ENABLED, State402.QUICK_STOP_ACTIVE)
        was = [d.state in powered for d in self.drives]
        off: list[float | None] = [None] * self.N

        def probe() -> None:
            for i, d in enumerate(self.drives):
                if off[i] is None and d.state not in powered:
                    off[i] = abs(d.velocity_rad_s)

        self.on_receive = probe
        if before is not None:
            before()
        self.close()
        self.on_receive = None
        for i in range(self.N):
            if was[i] and i not in spared:
                d = self.drives[i]
                assert off[i] is not None, (
                    f"S6: drive {i} left {State402(d.state).name} at {d.velocity_rad_s:.1f}"
                )
                assert off[i] < POWER_OFF_RAD_S, f"S6: drive {i} lost power at {off[i]:.2f} rad/s"
        assert self.net is not None and self.net.last_wind_down is not None
        for axis in self.net.last_wind_down.axes:  # watched to the end, not given up nor timed out
            if was[axis.axis] and axis.axis not in spared:
                assert axis.how in ("stopped", "state"), f"S6: {axis}"

    @precondition(ready_to_close)
    @rule(n=st.integers(1, 6))
    def close_with_a_short_working_counter(self, n: int) -> None:
        self._close_watched(set(), lambda: self.chain.corrupt_wkc(-1, n))

    @precondition(ready_to_close)
    @rule(slave=st.integers(0, N - 1))
    def close_after_a_power_cycle(self, slave: int) -> None:
        self._close_watched({slave}, lambda: self.chain.power_cycle(slave))

    @precondition(ready_to_close)
    @rule(delay=st.integers(1, 30), other_thread=st.booleans())
    def close_twice(self, delay: int, other_thread: bool) -> None:
        assert self.net is not None
        net = self.net
        t = threading.Thread(target=net.close)

        def second() -> None:
            if other_thread:
                t.start()
                t.join(0.2)  # it waits for the first
            else:
                net.close()  # a signal handler in the closing thread

        def arm() -> None:
            self.clock.at, self.clock.hook = self.clock.sleeps + delay, second

        self._close_watched(set(), arm)
        if t.is_alive() or t.ident is not None:
            t.join()


TransitionMachine.TestCase.settings = _profile(examples=15, steps=40)
test_no_transition_starts_motion_on_sim = TransitionMachine.TestCase


@pytest.mark.parametrize(
    "close",
    ["close_with_a_short_working_counter", "close_after_a_power_cycle", "same_thread", "other_thread"],
)
def test_every_close_under_a_fault_stops_every_moving_drive(close: str) -> None:
    """The machine's close rules on three drives moving in CSV at 3 rad/s (S6 checked by the rule)."""
    machine = TransitionMachine()
    try:
        machine.bring_up()
        machine.ctrl.request_mode(Mode.CSV)
        machine._run(300)
        assert machine.ctrl.all_reached
        for axis in range(TransitionMachine.N):
            machine._command(axis, 1.0)
        machine._run(300)
        assert all(d.velocity_rad_s > 2.5 for d in machine.drives)
        if close == "close_with_a_short_working_counter":
            machine.close_with_a_short_working_counter(6)
        elif close == "close_after_a_power_cycle":
            machine.close_after_a_power_cycle(1)
        else:
            machine.close_twice(10, close == "other_thread")
        assert machine.closed
    finally:
        machine.teardown()


@pytest.mark.parametrize("kind", ["reenable", "switch", "safe_stop", "power_cycle", "fault"])
def test_every_transition_from_every_mode_starts_no_motion(kind: str) -> None:
    """The machine's transition rule, every kind from every cyclic mode (to every mode for a switch),
    in a fixed order on one network: the sweep the random search may not reach in its few examples."""
    machine = TransitionMachine()
    try:
        machine.bring_up()
        modes = (Mode.CSP, Mode.CSV, Mode.CST)
        for k, (mode, then) in enumerate(itertools.product(modes, modes if kind == "switch" else (None,))):
            machine.transition(kind, k % TransitionMachine.N, mode, then or mode, 0.8 if k % 2 else -0.8)
            machine.stays_consistent()
        assert machine.transitions_done == (9 if kind == "switch" else 3)  # none skipped
    finally:
        machine.teardown()


# -- raw-CAN MIT motors on python-can's virtual bus -----------------------------------------------------


class RawCanMachine(ContractMachine):
    target = "position"
    window = (-12.5, 12.5)  # the MIT frame's position field, min..max

    def __init__(self) -> None:
        super().__init__()
        self.held: dict[
            int, float
        ] = {}  # S12: axis -> the position read when the latch opened, until a write

    def check_wire(self) -> None:
        """The MIT command frames on the bus (p16 big-endian over min..max) equal what the rules sent; after
        the latch opened and until the next command, each holds the position read then with no speed,
        gains nor torque (S12; v12 kp12 kd12 t12 decoded per the published MIT layout)."""
        lo, hi = self.window
        sent, self.flaky.sent = self.flaky.sent, {}  # the frames of this exchange only
        for axis in set(self.expect) | set(self.held):
            data = sent.get(1 + axis)
            if data is None or len(data) != 8 or data[:7] == b"\xff" * 7:  # none, or enter / exit / zero
                continue
            x = int.from_bytes(data, "big")
            got = (x >> 48) / 0xFFFF * (hi - lo) + lo
            if axis in self.expect:
                assert got == pytest.approx(self.expect[axis], abs=(hi - lo) / 0xFFFF), (
                    axis,
                    got,
                    self.expect,
                )
            if axis in self.held:
                assert got == pytest.approx(self.held[axis], abs=(hi - lo) / 0xFFFF), (axis, got, self.held)
                v, kp, kd, t = (x >> 36) & 0xFFF, (x >> 24) & 0xFFF, (x >> 12) & 0xFFF, x & 0xFFF
                assert (kp, kd) == (0, 0) and v in (2047, 2048) and t in (2047, 2048), (axis, hex(x))

    def _opened(self) -> None:
        """The latch opened: from the next cycle every motor holds the position read now (S12)."""
        assert self.op is not None
        pos = self.op["bus"].inputs["position"]
        self.held = {axis: float(pos[axis]) for axis in range(len(pos))}
        self.expect = dict(self.held)  # the image's targets are the seed now: what the path sends

    def _check_outputs(self) -> None:
        assert self.op is not None
        if self.latched and not self.op.result.safe_stop:  # the latch opened in this exchange
            self.check_wire()  # its frames: still the safe stop's, sent before the seed
            self._opened()
        super()._check_outputs()

    @rule()
    def clear(self) -> None:
        was = self.latched
        super().clear()
        if was and not self.latched and not self.closed:
            self._opened()

    @rule(axis=st.integers(0, 7), value=BAD)
    def bad_command(self, axis: int, value: float) -> None:
        super().bad_command(axis, value)
        self.held.pop(axis % 2, None)  # a command after the transition: followed from now on

    @rule(lost=st.integers(SAFE_STOP_AFTER, SAFE_STOP_AFTER + 3))
    def stop_then_clear(self, lost: int) -> None:
        """A safe stop (every reply lost), then its clear and release: the transition S12 judges."""
        if self.closed:
            return
        for node in (1, 2):
            self.sim.drop_replies(node, lost)
        for _ in range(50):  # bounded: a loaded machine may miss on its own
            self._exchange()
            if self.latched and self.last_ok:
                break
        self.clear()
        for _ in range(50):
            if not self.latched:
                break
            self._exchange()
        self._exchange()  # the first cycle after the release: the hold on the wire (check_wire)

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
