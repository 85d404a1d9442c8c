"""The output path's rules (fieldbus.core.output_rules) on a process image, and the map's ``limits:`` section."""

from __future__ import annotations

import math
import struct

import numpy as np
import pytest

from fieldbus.core.cubemars import ServoField, encode_servo
from fieldbus.core.damiao import ModeField, encode_fields
from fieldbus.core.output_rules import OutputRules, Reason, UnsafeOutputError, channel_limits
from fieldbus.core.pdo import drive_map_from_text
from fieldbus.core.pdo.image import ProcessImage
from fieldbus.core.pdo.layout import layout
from fieldbus.errors import PdoMapError

MAP = """
name: joint
vendor_id: 1
product_id: 2
profile: cia402
sdo:
  - {index: 0x607D, sub_index: 1, type: int32, value: -20000}
  - {index: 0x607D, sub_index: 2, type: int32, value: 40000}
rpdo:
  - index: 0x1600
    channels:
      - {index: 0x6040, sub_index: 0, type: uint16}
      - {index: 0x607A, sub_index: 0, type: int32, factor: 10000.0, unit: rad}
      - {index: 0x6071, sub_index: 0, type: int16, factor: 1000.0, unit: N·m}
      - {index: 0x60FF, sub_index: 0, type: int32}
tpdo:
  - index: 0x1A00
    channels:
      - {index: 0x6041, sub_index: 0, type: uint16}
      - {index: 0x6061, sub_index: 0, type: int8}
"""


def rules_for(text: str, n: int = 3, cycle_s: float = 0.001) -> tuple[ProcessImage, OutputRules]:
    drive = drive_map_from_text(text, "joint.yaml")
    img = ProcessImage(layout(drive), n)
    lim = channel_limits(drive, img.layout.outputs, cycle_s)
    inp = img.inputs.values
    return img, OutputRules("g", img.outputs, lim, inp["statusword"], inp["modes_of_operation_display"])


def wire_target(img: ProcessImage) -> list[int]:
    img.outputs.to_wire()
    return [struct.unpack_from("<i", bytes(img.outputs.wire[i]), 2)[0] for i in range(img.n_axes)]


def test_nan_keeps_the_last_value_sent_and_is_counted_per_axis() -> None:
    img, rules = rules_for(MAP)
    out = img.outputs
    out["target_position"][:] = [0.5, 1.0, 1.5]
    assert not rules.apply()
    out["target_position"][1] = math.nan
    assert rules.apply()
    assert list(out["target_position"]) == [0.5, 1.0, 1.5]
    assert wire_target(img) == [5000, 10000, 15000]
    assert rules.counts[:, Reason.NAN].tolist() == [0, 1, 0]
    (ev,) = rules.events(7)
    assert (ev.cycle, ev.axis, ev.channel, ev.reason, ev.sent) == (7, 1, "target_position", Reason.NAN, 1.0)
    assert math.isnan(ev.asked)


def test_inf_and_out_of_range_saturate_to_the_maps_window_from_0x607d_not_the_wire_type() -> None:
    img, rules = rules_for(MAP)
    out = img.outputs
    out["target_position"][:] = [math.inf, -math.inf, 1e9]
    assert rules.apply()
    assert wire_target(img) == [40000, -20000, 40000]  # 0x607D:02 / :01, never INT32_MAX
    assert rules.counts[:, Reason.INF].tolist() == [1, 1, 0]
    assert rules.counts[:, Reason.RANGE].tolist() == [0, 0, 1]
    events = rules.events(0)
    assert [(e.axis, e.reason, e.sent) for e in events] == [
        (0, Reason.INF, 4.0),
        (1, Reason.INF, -2.0),
        (2, Reason.RANGE, 4.0),
    ]
    out["target_position"][2] = 1e9  # the controller asks again: counted, no new event (one per streak)
    rules.apply()
    assert rules.events(1) == [] and rules.counts[:, Reason.RANGE].tolist() == [0, 0, 2]


