"""A raw-CAN family shipped by a third party: registered through the ``fieldbus.rawcan_families`` entry
point group (faked here with monkeypatch), found by :func:`fieldbus.core.canfamily.families`, parsed by
the map loader through it and run by the real raw-CAN backend on a python-can virtual bus.

The motor on the other side is this test's own responder (there is no independent oracle for a made-up
family): what is judged is that the backend reaches the family only through the protocol.
"""

from __future__ import annotations

import itertools
import os
import sys
import types
from collections.abc import Iterator
from importlib.metadata import EntryPoint
from pathlib import Path
from typing import Any

import can
import pytest

from fieldbus.core import canfamily
from fieldbus.core.canfamily import GROUP, CanFamily, families
from fieldbus.core.canframes import FramesFamily
from fieldbus.core.pdo import load_drive_map
from fieldbus.errors import FieldbusError
from fieldbus.network import open_network

_channels = itertools.count()
ACME_MAP = """\
name: acme_wheel
rawcan:
  family: acme
  command:  {id: 0x210, fields: [{name: velocity, type: int, bits: 16, scale: 1, safe_value: 0}]}
  feedback: {id: 0x290, fields: [{name: position, type: int, bits: 16, scale: 100, unit: rad},
                                 {name: code, type: uint, bits: 8}]}
  fault: {field: code, codes: {0: ok, 7: stall}}
  enable: [0x01]
  disable: [0x00]
  clear: [0x03]
"""


class AcmeFamily(FramesFamily):
    """A third party's family: the declarative grammar under its own name (so the backend's ``frames``
    branches, were any left, would not run it)."""

    name = "acme"


class NotAFamily:
    pass


def _register(monkeypatch: pytest.MonkeyPatch, **targets: Any) -> None:
    module = types.ModuleType("acme_motors")
    for attr, obj in targets.items():
        setattr(module, attr, obj)
    monkeypatch.setitem(sys.modules, "acme_motors", module)
    eps = [EntryPoint(name, f"acme_motors:{attr}", GROUP) for attr, name in (("AcmeFamily", "acme"),)]
    eps += [EntryPoint(n, f"acme_motors:{n}", GROUP) for n in targets if n != "AcmeFamily"]
    monkeypatch.setattr(canfamily, "entry_points", lambda group: eps if group == GROUP else [])


def test_an_entry_point_family_is_found_beside_the_built_in_ones(monkeypatch: pytest.MonkeyPatch) -> None:
    assert "acme" not in families()
    _register(monkeypatch, AcmeFamily=AcmeFamily)
    found = families()
    assert found["acme"] is AcmeFamily and found["frames"] is FramesFamily
    assert all(issubclass(c, CanFamily) for c in found.values())


def test_an_entry_point_that_is_no_family_is_refused_by_name(monkeypatch: pytest.MonkeyPatch) -> None:
    _register(monkeypatch, AcmeFamily=AcmeFamily, frames=AcmeFamily, bogus=NotAFamily)
    with pytest.raises(TypeError, match="bogus"):
        families()


def test_a_built_in_family_is_not_replaced_by_an_entry_point(monkeypatch: pytest.MonkeyPatch) -> None:
    _register(monkeypatch, AcmeFamily=AcmeFamily)
    monkeypatch.setattr(
        canfamily, "entry_points", lambda group: [EntryPoint("frames", "acme_motors:AcmeFamily", GROUP)]
    )
    assert families()["frames"] is FramesFamily


def test_an_unregistered_family_name_is_a_typed_error_naming_the_field(tmp_path: Path) -> None:
    f = tmp_path / "acme.yaml"
    f.write_text(ACME_MAP)
    with pytest.raises(FieldbusError, match="family"):
        load_drive_map(f)


class _Responder(can.Listener):
    """Answers each 2-byte command on 0x211/0x212 with the feedback: position = the command's raw value,
    code 7 (stall) when the command is 99; records every frame it saw."""

    def __init__(self, bus: can.BusABC) -> None:
        self.bus, self.seen = bus, []

    def on_message_received(self, msg: can.Message) -> None:
        self.seen.append((msg.arbitration_id, bytes(msg.data)))
        if msg.arbitration_id in (0x211, 0x212) and len(msg.data) == 2:
            raw = int.from_bytes(msg.data, "little", signed=True)
            data = raw.to_bytes(2, "little", signed=True) + bytes([7 if raw == 99 else 0])
            self.bus.send(
                can.Message(arbitration_id=msg.arbitration_id + 0x80, data=data, is_extended_id=False)
            )


