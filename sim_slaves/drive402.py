"""An emulated CiA 402 drive: the state machine of ``fieldbus.core.cia402`` plus rotor physics.

Shared by the EtherCAT and CANopen emulators: each cycle the emulator calls
:meth:`Cia402Drive.step` with the drive's object dictionary (anything with
``get_value``/``set_value``, see :class:`ObjectStore`) and the cycle time.
The drive reads what the master wrote (controlword 0x6040, modes 0x6060,
targets 0x607A/0x60FF/0x6071 — the master's outputs, RxPDO here) and writes
what the master reads (statusword 0x6041, modes display 0x6061, actual
values 0x6064/0x606C/0x6077, following error 0x60F4, error code 0x603F —
the master's inputs, TxPDO here).

State machine: :data:`fieldbus.core.cia402.TRANSITIONS`, the same table the
master's controller plans with. A commanded transition takes effect once the
command has been seen for ``transition_cycles`` consecutive steps (default 1:
on the step that first sees it). Fault reset acts on the rising edge of
controlword bit 7; a held bit 7 is ignored.

Physics (SI inside, at the motor shaft; counts at the object dictionary): a
rigid rotor + load of inertia ``J`` [kg·m²] (the load reflected through the
gear: its inertia / gear ratio²) with viscous friction ``b`` [N·m·s/rad], integrated
exactly for a torque held over each control substep (``control_rate_hz``).
Torque limit from 0x6072 [‰ of rated torque]. CSP: cascaded position P ->
velocity PI -> torque with velocity (and optional acceleration) feed-forward
and linear interpolation of the target over the cycle, as real drives do.
CSV: the velocity PI alone. CST: torque directly. Optional thermal model:
winding temperature from I²R losses through a first-order thermal network;
the torque constant falls by ``kt_temp_coeff_per_k`` (NdFeB: -0.1 %/K), so the
shaft torque falls short of the demand, while 0x6077 reports the drive's own
estimate (current x nominal kt), as a real drive does.

Units (CiA 402's factor group without a feed constant): position units are
encoder counts, ``counts_per_rev`` per motor revolution (0x608F); the gear
(0x6091, motor revolutions per revolution of the driven shaft) only converts
for the driven shaft (:attr:`Cia402Drive.output_position_rad`); velocity units
are ``velocity_units_per_count_s`` per count/s (1: counts/s), acceleration
units (0x6085) velocity units per second; torque in ‰ of the motor's rated
torque (0x6076, mN·m). Limits: 0x6072 max torque, 0x6080 max motor speed [rpm]
(the velocity demand of CSP/CSV is held within it), 0x607D software position
limits [counts] (the CSP target is held within them). :mod:`sim_slaves.drive_config`
derives all of it from a drive map's scaling and a network file's ``emulator:`` options.

The physics is computed by :class:`sim_slaves.drive_bank.DriveBank`: a drive's
numeric state lives in one slot of a bank's arrays (:data:`FLOAT_SLOTS` ...),
and a drive built alone is the one drive of a bank of its own, so a drive
alone and a drive of an emulator's bank run the same code. This module holds
the drive's event logic: the state machine, mode switches, homing, the PP/PV
trajectory generator, configuration from the OD, fault injection.

Deterministic: no clock (``dt_s`` is a parameter); encoder noise from a seeded generator.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from enum import IntEnum
from fractions import Fraction
from typing import TYPE_CHECKING, Any, Protocol

from fieldbus.core.cia402 import (
    COMMAND_BY_NIBBLE,
    FAULT_RESET_BIT,
    TRANSITION_INDEX,
    Mode,
    State402,
    StatusBit,
    Transition,
    Trigger,
)
from fieldbus.errors import FieldbusError
from sim_slaves.profile402 import position_step, stopping_distance, velocity_step

if TYPE_CHECKING:
    from sim_slaves.drive_bank import DriveBank

TWO_PI = 2.0 * math.pi


class ObjectStore(Protocol):
    """The drive's object dictionary. ``get_value`` raises ``LookupError`` (e.g. ``KeyError``) for a missing object."""

    def get_value(self, index: int, sub: int) -> int | float: ...

    def set_value(self, index: int, sub: int, value: int | float) -> None: ...


class Obj(IntEnum):
    """CiA 402 objects the drive uses (sub-index 0, records: see :data:`RECORDS`).

    Units at the OD: counts, velocity units (counts/s by default), ‰, ms.
    """

    ERROR_CODE = 0x603F  # UNSIGNED16, written by the drive
    CONTROLWORD = 0x6040  # UNSIGNED16, master output (required)
    STATUSWORD = 0x6041  # UNSIGNED16, master input (required)
    QUICK_STOP_OPTION = 0x605A  # INTEGER16: 0 coast, 1/2 ramp -> SOD, 5/6 ramp and stay
    FAULT_REACTION_OPTION = 0x605E  # INTEGER16: 0 coast, 1/2 ramp
    MODES_OF_OPERATION = 0x6060  # INTEGER8, master output
    MODES_DISPLAY = 0x6061  # INTEGER8, master input
    POSITION_ACTUAL = 0x6064  # INTEGER32 counts, master input
    FOLLOWING_ERROR_WINDOW = 0x6065  # UNSIGNED32 counts; 0xFFFFFFFF = off
    FOLLOWING_ERROR_TIMEOUT = 0x6066  # UNSIGNED16 ms
    POSITION_WINDOW = 0x6067  # UNSIGNED32 counts (target reached, CSP)
    VELOCITY_ACTUAL = 0x606C  # INTEGER32 counts/s, master input
    VELOCITY_WINDOW = 0x606D  # UNSIGNED16 counts/s (target reached, CSV)
    TARGET_TORQUE = 0x6071  # INTEGER16 ‰ of rated torque, master output
    MAX_TORQUE = 0x6072  # UNSIGNED16 ‰ of rated torque
    TORQUE_ACTUAL = 0x6077  # INTEGER16 ‰ of rated torque, master input
    MOTOR_RATED_TORQUE = 0x6076  # UNSIGNED32 mN·m (1000 ‰ of 0x6071/0x6072/0x6077)
    TARGET_POSITION = 0x607A  # INTEGER32 counts, master output
    SOFTWARE_POSITION_LIMIT = 0x607D  # record: 1 min, 2 max, INTEGER32 counts
    MAX_MOTOR_SPEED = 0x6080  # UNSIGNED32 rpm; 0: no limit (this emulator)
    QUICK_STOP_DECELERATION = 0x6085  # UNSIGNED32 acceleration units (counts/s² by default)
    POSITION_ENCODER_RESOLUTION = 0x608F  # record: 1 encoder increments, 2 motor revolutions (UNSIGNED32)
    GEAR_RATIO = 0x6091  # record: 1 motor revolutions, 2 driven-shaft revolutions (UNSIGNED32)
    FOLLOWING_ERROR_ACTUAL = 0x60F4  # INTEGER32 counts, master input
    TARGET_VELOCITY = 0x60FF  # INTEGER32 counts/s, master output


