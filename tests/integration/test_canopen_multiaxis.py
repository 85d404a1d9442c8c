"""Multi-axis CiA 402 drives on CANopen (issue 25 item 4): one node, two axes at +0x800.

Axis 2's PDOs follow axis 1's in PDO number (RPDO3-4 / TPDO3-4 with CiA 301's pre-defined
COB-IDs). The run on the CANopen emulator uses our own code on both sides; canopen's
``RemoteNode`` (an independent master) reads axis 2's objects and its TPDO mapping from the
emulated node as the oracle.
"""

from __future__ import annotations

import itertools
import time
from pathlib import Path

import numpy as np
import pytest

can = pytest.importorskip("can")
canopen = pytest.importorskip("canopen")

import fieldbus  # noqa: E402
from fieldbus import PDO_MAPS, canopen_plan, load_drive_map  # noqa: E402
from fieldbus.core.cia402 import State402  # noqa: E402
from fieldbus.core.drivefault import DriveFault  # noqa: E402
from fieldbus.errors import FieldbusError  # noqa: E402
from fieldbus.testing import emulate  # noqa: E402
from sim_slaves.canopen import CanopenSimulator, NmtState  # noqa: E402
from sim_slaves.canopen.eds import to_canopen_od  # noqa: E402

TARGETS = np.array([1000.0, -2000.0, 3000.0, 500.0])  # counts, one per axis (row)
_channels = itertools.count()


def _two_axis_map(tmp_path: Path, extra: str = "") -> Path:
    """The shipped generic CiA 402 map (2 RPDOs + 2 TPDOs, a canopen section) with ``axes: 2``."""
    path = tmp_path / "two_axis_can.yaml"
    path.write_text((PDO_MAPS / "generic_cia402.yaml").read_text() + "axes: 2\n" + extra)
    return path


def _network(tmp_path: Path, map_path: Path) -> Path:
    net = tmp_path / "arm.yaml"
    net.write_text(
        "name: arm\ncycle_time_us: 1000\nbuses:\n  - name: arm\n    type: canopen\n    interface: can0\n"
        "    can_interface: socketcan\n    receive_timeout_us: 2000\n    slaves:\n"
        f"      - {{name: shoulder, map: {map_path}, node_id: 3}}\n"
        f"      - {{name: elbow, map: {map_path}, node_id: 4}}\n"
    )
    return net


def test_axis_2_has_its_own_pdos_with_cia301_default_cob_ids(tmp_path: Path) -> None:
    drive = load_drive_map(_two_axis_map(tmp_path))
    bus = drive.bus_map
    cobs = [(p.index, p.canopen.cob_id_for(3)) for p in (*bus.rpdo, *bus.tpdo) if p.canopen is not None]
    assert cobs == [
        (0x1600, 0x203), (0x1601, 0x303), (0x1602, 0x403), (0x1603, 0x503),
        (0x1A00, 0x183), (0x1A01, 0x283), (0x1A02, 0x383), (0x1A03, 0x483),
    ]  # fmt: skip
    assert bus.rpdo[2].channels[0].index == 0x6840 and bus.tpdo[2].channels[0].index == 0x6841
    steps = {(s.index, s.sub_index) for s in canopen_plan(drive, 3).steps}
    assert {(0x1602, 1), (0x1A03, 1), (0x6860, 0)} <= steps  # axis 2's mapping and start-up SDO


def test_a_copy_takes_axis_1s_parameters_unless_canopen_pdo_names_it(tmp_path: Path) -> None:
    path = tmp_path / "params.yaml"
    text = (PDO_MAPS / "generic_cia402.yaml").read_text()
    text = text.replace("{index: 0x1A01, transmission_type: 1}", "{index: 0x1A01, transmission_type: 2}")
    path.write_text(text + "    - {index: 0x1A02, transmission_type: 3, cob_id: 0x1C0}\naxes: 2\n")
    tpdo = load_drive_map(path).bus_map.tpdo
    got = [(p.index, p.canopen.cob_id, p.canopen.transmission_type) for p in tpdo if p.canopen is not None]
    assert got == [(0x1A00, 0x180, 1), (0x1A01, 0x280, 2), (0x1A02, 0x1C0, 3), (0x1A03, 0x480, 2)]


def test_a_third_axis_past_the_predefined_pdos_needs_its_cob_ids(tmp_path: Path) -> None:
    path = tmp_path / "three.yaml"
    path.write_text((PDO_MAPS / "generic_cia402.yaml").read_text() + "axes: 3\n")
    with pytest.raises(FieldbusError, match=r"axis 3's copy of PDO 0x1600 is 0x1604, RPDO5.*canopen\.pdo"):
        load_drive_map(path)


