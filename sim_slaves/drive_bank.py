"""Every CiA 402 drive of one emulator stepped together as numpy arrays.

:class:`DriveBank` holds the state of N drives in arrays (one element per
drive) and advances a contiguous run of them in one call: CSP/CSV/CST
cascade, rotor and load, torque limit, quick stop / fault reaction ramps,
following-error and over-temperature faults, thermal model, command delay,
current-loop lag, encoder resolution and noise, dry friction. The cost per
call is a fixed number of numpy operations, nearly flat in N.

This is the one CiA 402 drive model: each drive, a
:class:`~sim_slaves.drive402.Cia402Drive`, keeps its numeric state in the
bank's arrays (its attributes are elements of them: ``drive402.FLOAT_SLOTS``
...), and a drive built alone is the one drive of a bank of its own. The drive
holds the event logic (state machine table, mode switch, homing, the PP/PV
trajectory generator, fault injection, configuration from the OD); the bank
calls it, through the drive's public methods, only for drives that need it
this cycle (a new controlword, a pending transition, a pending fault, a mode
change, or a state left on its own: NOT READY, QUICK STOP, FAULT REACTION,
FAULT; homing and profile drives every cycle); in steady operation no drive
does. The physics is the bank's alone.

Physics: as :mod:`sim_slaves.drive402` describes it. Three
paths compute it: :meth:`DriveBank._csp` (every drive of the run enabled in
plain CSP), :meth:`DriveBank._idle` (none powered), and the general
:meth:`DriveBank._physics` (power stage, feed-forward, then the substep
cascade); the first two are the general one with the terms that are zero left out.

Inputs (the master's outputs) go into :attr:`DriveBank.controlword`,
``mode_request``, ``target_position``, ``target_velocity``, ``target_torque``
(counts, counts/s, ‰); outputs come out in ``statusword``,
``position_counts``, ``velocity_counts``, ``torque_permille``,
``following_error``, and the state arrays (``mode_display``, ``error_code``).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from itertools import pairwise
from typing import Any, Protocol

import numpy as np
import numpy.typing as npt

from fieldbus.core.cia402 import STATUSWORD_STATE_BITS, State402, StatusBit
from sim_slaves.drive402 import (
    ERROR_FOLLOWING,
    ERROR_OVERTEMPERATURE,
    FOLLOWING_ERROR_OFF,
    HOMING_CHECK_S,
    STICTION_RAD_S,
    TWO_PI,
    Cia402Drive,
    DictObjectStore,
    DriveParams,
    Obj,
    ObjectStore,
)

F64 = npt.NDArray[np.float64]
I64 = npt.NDArray[np.int64]
B = npt.NDArray[np.bool_]

_STATES = tuple(State402)
_NR, _SOD, _RTSO, _SO, _OE, _QSA, _FRA, _FAULT = (int(s) for s in _STATES)
_PP, _PV, _HM, _CSP, _CSV, _CST = 1, 3, 6, 8, 9, 10
# statusword bits (plain ints: the cycle's arithmetic)
_SW_REMOTE = int(StatusBit.REMOTE)
_SW_VOLTAGE = int(StatusBit.VOLTAGE_ENABLED)
_SW_FOLLOWS = int(StatusBit.FOLLOWS_TARGET)
_SW_FOLLOWING_ERROR = int(StatusBit.FOLLOWING_ERROR)
_SW_TARGET_REACHED = int(StatusBit.TARGET_REACHED)
_SW_LIMIT = int(StatusBit.INTERNAL_LIMIT_ACTIVE)
_SW_WARNING = int(StatusBit.WARNING)
_NOT_FOLLOWS_REACHED = ~(_SW_FOLLOWS | _SW_TARGET_REACHED)
_SW_BY_STATE = np.array([int(STATUSWORD_STATE_BITS[s]) for s in _STATES], dtype=np.int64)
_SW_CSP = int(_SW_BY_STATE[_OE]) | _SW_REMOTE | _SW_VOLTAGE | _SW_FOLLOWS
_SW_CSP_REACHED = _SW_CSP | _SW_TARGET_REACHED
_SW_CSP_BITS = (_SW_CSP, _SW_CSP_REACHED, _SW_LIMIT)  # the C kernel's statuswords
# objects the bank reads and writes through a drive's OD (plain ints: enum attribute access costs ~100 ns)
_X_ERROR_CODE = int(Obj.ERROR_CODE)
_X_CONTROLWORD = int(Obj.CONTROLWORD)
_X_STATUSWORD = int(Obj.STATUSWORD)
_X_MODES = int(Obj.MODES_OF_OPERATION)
_X_MODES_DISPLAY = int(Obj.MODES_DISPLAY)
_X_POSITION_ACTUAL = int(Obj.POSITION_ACTUAL)
_X_VELOCITY_ACTUAL = int(Obj.VELOCITY_ACTUAL)
_X_TORQUE_ACTUAL = int(Obj.TORQUE_ACTUAL)
_X_TARGET_POSITION = int(Obj.TARGET_POSITION)
_X_TARGET_VELOCITY = int(Obj.TARGET_VELOCITY)
_X_TARGET_TORQUE = int(Obj.TARGET_TORQUE)
_X_FOLLOWING_ERROR = int(Obj.FOLLOWING_ERROR_ACTUAL)


class MotionKernel(Protocol):
    """``sim_slaves._motion`` (``sim_slaves/_motion.c``): the plain CSP path's step in C, the numpy path's
    bits (:meth:`DriveBank._csp_substeps`, :meth:`DriveBank._csp_outputs_numpy`)."""

    csp: Callable[..., bool]
    csp_outputs: Callable[..., bool]


def _c_kernel() -> MotionKernel | None:
    """``sim_slaves._motion`` if it is built (``pip install -e .`` / ``setup.py build_ext``), else None."""
    try:
        from sim_slaves import _motion
    except ImportError:
        return None
    return _motion


#: the plain CSP path's step in C, or None where ``sim_slaves._motion`` is not built (then numpy)
motion_kernel = _c_kernel()


#: the bank arrays ``sim_slaves._motion.Bank`` holds, in the orders of its C enums (csp's, csp_outputs', idle's)
_KERNEL_CSP_ARRAYS = (
    *("pos", "vel", "integ", "prev_target", "prev_vff", "tau", "tau_eff", "shaft", "limit"),
    *("vff_gain", "tff_gain", "kv", "kp", "tmax", "load", "epr", "rpe", "vmax"),
)
_KERNEL_OUTPUT_ARRAYS = (
    *("statusword", "following_error", "position_counts", "velocity_counts", "torque_permille", "fe_time"),
    *("pos", "vel", "tau", "cpr", "epr", "enc_to_counts", "vpr", "rated"),
    *("noise", "fe_window", "position_window", "limit"),
)
_KERNEL_IDLE_ARRAYS = (
    *("pos", "vel", "prev_target", "tau", "tau_eff", "shaft"),
    *("statusword", "following_error", "position_counts", "velocity_counts", "torque_permille", "limit"),
    *("state", "load", "cpr", "vpr"),
)

_TINY = float(np.finfo(np.float64).tiny)  # the smallest normal float64, 2.2e-308


def _flush_subnormal(x: F64) -> F64:
    """``x`` with its subnormal values set to 0: a rotor holding still decays its speed and integrator
    into them within seconds, and x86 computes with them some 100 times slower (a bank of 64 drives went
    from 27 to 111 us per step after 4 s of hold). A NaN stays NaN (the C kernel does the same)."""
    return np.where(np.abs(x) < _TINY, 0.0, x)


def integration_coefficients(j: float, b: float, h: float) -> tuple[float, float, float, float]:
    """Exact integration of a rotor (inertia ``j`` kg m², viscous friction ``b`` N m s/rad) over ``h`` s.

    Under a torque held over the substep: velocity' = e x velocity + f x
    torque, position' = position + g x velocity + hh x torque. Returns
    (e, f, g, hh).
    """
    if b > 0.0:
        e = math.exp(-b * h / j)  # velocity decay over h
        g = (1.0 - e) * j / b  # position per unit initial velocity
        return e, (1.0 - e) / b, g, (h - g) / b  # f: velocity, hh: position per unit torque
    return 1.0, h / j, h, h * h / (2.0 * j)


def _param_array(params: Sequence[DriveParams], get: Callable[[DriveParams], float]) -> F64:
    return np.array([get(p) for p in params], dtype=np.float64)


def _rotor_coefficients(j: F64, fb: F64, h: F64 | float) -> tuple[F64, F64, F64, F64]:
    """:func:`integration_coefficients` element by element: e, f, g, hh."""
    viscous = fb > 0.0
    fb_safe = np.where(viscous, fb, 1.0)
    e_ = np.where(viscous, np.exp(-fb * h / j), 1.0)
    f_ = np.where(viscous, (1.0 - e_) / fb_safe, h / j)
    g_ = np.where(viscous, (1.0 - e_) * j / fb_safe, h)
    hh_ = np.where(viscous, (h - g_) / fb_safe, h * h / (2.0 * j))
    return e_, f_, g_, hh_


class DriveBank:
    """N CiA 402 drives as arrays; :attr:`drives` are their per-drive views (:class:`~sim_slaves.drive402.Cia402Drive`).

    ``params``: one :class:`DriveParams` per drive; ``seed``: the encoder
    noise's. The arrays are public for the emulator that feeds them (see the
    module docstring); ``step(a, b, dt_s)`` advances drives ``a..b-1``.
    ``drives``: the drives themselves, when they are being built (a drive
    built alone makes a bank of one for itself); by default the bank builds them.
    """

    def __init__(
        self, params: Sequence[DriveParams], *, seed: int = 0, drives: Sequence[Cia402Drive] | None = None
    ) -> None:
        n = len(params)
        self.n = n
        self.params = list(params)
        #: the C kernel's hold on the arrays where built (:data:`motion_kernel`): the idle path and the CSP
        #: cycle in one call each; False: the paths before it (numpy; the CSP kernel's two calls), the reference
        self.lean = True
        self._held: tuple[object, Any] | None = None  # (kernel, its Bank on these arrays)
        self._target: F64 = np.zeros(n)  # the CSP target of the C cycle [rad]
        self._state_arrays(n)
        self._io_arrays(n)
        self._controller_parameters(self.params)
        self._thermal_parameters(self.params)
        self._imperfections(self.params, seed)
        self._path_caches()
        self.drives: list[Cia402Drive] = (
            list(drives)
            if drives is not None
            else [Cia402Drive(p, bank=self, slot=i) for i, p in enumerate(params)]
        )

    def _state_arrays(self, n: int) -> None:
        """Each drive's state (SI); a drive's attributes are elements of these (drive402.FLOAT_SLOTS ...)."""
        z = np.zeros
        self.state = np.full(n, _NR, dtype=np.int64)
        self.pos: F64 = z(n)
        self.vel: F64 = z(n)
        self.tau: F64 = z(n)
        self.shaft: F64 = z(n)
        self.load: F64 = z(n)
        self.temp: F64 = z(n)
        self.integ: F64 = z(n)
        self.prev_target: F64 = z(n)
        self.prev_vff: F64 = z(n)
        self.ramp_v: F64 = z(n)
        self.fe_time: F64 = z(n)
        self.tau_eff: F64 = z(n)
        self.fe_timeout: F64 = z(n)
        self.tmax: F64 = z(n)
        self.qs_decel: F64 = z(n)
        self.rated: F64 = z(n)  # motor rated torque [N·m] (0x6076)
        self.vmax: F64 = z(n)  # max motor speed [rad/s] (0x6080; inf: none)
        self.pmin: F64 = z(n)  # software position limits [counts] (0x607D; ±inf: none)
        self.pmax: F64 = z(n)
        self.frame: F64 = z(n)  # homing: reported - physical position [rad]
        self.home_v: F64 = z(n)  # homing: speed demand [rad/s]
        self.home_bits: I64 = z(n, dtype=np.int64)  # homing: statusword bits 10, 12, 13
        self.home_phase: I64 = z(n, dtype=np.int64)  # homing: 0 idle, 1 searching, 2 found
        self.prof_pos: F64 = z(n)  # PP: the trajectory generator's position [rad]
        self.prof_v: F64 = z(n)  # PV: the ramp's velocity [rad/s]
        self.prof_bits: I64 = z(n, dtype=np.int64)  # PP/PV: statusword bits 10 and 12
        self.error_code: I64 = z(n, dtype=np.int64)
        self.mode_display: I64 = z(n, dtype=np.int64)
        self.following_error: I64 = z(n, dtype=np.int64)
        self.fault_pending: I64 = z(n, dtype=np.int64)
        self.prev_cw: I64 = z(n, dtype=np.int64)
        self.fe_window: I64 = z(n, dtype=np.int64)
        self.position_window: I64 = z(n, dtype=np.int64)
        self.velocity_window: I64 = z(n, dtype=np.int64)
        self.qs_option: I64 = z(n, dtype=np.int64)
        self.fr_option: I64 = z(n, dtype=np.int64)
        self.noise: I64 = z(n, dtype=np.int64)
        self.limit: B = z(n, dtype=np.bool_)
        self.standstill: B = z(n, dtype=np.bool_)
        self.quiet = z(n, dtype=np.bool_)  # the state machine has nothing to do while the controlword holds

    def _io_arrays(self, n: int) -> None:
        """The master's outputs (inputs here) and inputs (outputs here), raw OD units; which objects exist."""
        z = np.zeros
        self.controlword = z(n, dtype=np.int64)
        self.mode_request = z(n, dtype=np.int64)
        self.target_position = z(n, dtype=np.int64)
        self.target_velocity = z(n, dtype=np.int64)
        self.target_torque = z(n, dtype=np.int64)
        self.statusword = z(n, dtype=np.int64)
        self.position_counts = z(n, dtype=np.int64)
        self.velocity_counts = z(n, dtype=np.int64)
        self.torque_permille = z(n, dtype=np.int64)
        # which optional objects each drive's OD has (set by bound)
        self.has_tp = z(n, dtype=np.bool_)
        self.has_tv = z(n, dtype=np.bool_)
        self.has_tt = z(n, dtype=np.bool_)
        self.has_modes = z(n, dtype=np.bool_)
        self._outputs_present: list[list[tuple[int, I64]]] = [[] for _ in range(n)]

    def _output_arrays(self) -> tuple[tuple[int, I64], ...]:
        """The optional objects a drive writes (the master's inputs besides the statusword), with their arrays."""
        return (
            (_X_MODES_DISPLAY, self.mode_display),
            (_X_POSITION_ACTUAL, self.position_counts),
            (_X_VELOCITY_ACTUAL, self.velocity_counts),
            (_X_TORQUE_ACTUAL, self.torque_permille),
            (_X_FOLLOWING_ERROR, self.following_error),
            (_X_ERROR_CODE, self.error_code),
        )

    def _controller_parameters(self, params: Sequence[DriveParams]) -> None:
        """Units, the rotor and the cascade's gains, per drive."""
        pa = _param_array
        self.rpc = pa(params, lambda p: TWO_PI / p.counts_per_rev)
        self.cpr = pa(params, lambda p: p.counts_per_rev / TWO_PI)
        self.vpr = self.cpr * pa(params, lambda p: p.velocity_units_per_count_s)  # velocity units per rad/s
        self.rpv = 1.0 / self.vpr
        self.inertia = pa(params, lambda p: p.inertia_kg_m2)
        self.friction = pa(params, lambda p: p.friction_nm_s_per_rad)
        self.control_rate = pa(params, lambda p: p.control_rate_hz)
        wv = pa(params, lambda p: TWO_PI * p.velocity_bandwidth_hz)
        self.kv = self.inertia * wv
        self.ki = self.kv * wv * 0.25
        self.kp = pa(params, lambda p: p.position_gain_per_s)
        self.vff_gain = pa(params, lambda p: p.velocity_feedforward)
        self.tff_gain = pa(params, lambda p: p.torque_feedforward) * self.inertia
        self.standstill_speed = pa(params, lambda p: p.standstill_rad_s)

    def _thermal_parameters(self, params: Sequence[DriveParams]) -> None:
        """The winding's thermal network and the torque constant's drift, per drive."""
        pa = _param_array
        self.thermal = np.array([p.thermal for p in params], dtype=np.bool_)
        self.any_thermal = bool(self.thermal.any())
        self.ambient = pa(params, lambda p: p.ambient_c)
        self.r0 = pa(params, lambda p: p.resistance_ohm)
        self.r_tc = pa(params, lambda p: p.resistance_temp_coeff_per_k)
        self.kt0_sq = pa(params, lambda p: p.torque_constant_nm_per_a**2)
        self.rth = pa(params, lambda p: p.thermal_resistance_k_per_w)
        self.tau_th = self.rth * pa(params, lambda p: p.thermal_capacitance_j_per_k)
        self.kt_tc = pa(params, lambda p: p.kt_temp_coeff_per_k)
        self.warn_c = pa(params, lambda p: p.warning_temperature_c)
        self.fault_c = pa(params, lambda p: p.fault_temperature_c)

    def _imperfections(self, params: Sequence[DriveParams], seed: int) -> None:
        """Command delay line, current-loop lag, encoder resolution and noise, dry friction."""
        pa = _param_array
        z = np.zeros
        n = len(params)
        self.delay = np.array([p.command_delay_cycles for p in params], dtype=np.int64)
        depth = int(self.delay.max(initial=0)) + 1
        self.history = z((3, depth, n), dtype=np.int64)  # raw targets, ring per drive
        self.head = z(n, dtype=np.int64)
        self.any_delay = depth > 1
        self.current_bw = pa(params, lambda p: p.current_loop_bandwidth_hz)
        self.any_current_lag = bool((self.current_bw > 0.0).any())
        self.epr = pa(params, lambda p: p.encoder_cpr / TWO_PI)
        self.rpe = pa(params, lambda p: TWO_PI / p.encoder_cpr)
        self.enc_to_counts = pa(params, lambda p: p.counts_per_rev / p.encoder_cpr)
        self.noise_sd = pa(params, lambda p: p.encoder_noise_counts)
        self.ideal_encoder = not bool((self.noise_sd > 0).any() or (self.enc_to_counts != 1.0).any())
        self.coulomb = pa(params, lambda p: p.coulomb_friction_nm)
        self.any_coulomb = bool((self.coulomb > 0.0).any())
        self.rng = np.random.default_rng(seed)

    def _path_caches(self) -> None:
        """What each run of drives was found to be, kept until something changes (see :meth:`changed`)."""
        self._uniform: dict[tuple[int, int], str] = {}  # run -> "csp", "idle" or "general" (see _kind)
        self._calm: set[tuple[int, int]] = set()  # runs whose state machines have nothing pending
        rate = self.control_rate
        self._rate = (
            float(rate[0]) if self.n and (rate == rate[0]).all() else None
        )  # one control rate for all
        self._coeffs: dict[tuple[int, int], tuple[float, tuple[F64 | float, ...]]] = {}
        # run -> the one inertia, friction, ki of its drives (None: they differ)
        self._same_mechanics: dict[tuple[int, int], tuple[float, float, float] | None] = {}
        self._limited: dict[tuple[int, int], tuple[bool, bool]] = {}  # run -> (speed limit, position limits)

    # -- per-drive bookkeeping --

    def changed(self) -> None:
        """Something outside the cycle changed a drive (fault injected, OD bound): look again next step."""
        self._uniform.clear()
        self._calm.clear()
        self._limited.clear()

    def reset_slot(self, i: int) -> None:
        """Power-on values for drive ``i`` (the drive then sets its own)."""
        self.quiet[i] = False
        self.changed()
        self.history[:, :, i] = 0
        self.head[i] = 0

    def bound(self, i: int, has: dict[int, bool]) -> None:
        """Drive ``i`` bound to an OD that has the objects in ``has``."""
        self.has_tp[i] = has[_X_TARGET_POSITION]
        self.has_tv[i] = has[_X_TARGET_VELOCITY]
        self.has_tt[i] = has[_X_TARGET_TORQUE]
        self.has_modes[i] = has[_X_MODES]
        self._outputs_present[i] = [
            (index, array) for index, array in self._output_arrays() if has.get(index)
        ]
        self.quiet[i] = False
        self.changed()

    def load_inputs(self, i: int, od: ObjectStore) -> None:
        """Drive ``i``'s inputs from its OD (objects the process data does not carry)."""
        d = self.drives[i]
        if d.od is not od:
            d.bind(od)
        get = od.get_value
        self.controlword[i] = int(get(_X_CONTROLWORD, 0))
        self.mode_request[i] = int(get(_X_MODES, 0)) if self.has_modes[i] else self.mode_display[i]
        if self.has_tp[i]:
            self.target_position[i] = int(get(_X_TARGET_POSITION, 0))
        if self.has_tv[i]:
            self.target_velocity[i] = int(get(_X_TARGET_VELOCITY, 0))
        if self.has_tt[i]:
            self.target_torque[i] = int(get(_X_TARGET_TORQUE, 0))

    def store_outputs(self, i: int, od: ObjectStore) -> None:
        """Drive ``i``'s outputs into its OD (for objects the process data does not carry, SDO reads)."""
        put = od.set_value
        put(_X_STATUSWORD, 0, int(self.statusword[i]))
        for index, array in self._outputs_present[i]:
            put(index, 0, int(array[i]))

    # -- the cycle --

    def step(self, a: int, b: int, dt_s: float | F64) -> None:
        """Advance drives ``a..b-1`` by ``dt_s`` seconds (one value, or one per drive of the run)."""
        if b <= a:
            return
        sl = slice(a, b)
        if isinstance(dt_s, float) and self._rate is not None:
            if dt_s <= 0.0:
                raise ValueError(f"dt_s must be > 0, got {dt_s}")
            self._state_machines(a, b)
            kind = self._uniform.get((a, b))
            if kind == "csp":
                self._csp(a, b, dt_s, max(1, round(dt_s * self._rate)))
                return
            if kind == "idle":
                self._idle(a, b, dt_s, max(1, round(dt_s * self._rate)))
                return
        else:
            self._state_machines(a, b)
        dt = np.broadcast_to(np.asarray(dt_s, dtype=np.float64), (b - a))
        if (dt <= 0.0).any():
            raise ValueError(f"dt_s must be > 0, got {dt_s}")
        searching = self.home_phase[sl] == 1
        if searching.any() and (dt[searching] > HOMING_CHECK_S).any():
            # a homing search through a long step: the searching drives in slices, each looking for its
            # home point between them (as Cia402Drive.step); the others in one piece
            edges = [0, *(np.flatnonzero(np.diff(searching)) + 1).tolist(), b - a]
            for lo, hi in pairwise(edges):
                if searching[lo]:
                    self._search(a + lo, a + hi, dt[lo:hi])
                else:
                    self._substeps(a + lo, a + hi, dt[lo:hi])
            return
        self._substeps(a, b, dt)

    def _search(self, a: int, b: int, dt: F64) -> None:
        """Drives ``a..b-1`` (all searching their home point) through ``dt``, in slices of at most
        HOMING_CHECK_S; between slices each looks for the home point (the target ring is fed once)."""
        k = max(1, math.ceil(float(dt.max()) / HOMING_CHECK_S))
        part = dt / k
        for j in range(k):
            if j:
                for i in range(a, b):
                    if self.home_phase[i] == 1:
                        self.drives[i].look_for_home()
            self._substeps(a, b, part, push=j == 0)

    def _substeps(self, a: int, b: int, dt: F64, *, push: bool = True) -> None:
        """Drives ``a..b-1`` through ``dt``, in the substeps of their control rates."""
        n = np.maximum(1, np.rint(dt * self.control_rate[a:b])).astype(np.int64)
        if b - a > 1 and (n != n[0]).any():
            # different substep counts (a drive stepped at another time, e.g. after a power cycle):
            # the stretches of drives with the same count, each together
            edges = [0, *(np.flatnonzero(np.diff(n)) + 1).tolist(), b - a]
            for lo, hi in pairwise(edges):
                self._advance(a + lo, a + hi, dt[lo:hi], n[lo:hi], push=push)
            return
        self._advance(a, b, dt, n, push=push)

    def _state_machines(self, a: int, b: int) -> None:
        sl = slice(a, b)
        if (a, b) in self._calm:
            # steady operation, said in few calls (a numpy call costs ~1-2 us, whatever the run's size):
            # the controlwords and mode requests as before, and no drive homing
            display = self.mode_display[sl]
            if (
                self.controlword[sl].tobytes() == self.prev_cw[sl].tobytes()
                and self.mode_request[sl].tobytes() == display.tobytes()
                and _HM not in display.tolist()
                and not self.home_phase[sl].tobytes().strip(b"\0")
            ):
                return
        cw = self.controlword[sl]
        mode_req = self.mode_request[sl]
        new_cw = cw != self.prev_cw[sl]
        new_mode = mode_req != self.mode_display[sl]
        homing = (self.mode_display[sl] == _HM) | (self.home_phase[sl] != 0)
        if homing.any():  # the homing procedure runs per drive, through the drive's own code
            self.changed()
            for i in (np.flatnonzero(homing) + a).tolist():
                self.quiet[i] = self.drives[i].command(int(cw[i - a]), int(mode_req[i - a]))
        elif (a, b) in self._calm and not new_cw.any() and not new_mode.any():
            return
        need = (new_cw | new_mode | ~self.quiet[sl] | (self.fault_pending[sl] != 0)) & ~homing
        if need.any():  # the state machines that have something to do, each through the drive's code
            self.changed()
            for i in (np.flatnonzero(need) + a).tolist():
                self.quiet[i] = self.drives[i].command(int(cw[i - a]), int(mode_req[i - a]))
        self.prev_cw[sl] = cw
        if self.quiet[sl].all() and not self.fault_pending[sl].any():
            self._calm.add((a, b))

    def _advance(self, a: int, b: int, dt: F64, n: I64, *, push: bool = True) -> None:
        """Drives ``a..b-1`` (one substep count ``n``) through ``dt``: the lean path the run allows, or the
        general one (targets by mode, the PP/PV generators, physics, statusword and actual values)."""
        sl = slice(a, b)
        kind = self._uniform.get((a, b))
        if kind is None:
            kind = self._uniform[(a, b)] = self._kind(sl)
        if kind != "general" and (dt == dt[0]).all():
            (self._csp if kind == "csp" else self._idle)(a, b, float(dt[0]), int(n[0]))
            return
        state = self.state[sl]
        mode = self.mode_display[sl]
        oe = state == _OE
        csp = mode == _CSP
        csv = mode == _CSV
        cst = mode == _CST
        hm = oe & (mode == _HM)
        (target, target_v, target_tau), speed_limited = self._targets(a, b, oe, csp, csv, cst, hm, push=push)
        pp = oe & (mode == _PP)
        pv = oe & (mode == _PV)
        prof = pp | pv
        profiled = (np.flatnonzero(prof) + a).tolist() if prof.any() else []
        if profiled:  # PP rides the position cascade on its generator's position, PV the velocity loop
            self._run_profiles(profiled, a, dt)
            target = np.where(pp, self.prof_pos[sl], target)
            target_v = np.where(pv, self.prof_v[sl], target_v)
            csp, csv = csp | pp, csv | pv
        if not self.ideal_encoder:
            sd = self.noise_sd[sl]
            self.noise[sl] = np.where(sd > 0.0, np.rint(self.rng.standard_normal(b - a) * sd), 0)
        self._physics(sl, dt, n, state, oe, csp, csv | hm, cst, target, target_v, target_tau, speed_limited)
        self._outputs(sl, dt, state, oe, csp, csv, cst, target, target_v)
        if hm.any():
            self.statusword[sl] |= np.where(hm, self.home_bits[sl], 0)
        for i in profiled:
            self.prof_bits[i] = self.drives[i].profile_status()
            self.statusword[i] = (int(self.statusword[i]) & _NOT_FOLLOWS_REACHED) | int(self.prof_bits[i])

    def _targets(
        self, a: int, b: int, oe: B, csp: B, csv: B, cst: B, hm: B, *, push: bool
    ) -> tuple[tuple[F64, F64, F64], bool]:
        """This cycle's demands by mode, SI: position [rad] (CSP; else the previous target), velocity
        [rad/s] (CSV; homing: the search speed), torque [N·m] (CST); from the targets ``delay`` cycles
        old, held within the position limits and max speed. Also: whether any drive has a max speed."""
        sl = slice(a, b)
        if self.any_delay:
            tp, tv, tt = self._delayed(a, b, push=push)
        else:
            tp, tv, tt = self.target_position[sl], self.target_velocity[sl], self.target_torque[sl]
        use_p = oe & csp & self.has_tp[sl]
        speed_limited, position_limited = self._limits(a, b)
        if position_limited:
            tp = np.clip(tp, self.pmin[sl], self.pmax[sl])
        target = np.where(use_p, tp * self.rpc[sl], self.prev_target[sl])
        target_v = np.where(oe & csv & self.has_tv[sl], tv * self.rpv[sl], 0.0)
        if speed_limited:
            vmax = self.vmax[sl]
            target_v = np.clip(target_v, -vmax, vmax)
        target_tau = np.where(oe & cst & self.has_tt[sl], tt * self.rated[sl] / 1000.0, 0.0)
        if hm.any():
            target_v = np.where(hm, self.home_v[sl], target_v)
        return (target, target_v, target_tau), speed_limited

    def _run_profiles(self, profiled: list[int], a: int, dt: F64) -> None:
        """One cycle of the PP/PV trajectory generator of each drive in ``profiled``, through the drive's code."""
        for i in profiled:
            self.drives[i].run_profile(
                int(self.controlword[i]),
                float(dt[i - a]),
                int(self.target_position[i]) if self.has_tp[i] else None,
                int(self.target_velocity[i]) if self.has_tv[i] else None,
            )

    def _limits(self, a: int, b: int) -> tuple[bool, bool]:
        """Whether any drive of the run has a max motor speed, and software position limits (cached)."""
        got = self._limited.get((a, b))
        if got is None:
            sl = slice(a, b)
            got = self._limited[(a, b)] = (
                bool(np.isfinite(self.vmax[sl]).any()),
                bool(np.isfinite(self.pmin[sl]).any() or np.isfinite(self.pmax[sl]).any()),
            )
        return got

    def _kind(self, sl: slice) -> str:
        """Which path steps a run: "csp" (all enabled in plain CSP), "idle" (none powered), "general"."""
        plain = not (
            self.thermal[sl].any() or (self.coulomb[sl] > 0.0).any() or (self.current_bw[sl] > 0.0).any()
        )
        state = self.state[sl]
        if plain and (state == _OE).all() and (self.mode_display[sl] == _CSP).all() and self.has_tp[sl].all():
            return "csp"
        if plain and not ((state == _OE) | (state == _QSA) | (state == _FRA)).any():
            return "idle"
        return "general"

    def _coefficients(self, a: int, b: int, h: float) -> tuple[F64 | float, ...]:
        """Exact-integration factors of the run for substep ``h`` [s] (cached): e, f, g, hh, ki·h.

        A run of drives with one inertia, friction and ki (the usual robot:
        the same drive many times) gets numbers, computed as the scalar drive
        does; others arrays.
        """
        cached = self._coeffs.get((a, b))
        if cached is None or cached[0] != h:  # (the served cycle's step, and so h, changes every cycle)
            if (a, b) not in self._same_mechanics:
                self._same_mechanics[(a, b)] = self._one_mechanics(a, b)
            one = self._same_mechanics[(a, b)]
            coeffs: tuple[F64 | float, ...]
            if one is not None:
                j, fb, ki = one
                coeffs = (*integration_coefficients(j, fb, h), ki * h)
            else:
                sl = slice(a, b)
                coeffs = (*_rotor_coefficients(self.inertia[sl], self.friction[sl], h), self.ki[sl] * h)
            cached = self._coeffs[(a, b)] = (h, coeffs)
        return cached[1]

    def _one_mechanics(self, a: int, b: int) -> tuple[float, float, float] | None:
        """The inertia, friction and ki that every drive of the run has, or None where they differ."""
        sl = slice(a, b)
        j, fb, ki = self.inertia[sl], self.friction[sl], self.ki[sl]
        if (j == j[0]).all() and (fb == fb[0]).all() and (ki == ki[0]).all():
            return float(j[0]), float(fb[0]), float(ki[0])
        return None

    def _idle(self, a: int, b: int, dt: float, steps: int) -> None:
        """No drive of the run powered (and no thermal model, dry friction, current lag): rotors coast."""
        sl = slice(a, b)
        if self.any_delay:
            self._delayed(a, b)  # the delay line records targets in every state
        e_, f_, g_, hh_, _ = self._coefficients(a, b, dt / steps)
        held = self._held_by_kernel() if self.lean and self.ideal_encoder else None
        if held is not None:  # in C: the same operations in the same order, the same bits
            if not held.idle_cycle(a, b, steps, e_, f_, g_, hh_, _SW_REMOTE, _SW_VOLTAGE, _NR):
                self._idle_outputs(sl, self.pos[sl], self.vel[sl])  # a value beyond int64 (NaN): numpy
            return
        pos, vel = self.pos[sl], self.vel[sl]
        net = -self.load[sl]
        for _ in range(steps):
            pos = pos + vel * g_ + net * hh_
            vel = vel * e_ + net * f_
        vel = _flush_subnormal(vel)
        self.pos[sl], self.vel[sl] = pos, vel
        self.prev_target[sl] = pos
        self.tau[sl] = self.tau_eff[sl] = self.shaft[sl] = 0.0
        self.limit[sl] = False
        self._idle_outputs(sl, pos, vel)

    def _idle_outputs(self, sl: slice, pos: F64, vel: F64) -> None:
        """:meth:`_idle`'s statusword and actual values from the rotors' position [rad] and speed [rad/s]."""
        a, b = sl.start, sl.stop
        cpr = self.cpr[sl]
        if self.ideal_encoder:
            self.position_counts[sl] = np.floor(pos * cpr + 0.5)
        else:
            sd = self.noise_sd[sl]
            noise = np.where(sd > 0.0, np.rint(self.rng.standard_normal(b - a) * sd), 0.0)
            self.noise[sl] = noise
            enc = np.floor(pos * self.epr[sl] + 0.5) + noise
            self.position_counts[sl] = np.floor(enc * self.enc_to_counts[sl] + 0.5)
        state = self.state[sl]
        self.statusword[sl] = _SW_BY_STATE[state] | np.where(
            state != _NR, _SW_REMOTE | _SW_VOLTAGE, _SW_REMOTE
        )
        self.following_error[sl] = 0
        self.velocity_counts[sl] = np.floor(vel * self.vpr[sl] + 0.5)
        self.torque_permille[sl] = 0

    def _csp(self, a: int, b: int, dt: float, steps: int) -> None:
        """Every drive of the run enabled in CSP, ideal current loop, no dry friction, no thermal model."""
        held = self._held_by_kernel() if self.lean and self.ideal_encoder and not self.any_delay else None
        if held is not None:
            speed_limited, position_limited = self._limits(a, b)
            if not position_limited:  # the whole cycle in one call: _csp_motion and _csp_outputs in C
                got = held.csp_cycle(
                    a, b, dt, steps, *self._coefficients(a, b, dt / steps), speed_limited, *_SW_CSP_BITS
                )
                if not got & 2:  # a following error beyond its window (or NaN): numpy does the outputs
                    self._csp_outputs_numpy(slice(a, b), dt, self._target[a:b], bool(got & 1))
                return
        target, limited = self._csp_motion(a, b, dt, steps)
        self._csp_outputs(slice(a, b), dt, target, limited)

    def _held_by_kernel(self) -> Any:
        """``sim_slaves._motion.Bank`` on this bank's arrays (made once per kernel), or None where the kernel
        has none: it runs :meth:`_csp_motion` and :meth:`_csp_outputs` of a cycle in one call, and
        :meth:`_idle`."""
        kernel = motion_kernel
        held = self._held
        if held is None or held[0] is not kernel:
            make = getattr(kernel, "Bank", None)
            arrays = None
            if make is not None:
                arrays = make(
                    tuple(getattr(self, name) for name in _KERNEL_CSP_ARRAYS),
                    tuple(getattr(self, name) for name in _KERNEL_OUTPUT_ARRAYS),
                    (*(getattr(self, name) for name in _KERNEL_IDLE_ARRAYS), _SW_BY_STATE),
                    self.target_position,
                    self.rpc,
                    self._target,
                )
            held = self._held = (kernel, arrays)
        return held[1]

    def _csp_motion(self, a: int, b: int, dt: float, steps: int) -> tuple[F64, bool]:
        """The cascade and rotor of :meth:`_csp` through ``steps`` substeps; returns the target [rad] and
        whether any drive hit its torque limit. In C (:data:`motion_kernel`) where it is built, else numpy
        (:meth:`_csp_substeps`): the same operations in the same order, the same bits."""
        sl = slice(a, b)
        tp = self._delayed(a, b)[0] if self.any_delay else self.target_position[sl]
        speed_limited, position_limited = self._limits(a, b)
        if position_limited:
            tp = np.clip(tp, self.pmin[sl], self.pmax[sl])
        target = tp * self.rpc[sl]
        coefficients = self._coefficients(a, b, dt / steps)
        noise = None
        if not self.ideal_encoder:
            sd = self.noise_sd[sl]
            noise = np.where(sd > 0.0, np.rint(self.rng.standard_normal(b - a) * sd), 0.0)
            self.noise[sl] = noise
        kernel = motion_kernel
        if kernel is None:
            return target, self._csp_substeps(sl, dt, steps, target, noise, coefficients, speed_limited)
        e_, f_, g_, hh_, ki_h = coefficients
        limited = kernel.csp(
            self.pos,
            self.vel,
            self.integ,
            self.prev_target,
            self.prev_vff,
            self.tau,
            self.tau_eff,
            self.shaft,
            self.limit,
            self.vff_gain,
            self.tff_gain,
            self.kv,
            self.kp,
            self.tmax,
            self.load,
            self.epr,
            self.rpe,
            self.vmax,
            target,
            noise,
            e_,
            f_,
            g_,
            hh_,
            ki_h,
            a,
            b,
            dt,
            steps,
            speed_limited,
        )
        return target, limited

    def _csp_substeps(
        self,
        sl: slice,
        dt: float,
        steps: int,
        target: F64,
        noise: F64 | None,
        coefficients: tuple[F64 | float, ...],
        speed_limited: bool,
    ) -> bool:
        """:meth:`_csp_motion`'s feed-forward and substeps as numpy operations on the run's arrays (the
        reference of ``sim_slaves._motion``, and the path without it); returns whether any drive hit its
        torque limit."""
        vmax = self.vmax[sl]
        prev_t = self.prev_target[sl]
        e_, f_, g_, hh_, ki_h = coefficients
        kv, kp = self.kv[sl], self.kp[sl]
        tmax = self.tmax[sl]
        ntmax = -tmax
        load = self.load[sl]
        vff = (target - prev_t) / dt
        aff = (vff - self.prev_vff[sl]) / dt
        self.prev_vff[sl] = vff
        vff *= self.vff_gain[sl]
        aff *= self.tff_gain[sl]
        epr, rpe = self.epr[sl], self.rpe[sl]
        pos, vel, integ = self.pos[sl], self.vel[sl], self.integ[sl]
        step = target - prev_t
        limited = False
        limit = None
        tau = vel
        for k in range(1, steps + 1):
            measured = np.floor(pos * epr + 0.5)
            if noise is not None:
                measured += noise
            measured *= rpe
            ev = prev_t + step * (k / steps)
            ev -= measured
            ev *= kp
            ev += vff
            if speed_limited:
                ev = np.clip(ev, -vmax, vmax)
            ev -= vel  # velocity error
            integ = np.minimum(np.maximum(integ + ki_h * ev, ntmax), tmax)
            tau = kv * ev
            tau += integ
            tau += aff
            clipped = np.minimum(np.maximum(tau, ntmax), tmax)
            if not limited and (clipped != tau).any():
                limited = True
                limit = clipped != tau
            elif limited:
                limit |= clipped != tau
            tau = clipped
            net = tau - load
            pos = pos + vel * g_ + net * hh_
            vel = vel * e_ + net * f_
        self.pos[sl], self.vel[sl], self.integ[sl] = pos, _flush_subnormal(vel), _flush_subnormal(integ)
        self.prev_target[sl] = target
        self.tau_eff[sl] = tau
        self.tau[sl] = tau
        self.shaft[sl] = tau
        self.limit[sl] = limited and limit is not None and limit
        return limited

    def _csp_outputs(self, sl: slice, dt: float, target: F64, limited: bool) -> None:
        """Statusword, following error (and its fault), actual values of :meth:`_csp`'s drives: in C
        (:data:`motion_kernel`) while every following error is within its window, else numpy."""
        kernel = motion_kernel
        if kernel is not None and kernel.csp_outputs(
            self.statusword,
            self.following_error,
            self.position_counts,
            self.velocity_counts,
            self.torque_permille,
            self.fe_time,
            self.pos,
            self.vel,
            self.tau,
            self.cpr,
            self.epr,
            self.enc_to_counts,
            self.vpr,
            self.rated,
            self.noise,
            self.fe_window,
            self.position_window,
            self.limit,
            target,
            sl.start,
            sl.stop,
            self.ideal_encoder,
            limited,
            _SW_CSP,
            _SW_CSP_REACHED,
            _SW_LIMIT,
        ):
            return
        self._csp_outputs_numpy(sl, dt, target, limited)

    def _csp_outputs_numpy(self, sl: slice, dt: float, target: F64, limited: bool) -> None:
        """:meth:`_csp_outputs` as numpy operations (the reference of ``sim_slaves._motion``)."""
        cpr = self.cpr[sl]
        pos, vel, tau = self.pos[sl], self.vel[sl], self.tau[sl]
        if not self.ideal_encoder:
            enc = np.floor(pos * self.epr[sl] + 0.5) + self.noise[sl]
            pos_counts = np.floor(enc * self.enc_to_counts[sl] + 0.5)
        else:
            pos_counts = np.floor(pos * cpr + 0.5)
        fe = np.floor(target * cpr + 0.5) - pos_counts
        afe = np.abs(fe)
        window = self.fe_window[sl]
        over = afe > window
        sw = np.where(afe <= self.position_window[sl], _SW_CSP_REACHED, _SW_CSP)
        if over.any():
            over &= window != FOLLOWING_ERROR_OFF
            fe_time = np.where(over, self.fe_time[sl] + dt, 0.0)
            self.fe_time[sl] = fe_time
            pending = self.fault_pending[sl]
            trip = over & (fe_time > self.fe_timeout[sl] + 1e-12) & (pending == 0)
            self.fault_pending[sl] = np.where(trip, ERROR_FOLLOWING, pending)
            if trip.any():
                self.changed()
            sw |= np.where(over, _SW_FOLLOWING_ERROR, 0)
        else:
            self.fe_time[sl] = 0.0
        if limited:
            sw |= np.where(self.limit[sl], _SW_LIMIT, 0)
        self.statusword[sl] = sw
        self.following_error[sl] = fe
        self.position_counts[sl] = pos_counts
        self.velocity_counts[sl] = np.floor(vel * self.vpr[sl] + 0.5)
        self.torque_permille[sl] = np.floor(tau * 1000.0 / self.rated[sl] + 0.5)

    def _delayed(self, a: int, b: int, *, push: bool = True) -> tuple[I64, I64, I64]:
        """Push this cycle's raw targets into each drive's ring (unless ``push`` is False: a later slice of
        the same cycle); return those of ``delay`` cycles ago."""
        sl = slice(a, b)
        hist = self.history
        depth = hist.shape[1]
        cols = np.arange(a, b)
        head = self.head[sl]
        if push:
            head = (head + 1) % depth
            self.head[sl] = head
            hist[0, head, cols] = self.target_position[sl]
            hist[1, head, cols] = self.target_velocity[sl]
            hist[2, head, cols] = self.target_torque[sl]
        old = (head - self.delay[sl]) % depth
        return hist[0, old, cols], hist[1, old, cols], hist[2, old, cols]

    def _physics(
        self,
        sl: slice,
        dt: F64,
        n: I64,
        state: I64,
        oe: B,
        csp: B,
        csv: B,
        cst: B,
        target: F64,
        target_v: F64,
        target_tau: F64,
        speed_limited: bool = False,
    ) -> None:
        """The general path: each drive of the run in its own state and mode, over ``n`` control substeps.

        ``csv`` also marks homing drives (their search speed is in ``target_v``); PP and PV arrive as CSP
        and CSV on their generator's position and velocity.
        """
        steps = int(n[0])
        powered, ramp = self._power_stage(sl, state, oe)
        vff, aff = self._csp_feedforward(sl, dt, powered & ~ramp & csp, target)
        kt_ratio = self._kt_ratio(sl)
        te, limit, tau_sq = self._cascade(
            sl,
            dt / n,
            steps,
            (powered, ramp, csp, csv, cst),
            (target, target_v, target_tau, vff, aff),
            kt_ratio,
            speed_limited,
        )
        self.prev_target[sl] = np.where(oe & csp, target, self.pos[sl])
        self.tau_eff[sl] = te
        self.tau[sl] = te
        self.shaft[sl] = te * kt_ratio
        self.limit[sl] = limit
        if self.any_thermal:
            self._thermal(sl, dt, tau_sq / steps)

    def _power_stage(self, sl: slice, state: I64, oe: B) -> tuple[B, B]:
        """Which drives the power stage drives, and which of them ramp to a stop (quick stop, fault reaction).

        Option code 0 of 0x605A / 0x605E disables the drive function: the motor coasts.
        """
        qsa, fra = state == _QSA, state == _FRA
        powered = oe | qsa | fra
        coast = (qsa & (self.qs_option[sl] == 0)) | (fra & (self.fr_option[sl] == 0))
        powered &= ~coast
        return powered, powered & ~oe

    def _csp_feedforward(self, sl: slice, dt: F64, m: B, target: F64) -> tuple[F64, F64]:
        """Velocity [rad/s] and torque [N·m] feed-forward of the drives ``m`` (enabled, CSP): the target's
        differences over the cycle, times their gains; the velocity kept for the next cycle's acceleration."""
        prev_t = self.prev_target[sl]
        vff = np.where(m, (target - prev_t) / dt, 0.0)
        aff = np.where(m, (vff - self.prev_vff[sl]) / dt, 0.0)
        self.prev_vff[sl] = np.where(m, vff, self.prev_vff[sl])
        return vff * self.vff_gain[sl], aff * self.tff_gain[sl]

    def _kt_ratio(self, sl: slice) -> F64 | float:
        """kt(T) / kt0 of the run: the thermal model's torque-constant drift (1 without it)."""
        if not self.any_thermal:
            return 1.0
        drift = np.maximum(0.0, 1.0 + self.kt_tc[sl] * (self.temp[sl] - self.ambient[sl]))
        return np.where(self.thermal[sl], drift, 1.0)

    def _cascade(
        self,
        sl: slice,
        h: F64,
        steps: int,
        masks: tuple[B, B, B, B, B],
        demands: tuple[F64, F64, F64, F64, F64],
        kt_ratio: F64 | float,
        speed_limited: bool,
    ) -> tuple[F64, B, F64]:
        """The control substeps of ``h`` s: velocity reference by mode, velocity PI, torque limit, current
        loop, rotor. Leaves position, velocity, integrator and ramp in the arrays; returns the current
        loop's torque [N·m], which drives hit the torque limit, and the sum of torque² over the substeps.

        ``masks``: powered, ramping, CSP, CSV (and homing), CST; ``demands``: target position [rad],
        velocity [rad/s], torque [N·m], velocity and torque feed-forward.
        """
        powered, ramp, csp, csv, cst = masks
        target, target_v, target_tau, vff, aff = demands
        e_, f_, g_, hh_ = _rotor_coefficients(self.inertia[sl], self.friction[sl], h)
        kv, ki, kp = self.kv[sl], self.ki[sl], self.kp[sl]
        tmax = self.tmax[sl]
        load = self.load[sl]
        pos, vel, integ = self.pos[sl].copy(), self.vel[sl].copy(), self.integ[sl].copy()
        prev_t = self.prev_target[sl]
        ramp_v = self.ramp_v[sl].copy()
        dv = self.qs_decel[sl] * h
        pi = powered & (ramp | csp | csv)
        direct = powered & cst & ~ramp
        csp_loop = csp & ~ramp
        csv_loop = csv & ~ramp
        ff = np.where(csp_loop, aff, 0.0)
        epr, rpe = self.epr[sl], self.rpe[sl]
        noise = self.noise[sl]
        limit = np.zeros(len(pos), dtype=np.bool_)
        tau_sq = np.zeros(len(pos))
        te = self.tau_eff[sl].copy()
        lag = self.any_current_lag
        if lag:
            bw = self.current_bw[sl]
            alpha = np.where(bw > 0.0, 1.0 - np.exp(-TWO_PI * bw * h), 1.0)
        fc = self.coulomb[sl]
        dry = self.any_coulomb
        any_ramp = bool(ramp.any())
        vmax = self.vmax[sl]
        # the same every substep: the bounds' negatives, the CSV reference and the CST torque
        # (np.minimum(np.maximum(x, lo), hi) is np.clip without its per-call overhead)
        nvmax, ntmax = -vmax, -tmax
        v_csv = np.where(csv_loop, target_v, 0.0)
        tau_direct = np.where(direct, target_tau, 0.0)
        for k in range(1, steps + 1):
            if any_ramp:
                ramp_v = np.where(ramp, _ramp_to_zero(ramp_v, dv), ramp_v)
            ref = prev_t + (target - prev_t) * (k / steps)
            measured = (np.floor(pos * epr + 0.5) + noise) * rpe
            v_pos = vff + kp * (ref - measured)
            if speed_limited:
                v_pos = np.minimum(np.maximum(v_pos, nvmax), vmax)
            v_ref = np.where(ramp, ramp_v, np.where(csp_loop, v_pos, v_csv))
            ev = v_ref - vel
            integ = np.where(pi, np.minimum(np.maximum(integ + ki * ev * h, ntmax), tmax), integ)
            tau = np.where(pi, kv * ev + integ + ff, tau_direct)
            limit |= powered & (np.abs(tau) > tmax)
            tau = np.where(powered, np.minimum(np.maximum(tau, ntmax), tmax), 0.0)
            te = te + (tau - te) * alpha if lag else tau
            applied = te * kt_ratio - load
            pos, vel = _rotor_substep(pos, vel, applied, (e_, f_, g_, hh_), fc if dry else None)
            tau_sq += te * te
        if any_ramp:
            self.standstill[sl] |= ramp & (ramp_v == 0.0) & (np.abs(vel) < self.standstill_speed[sl])
        self.pos[sl], self.vel[sl], self.integ[sl] = pos, vel, integ
        self.ramp_v[sl] = ramp_v
        return te, limit, tau_sq

    def _thermal(self, sl: slice, dt: F64, tau_sq_mean: F64) -> None:
        on = self.thermal[sl]
        t = self.temp[sl]
        amb = self.ambient[sl]
        r = self.r0[sl] * (1.0 + self.r_tc[sl] * (t - amb))
        t_ss = amb + tau_sq_mean / self.kt0_sq[sl] * r * self.rth[sl]
        new_t = np.where(on, t_ss + (t - t_ss) * np.exp(-dt / self.tau_th[sl]), t)
        self.temp[sl] = new_t
        state = self.state[sl]
        hot = (
            on
            & (new_t > self.fault_c[sl])
            & (self.fault_pending[sl] == 0)
            & (state != _FRA)
            & (state != _FAULT)
        )
        if hot.any():
            self.fault_pending[sl] = np.where(hot, ERROR_OVERTEMPERATURE, self.fault_pending[sl])
            self.changed()

    def _outputs(
        self, sl: slice, dt: F64, state: I64, oe: B, csp: B, csv: B, cst: B, target: F64, target_v: F64
    ) -> None:
        cpr = self.cpr[sl]
        if self.ideal_encoder:
            pos_counts = np.floor(self.pos[sl] * cpr + 0.5)
        else:
            enc = np.floor(self.pos[sl] * self.epr[sl] + 0.5) + self.noise[sl]
            pos_counts = np.floor(enc * self.enc_to_counts[sl] + 0.5)
        sw = _SW_BY_STATE[state] | _SW_REMOTE | np.where(state != _NR, _SW_VOLTAGE, 0)
        oe_csp = oe & csp
        fe = np.where(oe_csp, np.floor(target * cpr + 0.5) - pos_counts, 0.0)
        afe = np.abs(fe)
        window = self.fe_window[sl]
        over = oe_csp & (window != FOLLOWING_ERROR_OFF) & (afe > window)
        fe_time = np.where(over, self.fe_time[sl] + dt, np.where(oe_csp, 0.0, self.fe_time[sl]))
        self.fe_time[sl] = fe_time
        pending = self.fault_pending[sl]
        trip = over & (fe_time > self.fe_timeout[sl] + 1e-12) & (pending == 0)
        self.fault_pending[sl] = np.where(trip, ERROR_FOLLOWING, pending)
        if trip.any():
            self.changed()
        vel = self.vel[sl]
        vpr = self.vpr[sl]
        reached = (
            (oe_csp & (afe <= self.position_window[sl]))
            | (oe & csv & (np.abs(vel - target_v) * vpr <= self.velocity_window[sl]))
            | (oe & cst)
            | ((state == _QSA) & self.standstill[sl])
        )
        sw |= np.where(oe & (csp | csv | cst), _SW_FOLLOWS, 0)
        sw |= np.where(over, _SW_FOLLOWING_ERROR, 0)
        sw |= np.where(reached, _SW_TARGET_REACHED, 0)
        sw |= np.where(self.limit[sl], _SW_LIMIT, 0)
        if self.any_thermal:
            sw |= np.where(self.thermal[sl] & (self.temp[sl] > self.warn_c[sl]), _SW_WARNING, 0)
        self.statusword[sl] = sw
        self.following_error[sl] = fe
        self.position_counts[sl] = pos_counts
        self.velocity_counts[sl] = np.floor(vel * vpr + 0.5)
        self.torque_permille[sl] = np.floor(self.tau[sl] * 1000.0 / self.rated[sl] + 0.5)


