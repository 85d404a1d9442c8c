"""Profile position (PP, mode 1) and profile velocity (PV, mode 3): the drive's own trajectory, per axis.

:class:`ProfileMove` runs on top of a :class:`~fieldbus.core.cia402.Cia402Controller`, one
:meth:`~ProfileMove.step` per cycle, never blocking, vectorised over the axes like
:class:`~fieldbus.core.cia402.Homing`. PP is the set-point handshake of CiA 402-2: the target in
0x607A, controlword bit 4 "new set-point" up, statusword bit 12 "set-point acknowledge" seen, bit 4
down, statusword bit 10 "target reached". PV writes 0x60FF and waits for bit 10 (at speed). The
trajectory's limits are the drive's: 0x6081 profile velocity, 0x6083/0x6084 acceleration and
deceleration, written at bring-up from the drive map's ``motion_profile:`` section.
"""

from __future__ import annotations

from collections.abc import Sequence
from enum import IntEnum
from typing import Any

import numpy as np
import numpy.typing as npt

from fieldbus.core.cia402 import Cia402Controller, Mode, ProcessImageLike, StatusBit
from fieldbus.core.pdo.model import DriveMap
from fieldbus.errors import ChannelNameError


class ProfilePhase(IntEnum):
    """Where each axis is in :class:`ProfileMove` (per-axis codes in :attr:`ProfileMove.phase`)."""

    IDLE = 0  # not asked to move (or never)
    WAIT = 1  # PP/PV requested; waiting for OPERATION ENABLED in the mode
    ARMED = 2  # PP: target written, bit 4 low until the drive's bit 12 is low (a clean edge next)
    SENT = 3  # PP: bit 4 high; waiting for bit 12 (set-point acknowledge)
    MOVING = 4  # PP: acknowledged, bit 4 low, waiting for bit 10; PV: ramping, waiting for bit 10
    DONE = 5  # PP: target reached; PV: at speed (0x60FF still written every cycle)
    TIMED_OUT = 6  # no result within timeout_cycles; bit 4 dropped


NEW_SETPOINT = 0x0010  # controlword bit 4 in PP (master output): rising edge hands over 0x607A
CHANGE_IMMEDIATELY = 0x0020  # controlword bit 5 in PP: replace the move in progress (0: queue behind it)
RELATIVE = 0x0040  # controlword bit 6 in PP: the target is relative to the previous one
HALT = 0x0100  # controlword bit 8 in PP/PV: ramp to a stop at 0x6084
SETPOINT_ACK = 0x1000  # statusword bit 12 in PP (master input); in PV "speed = 0"
_MANAGED = NEW_SETPOINT | CHANGE_IMMEDIATELY | RELATIVE | HALT
_REACHED = int(StatusBit.TARGET_REACHED)  # statusword bit 10
_PP, _PV = np.int8(Mode.PROFILE_POSITION), np.int8(Mode.PROFILE_VELOCITY)
SETTLE_CYCLES = 2  # PV: cycles in MOVING before bit 10 is believed (an earlier target's is stale until then)


