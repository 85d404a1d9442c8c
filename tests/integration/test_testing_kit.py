"""fieldbus.testing: networks emulated as written, faults by name with what the master sees, virtual time.

The master is the real one (open_network, the sim / CANopen / raw-CAN backends);
the oracle for each fault is the master's own per-cycle verdict and inputs, so
these tests can only use our own code on both sides (the veth test uses pysoem).
"""

from __future__ import annotations

import math
import subprocess
import threading
from pathlib import Path
from typing import Any

import numpy as np
import pytest

pytest.importorskip("can")

import fieldbus
from fieldbus.core.wkc import Verdict
from fieldbus.testing import (
    FaultNotSupported,
    assert_inputs_held,
    assert_no_miss,
    assert_safe_stop_latched,
    emulate,
)

DEMO = Path(fieldbus.__file__).parent / "data" / "demo_joint.yaml"
MIT = fieldbus.PDO_MAPS / "cubemars_ak80_9_mit.yaml"
OK, SHORT, TIMEOUT = int(Verdict.OK), int(Verdict.SHORT), int(Verdict.TIMEOUT)


def _network(tmp_path: Path, kind: str, n: int = 3, name: str = "net.yaml") -> Path:
    """A network file as a user writes it: the robot's interfaces, not the emulator's."""
    head = "cycle_time_us: 1000\nreceive_timeout_us: 500\nsafe_stop_after: 10\nbuses:\n"
    bus = {
        "ethercat": f"  - {{name: arm, type: ethercat, interface: enp3s0,\n     slaves: [{{name: 'j{{i}}', map: '{DEMO}', count: {n}}}]}}\n",
        "canopen": f"  - {{name: co, type: canopen, interface: can0, can_interface: socketcan, receive_timeout_us: 2000,\n     slaves: [{{name: 'c{{i}}', map: '{DEMO}', node_id: 1, count: {n}}}]}}\n",
        "rawcan": f"  - {{name: mit, type: rawcan, interface: can1, can_interface: socketcan,\n     slaves: [{{name: 'm{{i}}', map: '{MIT}', node_id: 1, count: {n}}}]}}\n",
    }
    f = tmp_path / name
    f.write_text(head + "".join(bus[k] for k in kind.split("+")))
    return f


class Follower:
    """A user's loop: enable every CiA 402 axis, then follow a sine; MIT motors: impedance to a sine."""

    def __init__(self, op: fieldbus.Operational) -> None:
        self.op = op
        self.parts = []
        for g in op:
            img = op[g]
            if "statusword" in img.inputs.names:
                ctrl = fieldbus.Cia402Controller(img.n_axes, mode=fieldbus.Mode.CSP)
                ctrl.set_goal(fieldbus.Goal.ENABLE)
                self.parts.append((img, ctrl))
            else:
                img.outputs["kp"][:] = 20.0
                img.outputs["kd"][:] = 1.0
                self.parts.append((img, None))
        self.k = 0

    def step(self, k: int) -> None:
        res = self.op.exchange()
        self.k = k
        if not res.fresh or res.safe_stop:
            return
        for img, ctrl in self.parts:
            if ctrl is None:
                img.outputs["position"][:] = 0.2 * math.sin(2 * math.pi * 0.5 * k / 1000)
                continue
            ctrl.step(img.inputs["statusword"], img.outputs["controlword"])
            if ctrl.all_reached:
                img.outputs["target_position"][:] = 0.3 * math.sin(2 * math.pi * 0.5 * k / 1000)
            else:
                img.outputs["target_position"][:] = img.inputs["position_actual_value"]


def _scenario(net: Path, seconds: float) -> dict[str, np.ndarray]:
    """Enable, follow, and on the way: a lost-frame burst, a power cycle, a drive fault, recovery."""
    with emulate(net) as emu:
        follower = Follower(emu.op)
        bus = emu.trace.bus_names[0]
        first = emu.model.bus(bus).slaves[0].name
        third = seconds / 3
        emu.run(follower.step, int(third * 1000))
        emu.lose_cycles(bus, 12)
        emu.run(follower.step, 200)
        emu.op.clear_safe_stop()
        emu.power_cycle(bus, first)
        emu.run(follower.step, int(third * 1000))
        emu.op.clear_safe_stop()
        if emu.model.bus(bus).type != "rawcan":
            emu.drive_fault(bus, first, 0x7300)
        emu.run(follower.step, int(third * 1000) - 200)
        out = {k: v.copy() for k, v in emu.trace.arrays().items()}
        out["clock_ns"] = np.array([emu.clock.now_ns()])
        return out


