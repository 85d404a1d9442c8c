"""The wheel drive of a two-wheel AMR base described in YAML only (family ``frames``), through the kit.

The expected bytes are written here by hand from the drive's byte table (commands on 0x200: left then
right wheel speed, int16 rpm little-endian; encoder feedback on 0x300: left then right, int16 counts
big-endian, sign-extended; 4096 counts per motor turn, reduction 20) with ``struct``, not with our
codec. The emulator is our own (built from the same map), so the feedback half checks our master's
decoding against bytes we construct independently; the command half checks the master's wire bytes.
"""

from __future__ import annotations

import math
import struct
from pathlib import Path
from typing import Any

import numpy as np
import pytest

pytest.importorskip("can")

import fieldbus
from fieldbus.core.pdo import drive_map_from_text
from fieldbus.errors import PdoMapError
from fieldbus.testing import emulate

pytestmark = pytest.mark.timeout(120)
EXAMPLE = Path(__file__).resolve().parents[2] / "examples" / "amr_seed_can.yaml"
RPM_PER_RAD_S = 60 / (2 * math.pi)
COUNTS_PER_RAD = 4096 * 20 / (2 * math.pi)


def _sim(emu: Any) -> Any:
    return emu.emulators["base"].sim


def test_one_cycle_s_wire_bytes_are_the_drive_s_byte_table() -> None:
    with emulate(EXAMPLE) as emu:
        base = emu.op["base"]
        sim = _sim(emu)
        # the master's command: 100 rpm left, -240 rpm right (in rad/s in the image; the map allows 248)
        base.outputs["velocity"][:] = np.array([100, -240]) / RPM_PER_RAD_S
        # the motors hold still at known encoder counts, then answer the next command
        for node, counts in ((1, 1234), (2, -4321)):
            st = sim.motor(node)
            st.position, st.velocity = counts / COUNTS_PER_RAD, 0.0
        sim.frames.clear()
        sim.sent.clear()
        res = emu.op.exchange()
        assert res.fresh
        assert sim.frames == [(0x200, struct.pack("<hh", 100, -240))]
        assert sim.sent == [(0x300, struct.pack(">hh", 1234, -4321))]
        assert base.inputs["position"] == pytest.approx(np.array([1234, -4321]) / COUNTS_PER_RAD, abs=1e-12)


def test_the_wheels_turn_and_the_encoder_counter_wraps_as_the_drive_s() -> None:
    with emulate(EXAMPLE) as emu:
        base = emu.op["base"]
        base.outputs["velocity"][:] = [2.0, -1.0]  # rad/s: 19.1 and -9.5 rpm, sent as 19 and -10
        emu.cycles(100)  # 1 s of virtual time
        sim = _sim(emu)
        assert sim.frames[-1] == (0x200, struct.pack("<hh", 19, -10))
        left, right = sim.motor(1), sim.motor(2)
        assert left.velocity == pytest.approx(19 / RPM_PER_RAD_S, abs=1e-3)
        assert right.velocity == pytest.approx(-10 / RPM_PER_RAD_S, abs=1e-3)
        # past +-2.51 rad the int16 counter wraps, as the drive's does: the image shows the wrapped angle
        assert left.position > 1.9
        emu.cycles(50)
        base.outputs["velocity"][:] = 0.0  # at rest, the feedback and the motor's state agree
        emu.cycles(50)
        counts = struct.unpack(">hh", sim.sent[-1][1])
        wrapped = [(p * COUNTS_PER_RAD + 32768) % 65536 - 32768 for p in (left.position, right.position)]
        assert counts == pytest.approx(wrapped, abs=1)
        assert base.inputs["position"][0] < 0 < left.position  # wrapped past +32767 counts


def test_a_nan_or_huge_speed_never_reaches_the_wire() -> None:
    with emulate(EXAMPLE) as emu:
        base = emu.op["base"]
        sim = _sim(emu)
        base.outputs["velocity"][:] = [1.0, 1.0]
        emu.cycles(2)
        sent = sim.frames[-1]
        base.outputs["velocity"][:] = [math.nan, math.inf]
        emu.cycles(1)
        left = struct.unpack("<hh", sim.frames[-1][1])
        rpm = round(26.0 * 60 / (2 * math.pi))  # the map's limits: 26 rad/s = 248 rpm
        assert left == (struct.unpack("<hh", sent[1])[0], rpm)  # NaN: the last value sent; inf: the map's max
        base.outputs["velocity"][:] = [-1e9, 0.0]
        emu.cycles(1)
        assert struct.unpack("<hh", sim.frames[-1][1]) == (-rpm, 0)  # never the int16's -32768


def test_the_safe_stop_sends_zero_speed_on_the_shared_frame() -> None:
    with emulate(EXAMPLE) as emu:
        base = emu.op["base"]
        sim = _sim(emu)
        base.outputs["velocity"][:] = [3.0, 3.0]
        emu.cycles(20)
        emu.silence("base", "left_wheel")  # the left wheel's slot no longer comes: the safe stop latches
        emu.cycles(20)
        assert sim.frames[-1] == (0x200, struct.pack("<hh", 0, 0))
        assert abs(sim.motor(2).velocity) < 0.05