class ProfileMove:
    """Non-blocking, per-axis PP moves and PV runs on top of a :class:`Cia402Controller`.

    :meth:`move_to` (PP) and :meth:`run_at` (PV) switch the axes' mode and
    set their goal; each :meth:`step` (or :meth:`step_image`), called right
    after the controller's step with the same arrays, writes the targets and
    controlword bits 4, 5, 6 and 8 of the axes it moves and follows their
    statuswords. Targets are in the image's units (a map's ``factor`` applies,
    e.g. rad). ``timeout_cycles`` (one number, or one per axis) bounds each
    move from :meth:`move_to`/:meth:`run_at` to bit 10; :meth:`from_maps`
    takes each axis's from its map's ``motion_profile.timeout_ms``. An axis
    stays in its profile mode when done (the drive holds the target, or keeps
    the speed); request another mode on the controller to leave it: the axis
    is then released (IDLE, bits 4-6 and 8 cleared, its targets the user's).
    """

    def __init__(self, ctrl: Cia402Controller, *, timeout_cycles: int | Sequence[int] = 30_000) -> None:
        n = ctrl.n_axes
        limit = np.broadcast_to(np.asarray(timeout_cycles, dtype=np.int64), (n,)).astype(np.int32)
        if (limit < 1).any():
            raise ValueError(f"timeout_cycles must be >= 1, got {timeout_cycles}")
        self.ctrl = ctrl
        self.timeout_cycles = limit  # per axis [cycles]
        self.phase: npt.NDArray[np.int8] = np.zeros(n, dtype=np.int8)
        self.cycles: npt.NDArray[np.int32] = np.zeros(n, dtype=np.int32)  # cycles since move_to/run_at
        self.mode: npt.NDArray[np.int8] = np.zeros(n, dtype=np.int8)  # 1 PP, 3 PV, 0 none yet
        self.target: npt.NDArray[np.float64] = np.zeros(n, dtype=np.float64)  # image units
        self.halted: npt.NDArray[np.bool_] = np.zeros(n, dtype=bool)
        self._moving = np.zeros(n, dtype=np.int32)  # cycles in MOVING
        self._bits = np.zeros(n, dtype=np.uint16)  # bits 5, 6 of each axis's set-point
        self._sw = np.zeros(n, dtype=np.uint16)
        self._m = np.zeros(n, dtype=bool)
        self._m2 = np.zeros(n, dtype=bool)
        self._word = np.zeros(n, dtype=np.uint16)
        self._not_managed = np.uint16(0xFFFF & ~_MANAGED)

    @classmethod
    def from_maps(cls, ctrl: Cia402Controller, maps: Sequence[DriveMap], cycle_time_us: int) -> ProfileMove:
        """Moves for axes described by ``maps`` (one per axis), each timed out after its
        ``motion_profile.timeout_ms`` (30 s without a section) at ``cycle_time_us``."""
        if len(maps) != ctrl.n_axes:
            raise ValueError(f"{len(maps)} drive maps for {ctrl.n_axes} axes")
        if cycle_time_us < 1:
            raise ValueError(f"cycle_time_us must be >= 1, got {cycle_time_us}")
        ms = [m.motion_profile.timeout_ms if m.motion_profile is not None else 30_000 for m in maps]
        return cls(ctrl, timeout_cycles=[max(1, -(-t * 1000 // cycle_time_us)) for t in ms])

    # -- requests (outside the cycle's hot path) --

    def move_to(
        self, targets: Any, axes: Any = slice(None), *, relative: bool = False, immediate: bool = False
    ) -> None:
        """PP: move ``axes`` (index, slice or mask) to ``targets`` (one value or one per selected axis, in
        the image's units); ``relative``: by ``targets`` from the previous target (bit 6); ``immediate``:
        replace a move in progress (bit 5) instead of queueing behind it."""
        self._begin(axes, _PP, targets)
        self._bits[axes] = (CHANGE_IMMEDIATELY if immediate else 0) | (RELATIVE if relative else 0)

    def run_at(self, velocities: Any, axes: Any = slice(None)) -> None:
        """PV: run ``axes`` at ``velocities`` (image units, e.g. rad/s); 0 ramps to a stop."""
        self._begin(axes, _PV, velocities)
        self._bits[axes] = 0

    def halt(self, axes: Any = slice(None), on: bool = True) -> None:
        """Controlword bit 8 for ``axes``: ramp to a stop at 0x6084 (PP resumes the move when it drops)."""
        self.halted[axes] = on

    def _begin(self, axes: Any, mode: np.int8, values: Any) -> None:
        self.target[axes] = values
        self.mode[axes] = mode
        self.phase[axes] = ProfilePhase.WAIT
        self.cycles[axes] = 0
        self._moving[axes] = 0
        self.ctrl.request_mode(int(mode), axes)

    # -- the cycle --

    def step_image(self, img: ProcessImageLike) -> None:
        """:meth:`step` on a group's image: its statusword, controlword, target_position and (when the map
        has it) target_velocity channels."""
        out, inp = img.outputs, img.inputs
        for d, name in ((inp, "statusword"), (out, "controlword")):
            if name not in d.names:
                raise ChannelNameError(f"ProfileMove needs a {name} channel (channels: {', '.join(d.names)})")
        tp = out["target_position"] if "target_position" in out.names else None
        tv = out["target_velocity"] if "target_velocity" in out.names else None
        for mode, channel, obj, have in (
            (_PP, "target_position", "0x607A", tp),
            (_PV, "target_velocity", "0x60FF", tv),
        ):
            if have is None and ((self.mode == mode) & (self.phase != ProfilePhase.IDLE)).any():
                raise ChannelNameError(
                    f"{'PP' if mode == _PP else 'PV'} needs a {channel} channel ({obj} in an rpdo of the map; "
                    f"channels: {', '.join(out.names)})"
                )
        self.step(inp["statusword"], out["controlword"], tp, tv)

    def step(
        self,
        statusword: npt.NDArray[Any],
        controlword_out: npt.NDArray[Any],
        target_position_out: npt.NDArray[Any] | None = None,
        target_velocity_out: npt.NDArray[Any] | None = None,
    ) -> None:
        """One cycle, after :meth:`Cia402Controller.step`: targets and controlword bits 4-6, 8 (master
        outputs) of the axes this moves, from their statuswords (master inputs)."""
        ph, m, m2 = self.phase, self._m, self._m2
        # an axis the controller was asked to put in another mode is released: its bits 4-6, 8 cleared
        # once, its targets left to the user (a PP target written on would override a CSP seed)
        np.not_equal(self.ctrl.mode_request, self.mode, out=m)
        m &= ph != ProfilePhase.IDLE
        if m.any():
            np.copyto(controlword_out, np.bitwise_and(controlword_out, self._not_managed), where=m)
            np.copyto(ph, np.int8(ProfilePhase.IDLE), where=m)
        np.copyto(self._sw, statusword, casting="unsafe")
        sw = self._sw
        ack = (sw & SETPOINT_ACK) != 0
        reached = (sw & _REACHED) != 0
        pp = self.mode == _PP
        pv = self.mode == _PV
        active = (ph >= ProfilePhase.WAIT) & (ph <= ProfilePhase.MOVING)
        np.add(self.cycles, active, out=self.cycles)
        # PP: SENT -> MOVING once the drive acknowledges (bit 12); ARMED -> SENT once bit 12 is low
        np.equal(ph, ProfilePhase.SENT, out=m)
        m &= ack
        np.copyto(ph, np.int8(ProfilePhase.MOVING), where=m)
        np.equal(ph, ProfilePhase.ARMED, out=m)
        m &= ~ack
        np.copyto(ph, np.int8(ProfilePhase.SENT), where=m)
        # WAIT -> ARMED (PP) / MOVING (PV) once enabled in the mode (the controller's goal reached)
        np.equal(ph, ProfilePhase.WAIT, out=m)
        np.logical_and(m, self.ctrl.reached, out=m)
        np.logical_and(m, pp, out=m2)
        np.copyto(ph, np.int8(ProfilePhase.ARMED), where=m2)
        m &= pv
        np.copyto(ph, np.int8(ProfilePhase.MOVING), where=m)
        # MOVING -> DONE on bit 10 (PP: with bit 12 down, the acknowledge of this set-point handed back;
        # PV: once the drive has answered the new 0x60FF)
        np.equal(ph, ProfilePhase.MOVING, out=m)
        np.add(self._moving, m, out=self._moving)
        m &= reached & ((pv & (self._moving > SETTLE_CYCLES)) | (pp & ~ack))
        np.copyto(ph, np.int8(ProfilePhase.DONE), where=m)
        late = ((ph >= ProfilePhase.WAIT) & (ph <= ProfilePhase.MOVING)) & (self.cycles > self.timeout_cycles)
        np.copyto(ph, np.int8(ProfilePhase.TIMED_OUT), where=late)
        # outputs of the axes this moves: targets (PP: until the drive took the set-point), bits 4-6 and 8
        mine = ph != ProfilePhase.IDLE
        if target_position_out is not None:
            handing = pp & (ph >= ProfilePhase.WAIT) & (ph <= ProfilePhase.SENT)
            np.copyto(target_position_out, self.target, where=handing, casting="unsafe")
        if target_velocity_out is not None:
            np.copyto(target_velocity_out, self.target, where=mine & pv, casting="unsafe")
        word = self._word
        np.copyto(word, self._bits)
        word |= np.where(ph == ProfilePhase.SENT, NEW_SETPOINT, 0).astype(np.uint16)
        word |= np.where(self.halted, HALT, 0).astype(np.uint16)
        kept = np.bitwise_and(controlword_out, self._not_managed)
        np.copyto(controlword_out, kept | word, where=mine, casting="unsafe")

    @property
    def done(self) -> bool:
        """No axis is on its way (each is IDLE, DONE or TIMED_OUT)."""
        return not bool(((self.phase >= ProfilePhase.WAIT) & (self.phase <= ProfilePhase.MOVING)).any())