@pytest.mark.parametrize(("kind", "seconds"), [("ethercat", 10.0), ("canopen+rawcan", 2.0)])
def test_a_scenario_on_virtual_time_gives_the_same_cycles_twice_bit_for_bit(
    tmp_path: Path, kind: str, seconds: float
) -> None:
    net = _network(tmp_path, kind)
    first, second = _scenario(net, seconds), _scenario(net, seconds)
    assert first.keys() == second.keys()
    n = len(first["fresh"])
    assert n == 3 * int(seconds / 3 * 1000)
    assert first["clock_ns"][0] >= n * 1_000_000  # time passed on the clock, not on the machine
    for key in first:
        assert first[key].dtype == second[key].dtype and first[key].tobytes() == second[key].tobytes(), key
    # and the run did something worth comparing: faults seen, the sine followed
    assert first["safe_stop"].any() and first["fresh"][-100:].all()
    group = next(k for k in first if k.endswith(".inputs"))
    assert np.ptp(first[group][:, 0][first[group].dtype.names[1]]) > 0.1


@pytest.mark.parametrize(("kind", "bus"), [("ethercat", "arm"), ("canopen", "co"), ("rawcan", "mit")])
def test_lose_cycles_loses_exactly_that_many_cycles_of_process_data(
    tmp_path: Path, kind: str, bus: str
) -> None:
    with emulate(_network(tmp_path, kind)) as emu:
        emu.cycles(200)
        assert_no_miss(emu.trace)
        since = emu.trace.mark()
        emu.lose_cycles(bus, 15)
        emu.cycles(40)
        verdicts = emu.trace.verdict(bus)[since:]
        assert (verdicts[:15] == TIMEOUT).all() and (verdicts[15:] == OK).all(), verdicts
        assert assert_safe_stop_latched(emu.trace, within=10, since=since) == since + 9
        assert assert_inputs_held(emu.trace, bus, since=since) == 15 * 3


def test_a_power_cycle_during_a_burst_still_loses_only_the_process_data(tmp_path: Path) -> None:
    """The recovery's frames (reading AL status, re-bring-up) are not eaten by a process-data drop."""
    with emulate(_network(tmp_path, "ethercat")) as emu:
        emu.cycles(100)
        since = emu.trace.mark()
        emu.power_cycle("arm", "j1")
        emu.lose_cycles("arm", 15)
        emu.cycles(400)
        verdicts = emu.trace.verdict("arm")[since:]
        assert (verdicts[:15] == TIMEOUT).all()
        status = emu.op.result.bus("arm")
        assert status.recoveries == 1 and not status.recovering and verdicts[-1] == OK


def test_ethercat_faults_as_the_master_sees_them(tmp_path: Path) -> None:
    with emulate(_network(tmp_path, "ethercat")) as emu:
        follower = Follower(emu.op)
        emu.run(follower.step, 300)
        arm = emu.op["arm"]
        since = emu.trace.mark()
        emu.short_wkc("arm", 3)
        emu.run(follower.step, 5)
        assert list(emu.trace.verdict("arm")[since:]) == [SHORT] * 3 + [OK] * 2
        # a delay shorter than the receive timeout: on time, and exchange() waited it on the clock
        t0 = emu.clock.now_ns()
        emu.delay("arm", 0.0002)
        emu.op.exchange()
        assert emu.op.result.fresh and emu.clock.now_ns() - t0 == 200_000
        since = emu.trace.mark()
        emu.delay("arm", 0.002, cycles=2)  # longer: a miss each
        emu.run(follower.step, 4)
        assert list(emu.trace.verdict("arm")[since:]) == [TIMEOUT] * 2 + [OK] * 2
        # corrupted inputs: fresh, wrong
        since = emu.trace.mark()
        good = arm.inputs["statusword"][1]
        emu.corrupt_inputs("arm", "j1", 1)
        emu.op.exchange()
        assert emu.op.result.fresh and arm.inputs["statusword"][1] == good ^ 0xFFFF
        emu.run(follower.step, 2)
        assert arm.inputs["statusword"][1] == good
        # a drive fault: FAULT in the statusword, the EMCY with its code
        emu.drive_fault("arm", "j2", 0x7300)
        emu.cycles(20)
        assert arm.inputs["statusword"][2] & 0x4F == 0x08  # FAULT
        assert emu.drive_states("arm")[2] is fieldbus.State402.FAULT
        code = emu.op.submit_sdo_read("arm", "j2", 0x603F, 0)
        emu.cycles(50)
        assert int.from_bytes(code.result(0), "little") == 0x7300
        assert (0x7300, 0x01) in [(c, r) for _, c, r in emu.network.backend("arm").emergencies]  # type: ignore[attr-defined]
        with pytest.raises(FaultNotSupported, match="bus_off"):
            emu.bus_off("arm", "j0")
        with pytest.raises(fieldbus.FieldbusError, match="no slave 'j9'"):
            emu.power_cycle("arm", "j9")


