"""The emulated drive a map implies (sim_slaves.drive_config), its objects, and the emulator options naming them."""

from __future__ import annotations

import math
from pathlib import Path

import pytest

from fieldbus.core.network import network_from_text
from fieldbus.core.pdo.load import drive_map_from_text, load_drive_map
from fieldbus.errors import FieldbusError
from sim_slaves.drive402 import Cia402Drive, DictObjectStore, DriveParams, Obj, default_objects
from sim_slaves.drive_config import drive_params
from sim_slaves.emulator_options import drive_options
from sim_slaves.od import ObjectDictionary

DATA = Path(__file__).resolve().parents[1] / "data"
REPO = Path(__file__).resolve().parents[2]
GEARED = load_drive_map(DATA / "geared_joint_2p20_50.yaml")
DEMO = load_drive_map(REPO / "fieldbus" / "data" / "demo_joint.yaml")


def _map(inputs: str, outputs: str = "", sdo: str = "") -> str:
    """A CiA 402 map with the given extra input (TxPDO) and output (RxPDO) channels."""
    return (
        "name: t\nvendor_id: 1\nproduct_id: 2\nprofile: cia402\n"
        + (f"sdo:\n{sdo}" if sdo else "")
        + "rpdo:\n  - index: 0x1600\n    channels:\n      - {index: 0x6040, sub_index: 0, type: uint16}\n"
        + outputs
        + "tpdo:\n  - index: 0x1A00\n    channels:\n      - {index: 0x6041, sub_index: 0, type: uint16}\n"
        + inputs
    )


def test_the_demo_joint_is_the_default_drive_as_before() -> None:
    """The demo's map says 17 bits, 1 N·m: exactly the drive every existing test ran."""
    p = drive_params(DEMO)
    d = DriveParams()
    assert (p.counts_per_rev, p.gear_ratio, p.velocity_units_per_count_s) == (d.counts_per_rev, 1.0, 1.0)
    assert p.rated_torque_nm == pytest.approx(d.rated_torque_nm, rel=1e-6)
    assert p.following_error_window_counts == d.following_error_window_counts
    assert p.quick_stop_decel_counts_s2 == d.quick_stop_decel_counts_s2


def test_a_2p20_count_50_to_1_map_gives_its_resolution_gear_and_rated_torque() -> None:
    alone = drive_params(GEARED)  # the scaling alone: 2^20 x 50 counts per revolution, no gear known
    assert (alone.counts_per_rev, alone.gear_ratio) == (2**20 * 50, 1.0)
    assert alone.rated_torque_nm == pytest.approx(50.0)  # 0.05 N·m per unit at the joint
    geared = drive_params(GEARED, {"gear_ratio": 50})
    assert (geared.counts_per_rev, geared.gear_ratio, geared.encoder_cpr) == (2**20, 50.0, 2**20)
    assert geared.rated_torque_nm == pytest.approx(1.0)
    # count-based defaults keep their physical size: 8x the counts of the 17-bit default
    assert geared.following_error_window_counts == 80_000
    assert geared.quick_stop_decel_counts_s2 == 16_000_000
    inferred = drive_params(GEARED, {"position_encoder_resolution": 2**20})
    assert (inferred.counts_per_rev, inferred.gear_ratio) == (2**20, 50.0)  # 49.9999996 from the factor: 50


def test_the_gear_written_at_start_up_counts_and_the_drive_reports_the_joint_angle() -> None:
    sdo = (
        "  - {index: 0x6091, sub_index: 1, type: uint32, value: 100}\n"
        "  - {index: 0x6091, sub_index: 2, type: uint32, value: 3}\n"
    )
    text = _map("      - {index: 0x6064, sub_index: 0, type: int32, factor: 1.0e-6, unit: rad}\n", sdo=sdo)
    p = drive_params(drive_map_from_text(text))
    assert p.gear_ratio == pytest.approx(100 / 3)
    assert p.counts_per_rev == round(2 * math.pi * 1e6 * 3 / 100)
    drive = Cia402Drive(p)
    drive.position_rad = 10.0
    assert drive.output_position_rad == pytest.approx(0.3)


@pytest.mark.parametrize(
    ("channels", "counts", "velocity_units"),
    [
        # degrees and rpm: 2^17 counts per revolution, velocity in counts/s
        (
            "      - {index: 0x6064, sub_index: 0, type: int32, factor: 0.00274658203125, unit: deg}\n"
            "      - {index: 0x606C, sub_index: 0, type: int32, factor: 0.000457763671875, unit: rpm}\n",
            2**17,
            1.0,
        ),
        # ethercat_driver_ros2's style: factors without units are SI; velocity in 0.001 rpm of a 55,100-count drive
        (
            "      - {index: 0x6064, sub_index: 0, type: int32, factor: 0.000114035}\n"
            "      - {index: 0x606C, sub_index: 0, type: int32, factor: 3.8011695906e-6}\n",
            55_100,
            30.0,
        ),
        # counts and % say nothing: the default drive
        (
            "      - {index: 0x6064, sub_index: 0, type: int32, unit: counts}\n"
            "      - {index: 0x6077, sub_index: 0, type: int16, factor: 0.1, unit: '%'}\n",
            2**17,
            1.0,
        ),
    ],
    ids=["deg-rpm", "ros2-no-units", "counts-percent"],
)
def test_units_of_the_scaling_are_read(channels: str, counts: int, velocity_units: float) -> None:
    p = drive_params(drive_map_from_text(_map(channels)))
    assert p.counts_per_rev == pytest.approx(counts, rel=1e-4)
    assert p.velocity_units_per_count_s == pytest.approx(velocity_units, rel=1e-4)
    assert p.rated_torque_nm == 1.0


