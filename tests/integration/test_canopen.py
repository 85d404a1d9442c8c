"""CANopen specifics on python-can's virtual bus: mapping by SDO, CiA 402 tracking, heartbeat, EMCY,
bring-up errors, stale inputs, recovery, transmission types, interop with canopen both ways.

The shared cyclic-API module (test_cyclic_api.py) runs its backend-neutral
tests (bring-up, identity, SDO aborts, tracking, stale inputs, the safe stop,
node-reset recovery) on this backend too.

Timing: the virtual bus is threads in one process (GIL switch interval 5 ms),
not real time, so networks here use a receive timeout of 20 ms (50 ms where a
miss must not come from load); on socketcan the seed's 500 µs is the default.
"""

from __future__ import annotations

import itertools
import json
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest

can = pytest.importorskip("can")
canopen = pytest.importorskip("canopen")

from fieldbus.commands.demo import DEMO_MAP  # noqa: E402
from fieldbus.core.cia402 import Cia402Controller, Goal, Mode, State402  # noqa: E402
from fieldbus.core.pdo import load_drive_map  # noqa: E402
from fieldbus.errors import SdoAbortError, StateTransitionError  # noqa: E402
from fieldbus.network import Network, open_network  # noqa: E402
from fieldbus.platform.clock import VirtualClock  # noqa: E402
from fieldbus.testing.lockstep import LockstepCanBus  # noqa: E402
from sim_slaves.canopen import CanopenNode, CanopenSimulator, NmtState  # noqa: E402
from sim_slaves.canopen.eds import to_canopen_od  # noqa: E402

pytestmark = pytest.mark.timeout(120)
_channels = itertools.count()
HEARTBEAT_MS = 100  # demo_joint.yaml
CYCLE_S = 0.005  # the networks' cycle_time_us; the emulated drives step this much per SYNC


@pytest.fixture
def channel() -> str:
    return f"fb-canopen-{next(_channels)}-{time.monotonic_ns()}"


def _net(
    tmp_path: Path,
    channel: str,
    map_file: Path,
    count: int,
    timeout_us: int = 20_000,
    safe_stop_after: int = 10,
) -> Path:
    f = tmp_path / "net.yaml"
    f.write_text(
        f"cycle_time_us: 5000\nreceive_timeout_us: {timeout_us}\nsafe_stop_after: {safe_stop_after}\nbuses:\n"
        f"  - {{name: bus, type: canopen, interface: {channel}, can_interface: virtual,\n"
        f"     slaves: [{{name: 'j{{i}}', map: {json.dumps(str(map_file))}, node_id: 1, count: {count}}}]}}\n"
    )
    return f


@pytest.fixture
def nodes() -> Iterator[CanopenSimulator]:
    """12 emulated drives in lockstep with the master on a virtual clock (fieldbus.testing's lockstep bus):
    what these tests assert (misses, time-outs, heartbeat times) is in cycles and virtual time, the same on
    a loaded machine; :func:`_open` opens a network on them."""
    drive = load_drive_map(DEMO_MAP)
    clock = VirtualClock()
    lockstep = LockstepCanBus(clock, "bus")
    sim = CanopenSimulator(lockstep.peer, [(drive, n) for n in range(1, 13)], dt_s=CYCLE_S, clock=clock)
    lockstep.handlers.append(sim.deliver)
    clock.watch(lambda _t: sim.deliver(None))  # heartbeats and timers run as virtual time passes
    sim.boot()
    _LOCKSTEP[id(sim)] = lockstep
    try:
        yield sim
    finally:
        del _LOCKSTEP[id(sim)]
    assert not sim.errors


_LOCKSTEP: dict[int, LockstepCanBus] = {}


def _open(nodes: CanopenSimulator, net_file: Path, **options: object) -> Network:
    """The network of ``net_file`` on the lockstep bus of ``nodes`` (its clock is the network's)."""
    lockstep = _LOCKSTEP[id(nodes)]
    return open_network(net_file, bus_options={"bus": {"can_bus": lockstep}}, clock=lockstep.clock, **options)


def _cycle(nodes: CanopenSimulator, op: Any) -> Any:
    """One cycle at the networks' rate: the cycle time passes on the virtual clock, then ``exchange()``."""
    _LOCKSTEP[id(nodes)].clock.advance(round(CYCLE_S * 1e9))
    return op.exchange()


def _now_s(nodes: CanopenSimulator) -> float:
    """The virtual time of ``nodes`` [s]."""
    return _LOCKSTEP[id(nodes)].clock.now_ns() / 1e9


