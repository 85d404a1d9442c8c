"""ODrive's own set-point codec (:func:`fieldbus.core.odrive.encode_setpoint`): the frame from the image's
output wire row, judged by odriverobotics' DBC (the ``odrive-can`` package) where it is installed."""

from __future__ import annotations

import math
import struct

import numpy as np
import pytest

from fieldbus import PDO_MAPS
from fieldbus.core import odrive
from fieldbus.core.pdo import load_drive_map
from fieldbus.core.pdo.image import ProcessImage
from fieldbus.core.pdo.layout import layout

DRIVE = load_drive_map(PDO_MAPS / "odrive_s1.yaml")
PROTO = DRIVE.rawcan.odrive if DRIVE.rawcan is not None else None


def _row(**values: float) -> np.ndarray:
    img = ProcessImage(layout(DRIVE), 1)
    for k, v in values.items():
        img.outputs.values[0][k] = v
    img.outputs.to_wire()
    return img.outputs.wire[0]


def test_set_input_pos_from_the_wire_row_decodes_in_the_dbc() -> None:
    assert PROTO is not None
    utils = pytest.importorskip("odrive_can.utils")
    out = bytearray(8)
    odrive.encode_setpoint(PROTO.mode_named("position"), _row(position=0.25, velocity=1.5, torque=-0.2), out)
    v = utils.get_dbc("odrive-cansimple-0.6.10").get_message_by_name("Axis0_Set_Input_Pos").decode(bytes(out))
    assert (v["Input_Pos"], v["Vel_FF"], v["Torque_FF"]) == pytest.approx((0.25, 1.5, -0.2))


def test_nan_in_a_feed_forward_sends_zero_and_out_of_range_saturates() -> None:
    """The int16 feed-forwards: NaN sends 0 (it used to raise out of the cycle), 100 N·m saturates."""
    assert PROTO is not None
    out = bytearray(b"\xff" * 8)
    odrive.encode_setpoint(
        PROTO.mode_named("position"), _row(position=1.0, velocity=math.nan, torque=100.0), out
    )
    assert bytes(out) == struct.pack("<fhh", 1.0, 0, 32767)
    assert odrive.decode_setpoint(PROTO.mode_named("position"), bytes(out)) == pytest.approx(
        {"position": 1.0, "velocity": 0.0, "torque": 32.767}
    )


def test_the_requested_state_is_read_from_the_wire_row() -> None:
    assert PROTO is not None
    assert odrive.requested_state(PROTO, _row(requested_state=8)) == 8
    assert odrive.requested_state(PROTO, _row()) == 0