def test_inf_without_a_limit_keeps_the_last_value() -> None:
    img, rules = rules_for(
        MAP.replace(
            "sdo:\n  - {index: 0x607D, sub_index: 1, type: int32, value: -20000}\n  - {index: 0x607D, sub_index: 2, type: int32, value: 40000}\n",
            "",
        )
    )
    out = img.outputs
    out["target_position"][:] = 0.25
    rules.apply()
    out["target_position"][:] = math.inf
    rules.apply()
    assert wire_target(img) == [2500, 2500, 2500]


def test_step_is_clamped_only_on_engaged_axes() -> None:
    text = MAP + "limits:\n  target_position: {max_rate: 2.0}\n"  # 2 rad/s at 1 ms: 0.002 rad a cycle
    img, rules = rules_for(text)
    sw, out = img.inputs["statusword"], img.outputs
    sw[:] = [0x0237, 0x0237, 0x0250]  # axes 0, 1 operation enabled; axis 2 switch on disabled
    img.inputs["modes_of_operation_display"][:] = 8  # CSP
    out["target_position"][:] = 0.0
    rules.apply()
    out["target_position"][:] = [0.001, 1.0, 1.0]
    assert rules.apply()
    assert out["target_position"].tolist() == pytest.approx([0.001, 0.002, 1.0])
    assert rules.counts[:, Reason.STEP].tolist() == [0, 1, 0]
    sw[1] = 0x0233  # no longer enabled: follows what is asked
    out["target_position"][1] = 1.0
    rules.apply()
    assert out["target_position"][1] == 1.0
    img.inputs["modes_of_operation_display"][0] = 1  # profile position: a destination, not ramped
    out["target_position"][0] = 2.5
    rules.apply()
    assert out["target_position"][0] == 2.5


def test_a_raw_integer_channel_with_a_limit_is_clamped() -> None:
    text = MAP + "limits:\n  target_velocity: {max: 5000}\n"
    img, rules = rules_for(text)
    img.outputs["target_velocity"][:] = [2**31 - 1, -(2**31), 100]
    rules.apply()
    assert img.outputs["target_velocity"].tolist() == [5000, -5000, 100]


def test_limits_off_keeps_only_nan_and_inf() -> None:
    img, rules = rules_for(MAP + "limits: off\n")
    img.outputs["target_position"][:] = 100.0
    rules.apply()
    assert wire_target(img) == [1_000_000] * 3


def test_the_clean_cycle_allocates_nothing() -> None:
    from fieldbus.platform.allocs import net_blocks

    img, rules = rules_for(MAP + "limits:\n  target_position: {max_rate: 2.0}\n")
    assert net_blocks(rules.apply, cycles=5000) <= 2
    target = img.outputs["target_position"]

    def refused() -> None:  # a controller that writes NaN and inf every cycle: the refusal path
        target[0], target[1] = math.nan, math.inf
        rules.apply()

    assert net_blocks(refused, cycles=5000) <= 2
    assert rules.counts[0, Reason.NAN] >= 5000 and rules.counts[1, Reason.INF] >= 5000


@pytest.mark.parametrize(
    ("limits", "where", "what"),
    [
        ("  target_postion: {max: 1}\n", "limits.target_postion", "did you mean target_position"),
        ("  target_position: {min: 2, max: 1}\n", "limits.target_position.max", "greater than min"),
        ("  target_position: {max_rate: 0}\n", "limits.target_position.max_rate", "greater than 0"),
        ("  target_velocity: {max: 1e12}\n", "limits.target_velocity.max", "outside what int32"),
        ("  target_position: {}\n", "limits.target_position", "give min"),
        ("  target_position: {max: -1}\n", "limits.target_position.max", "positive max"),
    ],
)
def test_bad_limits_are_located_errors(limits: str, where: str, what: str) -> None:
    with pytest.raises(PdoMapError) as err:
        drive_map_from_text(MAP + "limits:\n" + limits, "joint.yaml")
    text = str(err.value)
    assert err.value.path == where and "joint.yaml:" in text and what in text, text
    assert err.value.line == MAP.count("\n") + 2