REQUIRED_OBJECTS: tuple[Obj, ...] = (Obj.CONTROLWORD, Obj.STATUSWORD)
"""Objects a drive cannot run without; every other object is used when present."""

RECORDS = frozenset({Obj.SOFTWARE_POSITION_LIMIT, Obj.POSITION_ENCODER_RESOLUTION, Obj.GEAR_RATIO})
"""Objects with sub-indices 1 and 2 (present when sub-index 1 is)."""

FOLLOWING_ERROR_OFF = 0xFFFFFFFF
INT32_MIN, INT32_MAX = -(1 << 31), (1 << 31) - 1
RPM = TWO_PI / 60.0  # rad/s per rpm
GEAR_DENOMINATOR = 1000  # 0x6091 holds the gear as motor : shaft revolutions, shaft revolutions up to this

MAX_COMMAND_DELAY_CYCLES = 1000
STICTION_RAD_S = 1e-6  # below this speed dry friction holds the rotor [rad/s]
ERROR_FOLLOWING = 0x8611  # CiA 402: following error
ERROR_OVERTEMPERATURE = 0x4310  # CiA 402: excess temperature, drive

# homing mode (CiA 402-2 "Homing mode", modes of operation 6)
_HM = 6
HOMING_METHODS = (17, 18, 33, 34, 35, 37)
"""Methods the emulated drive implements: 17/18 limit (home) switch negative/positive, 33/34 index pulse
negative/positive, 35/37 the current position."""
HOMING_METHOD, HOME_OFFSET, HOMING_SPEEDS, HOMING_ACCELERATION = 0x6098, 0x607C, 0x6099, 0x609A
_SW_HOMING_ATTAINED = 1 << 12  # statusword bit 12 in homing mode
_SW_HOMING_ERROR = 1 << 13  # statusword bit 13 in homing mode
_CW_HOMING_START = 1 << 4  # controlword bit 4 in homing mode: rising edge starts, 0 interrupts
HOMING_CHECK_S = 1e-3
"""While it searches, the emulated drive looks for its home switch or index pulse at least this often [s of
its own time], however long the master leaves between two frames: a real drive watches them in its own
loop. (A step of 0.1 s, a stalled master, at a 4.8 rad/s search speed would otherwise run 0.48 rad past
the home point before it saw it.)"""

# profile modes (CiA 402-2 "Profile position mode", modes of operation 1; "Profile velocity mode", 3)
_PV = 3  # profile velocity; the profile code takes any other mode it runs in for profile position (1)
PROFILE_VELOCITY, PROFILE_ACCELERATION, PROFILE_DECELERATION = 0x6081, 0x6083, 0x6084
VELOCITY_THRESHOLD = 0x606F  # PV: statusword bit 12 "speed = 0" while |velocity actual| <= it
MOTION_PROFILE_TYPE = 0x6086  # PP/PV: 0 linear ramp (the one emulated)
POSITIONING_OPTION_CODE = 0x60F2  # PP: how a new set-point and a relative target are taken
_CW_NEW_SETPOINT = 1 << 4  # PP: rising edge hands the target (0x607A) to the trajectory generator
_CW_CHANGE_IMMEDIATELY = 1 << 5  # PP: 1 the new set-point replaces the one in progress, 0 it queues
_CW_RELATIVE = 1 << 6  # PP: 1 the target is relative to the previous target, 0 absolute
_CW_HALT = 1 << 8  # PP/PV: ramp to a stop at the profile deceleration (a move resumes when it drops)
_CW_CHANGE_ON_SETPOINT = 1 << 9  # PP: pass the target in progress at speed on to the next set-point
_SW_SETPOINT_ACK = 1 << 12  # PP: the generator took the set-point (PV: speed = 0)


class MissingObjectError(FieldbusError, LookupError):
    """The object dictionary lacks an object the drive needs."""

    def __init__(self, index: int, sub: int = 0) -> None:
        self.index = index
        self.sub = sub
        super().__init__(f"CiA 402 drive needs object {index:#06x}:{sub} in its object dictionary")