MAP = """
name: wheels
rawcan:
  family: frames
  command:
    id: 0x200
    motors: 2
    fields:
      - {name: velocity, type: int, bits: 16, scale: 9.55, safe_value: 0}
  feedback:
    id: 0x300
    motors: 2
    fields:
      - {name: position, type: int, bits: 16, byte_order: big, scale: 13037.97}
"""


@pytest.mark.parametrize(
    ("old", "new", "where"),
    [
        ("type: int, bits: 16, scale: 9.55", "type: int, bits: 12, scale: 9.55", "command.fields[0].bits"),
        ("byte_order: big, scale: 13037.97", "byte_order: big, scale: 13037.97, safe_value: 1", "safe_value"),
        (
            "motors: 2\n    fields:\n      - {name: velocity",
            "motors: 5\n    fields:\n      - {name: velocity",
            "command.fields",
        ),
        ("scale: 9.55, safe_value: 0", "scale: 9.55", "command.fields"),
        ("byte_order: big", "byte_order: middle", "byte_order"),
        ("scale: 9.55,", "scale: 0,", "scale"),
    ],
)
def test_a_bad_description_is_refused_naming_file_line_and_field(old: str, new: str, where: str) -> None:
    assert old in MAP
    with pytest.raises(PdoMapError) as err:
        drive_map_from_text(MAP.replace(old, new), "wheels.yaml")
    text = str(err.value)
    assert "wheels.yaml:" in text and where in text, text


def test_the_shipped_map_is_the_one_the_example_uses() -> None:
    assert (fieldbus.PDO_MAPS / "amr_seed_wheels.yaml").is_file()
    assert "../pdo_maps/amr_seed_wheels.yaml" in EXAMPLE.read_text()


def test_the_wheels_run_in_the_emulator_process_over_fieldbus_udp() -> None:
    """The same YAML, the emulator in a child process (``sim_slaves.can_process``, kind auto): the master
    reads both wheels from the one shared feedback frame every cycle (wall clock: judged in cycles)."""
    with emulate(EXAMPLE, can="udp", receive_timeout_us=20_000) as emu:
        base = emu.op["base"]
        base.outputs["velocity"][:] = [1.0, -1.0]
        fresh = 0

        def step(_k: int) -> None:
            nonlocal fresh
            fresh += bool(emu.op.exchange().fresh)

        emu.run(step, 100)  # paced at the network's 10 ms: at least 1 s of the motors' own time
        assert fresh >= 75, fresh  # a loaded machine may miss a few
        left, right = base.inputs["position"]
        assert left > 0.05 and right < -0.05  # both wheels turned, each its own way


FAULTY = """
name: faulty_wheels
rawcan:
  family: frames
  command:
    id: 0x210
    fields:
      - {name: velocity, type: int, bits: 16, scale: 100, unit: rad/s, safe_value: 0}
  feedback:
    id: 0x310
    fields:
      - {name: position, type: int, bits: 32, scale: 10000, unit: rad}
      - {name: status, type: uint, bits: 4}
      - {name: spare, type: uint, bits: 4}
  enable: [0x01]
  disable: [0x00]
  clear: [0x03]
  fault: {field: status, codes: {0: ok, 1: enabled, 9: over-current}, ok: [0, 1]}
"""


def test_a_declared_fault_code_is_a_named_event_and_recovery_uses_the_map_s_patterns(tmp_path: Path) -> None:
    (tmp_path / "faulty.yaml").write_text(FAULTY)
    net = tmp_path / "net.yaml"
    net.write_text(
        "cycle_time_us: 1000\nbuses:\n  - {name: base, type: rawcan, interface: can0, slaves: "
        "[{name: 'w{i}', map: faulty.yaml, node_id: 1, count: 2}]}\n"
    )
    with emulate(net) as emu:
        base, sim = emu.op["base"], _sim(emu)
        assert sim.frames[:2] == [(0x211, b"\x01"), (0x212, b"\x01")]  # per motor: id + node, enabled
        base.outputs["velocity"][:] = 2.0
        emu.cycles(200)
        assert sim.motor(2).velocity == pytest.approx(2.0, abs=0.01)
        emu.drive_fault("base", "w1", 9)
        events = [e for _ in range(5) for e in emu.op.exchange().events if isinstance(e, fieldbus.DriveFault)]
        assert [(e.slave, e.code, e.name) for e in events] == [("w1", 9, "over-current")]
        assert not sim.motor(2).enabled
        assert emu.recover_motor("base", "w1")
        assert sim.frames[-2:] == [(0x212, b"\x03"), (0x212, b"\x01")]  # clear, then enable
        assert sim.motor(2).enabled and sim.error[2] == 0
        assert base.outputs["velocity"][1] == 0.0  # seeded: no motion until the controller asks
        emu.cycles(50)
        assert abs(sim.motor(2).velocity) < 0.01