def test_family_codecs_refuse_a_value_that_did_not_pass_the_rules() -> None:
    with pytest.raises(UnsafeOutputError, match="position"):
        encode_servo((ServoField("position", "int32", 572957.795),), {"position": math.nan})
    with pytest.raises(UnsafeOutputError, match="velocity"):
        encode_fields((ModeField("velocity", "float32"),), {"velocity": math.inf}, {})
    assert struct.unpack(">i", encode_servo((ServoField("position", "int32", 10.0),), {"position": 1.0})) == (
        10,
    )


def test_rules_vectorise_over_every_scaled_channel_of_a_rawcan_map() -> None:
    from fieldbus import PDO_MAPS

    drive = drive_map_from_text((PDO_MAPS / "damiao_dm_j4310.yaml").read_text(), "dm.yaml")
    img = ProcessImage(layout(drive, pdo_align=8), 2)
    rules = OutputRules("g", img.outputs, channel_limits(drive, img.layout.outputs, 0.001))
    out = img.outputs
    out["velocity"][:] = [1000.0, math.nan]
    out["kp"][:] = [-5.0, 600.0]
    rules.apply()
    assert out["velocity"].tolist() == [30.0, 0.0]  # VMAX; NaN keeps the default (0)
    assert out["kp"].tolist() == [0.0, 500.0]
    assert np.isfinite(out["position"]).all()


def test_damiaos_mode_channels_share_the_mit_frames_block_each_with_its_own_rules() -> None:
    """Damiao's mode channels (float32 ones too) are scaled image channels beside the MIT frame's: the
    rules are one block for all eleven (as MIT's five), each column with its own window, NaN and inf
    handling, counts and events, and a network file's narrowing of one row; the wire gets float32."""
    from fieldbus import PDO_MAPS
    from fieldbus.core.output_rules import ChannelLimit
    from fieldbus.platform.allocs import net_blocks

    drive = drive_map_from_text((PDO_MAPS / "damiao_dm_j4310.yaml").read_text(), "dm.yaml")
    img = ProcessImage(layout(drive), 3)
    lay = img.layout.outputs
    lims = channel_limits(drive, lay, 0.001)
    row2 = [*lims, ChannelLimit("velocity.velocity", -1.0, 1.0, source="network")]
    rules = OutputRules("g", img.outputs, lims, rows={2: tuple(row2)})
    assert [sorted(b.names) for b in rules.blocks] == [sorted(img.outputs.names)]
    out = img.outputs
    out["velocity.velocity"][:] = [2.0, 3.0, 0.5]
    out["position_force.position"][:] = [1.0, 1.0, 1.0]
    assert not rules.apply()
    assert net_blocks(rules.apply, cycles=2000) <= 2  # the clean cycle allocates nothing
    out["velocity.velocity"][:] = [math.nan, math.inf, 5.0]
    out["position_velocity.position"][:] = [100.0, 0.25, -math.inf]
    assert rules.apply()
    assert out["velocity.velocity"].tolist() == [2.0, 30.0, 1.0]  # held, VMAX, the row's own window
    assert out["position_velocity.position"].tolist() == [12.5, 0.25, -12.5]  # PMAX both ways
    assert out["position_force.position"].tolist() == [1.0, 1.0, 1.0]  # untouched
    assert rules.counts[:, Reason.NAN].tolist() == [1, 0, 0]
    assert rules.counts[:, Reason.INF].tolist() == [0, 1, 1]
    assert rules.counts[:, Reason.RANGE].tolist() == [1, 0, 1]
    got = {(e.axis, e.channel, e.reason) for e in rules.events(7)}
    assert got == {
        (0, "velocity.velocity", Reason.NAN),
        (1, "velocity.velocity", Reason.INF),
        (2, "velocity.velocity", Reason.RANGE),
        (0, "position_velocity.position", Reason.RANGE),
        (2, "position_velocity.position", Reason.INF),
    }
    out["velocity.velocity"][1] = 0.1
    img.outputs.to_wire()  # float32 little-endian at byte 16, as the value rounds to float32
    sent = [struct.unpack_from("<f", bytes(img.outputs.wire[i]), 16)[0] for i in range(3)]
    assert sent == [2.0, float(np.float32(0.1)), 1.0]


