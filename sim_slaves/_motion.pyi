"""Types of the optional C module sim_slaves._motion (sim_slaves/_motion.c); absent where it is not built."""

import numpy as np
import numpy.typing as npt

_F64 = npt.NDArray[np.float64]
_I64 = npt.NDArray[np.int64]

def csp(
    pos: _F64,
    vel: _F64,
    integ: _F64,
    prev_target: _F64,
    prev_vff: _F64,
    tau: _F64,
    tau_eff: _F64,
    shaft: _F64,
    limit: npt.NDArray[np.bool_],
    vff_gain: _F64,
    tff_gain: _F64,
    kv: _F64,
    kp: _F64,
    tmax: _F64,
    load: _F64,
    epr: _F64,
    rpe: _F64,
    vmax: _F64,
    target: _F64,
    noise: _F64 | None,
    e: _F64 | float,
    f: _F64 | float,
    g: _F64 | float,
    hh: _F64 | float,
    ki_h: _F64 | float,
    a: int,
    b: int,
    dt: float,
    steps: int,
    speed_limited: bool,
    /,
) -> bool:
    """The plain-CSP substeps of drives a..b-1 (the bank's arrays whole); whether any hit its torque limit."""

def csp_outputs(
    statusword: _I64,
    following_error: _I64,
    position_counts: _I64,
    velocity_counts: _I64,
    torque_permille: _I64,
    fe_time: _F64,
    pos: _F64,
    vel: _F64,
    tau: _F64,
    cpr: _F64,
    epr: _F64,
    enc_to_counts: _F64,
    vpr: _F64,
    rated: _F64,
    noise: _I64,
    fe_window: _I64,
    position_window: _I64,
    limit: npt.NDArray[np.bool_],
    target: _F64,
    a: int,
    b: int,
    ideal_encoder: bool,
    limited: bool,
    sw_csp: int,
    sw_reached: int,
    sw_limit: int,
    /,
) -> bool:
    """Statusword, following error, actual values of drives a..b-1; False (nothing settled): numpy's turn."""

class Bank:
    """The kernel's hold on one drive bank's arrays (taken once): a cycle of the plain CSP path, or of the
    idle path, in one call."""

    def __init__(
        self,
        csp_arrays: tuple[npt.NDArray[np.generic], ...],
        out_arrays: tuple[npt.NDArray[np.generic], ...],
        idle_arrays: tuple[npt.NDArray[np.generic], ...],
        target_position: _I64,
        rpc: _F64,
        target: _F64,
    ) -> None: ...
    def csp_cycle(
        self,
        a: int,
        b: int,
        dt: float,
        steps: int,
        e: _F64 | float,
        f: _F64 | float,
        g: _F64 | float,
        hh: _F64 | float,
        ki_h: _F64 | float,
        speed_limited: bool,
        sw_csp: int,
        sw_reached: int,
        sw_limit: int,
        /,
    ) -> int:
        """limited | outputs done << 1 (outputs not done: numpy's turn, the target in ``target``)."""
    def idle_cycle(
        self,
        a: int,
        b: int,
        steps: int,
        e: _F64 | float,
        f: _F64 | float,
        g: _F64 | float,
        hh: _F64 | float,
        sw_remote: int,
        sw_voltage: int,
        nr: int,
        /,
    ) -> bool:
        """Rotors of drives a..b-1 coasting, then their outputs; False (the motion done): numpy's outputs."""