def test_an_input_and_an_output_that_disagree_say_nothing() -> None:
    """ethercat_driver_ros2's EPOS4 file scales target and actual position 1000x apart: not one drive."""
    epos = load_drive_map(DATA / "ethercat_driver_ros2" / "maxon_epos4_50_5.yaml")
    assert drive_params(epos).counts_per_rev == DriveParams().counts_per_rev


def test_options_override_what_the_map_implies_and_the_od_carries_them() -> None:
    options = {
        "gear_ratio": 50,
        "motor_rated_torque_nm": 0.64,
        "max_torque_permille": 2500,
        "max_motor_speed_rpm": 3000.0,
        "software_position_limit": (-1_000_000, 2_000_000),
        "quick_stop_deceleration": 9_000_000,
        "quick_stop_option": 6,
        "following_error_window": 123_456,
        "inertia_kg_m2": 3e-4,
        "command_delay_cycles": 2,
    }
    p = drive_params(GEARED, options)
    assert p.rated_torque_nm == 0.64 and p.inertia_kg_m2 == 3e-4 and p.command_delay_cycles == 2
    od = ObjectDictionary.from_drive_map(GEARED, p)
    expected = {
        (0x608F, 1): 2**20,
        (0x608F, 2): 1,
        (0x6091, 1): 50,
        (0x6091, 2): 1,
        (0x6076, 0): 640,
        (0x6072, 0): 2500,
        (0x6080, 0): 3000,
        (0x607D, 1): -1_000_000,
        (0x607D, 2): 2_000_000,
        (0x6085, 0): 9_000_000,
        (0x605A, 0): 6,
        (0x6065, 0): 123_456,
    }
    assert {k: od.get_value(*k) for k in expected} == expected
    # and the drive applies them once bound to that OD
    drive = Cia402Drive(p)
    drive.bind(od)
    assert drive.rated_torque_nm == pytest.approx(0.64)
    assert drive.max_torque_nm == pytest.approx(1.6)
    assert drive.max_speed_rad_s == pytest.approx(3000 * 2 * math.pi / 60)
    assert (drive.position_limit_min, drive.position_limit_max) == (-1_000_000, 2_000_000)
    assert drive.qs_decel == pytest.approx(9_000_000 * 2 * math.pi / 2**20)


def test_a_write_to_the_rated_torque_and_limits_takes_effect_at_the_next_transition() -> None:
    """0x6076, 0x607D and 0x6080 are read like 0x6072: at bind and on every state transition."""
    values = default_objects()
    od = DictObjectStore(values)
    drive = Cia402Drive()
    drive.step(od, 1e-3)
    assert drive.position_limit_max == math.inf and drive.max_speed_rad_s == math.inf
    values[(0x6076, 0)] = 2500
    values[(0x607D, 1)], values[(0x607D, 2)] = -100, 100
    values[(0x6080, 0)] = 60
    values[(int(Obj.CONTROLWORD), 0)] = 0x06  # shutdown: a transition
    for _ in range(3):
        drive.step(od, 1e-3)
    assert drive.rated_torque_nm == 2.5 and drive.max_torque_nm == pytest.approx(7.5)
    assert (drive.position_limit_min, drive.position_limit_max) == (-100, 100)
    assert drive.max_speed_rad_s == pytest.approx(2 * math.pi)


def test_an_unknown_option_is_refused() -> None:
    with pytest.raises(ValueError, match="unknown drive options: gearratio"):
        drive_params(GEARED, {"gearratio": 50})


NET = """cycle_time_us: 1000
buses:
  - name: arm
    type: ethercat
    interface: sim
    slaves:
      - {{name: j, map: {map}, emulator: {emulator}}}
"""


@pytest.mark.parametrize(
    ("emulator", "message"),
    [
        ("{gear_ratio: 0}", "gear_ratio: must be > 0"),
        ("{position_encoder_resolution: -4}", "position_encoder_resolution"),
        ("{software_position_limit: [5, 1]}", "min 5 must be below max 1"),
        ("{software_position_limit: [5]}", r"give \[min, max\]"),
        ("{quick_stop_option: 3}", "quick stop option 3 is not emulated"),
        ("{max_torque_permille: 70000}", "max_torque_permille"),
        ("{gear_ration: 50}", "did you mean gear_ratio"),
    ],
)
def test_bad_drive_options_are_refused_with_file_line_and_key(emulator: str, message: str) -> None:
    text = NET.format(map=DATA / "geared_joint_2p20_50.yaml", emulator=emulator)
    with pytest.raises(FieldbusError, match=message) as info:
        network_from_text(text, "net.yaml")
    assert "net.yaml:7:" in str(info.value)


def test_the_network_options_reach_the_drive() -> None:
    text = NET.format(
        map=DATA / "geared_joint_2p20_50.yaml", emulator="{gear_ratio: 50, max_motor_speed_rpm: 3000}"
    )
    slave = network_from_text(text, "net.yaml").buses[0].slaves[0]
    assert slave.emulator is not None
    p = drive_params(slave.map, drive_options(slave.emulator))
    assert (p.counts_per_rev, p.gear_ratio, p.max_motor_speed_rpm) == (2**20, 50.0, 3000.0)