def test_mapping_changed_by_sdo_is_what_the_nodes_send(
    nodes: CanopenSimulator, channel: str, tmp_path: Path
) -> None:
    """The network's map drops velocity from TPDO2: the plan remaps 12 nodes and the frames follow."""
    text = DEMO_MAP.read_text().replace(
        "      - {index: 0x606C, sub_index: 0, type: int32, factor: 4.79369e-5, unit: rad/s}\n", ""
    )
    assert text != DEMO_MAP.read_text()
    variant = tmp_path / "demo_joint_small.yaml"
    variant.write_text(text)
    with _open(nodes, _net(tmp_path, channel, variant, 12)) as net:
        op = net.bring_up()
        for n in range(1, 13):
            node = nodes.node(n)
            assert node.state is NmtState.OPERATIONAL
            assert [(c.index, c.sub_index) for c in node.od.pdo(0x1A01).channels] == [
                (0x6077, 0),
                (0x6061, 0),
            ]
            # what the node sends follows: TPDO2 is 3 bytes now (int16 + int8), TPDO1 still 6
            assert node.tpdo_sizes() == {0x180 + n: 6, 0x280 + n: 3}
        # read back through the backend too
        assert net.backends[0].sdo_read(4, 0x1A01, 0) == b"\x02"
        for _ in range(10):
            res = _cycle(nodes, op)
        assert res.fresh and res.buses[0].wkc == 24  # 12 nodes x 2 TPDOs
        img = op["bus"]
        assert "velocity_actual_value" not in img.inputs.values.dtype.names
        assert np.all(img.inputs["modes_of_operation_display"] == 8)
        assert nodes.syncs >= 10 and nodes.node(12).received_rpdos >= 20


def test_twelve_nodes_enable_through_cia402_and_track_a_sine_in_csp(
    nodes: CanopenSimulator, channel: str, tmp_path: Path
) -> None:
    """Bound: targets start + A (1 - cos 2 pi f t) / 2 with A = 0.5-1.05 rad, f = 0.5 Hz, 5 ms per SYNC
    (peak A pi f = 1.65 rad/s, 8.2 mrad per cycle): |actual - target sent in the same cycle| < 2 mrad.

    The RPDO is applied at the SYNC that follows it and the drive's CSP interpolation reaches it
    within that cycle, so the TPDO of the same SYNC reports it (measured: 0.45 mrad worst).
    """
    with _open(nodes, _net(tmp_path, channel, DEMO_MAP, 12)) as net:
        op = net.bring_up()
        img = op["bus"]
        sw, cw = img.inputs["statusword"], img.outputs["controlword"]
        display, mode = img.inputs["modes_of_operation_display"], img.outputs["modes_of_operation"]
        pos, target = img.inputs["position_actual_value"], img.outputs["target_position"]
        ctrl = _enable_csp(nodes, op, 12)
        assert [nodes.node(n).app.state for n in range(1, 13)] == [State402.OPERATION_ENABLED] * 12
        start = pos.copy()
        amplitude = 0.5 * (1 + 0.1 * np.arange(12))
        worst = 0.0
        for k in range(1, 401):  # one period: up and back
            target[:] = start + amplitude * (1 - np.cos(2 * np.pi * 0.5 * k * CYCLE_S)) / 2
            res = _cycle(nodes, op)
            assert res.fresh and not res.safe_stop
            ctrl.step(sw, cw, display, mode)
            worst = max(worst, float(np.abs(pos - target).max()))
            if k == 200:
                assert np.allclose(pos - start, amplitude, atol=2e-3)  # half way: at the top
        assert worst < 2e-3, worst
        assert ctrl.all_reached and np.all(np.abs(pos - start) < 2e-3)


def _enable_csp(nodes: CanopenSimulator, op: Any, n: int) -> Cia402Controller:
    """Bring the ``n`` drives of bus ``bus`` to OPERATION ENABLED in CSP, targets following the joints."""
    img = op["bus"]
    sw, cw = img.inputs["statusword"], img.outputs["controlword"]
    display, mode = img.inputs["modes_of_operation_display"], img.outputs["modes_of_operation"]
    pos, target = img.inputs["position_actual_value"], img.outputs["target_position"]
    ctrl = Cia402Controller(n, mode=Mode.CSP)
    ctrl.set_goal(Goal.ENABLE)
    for _ in range(100):
        if _cycle(nodes, op).fresh:
            ctrl.step(sw, cw, display, mode)
            target[:] = pos  # follow the joint while enabling: no jump on enable
            if ctrl.all_reached:
                break
    assert ctrl.all_reached, ctrl.state
    return ctrl