RAW_FLOATS = """
name: floats
vendor_id: 1
product_id: 2
rpdo:
  - index: 0x1600
    channels:
      - {index: 0x2000, sub_index: 1, type: float, name: a}
      - {index: 0x2000, sub_index: 2, type: float, name: b}
      - {index: 0x2000, sub_index: 3, type: int16, name: gap}
      - {index: 0x2000, sub_index: 4, type: float, name: c}
      - {index: 0x2000, sub_index: 5, type: double, name: d}
limits:
  a: {min: -1.0, max: 1.0}
  b: {min: 0.0, max: 10.0}
  c: {min: -5.0, max: 5.0}
tpdo: []
"""


def test_side_by_side_raw_floats_are_one_block_with_each_columns_own_rules() -> None:
    """Unscaled floats lying side by side in the row, of one dtype, are one block (a, b); a float after
    another column (c) or of another dtype (d) starts its own. Each column keeps its own rules."""
    drive = drive_map_from_text(RAW_FLOATS, "floats.yaml")
    img = ProcessImage(layout(drive), 2)
    rules = OutputRules("g", img.outputs, channel_limits(drive, img.layout.outputs, 0.001))
    assert [b.names for b in rules.blocks] == [["a", "b"], ["c"], ["d"]]
    out = img.outputs
    out["a"][:], out["b"][:], out["c"][:], out["d"][:] = [0.5, -0.5], [2.0, 3.0], [1.0, 1.0], [7.0, 8.0]
    assert not rules.apply()
    out["a"][:], out["b"][:] = [math.nan, 4.0], [20.0, -math.inf]
    out["d"][:] = [math.nan, math.inf]
    assert rules.apply()
    assert out["a"].tolist() == [0.5, 1.0] and out["b"].tolist() == [10.0, 0.0]
    assert out["d"].tolist() == [7.0, 8.0]  # no limit: NaN and inf keep the value sent last
    assert rules.counts[:, Reason.NAN].tolist() == [2, 0] and rules.counts[:, Reason.INF].tolist() == [0, 2]
    img.outputs.to_wire()
    assert struct.unpack_from("<ff", bytes(img.outputs.wire[0]), 0) == (0.5, 10.0)


def test_a_transition_hold_seeds_the_row_and_the_rules_restart_from_it() -> None:
    """S12 on raw CAN (fieldbus.core.hold): position <- the one read, speed and torque 0, gains kept; a
    NaN afterwards keeps the seed and a step limit ramps from it, not from what was sent before."""
    from fieldbus import PDO_MAPS
    from fieldbus.core.hold import TransitionHold

    text = (PDO_MAPS / "damiao_dm_j4310.yaml").read_text() + "limits:\n  position: {max_step: 0.01}\n"
    drive = drive_map_from_text(text, "dm.yaml")
    img = ProcessImage(layout(drive, pdo_align=8), 2)
    rules = OutputRules("g", img.outputs, channel_limits(drive, img.layout.outputs, 0.001))
    out, inp = img.outputs, img.inputs
    out["position"][:], out["velocity"][:], out["torque"][:], out["kp"][:] = 0.0, 0.0, 0.0, 20.0
    rules.apply()
    for _ in range(500):  # the controller's set-point runs to 4 rad within the step
        out["position"][:] = 4.0
        rules.apply()
    assert out["position"].tolist() == pytest.approx([4.0, 4.0])
    out["velocity"][:], out["torque"][:] = 3.0, 2.0
    inp["position"][:] = [0.5, -0.25]  # where the motors are
    hold = TransitionHold(img, rules)
    hold.seed(np.array([True, False]))
    assert out["position"].tolist() == [0.5, 4.0] and out["velocity"].tolist() == [0.0, 3.0]
    assert out["torque"].tolist() == [0.0, 2.0] and out["kp"].tolist() == [20.0, 20.0]
    assert hold.held.tolist() == [True, False]
    out["position"][0] = math.nan
    rules.apply()
    assert float(out["position"][0]) == 0.5  # before the rebase: 4.0, the target sent before
    out["position"][0] = 0.7
    rules.apply()
    assert float(out["position"][0]) == pytest.approx(0.51)  # a step from the seed
    out["position"][:] = math.inf  # a seed of every row replaces what the controller wrote
    hold.seed()
    assert out["position"].tolist() == [0.5, -0.25]
