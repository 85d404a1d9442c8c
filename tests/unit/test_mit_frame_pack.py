"""MitFrame.pack (values in field order, no dict) gives the bits MitFrame.bits gives from a dict."""

from __future__ import annotations

import math

import pytest

from fieldbus import PDO_MAPS
from fieldbus.core.pdo import load_drive_map
from sim_slaves.damiao import ROTOR_FIELDS
from sim_slaves.mit_motor import MitFrame


def _reply_frame() -> MitFrame:
    cfg = load_drive_map(PDO_MAPS / "damiao_dm_j4310.yaml").rawcan
    assert cfg is not None
    return MitFrame(cfg.reply, cfg.span)


@pytest.mark.parametrize(
    "values",
    [(0.0, 0.0, 0.0), (1.25, -3.5, 0.75), (1e9, -1e9, 1e9), (-12.5, 30.0, -10.0), (math.pi, 1e-9, -1e-9)],
)
def test_pack_is_bits_from_a_dict(values: tuple[float, float, float]) -> None:
    frame = _reply_frame()
    rotor = [next(f for f in frame.fields if f[0] == name) for name in ROTOR_FIELDS]
    assert frame.pack(values, rotor) == frame.bits(dict(zip(ROTOR_FIELDS, values, strict=True)), rotor)


def test_pack_refuses_values_not_matching_the_fields() -> None:
    frame = _reply_frame()
    rotor = [next(f for f in frame.fields if f[0] == name) for name in ROTOR_FIELDS]
    with pytest.raises(ValueError):
        frame.pack((1.0, 2.0), rotor)