def test_one_drive_of_the_bank_faults_while_the_others_keep_tracking(
    nodes: CanopenSimulator, channel: str, tmp_path: Path
) -> None:
    """The 12 emulated drives are one DriveBank stepped together on SYNC; a fault in one stops only it."""
    assert nodes.bank.n == 12 and all(nodes.node(n).app is nodes.bank.drives[n - 1] for n in range(1, 13))
    with _open(nodes, _net(tmp_path, channel, DEMO_MAP, 12, safe_stop_after=1000)) as net:
        op = net.bring_up()
        pos, target = op["bus"].inputs["position_actual_value"], op["bus"].outputs["target_position"]
        _enable_csp(nodes, op, 12)
        start = pos.copy()
        nodes.node(5).app.inject_fault(0x2310)  # over-current in node 5's drive
        for k in range(1, 101):
            target[:] = start + 0.002 * k  # 0.4 rad/s ramp
            _cycle(nodes, op)
        states = [nodes.node(n).app.state for n in range(1, 13)]
        assert states[4] is State402.FAULT
        assert states[:4] + states[5:] == [State402.OPERATION_ENABLED] * 11
        others = np.arange(12) != 4
        assert np.all(np.abs(pos[others] - target[others]) < 5e-3)  # they still follow the ramp
        assert abs(pos[4] - start[4]) < 0.05  # the faulted one stopped (its quick-stop ramp, then still)


def test_sdo_abort_at_bring_up_names_node_object_code_and_enables_nothing(
    nodes: CanopenSimulator, channel: str, tmp_path: Path
) -> None:
    nodes.abort_sdo(3, 0x6060, 0, 0x06090030)  # node 3 refuses the map's start-up SDO (modes of operation)
    with pytest.raises(SdoAbortError) as exc, _open(nodes, _net(tmp_path, channel, DEMO_MAP, 12)) as net:
        net.bring_up()
    err = exc.value
    assert (err.code, err.index, err.sub_index, err.slave) == (0x06090030, 0x6060, 0, "j2")
    text = str(err)
    assert "node 3" in text and "0x6060:00" in text and "0x06090030" in text and "j2" in text
    _LOCKSTEP[id(nodes)].clock.advance(150_000_000)  # a heartbeat period: every node has reported since
    assert {nodes.node(n).state for n in range(1, 13)} == {NmtState.PRE_OPERATIONAL}  # nobody started
    assert all(nodes.node(n).app.state != State402.OPERATION_ENABLED for n in range(1, 13))
    assert nodes.syncs == 0  # no cycle ran


def test_identity_mismatch_lists_node_expected_and_found(channel: str, tmp_path: Path) -> None:
    other = tmp_path / "other_joint.yaml"
    other.write_text(DEMO_MAP.read_text().replace("product_id: 0x00000D01", "product_id: 0x00000D02"))
    demo = load_drive_map(DEMO_MAP)
    with (
        can.Bus(interface="virtual", channel=channel) as bus,
        CanopenSimulator(bus, [(demo, 1), (load_drive_map(other), 2), (demo, 3)]) as sim,
    ):
        with (
            pytest.raises(StateTransitionError) as exc,
            open_network(_net(tmp_path, channel, DEMO_MAP, 3)) as net,
        ):
            net.bring_up()
        text = str(exc.value)
        assert "node 2 (j1): expected demo_joint vendor 0x00000FB1 product 0x00000D01" in text
        assert "found vendor 0x00000FB1 product 0x00000D02" in text
        assert "node 1 " not in text and "node 3 " not in text
        assert {n.state for n in sim.nodes.values()} == {NmtState.PRE_OPERATIONAL}
        assert not sim.errors


