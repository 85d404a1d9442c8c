"""A served group's JointState / AxisState encoded in place: the bytes cyclonedds's own serializer makes
of the same sample (the oracle), cycle after cycle, as values, owners and counters change."""

from __future__ import annotations

import math

import numpy as np
import pytest

pytest.importorskip("cyclonedds")

from fieldbus.dds import messages as m
from fieldbus.dds.state_bytes import AxisStateBytes, JointStateBytes


def _cyclone(sample: object) -> bytes:
    raw: bytes = sample.serialize(use_version_2=False)  # type: ignore[attr-defined]
    return raw.ljust((len(raw) + 3) & ~3, b"\x00")


def _floats(rng: np.random.Generator, n: int) -> np.ndarray:
    v = rng.normal(0, 100, n)
    special = np.array([math.nan, math.inf, -math.inf, -0.0, 5e-324])
    mask = rng.random(n) < 0.2
    v[mask] = rng.choice(special, mask.sum())
    return v


@pytest.mark.parametrize(
    "names, roles",
    [
        (["j0", "j1", "j2"], ["position", "velocity", "effort"]),
        (["hip", "knee"], ["position"]),
        (["Gelenk ä", "x" * 33, "", "w"], ["velocity", "effort"]),
        ([], ["position", "velocity"]),
        (["only"], []),
    ],
)
def test_joint_state_bytes_are_cyclonedds_bytes_cycle_after_cycle(names: list[str], roles: list[str]) -> None:
    rng = np.random.default_rng(len(names) * 7 + len(roles))
    enc = JointStateBytes(names, roles)
    for k in range(100):
        stamp = int(rng.integers(0, 2**31 - 1)) * 1_000_000_000 + int(rng.integers(0, 999_999_999))
        values = {r: _floats(rng, len(names)) for r in roles}
        js = m.JointState(header=m.Header(stamp=m.Time.of_ns(stamp), frame_id=""), name=list(names))
        for r in roles:
            setattr(js, r, values[r].tolist())
        assert enc.encode(stamp, values) == _cyclone(js), k


def test_axis_state_bytes_are_cyclonedds_bytes_as_owners_and_counters_change() -> None:
    rng = np.random.default_rng(33)
    n, channels = 3, 5
    enc = AxisStateBytes(n, channels)
    owners = ["", "bench", "operator_ä", "x" * 17, "b"] + [f"client{i}" for i in range(10)]  # > kept layouts
    for k in range(300):
        fresh = rng.random(n) < 0.7
        drive_state = rng.integers(-1, 9, n).astype(np.int8)
        inputs = _floats(rng, n * channels).reshape(n, channels)
        fields = dict(
            cycle=int(rng.integers(0, 2**64 - 1, dtype=np.uint64)),
            safe_stop=bool(rng.random() < 0.5),
            gate=int(rng.integers(0, 4)),
            command_sequence=int(rng.integers(0, 2**63)),
            command_age=int(rng.integers(0, 2**32 - 1)),
            owner=owners[k % len(owners)] if k % 3 else owners[1],
            dropped_sequences=int(rng.integers(0, 2**32 - 1)),
            refused_commands=int(rng.integers(0, 2**32 - 1)),
        )
        stamp = int(rng.integers(0, 2**31 - 1)) * 1_000_000_000 + int(rng.integers(0, 999_999_999))
        st = m.AxisState(
            header=m.Header(stamp=m.Time.of_ns(stamp), frame_id=""),
            fresh=fresh.tolist(),
            drive_state=drive_state.tolist(),
            inputs=inputs.ravel().tolist(),
            all_fresh=bool(fresh.all()),
            **fields,  # type: ignore[arg-type]
        )
        ours = enc.encode(stamp, fresh=fresh, drive_state=drive_state, inputs=inputs, **fields)  # type: ignore[arg-type]
        assert ours == _cyclone(st), k


def test_axis_state_counters_past_uint32_saturate_instead_of_failing_the_cycle() -> None:
    enc = AxisStateBytes(1, 1)
    kw = dict(cycle=1, safe_stop=False, gate=1, command_sequence=1, owner="a")
    ours = enc.encode(
        0,
        fresh=np.ones(1, bool),
        drive_state=np.zeros(1, np.int8),
        inputs=np.zeros((1, 1)),
        command_age=2**40,
        dropped_sequences=2**33,
        refused_commands=2**32,
        **kw,  # type: ignore[arg-type]
    )
    st = m.AxisState(
        fresh=[True],
        drive_state=[0],
        inputs=[0.0],
        all_fresh=True,
        command_age=2**32 - 1,
        dropped_sequences=2**32 - 1,
        refused_commands=2**32 - 1,
        **kw,  # type: ignore[arg-type]
    )
    assert ours == _cyclone(st)