@dataclass(frozen=True)
class DriveParams:
    """Drive and motor parameters (SI units unless the name says otherwise).

    Defaults: a small robot-joint servo, 17-bit encoder, no gear, 1 N·m rated, 3 N·m peak.
    Objects present in the OD (0x6065, 0x6066, 0x6067, 0x606D, 0x6072, 0x6076,
    0x607D, 0x6080, 0x6085, 0x605A, 0x605E) override the matching defaults here;
    they are read when the drive binds to an OD (first step, or
    :meth:`Cia402Drive.bind`) and again on every state transition, so an SDO
    write during PRE-OP takes effect by the time the drive is enabled; call
    ``bind(od)`` to apply one at once. The units (``counts_per_rev``,
    ``gear_ratio``, ``velocity_units_per_count_s``: 0x608F, 0x6091) are fixed
    when the drive is built. :func:`sim_slaves.drive_config.drive_params` makes
    them from a drive map; :func:`default_objects` puts them into an OD.
    """

    counts_per_rev: int = 1 << 17  # position units (counts) per motor revolution
    inertia_kg_m2: float = 2.0e-4  # rotor + load, at the motor shaft (load inertia / gear ratio²)
    friction_nm_s_per_rad: float = 1.0e-3  # viscous friction b, at the motor shaft
    rated_torque_nm: float = 1.0  # motor rated torque (0x6076): 1000 ‰ in 0x6071/0x6072/0x6077
    gear_ratio: float = 1.0  # 0x6091: motor revolutions per revolution of the driven shaft
    velocity_units_per_count_s: float = 1.0  # velocity units (0x606C/0x60FF/0x606D) per count/s
    max_motor_speed_rpm: float = 0.0  # 0x6080: CSP/CSV velocity demand held within it; 0: no limit
    software_position_limit: tuple[int, int] | None = (
        None  # 0x607D (min, max) [counts]: CSP target held within
    )
    max_torque_permille: int = 3000  # default for 0x6072
    torque_constant_nm_per_a: float = 0.1  # kt at ambient_c
    resistance_ohm: float = 0.5  # winding (phase-equivalent) resistance at ambient_c
    # control (cascade: position P -> velocity PI -> torque)
    control_rate_hz: float = 4000.0  # internal loop rate; substeps = round(dt_s * rate)
    velocity_bandwidth_hz: float = 100.0  # kv = J * 2π f; PI zero at f/4
    position_gain_per_s: float = 150.0  # kp (rad/s per rad)
    velocity_feedforward: float = 1.0  # CSP: gain on the target's velocity
    torque_feedforward: float = 0.0  # CSP: gain on J * the target's acceleration
    # defaults of objects the OD may lack
    following_error_window_counts: int = 10_000  # 0x6065
    following_error_timeout_ms: int = 0  # 0x6066: fault when exceeded for longer than this
    position_window_counts: int = 100  # 0x6067
    velocity_window_counts_s: int = 1000  # 0x606D
    quick_stop_decel_counts_s2: int = 2_000_000  # 0x6085, acceleration units (counts/s² by default)
    quick_stop_option: int = 2  # 0x605A
    fault_reaction_option: int = 0  # 0x605E
    # state machine timing, in steps (cycles)
    transition_cycles: int = 1  # steps a command must be seen before its transition
    self_test_cycles: int = 1  # NOT_READY_TO_SWITCH_ON -> SWITCH_ON_DISABLED (transition 1)
    fault_reaction_cycles: int = 1  # minimum steps in FAULT_REACTION_ACTIVE (transition 14)
    mode_switch_cycles: int = 1  # steps before 0x6061 follows a new 0x6060
    initial_mode: int = Mode.CSP
    supported_modes: tuple[int, ...] = (
        Mode.NO_MODE,
        Mode.PROFILE_POSITION,
        Mode.PROFILE_VELOCITY,
        Mode.HOMING,
        Mode.CSP,
        Mode.CSV,
        Mode.CST,
    )
    # profile modes (PP/PV): defaults of 0x6081 [velocity units], 0x6083/0x6084 [acceleration units]
    profile_velocity: int = 200_000
    profile_acceleration: int = 2_000_000
    profile_deceleration: int = 2_000_000
    # homing mode: defaults of 0x6098 (37: home at the current position), 0x6099:01/02 search speeds
    # [velocity units], 0x609A acceleration [acceleration units]; 0x607C home offset starts at 0
    homing_method: int = 37
    homing_speed_switch: int = 100_000
    homing_speed_zero: int = 10_000
    homing_acceleration: int = 1_000_000
    # homing: where the switches are on the motor shaft [rad from the power-on position] (17/18); the
    # index pulse is at every whole motor revolution from there (33/34)
    negative_switch_rad: float = -1.0
    positive_switch_rad: float = 1.0
    # thermal model
    thermal: bool = False
    ambient_c: float = 25.0
    thermal_resistance_k_per_w: float = 1.0  # winding to ambient
    thermal_capacitance_j_per_k: float = 60.0  # winding + stator
    kt_temp_coeff_per_k: float = -0.001  # NdFeB remanence: -0.1 %/K
    resistance_temp_coeff_per_k: float = 0.00393  # copper
    warning_temperature_c: float = 100.0  # statusword bit 7
    fault_temperature_c: float = 130.0  # fault 0x4310 (reset refused above the warning level)
    standstill_rad_s: float = 0.01  # quick stop / fault reaction is done below this speed
    # real-world imperfections (defaults: an ideal drive, as before)
    command_delay_cycles: int = 0  # targets (0x607A/0x60FF/0x6071) act this many cycles late
    current_loop_bandwidth_hz: float = 0.0  # first-order torque lag; 0: torque follows the demand at once
    encoder_counts_per_rev: int = 0  # encoder resolution; 0: counts_per_rev
    encoder_noise_counts: float = 0.0  # Gaussian noise on the measured position, std dev [encoder counts]
    noise_seed: int = 0  # seed of the encoder noise (runs stay reproducible)
    coulomb_friction_nm: float = 0.0  # dry friction opposing motion [N·m]

    def __post_init__(self) -> None:
        positive = (
            "counts_per_rev",
            "inertia_kg_m2",
            "rated_torque_nm",
            "torque_constant_nm_per_a",
            "gear_ratio",
            "velocity_units_per_count_s",
        )
        for name in positive:
            if getattr(self, name) <= 0:
                raise ValueError(f"DriveParams.{name} must be > 0")
        for name in (
            "friction_nm_s_per_rad",
            "command_delay_cycles",
            "current_loop_bandwidth_hz",
            "encoder_counts_per_rev",
            "encoder_noise_counts",
            "coulomb_friction_nm",
            "max_motor_speed_rpm",
        ):
            if getattr(self, name) < 0:
                raise ValueError(f"DriveParams.{name} must be >= 0")
        if self.command_delay_cycles > MAX_COMMAND_DELAY_CYCLES:
            raise ValueError(f"DriveParams.command_delay_cycles must be <= {MAX_COMMAND_DELAY_CYCLES}")
        for name in ("transition_cycles", "self_test_cycles", "fault_reaction_cycles", "mode_switch_cycles"):
            if getattr(self, name) < 1:
                raise ValueError(f"DriveParams.{name} must be >= 1")
        limits = self.software_position_limit
        if limits is not None and not INT32_MIN <= limits[0] < limits[1] <= INT32_MAX:
            raise ValueError(
                f"DriveParams.software_position_limit must be (min, max) in int32, min < max: {limits}"
            )

    @property
    def encoder_cpr(self) -> int:
        """Encoder counts per revolution in force (``encoder_counts_per_rev`` or ``counts_per_rev``)."""
        return self.encoder_counts_per_rev or self.counts_per_rev


COMMUNICATION_FAULT = 0x8100  # CiA 301 emergency code: communication, generic
_POWERED = frozenset({State402.OPERATION_ENABLED, State402.QUICK_STOP_ACTIVE, State402.FAULT_REACTION_ACTIVE})
_OE = State402.OPERATION_ENABLED
_QSA = State402.QUICK_STOP_ACTIVE
_FRA = State402.FAULT_REACTION_ACTIVE
_FAULT = State402.FAULT
_NOT_READY = State402.NOT_READY_TO_SWITCH_ON
_SW_TARGET_REACHED = int(StatusBit.TARGET_REACHED)
_STEADY = frozenset({State402.SWITCH_ON_DISABLED, State402.READY_TO_SWITCH_ON, State402.SWITCHED_ON, _OE})
"""States a constant controlword cannot leave by itself (no automatic transition)."""