def test_heartbeat_loss_is_seen_within_consumer_time_plus_a_cycle(
    nodes: CanopenSimulator, channel: str, tmp_path: Path
) -> None:
    with _open(nodes, _net(tmp_path, channel, DEMO_MAP, 12)) as net:
        op = net.bring_up()
        backend = net.backends[0]
        for _ in range(5):
            _cycle(nodes, op)
        nodes.silence_heartbeat(7)
        t0 = _now_s(nodes)
        while not backend.heartbeat_lost[6]:
            res = _cycle(nodes, op)
            assert _now_s(nodes) - t0 < 1.0
        seen = _now_s(nodes) - t0
        consumer = 1.5 * HEARTBEAT_MS / 1000
        # the last heartbeat came up to one period before the silence, and one cycle may pass unseen
        assert consumer - HEARTBEAT_MS / 1000 <= seen <= consumer + 0.05, seen
        assert not res.buses[0].fresh[6] and res.buses[0].fresh[[0, 1, 5, 7, 11]].all()
        assert backend.heartbeat_lost.sum() == 1 and backend.heartbeat_lost_slaves() == ["j6"]
        # the heartbeat comes back saying OPERATIONAL: fresh again, nothing to reconfigure
        nodes.silence_heartbeat(7, False)
        for _ in range(100):
            if _cycle(nodes, op).fresh:
                break
        assert op.result.fresh and not backend.heartbeat_lost.any() and backend.recoveries == 0


def test_heartbeat_consumer_time_from_the_backend_option(
    nodes: CanopenSimulator, channel: str, tmp_path: Path
) -> None:
    with _open(nodes, _net(tmp_path, channel, DEMO_MAP, 12), heartbeat_consumer_ms=400) as net:
        op = net.bring_up()
        backend = net.backends[0]
        nodes.silence_heartbeat(2)
        t0 = _now_s(nodes)
        while not backend.heartbeat_lost[1]:
            _cycle(nodes, op)
            assert _now_s(nodes) - t0 < 2.0
        assert 0.4 - HEARTBEAT_MS / 1000 <= _now_s(nodes) - t0 <= 0.4 + 0.05


def test_emergency_reported_with_its_name(nodes: CanopenSimulator, channel: str, tmp_path: Path) -> None:
    with _open(nodes, _net(tmp_path, channel, DEMO_MAP, 12)) as net:
        op = net.bring_up()
        backend = net.backends[0]
        nodes.send_emergency(3, 0x2310, register=0x03)
        for _ in range(5):
            _cycle(nodes, op)
        (emcy,) = [e for e in backend.emergencies if e.node_id == 3]
        assert (emcy.code, emcy.register, emcy.name) == (0x2310, 0x03, "continuous over-current")
        assert "node 3: EMCY 0x2310 continuous over-current" in str(emcy)
        assert backend.last_emergency[3] is emcy and set(backend.last_emergency) == {3}
        nodes.send_emergency(3, 0x8611, register=0x21)
        for _ in range(5):
            _cycle(nodes, op)
        assert backend.last_emergency[3].name == "following error"


def test_a_dropped_tpdo_makes_only_that_node_stale(
    nodes: CanopenSimulator, channel: str, tmp_path: Path
) -> None:
    with _open(nodes, _net(tmp_path, channel, DEMO_MAP, 12, timeout_us=50_000)) as net:
        op = net.bring_up()
        img = op["bus"].inputs
        for _ in range(5):
            _cycle(nodes, op)
        held = img.values[4].copy()
        nodes.drop_tpdos(5, 1)
        res = _cycle(nodes, op)
        fresh = res.buses[0].fresh
        assert not fresh[4] and fresh.sum() == 11 and res.buses[0].wkc == 23
        assert img.values[4] == held  # node 5's row held as it was


def test_recovery_never_holds_the_cycle_when_a_rebooted_node_stops_answering(
    nodes: CanopenSimulator, channel: str, tmp_path: Path
) -> None:
    """A node boots, then goes bus-off in the middle of being configured again: its SDO answer never
    comes. Recovery waits for it without holding a single cycle (its SDO timeout is 0.5 s), records the
    timeout, and configures the node when it boots again."""
    with _open(nodes, _net(tmp_path, channel, DEMO_MAP, 12, safe_stop_after=100_000)) as net:
        op = net.bring_up()
        backend = net.backends[0]
        for _ in range(5):
            _cycle(nodes, op)
        nodes.power_cycle(4)
        while 4 not in backend.boots:
            _cycle(nodes, op)
        nodes.bus_off(4)  # gone while the recovery talks to it
        longest = 0.0
        t0 = _now_s(nodes)
        while not backend.recovery_errors:
            before = _now_s(nodes) + CYCLE_S
            res = _cycle(nodes, op)
            longest = max(longest, _now_s(nodes) - before)  # virtual time inside exchange() [s]
            assert _now_s(nodes) - t0 < 3.0, "the SDO timeout never came"
            assert res.buses[0].fresh[[0, 1, 2, 4, 11]].all() and not res.buses[0].fresh[3]
        assert "node 4: no SDO answer within 500 ms" in backend.recovery_errors[0]
        # each cycle waited at most its receive timeout (node 4's TPDOs are missing), never for the SDO
        assert 0.019 < longest <= 0.0201, longest  # the receive timeout (20 ms) passed, not the SDO's 500 ms
        nodes.bus_off(4, False)  # back: it boots
        streak = 0
        for _ in range(1000):
            streak = streak + 1 if _cycle(nodes, op).fresh else 0
            if streak == 20:
                break
        assert streak == 20 and backend.recoveries == 1
        assert nodes.node(4).state is NmtState.OPERATIONAL


