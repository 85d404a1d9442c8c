"""The Damiao DM-J register table: number, name, type and access (pure data, no I/O).

From the Damiao motor manual's parameter list as the ``damiao-motor`` package (PyPI, MIT licence,
``damiao_motor/core/motor.py``, register table) and enactic/openarm_can (``dm_motor_constants.hpp``)
publish it: registers 0-36 hold protection limits, ids, the CAN timeout, the control mode, the
motor's physical constants (read-only), the MIT mapping ranges PMAX/VMAX/TMAX and the loop gains;
each is a float32 or a uint32 in 4 little-endian bytes (see :mod:`fieldbus.core.damiao`).
"""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class Register:
    """One register: number, name as the manual spells it, float32 (else uint32), read-only, unit."""

    number: int
    name: str
    is_float: bool
    read_only: bool = False
    unit: str = ""
    text: str = ""


_F, _U = True, False
REGISTERS: tuple[Register, ...] = (
    Register(0, "UV_Value", _F, unit="V", text="under-voltage protection"),
    Register(1, "KT_Value", _F, text="torque coefficient"),
    Register(2, "OT_Value", _F, unit="°C", text="over-temperature protection"),
    Register(3, "OC_Value", _F, text="over-current protection (per unit)"),
    Register(4, "ACC", _F, text="acceleration"),
    Register(5, "DEC", _F, text="deceleration"),
    Register(6, "MAX_SPD", _F, unit="rad/s", text="maximum speed"),
    Register(7, "MST_ID", _U, text="master (feedback) CAN id the motor replies on"),
    Register(8, "ESC_ID", _U, text="the motor's own CAN id (commands)"),
    Register(9, "TIMEOUT", _U, unit="50 us", text="CAN timeout: disable after this long without a command"),
    Register(
        10, "CTRL_MODE", _U, text="control mode: 1 MIT, 2 position-velocity, 3 velocity, 4 position-force"
    ),
    Register(11, "Damp", _F, True, text="viscous damping coefficient"),
    Register(12, "Inertia", _F, True, text="moment of inertia"),
    Register(13, "hw_ver", _U, True, text="reserved"),
    Register(14, "sw_ver", _U, True, text="software version"),
    Register(15, "SN", _U, True, text="reserved"),
    Register(16, "NPP", _U, True, text="pole pairs"),
    Register(17, "Rs", _F, True, unit="ohm", text="phase resistance"),
    Register(18, "Ls", _F, True, unit="H", text="phase inductance"),
    Register(19, "Flux", _F, True, unit="Wb", text="flux linkage"),
    Register(20, "Gr", _F, True, text="gear ratio"),
    Register(21, "PMAX", _F, unit="rad", text="position range of the MIT frame"),
    Register(22, "VMAX", _F, unit="rad/s", text="velocity range of the MIT frame"),
    Register(23, "TMAX", _F, unit="N·m", text="torque range of the MIT frame"),
    Register(24, "I_BW", _F, unit="Hz", text="current loop bandwidth"),
    Register(25, "KP_ASR", _F, text="speed loop Kp"),
    Register(26, "KI_ASR", _F, text="speed loop Ki"),
    Register(27, "KP_APR", _F, text="position loop Kp"),
    Register(28, "KI_APR", _F, text="position loop Ki"),
    Register(29, "OV_Value", _F, unit="V", text="over-voltage protection"),
    Register(30, "GREF", _F, text="gear torque efficiency"),
    Register(31, "Deta", _F, text="speed loop damping coefficient"),
    Register(32, "V_BW", _F, unit="Hz", text="speed loop filter bandwidth"),
    Register(33, "IQ_c1", _F, text="current loop enhancement coefficient"),
    Register(34, "VL_c1", _F, text="speed loop enhancement coefficient"),
    Register(35, "can_br", _U, text="CAN bit rate code"),
    Register(36, "sub_ver", _U, True, text="sub-version"),
)
BY_NUMBER = {r.number: r for r in REGISTERS}
BY_NAME = {r.name.upper(): r for r in REGISTERS}


def lookup(text: str) -> Register | int | None:
    """The register ``text`` names (a name, any case, or a number in the table); a number outside the
    table (0..255) as an ``int``; None when it is neither."""
    found = BY_NAME.get(text.upper())
    if found is not None:
        return found
    try:
        number = int(text, 0)
    except ValueError:
        return None
    if not 0 <= number <= 0xFF:
        return None
    return BY_NUMBER.get(number, number)
