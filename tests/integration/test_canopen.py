"""CANopen specifics on python-can's virtual bus: mapping by SDO, heartbeat, EMCY, interop with canopen.

The shared cyclic-API module (test_cyclic_api.py) covers bring-up, identity,
SDO aborts, tracking, stale inputs, the safe stop and node-reset recovery on
this backend too.
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
from fieldbus.core.pdo import load_drive_map  # noqa: E402
from fieldbus.network import open_network  # noqa: E402
from sim_slaves.canopen import CanopenSimulator, NmtState  # noqa: E402
from sim_slaves.canopen.eds import to_canopen_od  # noqa: E402

pytestmark = pytest.mark.timeout(120)
_channels = itertools.count()
HEARTBEAT_MS = 100  # demo_joint.yaml


@pytest.fixture
def channel() -> str:
    return f"fb-canopen-{next(_channels)}-{time.monotonic_ns()}"


def _net(tmp_path: Path, channel: str, map_file: Path, count: int, timeout_us: int = 20_000) -> Path:
    f = tmp_path / "net.yaml"
    f.write_text(
        f"cycle_time_us: 5000\nreceive_timeout_us: {timeout_us}\nbuses:\n"
        f"  - {{name: bus, type: canopen, interface: {channel}, can_interface: virtual,\n"
        f"     slaves: [{{name: 'j{{i}}', map: {json.dumps(str(map_file))}, node_id: 1, count: {count}}}]}}\n"
    )
    return f


@pytest.fixture
def nodes(channel: str) -> Iterator[CanopenSimulator]:
    drive = load_drive_map(DEMO_MAP)
    with (
        can.Bus(interface="virtual", channel=channel) as bus,
        CanopenSimulator(bus, [(drive, n) for n in range(1, 13)]) as sim,
    ):
        yield sim
    assert not sim.errors


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
    with open_network(_net(tmp_path, channel, variant, 12)) as net:
        op = net.bring_up()
        for n in range(1, 13):
            node = nodes.node(n)
            assert node.state is NmtState.OPERATIONAL
            assert [(c.index, c.sub_index) for c in node.od.pdo(0x1A01).channels] == [
                (0x6077, 0),
                (0x6061, 0),
            ]
        # read back through the backend too
        assert net.backends[0].sdo_read(4, 0x1A01, 0) == b"\x02"
        for _ in range(10):
            res = op.exchange()
        assert res.fresh and res.buses[0].wkc == 24  # 12 nodes x 2 TPDOs
        img = op["bus"]
        assert "velocity_actual_value" not in img.inputs.values.dtype.names
        assert np.all(img.inputs["modes_of_operation_display"] == 8)
        assert nodes.syncs >= 10 and nodes.node(12).received_rpdos >= 20


def test_heartbeat_loss_is_seen_within_consumer_time_plus_a_cycle(
    nodes: CanopenSimulator, channel: str, tmp_path: Path
) -> None:
    with open_network(_net(tmp_path, channel, DEMO_MAP, 12)) as net:
        op = net.bring_up()
        backend = net.backends[0]
        for _ in range(5):
            op.exchange()
        nodes.silence_heartbeat(7)
        t0 = time.monotonic()
        while not backend.heartbeat_lost[6]:
            res = op.exchange()
            assert time.monotonic() - t0 < 1.0
        seen = time.monotonic() - t0
        consumer = 1.5 * HEARTBEAT_MS / 1000
        # the last heartbeat came up to one period before the silence, and one cycle may pass unseen
        assert consumer - HEARTBEAT_MS / 1000 <= seen <= consumer + 0.05, seen
        assert not res.buses[0].fresh[6] and res.buses[0].fresh[[0, 1, 5, 7, 11]].all()
        assert backend.heartbeat_lost.sum() == 1


def test_emergency_reported_with_its_name(nodes: CanopenSimulator, channel: str, tmp_path: Path) -> None:
    with open_network(_net(tmp_path, channel, DEMO_MAP, 12)) as net:
        op = net.bring_up()
        backend = net.backends[0]
        nodes.send_emergency(3, 0x2310, register=0x03)
        for _ in range(5):
            op.exchange()
        (emcy,) = [e for e in backend.emergencies if e.node_id == 3]
        assert (emcy.code, emcy.register, emcy.name) == (0x2310, 0x03, "continuous over-current")
        assert "node 3: EMCY 0x2310 continuous over-current" in str(emcy)


def test_a_dropped_tpdo_makes_only_that_node_stale(
    nodes: CanopenSimulator, channel: str, tmp_path: Path
) -> None:
    with open_network(_net(tmp_path, channel, DEMO_MAP, 12, timeout_us=50_000)) as net:
        op = net.bring_up()
        img = op["bus"].inputs
        for _ in range(5):
            op.exchange()
        held = img.values[4].copy()
        nodes.drop_tpdos(5, 1)
        res = op.exchange()
        fresh = res.buses[0].fresh
        assert not fresh[4] and fresh.sum() == 11 and res.buses[0].wkc == 23
        assert img.values[4] == held  # node 5's row held as it was


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


def test_our_sdo_client_against_canopen_local_node(channel: str) -> None:
    """canopen's LocalNode is an SDO server only (no SYNC-triggered TPDOs): identity and a write."""
    from canopen.objectdictionary import ODRecord, ODVariable, datatypes

    from fieldbus.backends.can_sdo import SdoClient
    from fieldbus.errors import SdoAbortError

    od = canopen.ObjectDictionary()
    ident = ODRecord("identity", 0x1018)
    for sub, name in ((1, "vendor"), (2, "product")):
        var = ODVariable(name, 0x1018, sub)
        var.data_type = datatypes.UNSIGNED32
        var.default = 0xFB1 if sub == 1 else 0xD01
        ident.add_member(var)
    od.add_object(ident)
    mode = ODVariable("modes of operation", 0x6060, 0)
    mode.data_type = datatypes.INTEGER8
    mode.default = 0
    od.add_object(mode)
    network = canopen.Network()
    network.connect(interface="virtual", channel=channel)
    try:
        local = canopen.LocalNode(11, od)
        network.add_node(local)
        with can.Bus(interface="virtual", channel=channel) as bus:
            client = SdoClient(bus)
            assert int.from_bytes(client.upload(11, 0x1018, 1), "little") == 0xFB1
            assert int.from_bytes(client.upload(11, 0x1018, 2), "little") == 0xD01
            client.download(11, 0x6060, 0, b"\x08")
            assert local.sdo[0x6060].raw == 8
            with pytest.raises(SdoAbortError) as exc:
                client.upload(11, 0x1234, 0)
            assert exc.value.code == 0x06020000
    finally:
        network.disconnect()


def test_two_can_buses_under_one_network(tmp_path: Path) -> None:
    """Seed 000, 62.4: split the joints over several buses; one exchange() serves them all."""
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