def test_tpdos_of_other_transmission_types_are_taken_but_not_awaited(channel: str, tmp_path: Path) -> None:
    """TPDO2 every 2nd SYNC (type 2): a cycle waits for TPDO1 only; TPDO2 lands in the inputs when it comes."""
    variant = tmp_path / "demo_joint_tt2.yaml"
    variant.write_text(
        DEMO_MAP.read_text().replace(
            "  heartbeat_ms: 100\n",
            "  heartbeat_ms: 100\n  pdo:\n    - {index: 0x1A01, transmission_type: 2}\n",
        )
    )
    drive = load_drive_map(variant)
    assert drive.tpdo[1].canopen is not None and drive.tpdo[1].canopen.transmission_type == 2
    with (
        can.Bus(interface="virtual", channel=channel) as bus,
        CanopenSimulator(bus, [(drive, n) for n in (1, 2, 3)], dt_s=CYCLE_S) as sim,
        open_network(_net(tmp_path, channel, variant, 3, timeout_us=50_000)) as net,
    ):
        op = net.bring_up()
        backend = net.backends[0]
        assert backend.expected_wkc == 3
        assert int(sim.node(2).od.get_value(0x1801, 2)) == 2  # the plan wrote it
        for _ in range(20):
            res = op.exchange()
            assert res.fresh and res.buses[0].wkc == 3
        # the emulator's thread sends a node's TPDO2 after its TPDO1, which is all a cycle waits for: on a
        # busy machine the last TPDO2s may still be on their way (a bounded wait for them, not a timing check)
        give_up = time.monotonic() + 10.0
        while min(sim.node(n).sent_tpdos for n in (1, 2, 3)) < 30 and time.monotonic() < give_up:
            time.sleep(0.001)
        assert [sim.node(n).sent_tpdos for n in (1, 2, 3)] == [
            20 + 10
        ] * 3  # TPDO1 every SYNC, TPDO2 every 2nd
        op.exchange()  # the last TPDO2s are taken from the queue at the next send()
        assert backend.extra_tpdos == 30 and backend.late_tpdos == 0
        assert np.all(op["bus"].inputs["modes_of_operation_display"] == 8)  # from TPDO2
        assert not sim.errors


# -- interop ------------------------------------------------------------------------------


def test_canopen_remote_node_drives_our_emulator(channel: str) -> None:
    """canopen's own master: SDO, pdo.read()/pdo.save(), NMT, SYNC then a TPDO."""
    drive = load_drive_map(DEMO_MAP)
    with can.Bus(interface="virtual", channel=channel) as bus, CanopenSimulator(bus, [(drive, 9)]) as sim:
        network = canopen.Network()
        network.connect(interface="virtual", channel=channel)
        try:
            node = canopen.RemoteNode(9, to_canopen_od(sim.node(9).od))
            network.add_node(node)
            assert int.from_bytes(node.sdo.upload(0x1018, 1), "little") == drive.vendor_id
            assert node.sdo.upload(0x1008, 0) == b"demo_joint"  # segmented upload
            node.sdo.download(0x6060, 0, b"\x09")
            assert node.sdo.upload(0x6060, 0) == b"\x09"
            node.tpdo.read(from_od=False)  # mapping read over SDO
            tpdo1 = node.tpdo[1]
            assert tpdo1.cob_id == 0x189 and [(v.index, v.subindex) for v in tpdo1.map] == [
                (0x6041, 0),
                (0x6064, 0),
            ]
            node.tpdo[2].enabled = False
            node.tpdo.save()  # canopen's own CiA 301 sequence: invalid, count 0, entries, count, valid
            assert int(sim.node(9).od.get_value(0x1801, 1)) & 0x80000000
            node.nmt.state = "OPERATIONAL"
            time.sleep(0.05)
            assert sim.node(9).state is NmtState.OPERATIONAL
            got: list[Any] = []
            network.subscribe(0x189, lambda cob, data, ts: got.append(bytes(data)))
            network.sync.transmit()
            deadline = time.monotonic() + 1.0
            while not got and time.monotonic() < deadline:
                time.sleep(0.01)
            assert got and len(got[0]) == 6  # statusword + position actual
        finally:
            network.disconnect()
        assert not sim.errors