@pytest.fixture
def acme_network(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Iterator[tuple[Path, str]]:
    _register(monkeypatch, AcmeFamily=AcmeFamily)
    drive = tmp_path / "acme_wheel.yaml"
    drive.write_text(ACME_MAP)
    channel = f"fb-acme-{os.getpid()}-{next(_channels)}"
    net = tmp_path / "net.yaml"
    net.write_text(
        "cycle_time_us: 2000\nreceive_timeout_us: 50000\nsafe_stop_after: 4\nbuses:\n"
        f"  - {{name: wheels, type: rawcan, interface: {channel}, can_interface: virtual,\n"
        f"     slaves: [{{name: 'w{{i}}', map: '{drive}', node_id: 1, count: 2}}]}}\n"
    )
    yield net, channel


def test_the_backend_runs_a_third_party_family_through_the_protocol(acme_network: tuple[Path, str]) -> None:
    net_file, channel = acme_network
    with can.Bus(interface="virtual", channel=channel, receive_own_messages=False) as sim_bus:
        responder = _Responder(sim_bus)
        notifier = can.Notifier(sim_bus, [responder])
        try:
            with open_network(net_file) as net:
                op = net.bring_up()
                wheels = op["wheels"]
                wheels.outputs["velocity"][:] = [3, -4]
                res = op.exchange()
                assert res.fresh  # answered: the responder has seen every frame before this cycle's
                enables = [k for k, (i, d) in enumerate(responder.seen) if d == b"\x01"]
                assert [responder.seen[k][0] for k in enables] == [0x211, 0x212] and enables == [0, 1]
                assert list(wheels.inputs["position"]) == pytest.approx([0.03, -0.04])
                backend = net.backend("wheels")
                wheels.outputs["velocity"][:] = [99, 5]
                assert op.exchange().fresh
                assert [(f.slave, f.code, f.name) for f in backend.faults] == [("w0", 7, "stall")]
                wheels.outputs["velocity"][:] = [6, 5]
                op.exchange()
                op.exchange()
                assert backend.motor_faults == 1  # the code went back to ok: no new fault
                n = len(responder.seen)
            notifier.stop()
            while (msg := sim_bus.recv(timeout=0)) is not None:  # what the notifier had not read yet
                responder.seen.append((msg.arbitration_id, bytes(msg.data)))
            tail = responder.seen[n:]
            # closing: the safe command (velocity 0) to each motor, then its disable pattern
            for can_id in (0x211, 0x212):
                frames = [d for i, d in tail if i == can_id]
                assert b"\x00\x00" in frames and b"\x00" in frames, tail and frames.index(
                    b"\x00\x00"
                ) < frames.index(b"\x00")
        finally:
            notifier.stop()


def test_the_testing_kit_emulates_a_third_party_family_through_the_table(
    acme_network: tuple[Path, str], tmp_path: Path
) -> None:
    """The kit finds the family's emulator in its class (here the declarative one): the wheels turn at the
    commanded speed, a stall is a named fault, recovery by name clears it and enables the motor again."""
    from fieldbus.testing import emulate

    net_file, _ = acme_network
    kit_net = tmp_path / "kit.yaml"
    kit_net.write_text(
        net_file.read_text()
        .replace("can_interface: virtual", "can_interface: socketcan")
        .replace("receive_timeout_us: 50000", "receive_timeout_us: 500")
    )
    with emulate(kit_net) as emu:
        wheels = emu.op["wheels"]
        wheels.outputs["velocity"][:] = [100, -50]  # raw 1 per rad/s: the map's scale 1
        emu.cycles(500)
        pos = list(wheels.inputs["position"])
        assert pos[0] > 0.5 and pos[1] < -0.2, pos  # turning, each its own way (feedback: 100 counts per rad)
        emu.drive_fault("wheels", "w1", 7)
        emu.cycles(10)
        backend = emu.op.network.backend("wheels")
        assert [(f.slave, f.code, f.name) for f in backend.faults] == [("w1", 7, "stall")]
        assert emu.recover_motor("wheels", "w1")
        emu.cycles(10)
        assert backend.error_code("w1") == 0 and backend.motor_faults == 1


def test_a_motor_without_a_slot_in_a_shared_frame_is_refused_naming_the_bus(
    acme_network: tuple[Path, str],
) -> None:
    """A family's ``ValueError`` for a bus it cannot run (node 3 in a frame of 2 motors) becomes a typed
    error naming the bus, at open."""
    net_file, _ = acme_network
    drive = net_file.parent / "acme_wheel.yaml"
    drive.write_text(drive.read_text().replace("{id: 0x210,", "{id: 0x210, motors: 2,"))
    net_file.write_text(net_file.read_text().replace("node_id: 1, count: 2", "node_id: 2, count: 2"))
    with pytest.raises(FieldbusError, match=r"bus 'wheels'.*node_id 3 has no slot in frame 0x210"):
        open_network(net_file).bring_up()


def test_mit_motors_that_answer_alike_are_refused_naming_the_bus(tmp_path: Path) -> None:
    """Family mit on the protocol: two motors replying on one id with no node byte to tell them apart."""
    from fieldbus import PDO_MAPS

    text = (
        (PDO_MAPS / "cubemars_ak80_9_mit.yaml")
        .read_text()
        .replace("  node_field: motor_id\n", "  reply_id: 0x100\n")
    )
    drive = tmp_path / "mit.yaml"
    drive.write_text(text)
    net = tmp_path / "net.yaml"
    net.write_text(
        "cycle_time_us: 2000\nbuses:\n"
        f"  - {{name: legs, type: rawcan, interface: fb-mit-refused-{os.getpid()}, can_interface: virtual,\n"
        f"     slaves: [{{name: 'm{{i}}', map: '{drive}', node_id: 1, count: 2}}]}}\n"
    )
    with pytest.raises(FieldbusError, match=r"bus 'legs'.*two motors answer as CAN id 0x100"):
        open_network(net).bring_up()
