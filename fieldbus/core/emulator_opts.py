"""Per-slave emulator options of a network file: the delays and imperfections of a real drive.

A slave may carry an ``emulator:`` mapping; the built-in emulators (the
``sim`` backend, ``python -m sim_slaves.ethercat``) give that drive these
properties. Real hardware ignores it. Keys (all optional; defaults: an
ideal drive, as the emulators behave without the mapping):

=============================  =======  =================================================
key                            default  meaning
=============================  =======  =================================================
``command_delay_cycles``       0        targets act this many cycles late (integer)
``command_delay_us``           0        the same in µs, rounded to whole bus cycles
``current_loop_bandwidth_hz``  0        first-order torque lag; 0 = torque follows at once
``encoder_counts_per_rev``     0        encoder resolution; 0 = the map's counts per rev
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

    def drive_params(self) -> dict[str, Any]:
        """Keyword arguments for ``sim_slaves.drive402.DriveParams``."""
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
        return out


KEYS = (
    "command_delay_cycles", "command_delay_us", "current_loop_bandwidth_hz", "encoder_counts_per_rev",
    "encoder_noise_counts", "coulomb_friction_nm", "viscous_friction_nm_s", "thermal", "kt_temp_coeff_per_k",
    "noise_seed",
)  # fmt: skip


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
    )


def _non_negative(r: Reader, value: Any, path: PathT) -> float:
    x = r.number(value, path)
    if x < 0:
        raise r.err(path, f"must be >= 0, got {x:g}")
    return x