def _ramp_to_zero(v: F64, dv: F64) -> F64:
    """One substep of the quick-stop / fault-reaction ramp: speed ``v`` [rad/s] ``dv`` closer to 0."""
    return np.where(v > dv, v - dv, np.where(v < -dv, v + dv, 0.0))


def _rotor_substep(
    pos: F64, vel: F64, applied: F64, coefficients: tuple[F64, F64, F64, F64], fc: F64 | None
) -> tuple[F64, F64]:
    """The rotor through one substep under the shaft torque ``applied`` [N·m]: position [rad], velocity
    [rad/s]. ``coefficients``: :func:`integration_coefficients`' e, f, g, hh; ``fc``: dry friction [N·m]
    (None: none), which holds a rotor that the torque cannot move and stops one it would reverse."""
    e_, f_, g_, hh_ = coefficients
    if fc is None:
        net = applied
    else:
        net, vel = _dry_friction(applied, vel, fc)
    pos = pos + vel * g_ + net * hh_
    v_new = vel * e_ + net * f_
    if fc is not None:
        v_new = np.where((fc > 0.0) & (v_new * vel < 0.0) & (np.abs(applied) <= fc), 0.0, v_new)
    return pos, v_new


def _dry_friction(applied: F64, vel: F64, fc: F64) -> tuple[F64, F64]:
    """Net torque with Coulomb friction ``fc`` [N·m] and the velocity (0 where the rotor sticks)."""
    sliding = np.abs(vel) > STICTION_RAD_S
    stuck = ~sliding & (np.abs(applied) <= fc)
    direction = np.where(sliding, np.sign(vel), np.sign(applied))
    net = np.where(stuck, 0.0, applied - direction * fc)
    return net, np.where(stuck, 0.0, vel)