# Where a drive's numeric state lives: attribute -> array of its bank (the drive's value is the element at
# its slot). The bank's physics reads and writes these arrays; the drive's event logic the attributes.
FLOAT_SLOTS = {
    "position_rad": "pos",
    "velocity_rad_s": "vel",
    "torque_demand_nm": "tau",
    "shaft_torque_nm": "shaft",
    "load_torque_nm": "load",
    "temperature_c": "temp",
    "_integral": "integ",
    "_prev_target_rad": "prev_target",
    "_prev_vff": "prev_vff",
    "_ramp_v": "ramp_v",
    "_fe_time_s": "fe_time",
    "_tau_eff": "tau_eff",
    "fe_timeout_s": "fe_timeout",
    "max_torque_nm": "tmax",
    "qs_decel": "qs_decel",
    "rated_torque_nm": "rated",
    "max_speed_rad_s": "vmax",
    "position_limit_min": "pmin",
    "position_limit_max": "pmax",
    "_frame_rad": "frame",
    "_home_v": "home_v",
    "_prof_pos": "prof_pos",
    "_prof_v": "prof_v",
}
INT_SLOTS = {
    "error_code": "error_code",
    "mode_display": "mode_display",
    "following_error_counts": "following_error",
    "_fault_pending": "fault_pending",
    "_prev_cw": "prev_cw",
    "fe_window": "fe_window",
    "position_window": "position_window",
    "velocity_window": "velocity_window",
    "qs_option": "qs_option",
    "fr_option": "fr_option",
    "_noise": "noise",
    "home_bits": "home_bits",
    "_home_phase": "home_phase",
    "prof_bits": "prof_bits",
}
BOOL_SLOTS = {"limit_active": "limit", "_standstill": "standstill"}