def test_two_two_axis_nodes_run_all_four_axes_on_the_canopen_emulator(tmp_path: Path) -> None:
    with emulate(_network(tmp_path, _two_axis_map(tmp_path))) as emu:
        op = emu.op
        arm = op["arm"]
        assert arm.n_axes == 4
        ctrl = fieldbus.Cia402Controller(arm.n_axes, mode=fieldbus.Mode.CSP)
        ctrl.set_goal(fieldbus.Goal.ENABLE)

        def step(k: int) -> None:
            if op.exchange().fresh:
                ctrl.step_image(arm)
                if k >= 300:
                    arm.outputs["target_position"][:] = TARGETS

        emu.run(step, cycles=1500)
        assert emu.drive_states("arm") == [State402.OPERATION_ENABLED] * 4  # the emulator's view, per axis
        assert list(arm.inputs["statusword"] & 0x6F) == [0x27] * 4
        np.testing.assert_allclose(arm.inputs["position_actual_value"], TARGETS, atol=20)
        # an SDO to axis 2's objects reaches axis 2: 0x6864 is its position, 0x6841 its statusword
        reads = [op.submit_sdo_read("arm", "shoulder", index, 0) for index in (0x6864, 0x6841)]
        emu.run(lambda _k: op.exchange() and all(r.done() for r in reads), cycles=100)
        position, statusword = (int.from_bytes(r.result(), "little", signed=True) for r in reads)
        assert abs(position - TARGETS[1]) <= 20 and statusword & 0x6F == 0x27


def test_canopen_remote_node_reads_axis_2_of_our_emulated_node(tmp_path: Path) -> None:
    """canopen's own master reads TPDO3's mapping (axis 2's), writes 0x6865 and reads 0x6841 from our node."""
    drive = load_drive_map(_two_axis_map(tmp_path))
    channel = f"fb-canopen-axes-{next(_channels)}-{time.monotonic_ns()}"
    with can.Bus(interface="virtual", channel=channel) as bus, CanopenSimulator(bus, [(drive, 5)]) as sim:
        network = canopen.Network()
        network.connect(interface="virtual", channel=channel)
        try:
            node = canopen.RemoteNode(5, to_canopen_od(sim.node(5).od))
            network.add_node(node)
            node.tpdo.read(from_od=False)  # the mapping read over SDO
            tpdo3 = node.tpdo[3]
            assert tpdo3.cob_id == 0x385 and [(v.index, v.subindex) for v in tpdo3.map] == [
                (0x6841, 0),
                (0x6864, 0),
            ]
            node.sdo.download(0x6865, 0, (5).to_bytes(4, "little"))  # axis 2's following error window
            assert int(sim.node(5).od.get_value(0x6865, 0)) == 5
            assert int.from_bytes(node.sdo.upload(0x6065, 0), "little") != 5  # axis 1's is its own
            node.nmt.state = "OPERATIONAL"
            time.sleep(0.05)
            assert sim.node(5).state is NmtState.OPERATIONAL
            got: list[bytes] = []
            network.subscribe(0x385, lambda cob, data, ts: got.append(bytes(data)))
            network.sync.transmit()  # both axes step; axis 2's TPDO3 comes
            deadline = time.monotonic() + 2.0
            while not got and time.monotonic() < deadline:
                time.sleep(0.01)
            statusword = int.from_bytes(node.sdo.upload(0x6841, 0), "little")
            assert statusword & 0x4F == 0x40  # axis 2: SWITCH ON DISABLED, read by SDO
            assert got and int.from_bytes(got[0][:2], "little") == statusword  # and in its TPDO
        finally:
            network.disconnect()
        assert not sim.errors


def test_drive_fault_on_axis_2_of_a_canopen_node_is_that_axis_s_event(tmp_path: Path) -> None:
    with emulate(_network(tmp_path, _two_axis_map(tmp_path))) as emu:
        op = emu.op
        arm = op["arm"]
        ctrl = fieldbus.Cia402Controller(arm.n_axes, mode=fieldbus.Mode.CSP)
        ctrl.set_goal(fieldbus.Goal.ENABLE)
        faults: list[DriveFault] = []

        def step(_k: int) -> None:
            res = op.exchange()
            faults.extend(e for e in res.events if isinstance(e, DriveFault) and e.code is not None)
            if res.fresh:
                ctrl.step_image(arm)

        emu.run(step, cycles=300)
        emu.drive_fault("arm", "elbow", 0x7300, axis=2)
        emu.run(step, cycles=50)
        assert [(f.slave, f.axis, f.slave_axis, f.code) for f in faults] == [("elbow", 3, 1, 0x7300)]
        assert any(e.code == 0x7300 and e.node_id == 4 for e in emu.network.backend("arm").emergencies)


def test_a_multi_axis_nodes_emcy_names_the_axis_that_faulted(tmp_path: Path) -> None:
    """EMCY manufacturer byte 0 is the faulted axis (1-based) on a multi-axis node: the code alone
    (0x7300 on either axis) would not say which one."""
    with emulate(_network(tmp_path, _two_axis_map(tmp_path))) as emu:
        emu.cycles(50)
        backend = emu.network.backend("arm")
        emu.drive_fault("arm", "elbow", 0x7300, axis=2)
        emu.drive_fault("arm", "shoulder", 0x7300, axis=1)
        emu.cycles(5)
        got = [(e.node_id, e.code, e.data[0]) for e in backend.emergencies]  # type: ignore[attr-defined]
    assert got == [(4, 0x7300, 2), (3, 0x7300, 1)], got
