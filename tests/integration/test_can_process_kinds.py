"""``python -m sim_slaves.can_process --kind``: the raw-CAN families come from the one family table, so a
third party's family registered through the ``fieldbus.rawcan_families`` entry point group (faked here
with monkeypatch, as in test_canfamily_registry.py) is a kind, and its emulator (named by its class)
serves the map's motors. The emulator is our declarative one under the family's own name: no oracle,
what is judged is that the process finds the family through the table and nowhere else."""

from __future__ import annotations

import itertools
import os
import sys
import types
from importlib.metadata import EntryPoint
from pathlib import Path

import pytest

can = pytest.importorskip("can")

from fieldbus.core import canfamily  # noqa: E402
from fieldbus.core.canfamily import GROUP  # noqa: E402
from fieldbus.core.canframes import FramesFamily  # noqa: E402
from fieldbus.core.pdo import load_drive_map  # noqa: E402
from sim_slaves.can_process import _emulator, bus_specs, kinds, parse_args  # noqa: E402

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
"""


class AcmeFamily(FramesFamily):
    """A third party's family (the declarative grammar under its own name)."""

    name = "acme"


def _register(monkeypatch: pytest.MonkeyPatch) -> None:
    module = types.ModuleType("acme_kinds")
    module.AcmeFamily = AcmeFamily  # type: ignore[attr-defined]
    monkeypatch.setitem(sys.modules, "acme_kinds", module)
    eps = [EntryPoint("acme", "acme_kinds:AcmeFamily", GROUP)]
    monkeypatch.setattr(canfamily, "entry_points", lambda group: eps if group == GROUP else [])


def test_the_built_in_families_are_kinds_from_the_table() -> None:
    found = kinds()
    assert found[0] == "canopen" and found[-1] == "auto" and len(set(found)) == len(found)
    assert {"mit", "damiao", "odrive", "cubemars", "frames"} <= set(found)
    assert set(canfamily.families()) <= set(found)


def test_a_third_party_family_is_a_kind_and_its_emulator_serves(
    monkeypatch: pytest.MonkeyPatch, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    drive = tmp_path / "acme_wheel.yaml"
    drive.write_text(ACME_MAP)
    channel = f"fb-kinds-{os.getpid()}-{next(_channels)}"
    argv = ["--kind", "acme", "--map", str(drive), "--nodes", "1", "--interface", "virtual"]
    with pytest.raises(SystemExit):  # not registered: no such kind
        parse_args([*argv, "--channel", channel])
    assert "invalid choice: 'acme'" in capsys.readouterr().err

    _register(monkeypatch)
    assert "acme" in kinds()
    args = parse_args([*argv, "--channel", channel])
    assert bus_specs(args) == [("acme", str(drive), [1])]
    drive_map = load_drive_map(drive)
    with (
        can.Bus(interface="virtual", channel=channel) as bus,
        can.Bus(interface="virtual", channel=channel) as master,
    ):
        with pytest.raises(ValueError, match="--kind damiao: the map acme_wheel is of family acme"):
            _emulator("damiao", bus, drive_map, [1], None)
        emulator = _emulator("acme", bus, drive_map, [1], None)
        assert type(emulator).__name__ == "FramesMotorSimulator"
        master.send(
            can.Message(
                arbitration_id=0x211, data=(5).to_bytes(2, "little", signed=True), is_extended_id=False
            )
        )
        assert emulator.serve(5.0)  # the command, handled (bounded: 5 s for the virtual bus to deliver it)
        reply = master.recv(timeout=5.0)
        assert reply is not None and reply.arbitration_id == 0x291 and len(reply.data) == 3
        assert emulator.motor(1).commands == 1