class Cia402Drive:
    """One emulated CiA 402 servo drive. Call :meth:`step` once per cycle.

    Public state (SI, motor shaft): ``state``, ``position_rad``, ``velocity_rad_s``,
    ``torque_demand_nm`` (what the drive commands and reports in 0x6077),
    ``shaft_torque_nm`` (what the motor delivers: demand x kt(T)/kt0),
    ``load_torque_nm`` (external torque opposing motion, set by a test),
    ``temperature_c``, ``error_code``, ``last_transition`` (number from the table);
    :attr:`output_position_rad` is the driven shaft's angle (after the gear).
    """

    def __init__(
        self,
        params: DriveParams | None = None,
        *,
        position_counts: int = 0,
        bank: DriveBank | None = None,
        slot: int = 0,
    ) -> None:
        p = params or DriveParams()
        if bank is None:
            from sim_slaves.drive_bank import DriveBank  # (a cycle of imports: the bank builds drives)

            bank = DriveBank([p], seed=p.noise_seed, drives=[self])
        self.bank = bank
        self.slot = slot
        self.params = p
        self.state = _NOT_READY
        self.last_transition: int = 0  # transition 0: power on
        self.transitions_taken: int = 0
        self.rad_per_count = TWO_PI / p.counts_per_rev
        self.counts_per_rad = p.counts_per_rev / TWO_PI
        self.velocity_per_rad_s = (
            self.counts_per_rad * p.velocity_units_per_count_s
        )  # velocity units per rad/s
        self.rad_s_per_velocity = 1.0 / self.velocity_per_rad_s
        self.position_rad = position_counts * self.rad_per_count
        self.velocity_rad_s = 0.0
        self.torque_demand_nm = 0.0
        self.shaft_torque_nm = 0.0
        self.load_torque_nm = 0.0
        self.temperature_c = p.ambient_c
        self.error_code = 0
        self.mode_display = int(p.initial_mode)
        self.following_error_counts = 0
        self.limit_active = False
        # control internals
        self._integral = 0.0
        self._prev_target_rad = self.position_rad
        self._prev_vff = 0.0
        self._ramp_v = 0.0
        self._prev_cw = 0
        self._pending: Transition | None = None
        self._pending_steps = 0
        self._mode_pending = self.mode_display
        self._mode_steps = 0
        self._auto_steps = 0  # steps spent in a state left automatically
        self._reset_latched = False
        self._fault_pending = 0
        self._fault_persistent = False
        self._fe_time_s = 0.0
        self._standstill = False
        self._power_on_homing()
        self._power_on_profile()
        self._tau_eff = 0.0  # the current loop's torque [N·m]
        self._noise = 0  # this cycle's encoder noise [encoder counts]
        # object dictionary binding
        self._od: ObjectStore | None = None
        self._has: dict[int, bool] = {}
        self._load_config_defaults()

    def _power_on_homing(self) -> None:
        """Homing at power-on: idle, no frame shift, no search."""
        # frame shift (reported - physical position) [rad], speed demand [rad/s], statusword bits
        self._frame_rad = 0.0
        self._home_v = 0.0
        self.home_bits = 0
        self._home_phase = 0  # 0 idle, 1 searching, 2 found (stopping)
        self._home_method = 0
        self._home_prev_cw = 0
        self._home_found_from = 0.0  # physical position where the search began [rad]
        self._home_on_switch = False  # 17/18: the search began on the limit switch (it moves off it)

    def _power_on_profile(self) -> None:
        """The PP/PV trajectory generator at power-on: at the rotor, at rest, nothing queued."""
        # the generator's position [rad] and velocity [rad/s] (the cascade's reference), its target
        # [rad], a queued set-point, and the statusword bits 10/12 it reports
        self._prof_pos = self.position_rad
        self._prof_v = 0.0
        self.prof_bits = 0
        self._prof_live = False  # seeded since the last state transition or mode switch
        self._prof_target = self.position_rad
        self._prof_queued: float | None = None
        self._prof_ack = False
        self._prof_done = True
        self._prof_halt = False
        self._prof_target_v = 0.0  # PV: the velocity the ramp goes to [rad/s]
        self._prof_prev_cw = 0

    @property
    def od(self) -> ObjectStore | None:
        """The object dictionary the drive is bound to (None: not yet; the first step binds it)."""
        return self._od

    @property
    def output_position_rad(self) -> float:
        """Angle of the driven shaft [rad]: the motor's divided by the gear ratio (0x6091)."""
        return self.position_rad / self.params.gear_ratio

    def place(self, position_rad: float) -> None:
        """Put the rotor at ``position_rad`` [rad] (an emulator adopting a drive); the loops start there."""
        self.position_rad = self._prev_target_rad = position_rad

    # -- fault injection (tests) --

    def power_cycle(self) -> None:
        """Power lost and back: the state machine restarts (NOT READY TO SWITCH ON), motion stops.

        The position is kept (an absolute encoder); configuration read from the
        OD is read again on the next step.
        """
        position_counts = round(self.position_rad * self.counts_per_rad)
        self.bank.reset_slot(self.slot)
        self.__init__(  # type: ignore[misc]
            self.params, position_counts=position_counts, bank=self.bank, slot=self.slot
        )

    def connection_lost(self) -> None:
        """The fieldbus left its operational state (EtherCAT OP, CANopen OPERATIONAL) while powered.

        The drive reacts as with abort connection option code 0x6007 = 1 (the
        usual default): a fault with error code 0x8100 (communication), so the
        fault reaction stops the motor without waiting for the master.
        """
        if self.state in _POWERED:
            self.inject_fault(COMMUNICATION_FAULT)

    def inject_fault(self, code: int, *, persistent: bool = False) -> None:
        """Raise a fault with error code ``code`` (0x603F) at the next step; a persistent one refuses reset."""
        if not 0 < code <= 0xFFFF:
            raise ValueError(f"error code must be 1..0xFFFF, got {code:#x}")
        self._fault_pending = code
        self._fault_persistent = persistent
        self.bank.changed()

    def clear_fault_cause(self) -> None:
        """Remove the cause of a persistent fault: a fault reset will now succeed."""
        self._fault_persistent = False

    # -- object dictionary --

    def _probe(self, od: ObjectStore, index: int) -> bool:
        try:
            od.get_value(index, 1 if index in RECORDS else 0)
        except LookupError:
            return False
        return True

    def bind(self, od: ObjectStore) -> None:
        """Check the OD (required objects present) and note which optional objects it has."""
        for obj in REQUIRED_OBJECTS:
            if not self._probe(od, obj):
                raise MissingObjectError(obj)
        self._has = {int(o): self._probe(od, o) for o in Obj}
        self._od = od
        self._read_config(od)
        self.bank.bound(self.slot, self._has)

    def _load_config_defaults(self) -> None:
        p = self.params
        self.fe_window = p.following_error_window_counts
        self.fe_timeout_s = p.following_error_timeout_ms / 1000.0
        self.position_window = p.position_window_counts
        self.velocity_window = p.velocity_window_counts_s
        self.rated_torque_nm = p.rated_torque_nm
        self.max_torque_nm = p.max_torque_permille * p.rated_torque_nm / 1000.0
        self.qs_decel = p.quick_stop_decel_counts_s2 * self.rad_s_per_velocity
        self.qs_option = p.quick_stop_option
        self.fr_option = p.fault_reaction_option
        self.max_speed_rad_s = p.max_motor_speed_rpm * RPM or math.inf
        lo, hi = p.software_position_limit or (INT32_MIN, INT32_MAX)
        self._set_position_limits(lo, hi)

    def _set_position_limits(self, lo: int, hi: int) -> None:
        """0x607D as the drive applies it [counts]; the int32 extremes, or min >= max, mean no limit."""
        if lo >= hi:
            lo, hi = INT32_MIN, INT32_MAX
        self.position_limit_min = -math.inf if lo <= INT32_MIN else float(lo)
        self.position_limit_max = math.inf if hi >= INT32_MAX else float(hi)

    def _read_config(self, od: ObjectStore) -> None:
        self._load_config_defaults()
        has = self._has
        p = self.params
        if has[Obj.FOLLOWING_ERROR_WINDOW]:
            self.fe_window = int(od.get_value(Obj.FOLLOWING_ERROR_WINDOW, 0))
        if has[Obj.FOLLOWING_ERROR_TIMEOUT]:
            self.fe_timeout_s = float(od.get_value(Obj.FOLLOWING_ERROR_TIMEOUT, 0)) / 1000.0
        if has[Obj.POSITION_WINDOW]:
            self.position_window = int(od.get_value(Obj.POSITION_WINDOW, 0))
        if has[Obj.VELOCITY_WINDOW]:
            self.velocity_window = int(od.get_value(Obj.VELOCITY_WINDOW, 0))
        if has[Obj.MOTOR_RATED_TORQUE] and float(od.get_value(Obj.MOTOR_RATED_TORQUE, 0)) > 0:
            self.rated_torque_nm = float(od.get_value(Obj.MOTOR_RATED_TORQUE, 0)) / 1000.0
        permille = float(od.get_value(Obj.MAX_TORQUE, 0)) if has[Obj.MAX_TORQUE] else p.max_torque_permille
        self.max_torque_nm = permille * self.rated_torque_nm / 1000.0
        if has[Obj.QUICK_STOP_DECELERATION]:
            self.qs_decel = float(od.get_value(Obj.QUICK_STOP_DECELERATION, 0)) * self.rad_s_per_velocity
        if has[Obj.MAX_MOTOR_SPEED]:
            self.max_speed_rad_s = float(od.get_value(Obj.MAX_MOTOR_SPEED, 0)) * RPM or math.inf
        if has[Obj.SOFTWARE_POSITION_LIMIT]:
            self._set_position_limits(
                int(od.get_value(Obj.SOFTWARE_POSITION_LIMIT, 1)),
                int(od.get_value(Obj.SOFTWARE_POSITION_LIMIT, 2)),
            )
        if has[Obj.QUICK_STOP_OPTION]:
            self.qs_option = int(od.get_value(Obj.QUICK_STOP_OPTION, 0))
        if has[Obj.FAULT_REACTION_OPTION]:
            self.fr_option = int(od.get_value(Obj.FAULT_REACTION_OPTION, 0))

    # -- the cycle --

    def step(self, od: ObjectStore, dt_s: float) -> None:
        """Advance one cycle of ``dt_s`` seconds: read the master's outputs from ``od``, write its inputs.

        The drive's bank computes the cycle, for this drive alone.
        """
        bank, i = self.bank, self.slot
        bank.load_inputs(i, od)
        bank.step(i, i + 1, dt_s)
        bank.store_outputs(i, od)

    def command(self, controlword: int, mode_request: int) -> bool:
        """This cycle's event logic: a pending fault, the state machine table, a mode switch, homing.

        ``controlword`` (0x6040) and ``mode_request`` (0x6060) are the master's outputs. Returns whether
        the drive is settled: in a state a constant controlword cannot leave, no transition pending or
        taken this cycle, not homing (its bank then skips it while the controlword and mode hold).
        """
        homing = self.mode_display == _HM or self._home_phase != 0
        taken = self.transitions_taken
        self._state_machine(controlword)
        self._modes(mode_request)
        if homing or self.mode_display == _HM or self._home_phase:
            self._homing(controlword)
            return False
        return self.state in _STEADY and self._pending is None and self.transitions_taken == taken

    def _limit_position(self, counts: float) -> float:
        """A target position held within the software position limits (0x607D) [counts]."""
        return min(max(counts, self.position_limit_min), self.position_limit_max)

    def _limit_speed(self, v: float) -> float:
        """A velocity demand held within the max motor speed (0x6080) [rad/s]."""
        vmax = self.max_speed_rad_s
        return vmax if v > vmax else -vmax if v < -vmax else v

    # -- state machine (table-driven) --

    def _take(self, t: Transition) -> None:
        src = self.state
        self._prof_live = False
        self.state = t.target
        self.last_transition = t.number
        self.transitions_taken += 1
        self._pending = None
        self._pending_steps = 0
        self._auto_steps = 0
        if t.target is _OE or t.target is _QSA or t.target is _FRA:
            self._integral = 0.0 if t.target is _OE else self._integral
            self._ramp_v = self.velocity_rad_s
            self._standstill = False
        if t.target is _OE:
            self._prev_target_rad = self.position_rad
            self._prev_vff = 0.0
            self._fe_time_s = 0.0
        if src is _FAULT:
            self.error_code = 0
        if self._od is not None:
            self._read_config(self._od)

    def _state_machine(self, cw: int) -> None:
        p = self.params
        state = self.state
        if self._fault_pending and state is not _FRA and state is not _FAULT:
            self.error_code = self._fault_pending
            self._fault_pending = 0
            self._take(TRANSITION_INDEX[(state, Trigger.FAULT)])
            return
        if state is _NOT_READY:
            self._auto_steps += 1
            if self._auto_steps >= p.self_test_cycles:
                self._take(TRANSITION_INDEX[(state, Trigger.AUTO)])
            return
        if state is _FRA:
            self._auto_steps += 1
            if self._auto_steps >= p.fault_reaction_cycles and (self.fr_option == 0 or self._standstill):
                self._take(TRANSITION_INDEX[(state, Trigger.AUTO)])
            return
        if state is _FAULT:
            if cw & FAULT_RESET_BIT and not self._prev_cw & FAULT_RESET_BIT:
                self._reset_latched = True
                self._pending_steps = 0
            if self._reset_latched:
                if self._fault_persistent or (
                    p.thermal
                    and self.error_code == ERROR_OVERTEMPERATURE
                    and self.temperature_c > p.warning_temperature_c
                ):
                    self._reset_latched = False  # cause still present: the reset is refused
                    return
                self._pending_steps += 1
                if self._pending_steps >= p.transition_cycles:
                    self._reset_latched = False
                    self._take(TRANSITION_INDEX[(state, Trigger.FAULT_RESET)])
            return
        trigger = COMMAND_BY_NIBBLE[cw & 0x0F]
        t = TRANSITION_INDEX.get((state, trigger))
        if t is not None and t.condition and not 5 <= self.qs_option <= 8:
            t = None  # transition 16 needs quick stop option code 5-8
        if t is None:
            self._pending = None
            self._pending_steps = 0
            if state is _QSA and self.qs_option <= 4 and (self._standstill or self.qs_option == 0):
                self._take(TRANSITION_INDEX[(state, Trigger.AUTO)])
            return
        if t is self._pending:
            self._pending_steps += 1
        else:
            self._pending = t
            self._pending_steps = 1
        if self._pending_steps >= p.transition_cycles:
            self._take(t)

    def _modes(self, mode_req: int) -> None:
        if mode_req == self.mode_display or mode_req not in self.params.supported_modes:
            self._mode_steps = 0
            return
        if mode_req != self._mode_pending:
            self._mode_pending = mode_req
            self._mode_steps = 0
        self._mode_steps += 1
        if self._mode_steps >= self.params.mode_switch_cycles:
            self.mode_display = mode_req
            self._mode_steps = 0
            self._prof_live = False
            # bumpless: loops restart from the present motion
            self._integral = 0.0
            self._prev_target_rad = self.position_rad
            self._prev_vff = self.velocity_rad_s

    # -- homing (mode 6) --

    def _home_param(self, index: int, sub: int, default: int) -> int:
        od = self._od
        try:
            return int(od.get_value(index, sub)) if od is not None else default
        except LookupError:
            return default

    def _homing(self, cw: int) -> None:
        """One cycle of the homing procedure: bit-4 edge starts it, bit 4 low interrupts it.

        Statusword bits (in HM, OPERATION ENABLED): 10 target reached, 12 homing attained,
        13 homing error. After homing, the position actual at the home point is the home offset (0x607C).
        """
        prev, self._home_prev_cw = self._home_prev_cw, cw
        if self.mode_display != _HM or self.state is not _OE:
            if self._home_phase == 1:  # left homing mode or enabled state while searching: error
                self.home_bits = _SW_HOMING_ERROR
            self._home_phase = 0
            self._home_v = 0.0
            return
        start = cw & _CW_HOMING_START and not prev & _CW_HOMING_START
        if start:
            method = self._home_param(HOMING_METHOD, 0, 0)
            self._home_method = method
            if method not in HOMING_METHODS:
                self.home_bits = _SW_HOMING_ERROR
                self._home_phase = 0
                return
            if method in (35, 37):
                self._home_at(self.position_rad - self._frame_rad)
                return
            fast = method in (17, 18)
            speed = self._home_param(HOMING_SPEEDS, 1 if fast else 2, 0) * self.rad_s_per_velocity
            self._home_v = -speed if method in (17, 33) else speed
            phys = self.position_rad - self._frame_rad
            self._home_on_switch = self._on_switch(method, phys)
            if self._home_on_switch:  # started on its limit switch: off it, to the switch's edge
                self._home_v = -self._home_v
            self.home_bits = 0
            self._home_phase = 1
            self._home_found_from = phys
            return
        if not cw & _CW_HOMING_START and self._home_phase == 1:  # interrupted
            self._home_phase = 0
            self._home_v = 0.0
            self.home_bits = _SW_TARGET_REACHED
            return
        if self._home_phase == 1:
            self.look_for_home()
        elif (
            self._home_phase == 2
            and abs(self.velocity_rad_s) * self.velocity_per_rad_s <= self.velocity_window
        ):
            self.home_bits = _SW_HOMING_ATTAINED | _SW_TARGET_REACHED
            self._home_phase = 0

    # -- profile position (mode 1) and profile velocity (mode 3) --

    def _profile_rates(self) -> tuple[float, float, float]:
        """0x6081 profile velocity [rad/s], 0x6083 acceleration, 0x6084 deceleration [rad/s²] (0: default)."""
        p = self.params
        k = self.rad_s_per_velocity
        v = self._home_param(PROFILE_VELOCITY, 0, p.profile_velocity) or p.profile_velocity
        a = self._home_param(PROFILE_ACCELERATION, 0, p.profile_acceleration) or p.profile_acceleration
        d = self._home_param(PROFILE_DECELERATION, 0, p.profile_deceleration) or p.profile_deceleration
        return min(v * k, self.max_speed_rad_s), a * k, d * k

    def run_profile(
        self, cw: int, dt_s: float, target_counts: int | None, target_velocity: int | None
    ) -> None:
        """One cycle of the PP/PV trajectory generator (the drive OPERATION ENABLED in mode 1 or 3).

        PP: a rising edge of controlword bit 4 takes the target 0x607A (bit 6: relative to the previous
        target); bit 5 replaces a move in progress, else the set-point queues (one deep) and is refused
        when the queue is full. Bit 12 acknowledges from the edge until bit 4 drops and the queue is empty.
        PV: the ramp to 0x60FF. Bit 8 (halt) ramps to a stop at 0x6084 in both. On the first cycle after a
        state transition or mode switch the generator starts from the present motion (no step).
        """
        v_max, accel, decel = self._profile_rates()
        if not self._prof_live:
            self._prof_live = True
            self._prof_pos = self.position_rad
            self._prof_v = self.velocity_rad_s
            self._prof_target = self.position_rad + stopping_distance(self.velocity_rad_s, decel)
            self._prof_queued = None
            self._prof_ack = False
            self._prof_done = False
            self._prof_prev_cw = cw  # a bit 4 already high is not a new set-point
        halt = bool(cw & _CW_HALT)
        self._prof_halt = halt
        v0 = self._prof_v
        if self.mode_display == _PV:
            tv = 0.0
            if not halt and target_velocity is not None:
                tv = self._limit_speed(target_velocity * self.rad_s_per_velocity)
            self._prof_target_v = tv
            self._prof_v = velocity_step(v0, tv, accel, decel, dt_s)
            self._prof_pos = self.position_rad
            self._prof_prev_cw = cw
            return
        if cw & _CW_NEW_SETPOINT and not self._prof_prev_cw & _CW_NEW_SETPOINT and target_counts is not None:
            self._setpoint(cw, target_counts)
        self._prof_prev_cw = cw
        if not cw & _CW_NEW_SETPOINT and self._prof_queued is None:
            self._prof_ack = False
        if halt:
            self._prof_v = velocity_step(v0, 0.0, accel, decel, dt_s)
            self._prof_pos += 0.5 * (v0 + self._prof_v) * dt_s
            self._prof_done = False
            return
        p, v, done = position_step(self._prof_pos, v0, self._prof_target, v_max, accel, decel, dt_s)
        self._prof_pos, self._prof_v, self._prof_done = p, v, done
        if done and self._prof_queued is not None:  # the queued set-point starts
            self._prof_target, self._prof_queued = self._prof_queued, None
            self._prof_done = False

    def _setpoint(self, cw: int, target_counts: int) -> None:
        """A new PP set-point (controlword bit-4 edge): take it, queue it, or refuse it (queue full).

        Relative (bit 6): to what 0x60F2 bits 0-1 name - 0 the preceding target, 1 the position demand
        (the generator's position), 2 the position actual value. Bit 9 (change on set-point) with bit 5
        low: a set-point beyond the target in progress, in the direction of travel, is taken at once, so
        the drive passes that target at the profile velocity instead of stopping on it.
        """
        rpc = self.rad_per_count
        if cw & _CW_RELATIVE:
            option = self._home_param(POSITIONING_OPTION_CODE, 0, 0) & 0x3
            if option == 1:
                base = self._prof_pos
            elif option == 2:
                base = self.position_rad
            else:
                base = self._prof_queued if self._prof_queued is not None else self._prof_target
            counts = base * self.counts_per_rad + target_counts
        else:
            counts = float(target_counts)
        new = self._limit_position(counts) * rpc
        busy = not self._prof_done or self._prof_halt
        ahead = self._prof_target - self._prof_pos  # what is left of the move in progress [rad]
        on_the_fly = (
            cw & _CW_CHANGE_ON_SETPOINT
            and self._prof_queued is None
            and not self._prof_halt
            and ahead * (new - self._prof_target) > 0.0
        )
        if cw & _CW_CHANGE_IMMEDIATELY or not busy or on_the_fly:
            self._prof_target, self._prof_queued = new, None
            self._prof_done = False
        elif self._prof_queued is None:
            self._prof_queued = new
        else:
            return  # queue full: not acknowledged
        self._prof_ack = True

    def profile_status(self) -> int:
        """Statusword bits 10 and 12 of PP/PV after this cycle's motion.

        PP: 10 target reached (the generator at the target and |target - actual| within 0x6067, or
        halted at standstill), 12 set-point acknowledge. PV: 10 |actual - target velocity| within 0x606D
        (halt: target 0), 12 speed = 0 (|actual| within 0x606F, default 0x606D).
        """
        vpr = self.velocity_per_rad_s
        bits = 0
        if self.mode_display == _PV:
            if abs(self.velocity_rad_s - self._prof_target_v) * vpr <= self.velocity_window:
                bits |= _SW_TARGET_REACHED
            threshold = self._home_param(VELOCITY_THRESHOLD, 0, self.velocity_window)
            if abs(self.velocity_rad_s) * vpr <= threshold:
                bits |= _SW_SETPOINT_ACK
            return bits
        if self._prof_ack:
            bits |= _SW_SETPOINT_ACK
        if self._prof_halt:
            if self._prof_v == 0.0 and abs(self.velocity_rad_s) * vpr <= self.velocity_window:
                bits |= _SW_TARGET_REACHED
        elif (
            self._prof_done
            and self._prof_queued is None
            and abs(self._prof_target - self.position_rad) * self.counts_per_rad <= self.position_window
        ):
            bits |= _SW_TARGET_REACHED
        return bits

    def look_for_home(self) -> None:
        """Searching: the home switch or index pulse passed since the last look? Then it is the home point."""
        phys = self.position_rad - self._frame_rad
        m = self._home_method
        p = self.params
        if m in (17, 18):
            # the switch's edge is the home point: where the switch changes from its state at the start
            # (on: searching towards it; off: the search started on it and moves off it)
            if self._on_switch(m, phys) != self._home_on_switch:
                self._home_at(p.negative_switch_rad if m == 17 else p.positive_switch_rad)
        elif m in (33, 34):
            rev_from = math.floor((self._home_found_from - p.negative_switch_rad) / TWO_PI)
            rev_now = math.floor((phys - p.negative_switch_rad) / TWO_PI)
            if rev_now != rev_from:
                self._home_at(p.negative_switch_rad + TWO_PI * max(rev_now, rev_from))

    def _on_switch(self, method: int, phys: float) -> bool:
        """Is the limit switch of method 17 (negative) or 18 (positive) on at physical position ``phys``?"""
        if method == 17:
            return phys <= self.params.negative_switch_rad
        return method == 18 and phys >= self.params.positive_switch_rad

    def _home_at(self, home_phys_rad: float) -> None:
        """The home point (physical position) is found: shift the reported frame so it reads the home offset."""
        offset_rad = self._home_param(HOME_OFFSET, 0, 0) * self.rad_per_count
        shift = offset_rad - home_phys_rad - self._frame_rad
        self._frame_rad += shift
        self.position_rad += shift
        self._prev_target_rad += shift
        self._home_v = 0.0
        self.home_bits = _SW_HOMING_ATTAINED
        self._home_phase = 2


