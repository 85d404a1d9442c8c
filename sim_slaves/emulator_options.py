"""The schema of a network file's ``emulator:`` section: the units, limits, delays and imperfections of a real drive.

A slave may carry an ``emulator:`` mapping; the built-in EtherCAT emulators
(the ``sim`` backend, ``python -m sim_slaves.ethercat --network``) give that
drive these properties (the CANopen simulator follows the map's scaling but
takes no options yet). Real hardware ignores it. fieldbus keeps the section
as written (:class:`fieldbus.core.emulator_opts.EmulatorSection`) and runs
:func:`check`, registered as the emulator part ``emulator_options``, when it
loads a network file; errors name the file, line and key.

Without the mapping the emulated drive already follows its map: a map that
scales position, velocity and torque to rad, rad/s and N·m gives it its
counts per revolution, velocity unit and rated torque
(``sim_slaves.drive_config``). The keys below that are named after a CiA 402
object set that object (the emulated object dictionary carries the value)
and override what the map implies. All optional:

==================================  =====================================================================
key                                 meaning (object)
==================================  =====================================================================
``position_encoder_resolution``     encoder increments per motor revolution (0x608F); with a scaled map
                                    and no gear the gear is inferred (counts per shaft rev / this)
``gear_ratio``                      motor revolutions per driven-shaft revolution (0x6091), number > 0
``motor_rated_torque_nm``           motor rated torque [N·m] (0x6076 holds mN·m): 1000 ‰ of 0x6071/0x6077
``max_torque_permille``             torque limit [‰ of rated] (0x6072), 0..65535
``max_motor_speed_rpm``             CSP/CSV velocity demand held within this [rpm] (0x6080); 0: no limit
``software_position_limit``         ``[min, max]`` [counts] (0x607D): the CSP target is held within them
``quick_stop_deceleration``         quick-stop ramp [acceleration units: counts/s² unless the map's
                                    velocity unit differs] (0x6085)
``quick_stop_option``               0x605A: 0 coast, 1/2 ramp then switch-on disabled, 5/6 ramp and stay
``following_error_window``          [counts] (0x6065); 4294967295: off
``inertia_kg_m2``                   rotor + load at the motor shaft [kg·m²] (load inertia / gear ratio²)
==================================  =====================================================================

The delays and imperfections (defaults: an ideal drive, as the emulators
behave without the mapping):

=============================  =======  =================================================
key                            default  meaning
=============================  =======  =================================================
``command_delay_cycles``       0        targets act this many cycles late (integer)
``command_delay_us``           0        the same in µs, rounded to whole bus cycles
``current_loop_bandwidth_hz``  0        first-order torque lag; 0 = torque follows at once
``encoder_counts_per_rev``     0        a coarser encoder the position is measured with; 0 = none
``encoder_noise_counts``       0        Gaussian noise on the measured position (std dev)
``coulomb_friction_nm``        0        dry friction opposing motion [N·m]
``viscous_friction_nm_s``      0.001    viscous friction [N·m·s/rad]
``thermal``                    false    winding temperature model on
``kt_temp_coeff_per_k``        -0.001   torque constant change per kelvin (thermal on)
``noise_seed``                 0        seed of the encoder noise
=============================  =======  =================================================
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from fieldbus.core.emulator_opts import EmulatorSection
from fieldbus.core.yamlread import Reader
from fieldbus.core.yamlsrc import PathT

MAX_DELAY_CYCLES = 1000


@dataclass(frozen=True)
class EmulatorOptions:
    """One slave's emulated imperfections (SI units; see the module docstring)."""

    command_delay_cycles: int = 0
    current_loop_bandwidth_hz: float = 0.0
    encoder_counts_per_rev: int = 0
    encoder_noise_counts: float = 0.0
    coulomb_friction_nm: float = 0.0
    viscous_friction_nm_s: float | None = None
    thermal: bool = False
    kt_temp_coeff_per_k: float | None = None
    noise_seed: int = 0
    drive: tuple[tuple[str, Any], ...] = ()  # the CiA 402 keys given (name, value), see DRIVE_KEYS

    def drive_params(self) -> dict[str, Any]:
        """Options for ``sim_slaves.drive_config.drive_params``: ``DriveParams`` keywords and the CiA 402 keys."""
        out: dict[str, Any] = {
            "command_delay_cycles": self.command_delay_cycles,
            "current_loop_bandwidth_hz": self.current_loop_bandwidth_hz,
            "encoder_counts_per_rev": self.encoder_counts_per_rev,
            "encoder_noise_counts": self.encoder_noise_counts,
            "coulomb_friction_nm": self.coulomb_friction_nm,
            "thermal": self.thermal,
            "noise_seed": self.noise_seed,
        }
        if self.viscous_friction_nm_s is not None:
            out["friction_nm_s_per_rad"] = self.viscous_friction_nm_s
        if self.kt_temp_coeff_per_k is not None:
            out["kt_temp_coeff_per_k"] = self.kt_temp_coeff_per_k
        out.update(self.drive)
        return out