_warmed = False


def runs(idx: npt.NDArray[np.intp]) -> list[tuple[int, int]]:
    """Sorted slot indices -> runs of consecutive ones as (start, stop): what :meth:`DriveBank.step` takes."""
    if not len(idx):
        return []
    breaks = (np.flatnonzero(np.diff(idx) != 1) + 1).tolist()
    starts = [0, *breaks]
    ends = [*breaks, len(idx)]
    return [(int(idx[a]), int(idx[b - 1]) + 1) for a, b in zip(starts, ends, strict=True)]


def warm_up() -> None:
    """Run every path of a small throwaway bank once (first calls into numpy cost up to milliseconds).

    Emulators call it at start-up, so the first cycles after a bring-up are
    as fast as the later ones (a master with a 0.5 ms receive timeout sees them).
    """
    global _warmed
    if _warmed:
        return
    _warmed = True
    bank = DriveBank(
        [DriveParams(), DriveParams(thermal=True, command_delay_cycles=1, coulomb_friction_nm=0.01)]
    )
    for d in bank.drives:
        d.bind(DictObjectStore())
    bank.mode_request[:] = _CSP
    for cw in (0x00, 0x06, 0x07, 0x0F, 0x0F, 0x0F):
        bank.controlword[:] = cw
        bank.step(0, 2, 1e-3)
        bank.step(0, 1, 2.5e-4)
    bank.drives[0].inject_fault(0x1000)
    bank.step(0, 2, np.array([1e-3, 1e-3]))