def default_objects(params: DriveParams | None = None) -> dict[tuple[int, int], int | float]:
    """Every object :class:`Cia402Drive` uses, at its default value (a starting OD for emulators and tests)."""
    p = params or DriveParams()
    values: dict[Obj, int | float] = {
        Obj.ERROR_CODE: 0,
        Obj.CONTROLWORD: 0,
        Obj.STATUSWORD: 0,
        Obj.QUICK_STOP_OPTION: p.quick_stop_option,
        Obj.FAULT_REACTION_OPTION: p.fault_reaction_option,
        Obj.MODES_OF_OPERATION: int(p.initial_mode),
        Obj.MODES_DISPLAY: int(p.initial_mode),
        Obj.POSITION_ACTUAL: 0,
        Obj.FOLLOWING_ERROR_WINDOW: p.following_error_window_counts,
        Obj.FOLLOWING_ERROR_TIMEOUT: p.following_error_timeout_ms,
        Obj.POSITION_WINDOW: p.position_window_counts,
        Obj.VELOCITY_ACTUAL: 0,
        Obj.VELOCITY_WINDOW: p.velocity_window_counts_s,
        Obj.TARGET_TORQUE: 0,
        Obj.MAX_TORQUE: p.max_torque_permille,
        Obj.TORQUE_ACTUAL: 0,
        Obj.TARGET_POSITION: 0,
        Obj.QUICK_STOP_DECELERATION: p.quick_stop_decel_counts_s2,
        Obj.FOLLOWING_ERROR_ACTUAL: 0,
        Obj.TARGET_VELOCITY: 0,
        Obj.MOTOR_RATED_TORQUE: round(p.rated_torque_nm * 1000.0),
        Obj.MAX_MOTOR_SPEED: round(p.max_motor_speed_rpm),
    }
    out: dict[tuple[int, int], int | float] = {(int(index), 0): value for index, value in values.items()}
    # the objects of the profile and homing modes (0x6502 advertises them: a real drive has them)
    out[(PROFILE_VELOCITY, 0)] = p.profile_velocity
    out[(PROFILE_ACCELERATION, 0)] = p.profile_acceleration
    out[(PROFILE_DECELERATION, 0)] = p.profile_deceleration
    out[(VELOCITY_THRESHOLD, 0)] = min(p.velocity_window_counts_s, 0xFFFF)
    out[(MOTION_PROFILE_TYPE, 0)] = 0
    out[(POSITIONING_OPTION_CODE, 0)] = 0
    out[(HOMING_METHOD, 0)] = p.homing_method
    out[(HOME_OFFSET, 0)] = 0
    out[(HOMING_SPEEDS, 1)] = p.homing_speed_switch
    out[(HOMING_SPEEDS, 2)] = p.homing_speed_zero
    out[(HOMING_ACCELERATION, 0)] = p.homing_acceleration
    gear = Fraction(p.gear_ratio).limit_denominator(GEAR_DENOMINATOR)
    records = {
        Obj.SOFTWARE_POSITION_LIMIT: p.software_position_limit or (INT32_MIN, INT32_MAX),
        Obj.POSITION_ENCODER_RESOLUTION: (p.encoder_cpr, 1),
        Obj.GEAR_RATIO: (gear.numerator, gear.denominator),
    }
    for index, (first, second) in records.items():
        out[(int(index), 1)] = first
        out[(int(index), 2)] = second
    return out


