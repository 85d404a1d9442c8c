"""A served group's per-cycle messages, encoded in place: ``JointState`` and ``AxisState`` bytes from the
image's arrays, without building the IDL samples (``fieldbus.dds.cdr.Layout``).

Their strings and sequence lengths are fixed for a group (its joint names,
its channels), except ``AxisState.owner``: a layout per owner label, made on
the first cycle with that owner. ``tests/unit/test_dds_state_bytes.py``
compares every message with cyclonedds's own serializer of the equivalent
sample.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np
import numpy.typing as npt

from fieldbus.dds import messages as m
from fieldbus.dds.cdr import Layout

U32_MAX = 0xFFFF_FFFF
_OWNERS_KEPT = 8  # AxisState layouts kept, one per owner label seen
_SCALARS = (  # AxisState's numbers, in encode()'s order
    "header.stamp.sec",
    "header.stamp.nanosec",
    "cycle",
    "all_fresh",
    "safe_stop",
    "gate",
    "command_sequence",
    "command_age",
    "dropped_sequences",
    "refused_commands",
)


class JointStateBytes:
    """``sensor_msgs/JointState`` for ``names``, with the ``roles`` (position, velocity, effort) given."""

    def __init__(self, names: list[str], roles: list[str]) -> None:
        n = len(names)
        proto = m.JointState(name=list(names))
        for r in roles:
            setattr(proto, r, [0.0] * n)
        self.layout = Layout(m.JointState, proto)
        self.values = {r: self.layout.array(r) for r in roles} if n else {}

    def encode(self, stamp_ns: int, values: dict[str, npt.NDArray[Any]]) -> bytes:
        """The message stamped ``stamp_ns`` (ns since the Unix epoch), each role's values from ``values``."""
        lay = self.layout
        sec, nanosec = divmod(stamp_ns, 1_000_000_000)
        lay.set("header.stamp.sec", sec)
        lay.set("header.stamp.nanosec", nanosec)
        for role, view in self.values.items():
            view[:] = values[role]
        return lay.bytes()


class AxisStateBytes:
    """``fieldbus_msgs/AxisState`` for ``n`` axes of ``channels`` input channels each."""

    def __init__(self, n: int, channels: int) -> None:
        self.n, self.channels = n, channels
        self._layouts: dict[str, tuple[Layout, dict[str, npt.NDArray[Any]], Callable[..., None]]] = {}
        self._for("")  # made here, not in the first served cycle

    def _for(self, owner: str) -> tuple[Layout, dict[str, npt.NDArray[Any]], Callable[..., None]]:
        got = self._layouts.get(owner)
        if got is None:
            if len(self._layouts) >= _OWNERS_KEPT:
                self._layouts.clear()
            n = self.n
            proto = m.AxisState(
                fresh=[False] * n, drive_state=[0] * n, inputs=[0.0] * (n * self.channels), owner=owner
            )
            lay = Layout(m.AxisState, proto)
            views = {f: lay.array(f) for f in ("fresh", "drive_state", "inputs")} if n else {}
            got = self._layouts[owner] = (lay, views, lay.packer(*_SCALARS))
        return got

    def encode(
        self,
        stamp_ns: int,
        *,
        cycle: int,
        fresh: npt.NDArray[np.bool_],
        drive_state: npt.NDArray[Any],
        inputs: npt.NDArray[np.float64],
        safe_stop: bool,
        gate: int,
        command_sequence: int,
        command_age: int,
        owner: str,
        dropped_sequences: int,
        refused_commands: int,
    ) -> bytes:
        """The message; ``inputs`` row-major (axis, channel); counters past uint32 saturate."""
        lay, views, pack = self._for(owner)
        sec, nanosec = divmod(stamp_ns, 1_000_000_000)
        if views:
            views["fresh"][:] = fresh
            views["drive_state"][:] = drive_state
            views["inputs"][:] = inputs.ravel()
        pack(
            sec,
            nanosec,
            cycle,
            bool(fresh.all()),
            safe_stop,
            gate,
            command_sequence,
            min(command_age, U32_MAX),
            min(dropped_sequences, U32_MAX),
            min(refused_commands, U32_MAX),
        )
        return lay.bytes()