DRIVE_KEYS = (
    "position_encoder_resolution", "gear_ratio", "motor_rated_torque_nm", "max_torque_permille",
    "max_motor_speed_rpm", "software_position_limit", "quick_stop_deceleration", "quick_stop_option",
    "following_error_window", "inertia_kg_m2",
)  # fmt: skip
QUICK_STOP_OPTIONS = (0, 1, 2, 5, 6)  # what the emulated drive does (sim_slaves.drive402)
INT32 = (-(1 << 31), (1 << 31) - 1)
UINT32_MAX = (1 << 32) - 1


KEYS = (
    "command_delay_cycles", "command_delay_us", "current_loop_bandwidth_hz", "encoder_counts_per_rev",
    "encoder_noise_counts", "coulomb_friction_nm", "viscous_friction_nm_s", "thermal", "kt_temp_coeff_per_k",
    "noise_seed", *DRIVE_KEYS,
)  # fmt: skip


def check(section: EmulatorSection) -> dict[str, Any]:
    """Validate ``section`` (errors name file, line and key); its options for
    :func:`sim_slaves.drive_config.drive_params` (``DriveParams`` keywords and the CiA 402 keys)."""
    return parse_emulator(
        section.reader(), section.options, section.path, section.cycle_time_us
    ).drive_params()


def drive_options(section: EmulatorSection | None) -> dict[str, Any] | None:
    """:func:`check` of a slave's section, None without one (an ideal drive that follows its map)."""
    return None if section is None else check(section)


def parse_emulator(r: Reader, raw: Any, path: PathT, cycle_time_us: int) -> EmulatorOptions:
    """Validate a slave's ``emulator:`` mapping; errors name the file, line and key."""
    m = r.mapping(raw, path, KEYS)
    if "command_delay_cycles" in m and "command_delay_us" in m:
        raise r.err(
            (*path, "command_delay_us"), "give command_delay_cycles or command_delay_us, not both", key=True
        )
    delay = 0
    if "command_delay_cycles" in m:
        delay = r.integer(m["command_delay_cycles"], (*path, "command_delay_cycles"), 0, MAX_DELAY_CYCLES)
    elif "command_delay_us" in m:
        us = _non_negative(r, m["command_delay_us"], (*path, "command_delay_us"))
        delay = round(us / cycle_time_us)
        if delay > MAX_DELAY_CYCLES:
            raise r.err((*path, "command_delay_us"), f"{us:g} µs is more than {MAX_DELAY_CYCLES} cycles")

    def num(key: str) -> float:
        return _non_negative(r, m[key], (*path, key)) if key in m else 0.0

    return EmulatorOptions(
        command_delay_cycles=delay,
        current_loop_bandwidth_hz=num("current_loop_bandwidth_hz"),
        encoder_counts_per_rev=r.integer(
            m.get("encoder_counts_per_rev", 0), (*path, "encoder_counts_per_rev"), 0, 1 << 31
        ),
        encoder_noise_counts=num("encoder_noise_counts"),
        coulomb_friction_nm=num("coulomb_friction_nm"),
        viscous_friction_nm_s=num("viscous_friction_nm_s") if "viscous_friction_nm_s" in m else None,
        thermal=r.boolean(m["thermal"], (*path, "thermal")) if "thermal" in m else False,
        kt_temp_coeff_per_k=(
            r.number(m["kt_temp_coeff_per_k"], (*path, "kt_temp_coeff_per_k"))
            if "kt_temp_coeff_per_k" in m
            else None
        ),
        noise_seed=r.integer(m.get("noise_seed", 0), (*path, "noise_seed"), 0, (1 << 32) - 1),
        drive=tuple((k, _drive_key(r, k, m[k], (*path, k))) for k in DRIVE_KEYS if k in m),
    )


def _drive_key(r: Reader, key: str, value: Any, path: PathT) -> Any:
    """One CiA 402 key, validated (its range is the object's, or what a drive can have)."""
    if key == "position_encoder_resolution":
        return r.integer(value, path, 1, UINT32_MAX)
    if key in ("gear_ratio", "motor_rated_torque_nm", "inertia_kg_m2"):
        x = r.number(value, path)
        if not x > 0:
            raise r.err(path, f"must be > 0, got {x:g}")
        return x
    if key == "max_torque_permille":
        return r.integer(value, path, 0, 0xFFFF)
    if key == "max_motor_speed_rpm":
        return _non_negative(r, value, path)
    if key in ("quick_stop_deceleration", "following_error_window"):
        return r.integer(value, path, 0, UINT32_MAX)
    if key == "quick_stop_option":
        code = r.integer(value, path, -(1 << 15), (1 << 15) - 1)
        if code not in QUICK_STOP_OPTIONS:
            raise r.err(path, f"quick stop option {code} is not emulated (one of {QUICK_STOP_OPTIONS})")
        return code
    assert key == "software_position_limit"
    items = r.sequence(value, path)
    if len(items) != 2:
        raise r.err(path, f"give [min, max] in counts, got {len(items)} values")
    lo, hi = (r.integer(v, (*path, i), *INT32) for i, v in enumerate(items))
    if lo >= hi:
        raise r.err(path, f"min {lo} must be below max {hi}")
    return (lo, hi)


def _non_negative(r: Reader, value: Any, path: PathT) -> float:
    x = r.number(value, path)
    if x < 0:
        raise r.err(path, f"must be >= 0, got {x:g}")
    return x