def test_our_backend_brings_up_a_canopen_local_node(channel: str, tmp_path: Path) -> None:
    """canopen's LocalNode (its own SDO server and NMT slave) serves the demo joint's objects.

    Our backend checks its identity, writes and reads back the whole CiA 301
    plan, starts it (LocalNode's heartbeat reports OPERATIONAL) and reads a
    segmented string. Not testable: the cycle. LocalNode sends no TPDO on SYNC
    (canopen issue #166) and keeps received RPDOs in its PdoMap, so a cycle
    against it times out - which is what is checked last.
    """
    od = to_canopen_od(CanopenNode(load_drive_map(DEMO_MAP), 11).od)  # what our emulated node holds
    network = canopen.Network()
    network.connect(interface="virtual", channel=channel)
    try:
        local = canopen.LocalNode(11, od)
        network.add_node(local)
        f = tmp_path / "net.yaml"
        f.write_text(
            "cycle_time_us: 5000\nreceive_timeout_us: 20000\nbuses:\n"
            f"  - {{name: bus, type: canopen, interface: {channel}, can_interface: virtual,\n"
            f"     slaves: [{{name: j, map: {json.dumps(str(DEMO_MAP))}, node_id: 11}}]}}\n"
        )
        with open_network(f) as net:
            op = net.bring_up()
            backend = net.backends[0]
            # the plan landed in LocalNode's data store, as written
            assert local.sdo[0x1A01][0].raw == 3 and local.sdo[0x1A01][1].raw == 0x606C0020
            assert local.sdo[0x1800][1].raw == 0x18B and local.sdo[0x1802][1].raw & 0x80000000
            assert local.sdo[0x1017].raw == HEARTBEAT_MS and local.sdo[0x6060].raw == 8
            assert local.nmt.state == "OPERATIONAL"
            assert backend.sdo_read(0, 0x1008, 0) == b"demo_joint"  # segmented upload from canopen's server
            with pytest.raises(SdoAbortError) as exc:
                backend.sdo_read(0, 0x1234, 0)
            assert exc.value.code == 0x06020000 and "node 11" in str(exc.value)
            res = op.exchange()
            assert not res.fresh and res.buses[0].wkc == -1  # no SYNC-triggered TPDOs from LocalNode
    finally:
        network.disconnect()


def test_two_can_buses_under_one_network(tmp_path: Path) -> None:
    """As in the legged-robot hardware tutorial (§62.4): split the joints over several buses; one exchange() serves them all."""
    drive = load_drive_map(DEMO_MAP)
    a, b = (f"fb-two-{k}-{time.monotonic_ns()}" for k in range(2))
    net_file = tmp_path / "two.yaml"
    net_file.write_text(
        "cycle_time_us: 5000\nreceive_timeout_us: 20000\nbuses:\n"
        + "".join(
            f"  - {{name: {name}, type: canopen, interface: {ch}, can_interface: virtual,\n"
            f"     slaves: [{{name: '{name}{{i}}', map: {json.dumps(str(DEMO_MAP))}, node_id: 1, count: 3}}]}}\n"
            for name, ch in (("left", a), ("right", b))
        )
    )
    with (
        can.Bus(interface="virtual", channel=a) as bus_a,
        can.Bus(interface="virtual", channel=b) as bus_b,
        CanopenSimulator(bus_a, [(drive, n) for n in (1, 2, 3)]) as sim_a,
        CanopenSimulator(bus_b, [(drive, n) for n in (1, 2, 3)]) as sim_b,
        open_network(net_file) as net,
    ):
        op = net.bring_up()
        assert set(op) == {"left", "right"}
        for _ in range(10):
            res = op.exchange()
        assert res.fresh and [s.wkc for s in res.buses] == [6, 6]
        sim_b.drop_tpdos(2, 2)
        res = op.exchange()
        assert res.bus("left").fresh.all() and list(res.bus("right").fresh) == [True, False, True]
        assert not sim_a.errors and not sim_b.errors