def test_an_sdo_abort_fails_the_bring_up_naming_slave_and_object(tmp_path: Path) -> None:
    for kind, bus in (("ethercat", "arm"), ("canopen", "co")):
        with emulate(_network(tmp_path, kind), bring_up=False) as emu:
            slave = emu.model.bus(bus).slaves[1].name
            emu.sdo_abort(bus, slave, 0x6060, 0, code=0x06090030)
            with pytest.raises(fieldbus.SdoAbortError) as exc:
                emu.bring_up()
            assert exc.value.slave == slave and exc.value.index == 0x6060 and exc.value.code == 0x06090030


def test_can_faults_as_the_master_sees_them(tmp_path: Path) -> None:
    with emulate(_network(tmp_path, "canopen")) as emu:
        follower = Follower(emu.op)
        emu.run(follower.step, 300)
        since = emu.trace.mark()
        emu.short_wkc("co", 2, slave="c1")
        emu.error_frames("co", 5)
        emu.run(follower.step, 4)
        fresh = emu.trace.slave_fresh("co")[since:]
        assert fresh[:2, 1].sum() == 0 and fresh[:2, [0, 2]].all() and fresh[2:].all()
        # silence: stale, then the heartbeat reported lost; back: fresh with no reconfiguration
        since = emu.trace.mark()
        emu.silence("co", "c2")
        emu.run(follower.step, 200)
        backend = emu.network.backend("co")
        assert backend.heartbeat_lost_slaves() == ["c2"]  # type: ignore[attr-defined]
        assert not emu.trace.slave_fresh("co")[since:, 2].any()
        emu.silence("co", "c2", False)
        _clear_when_back(emu, follower.step)  # a clear during the outage is refused (docs/safety.md S4)
        emu.run(follower.step, 300)
        assert emu.op.result.fresh and emu.op.result.bus("co").recoveries == 0
        # bus-off and back: the node boots and is configured again by the master
        emu.bus_off("co", "c0")
        emu.run(follower.step, 50)
        emu.bus_off("co", "c0", off=False)
        _clear_when_back(emu, follower.step, within=500)
        emu.run(follower.step, 500)
        assert emu.op.result.fresh and emu.op.result.bus("co").recoveries == 1
        # a drive fault reaches the master as an EMCY with its code
        emu.drive_fault("co", "c1", 0x7300)
        emu.run(follower.step, 5)
        assert [e.code for e in backend.emergencies][-1:] == [0x7300]  # type: ignore[attr-defined]
        with pytest.raises(FaultNotSupported, match="delay"):
            emu.delay("co", 0.01)


def test_everything_is_torn_down_when_the_body_raises(tmp_path: Path) -> None:
    """Wall-clock CAN (python-can virtual bus, the simulator's thread): the thread is gone afterwards."""
    before = {t.name for t in threading.enumerate()}
    assert "canopen-nodes" not in before
    with (
        pytest.raises(RuntimeError, match="the test failed"),
        emulate(_network(tmp_path, "canopen"), clock=fieldbus.testing.WallClock()) as emu,
    ):
        assert not emu.virtual
        assert "canopen-nodes" in {t.name for t in threading.enumerate()}
        emu.cycles(20)
        raise RuntimeError("the test failed")
    assert "canopen-nodes" not in {t.name for t in threading.enumerate()}
    with pytest.raises(fieldbus.PhaseError):
        emu.op.exchange()


@pytest.mark.veth
def test_over_veth_the_file_is_run_as_written_and_the_pair_removed(
    tmp_path: Path, request: pytest.FixtureRequest
) -> None:
    request.getfixturevalue("veth_possible")  # pysoem there, the machine makes a veth pair
    net = _network(tmp_path, "ethercat")
    text = net.read_text()
    try:
        with emulate(net, ethercat="veth", receive_timeout_us=20000) as emu:
            iface = emu.model.bus("arm").interface
            assert iface is not None and iface.startswith("fbm")
            emu.cycles(50)
            emu.lose_cycles("arm", 3)
            since = emu.trace.mark()
            emu.cycles(10)
            assert (emu.trace.verdict("arm")[since : since + 3] == TIMEOUT).all()
            raise RuntimeError("the test failed")
    except RuntimeError:
        pass
    assert net.read_text() == text
    gone = subprocess.run(["ip", "link", "show", iface], capture_output=True, check=False)
    assert gone.returncode != 0


def _clear_when_back(emu: Any, step: Any, within: int = 300) -> None:
    """Run until every bus is fresh again (at most ``within`` cycles), then ask to clear the safe stop."""
    for _ in range(within):
        if emu.op.result.fresh:
            break
        emu.run(step, 1)
    assert emu.op.result.fresh, f"not back within {within} cycles"
    emu.op.clear_safe_stop()