class DictObjectStore:
    """A minimal dict-backed :class:`ObjectStore` (tests, examples); missing objects raise ``KeyError``."""

    def __init__(self, values: dict[tuple[int, int], int | float] | None = None) -> None:
        self.values: dict[tuple[int, int], int | float] = default_objects() if values is None else values

    def get_value(self, index: int, sub: int) -> int | float:
        return self.values[(index, sub)]

    def set_value(self, index: int, sub: int, value: int | float) -> None:
        self.values[(index, sub)] = value


def _slot(array: str, cast: Callable[[Any], Any]) -> property:
    """A drive attribute that is element ``slot`` of its bank's ``array``."""

    def get(self: Cia402Drive) -> Any:
        return cast(getattr(self.bank, array)[self.slot])

    def put(self: Cia402Drive, value: Any) -> None:
        getattr(self.bank, array)[self.slot] = value

    return property(get, put)


def _state_get(self: Cia402Drive) -> State402:
    return _STATES[int(self.bank.state[self.slot])]


def _state_put(self: Cia402Drive, value: State402) -> None:
    self.bank.state[self.slot] = int(value)


_STATES = tuple(State402)
Cia402Drive.state = property(_state_get, _state_put)  # type: ignore[assignment]
for _slots, _cast in ((FLOAT_SLOTS, float), (INT_SLOTS, int), (BOOL_SLOTS, bool)):
    for _name, _array in _slots.items():
        setattr(Cia402Drive, _name, _slot(_array, _cast))
