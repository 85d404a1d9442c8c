"""The guard at a family codec's boundary: a NaN or infinite command value is refused, never packed.

The output rules (:mod:`fieldbus.core.output_rules`) keep such values out of
the image; a codec that packs frames itself (Damiao, CubeMars) checks again
with :func:`finite`.
"""

from __future__ import annotations

import math

from fieldbus.errors import FieldbusError


class UnsafeOutputError(FieldbusError, ValueError):
    """A codec was handed a command value that did not pass the rules (NaN or infinite): refused, not packed."""


def finite(name: str, value: float) -> float:
    """``value`` when finite; otherwise :class:`UnsafeOutputError` (the guard at a family codec's boundary)."""
    if not math.isfinite(value):
        raise UnsafeOutputError(
            f"command '{name}' is {value}: refused at the codec (the output rules keep NaN out)"
        )
    return value
