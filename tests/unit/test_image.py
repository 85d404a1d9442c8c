"""Process image: vectorised pack/unpack against the scalar reference codec."""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import pytest
import yaml
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from fieldbus.core.pdo import drive_map_from_text
from fieldbus.core.pdo.image import ProcessImage
from fieldbus.core.pdo.layout import get_value, layout, set_value
from fieldbus.platform.allocs import net_blocks

ENGINES = ["numpy", "auto"]  # "auto" is the C codec where it is built (checked below)

INT_TYPES = ["int8", "int16", "int32", "int64", "uint8", "uint16", "uint32", "uint64"]


@st.composite
def channel_lists(draw: Any, base_index: int, bit: int) -> tuple[list[dict[str, Any]], int]:
    """Random entries for one PDO starting at ``bit``: ints, floats, bools, named bitN, gaps."""
    chans: list[dict[str, Any]] = []
    for k in range(draw(st.integers(1, 10))):
        kind = draw(st.sampled_from(["int", "int", "float", "bool", "bits", "gap", "scaled"]))
        ch: dict[str, Any] = {"index": base_index + k, "sub_index": draw(st.integers(0, 3))}
        if kind == "gap":
            ch = {"index": 0, "sub_index": 0, "type": f"bit{draw(st.integers(1, 12))}"}
        elif kind == "bool":
            ch["type"] = "bool"
            if draw(st.booleans()):
                ch["mask"] = 1 << (bit % 8)
        elif kind == "bits":
            ch["type"] = f"bit{draw(st.integers(2, 7))}"
        elif kind == "float":
            if bit % 8:  # floats must start on a byte: pad
                chans.append({"index": 0, "sub_index": 0, "type": f"bit{8 - bit % 8}"})
                bit += 8 - bit % 8
            ch["type"] = draw(st.sampled_from(["float", "double"]))
        else:
            t = draw(st.sampled_from(INT_TYPES if bit % 8 == 0 else [t for t in INT_TYPES if "64" not in t]))
            ch["type"] = t
            if kind == "scaled":
                ch["factor"] = draw(st.sampled_from([0.001, 2.0, -0.5, 1e-6]))
                ch["offset"] = draw(st.sampled_from([0.0, 3.0, -7.5]))
        chans.append(ch)
        bits = {"bool": 1, "float": 32, "double": 64}.get(ch["type"]) or (
            int(ch["type"][3:]) if ch["type"].startswith("bit") else int(ch["type"].lstrip("uint"))
        )
        bit += bits
    return chans, bit


@st.composite
def drive_maps(draw: Any) -> str:
    doc: dict[str, Any] = {"vendor_id": 1, "product_id": 2, "rpdo": [], "tpdo": []}
    for key, base in (("rpdo", 0x1600), ("tpdo", 0x1A00)):
        bit = 0
        for p in range(draw(st.integers(1, 3))):
            chans, bit = draw(channel_lists(0x2000 + 0x100 * p, bit))
            doc[key].append({"index": base + p, "channels": chans})
    return yaml.safe_dump(doc)


def random_raw(rng: np.random.Generator, ch: Any) -> float | int | bool:
    dt = ch.type
    if dt.name == "bool":
        return bool(rng.integers(0, 2))
    if dt.is_float:
        return float(np.float32(rng.normal() * 1e3)) if dt.bits == 32 else float(rng.normal() * 1e6)
    raw = int.from_bytes(rng.bytes(8), "little") & ((1 << dt.bits) - 1)
    return raw - (1 << dt.bits) if dt.signed and raw >> (dt.bits - 1) else raw


@settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(
    text=drive_maps(), n=st.integers(1, 5), seed=st.integers(0, 2**32 - 1), engine=st.sampled_from(ENGINES)
)
def test_roundtrip_matches_scalar_codec(text: str, n: int, seed: int, engine: str) -> None:
    drive = drive_map_from_text(text)
    rng = np.random.default_rng(seed)
    byte_pdos = all(p.bits % 8 == 0 for p in (*drive.rpdo, *drive.tpdo))
    for align in (1, 8) if byte_pdos else (1,):
        lay = layout(drive, pdo_align=align)
        for dl in (lay.outputs, lay.inputs):
            pick = (lambda pi: pi.outputs) if dl is lay.outputs else (lambda pi: pi.inputs)
            img = pick(ProcessImage(lay, n, engine=engine))
            # 1. scalar-encode random raw values into a reference wire image; gaps stay zero
            ref = bytearray(n * dl.size)
            raws = []
            for axis in range(n):
                row = {}
                for e in dl.channels:
                    v = random_raw(rng, e.channel)
                    set_value(ref, e, v, base=axis * dl.size)
                    row[e.name] = get_value(ref, e, base=axis * dl.size)
                raws.append(row)
            # 2. vectorised decode of the reference bytes
            img.wire[:] = np.frombuffer(bytes(ref), dtype=np.uint8).reshape(n, dl.size)
            img.from_wire()
            for e in dl.channels:
                ch = e.channel
                got = img.values[e.name]
                want = np.array([r[e.name] for r in raws])
                if ch.scaled:
                    if dl is lay.inputs:
                        np.testing.assert_allclose(
                            got, want.astype(float) * ch.factor + ch.offset, rtol=1e-12
                        )
                    else:
                        np.testing.assert_allclose(
                            got, (want.astype(float) - ch.offset) / ch.factor, rtol=1e-9
                        )
                else:
                    assert np.array_equal(got.astype(want.dtype), want), (e.name, got, want)
            # 3. vectorised encode of the decoded values (in a fresh image) reproduces the bytes
            fresh = pick(ProcessImage(lay, n, engine=engine))
            for name in dl.names:
                fresh.values[name] = img.values[name]
            fresh.to_wire()
            if not any(e.channel.scaled and e.channel.type.bits == 64 for e in dl.channels):
                assert fresh.wire.tobytes() == bytes(ref)


def _image(text: str, n: int = 3, engine: str = "auto") -> ProcessImage:
    return ProcessImage(layout(drive_map_from_text(text)), n, engine=engine)


SCALED = """
vendor_id: 1
product_id: 2
rpdo:
  - index: 0x1600
    channels:
      - {index: 0x6040, sub_index: 0, type: uint16}
      - {index: 0x607a, sub_index: 0, type: int32, name: target_position, factor: 1000.0, unit: rad, default: 5}
      - {index: 0x6071, sub_index: 0, type: int16, name: target_torque, factor: 10.0, offset: 1.0}
tpdo:
  - index: 0x1a00
    channels:
      - {index: 0x6064, sub_index: 0, type: int32, name: position, factor: 0.001, offset: 0.5}
"""


@pytest.mark.parametrize("engine", ENGINES)
def test_scaled_outputs_round_saturate_and_hold_on_nan(engine: str) -> None:
    img = _image(SCALED, engine=engine)
    out = img.outputs
    # default 5 (raw) shows as (5 - 0) / 1000 rad before anything is written
    assert np.allclose(out["target_position"], 0.005)
    out["target_position"][:] = [0.0014, -0.0016, np.nan]
    out["target_torque"][:] = [1e9, -1e9, 2.04]
    out.to_wire()
    assert list(out.raw("target_position")) == [1, -2, 5]  # rounded; NaN keeps the default
    assert list(out.raw("target_torque")) == [32767, -32768, 21]  # saturated; 10*2.04+1 = 21.4 -> 21
    out["target_position"][:] = [np.nan, 0.003, 0.004]
    out.to_wire()
    assert list(out.raw("target_position")) == [1, 3, 4]  # NaN keeps the raw value sent last


def test_scaled_inputs_use_factor_then_offset() -> None:
    img = _image(SCALED)
    img.inputs.wire[:] = np.array(
        [[0xE8, 0x03, 0, 0], [0x18, 0xFC, 0xFF, 0xFF], [0, 0, 0, 0]], dtype=np.uint8
    )
    img.inputs.from_wire()
    assert np.allclose(img.inputs["position"], [1.5, -0.5, 0.5])


def test_wire_rows_are_contiguous_views_of_values() -> None:
    img = _image(SCALED)
    out = img.outputs
    assert out.wire.shape == (3, 8) and out.wire[0].flags["C_CONTIGUOUS"]
    out["controlword"][:] = [6, 7, 15]  # unscaled byte-aligned: written straight into the wire bytes
    assert list(out.wire[:, 0]) == [6, 7, 15]


def test_c_codec_is_built_here() -> None:
    """The C codec builds with the project's install (gcc and Python headers are on every machine here)."""
    assert _image(SCALED).outputs.engine == "c"
    assert _image(SCALED, engine="numpy").outputs.engine == "numpy"


@pytest.mark.parametrize("engine", ENGINES)
def test_engines_agree_on_nan_saturation_and_rounding(engine: str) -> None:
    img = _image(SCALED, engine=engine)
    out = img.outputs
    out["target_position"][:] = [2.5e-3, -2.5e-3, np.nan]  # 2.5 and -2.5 counts: half to even
    out["target_torque"][:] = [np.inf, -np.inf, 0.25]
    out.to_wire()
    assert list(out.raw("target_position")) == [2, -2, 5]
    assert list(out.raw("target_torque")) == [32767, -32768, 4]  # 10*0.25+1 = 3.5 -> 4


@pytest.mark.parametrize("engine", ENGINES)
def test_cycle_allocates_nothing(engine: str) -> None:
    text = SCALED.replace(
        "      - {index: 0x6071",
        "      - {index: 0x2000, sub_index: 1, type: bool, mask: 1}\n"
        "      - {index: 0, sub_index: 0, type: bit7}\n"
        "      - {index: 0x2001, sub_index: 1, type: int64, name: big, factor: 2.0}\n      - {index: 0x6071",
    )
    img = _image(text, 64, engine=engine)
    q = np.linspace(-1, 1, 64)
    tp = img.outputs["target_position"]

    img.outputs["big"][:] = 1e300  # the 64-bit saturation path (float64 cannot hold INT64_MAX)

    def cycle() -> None:
        np.copyto(tp, q)
        img.outputs.to_wire()
        img.inputs.from_wire()

    assert net_blocks(cycle, cycles=5000) <= 2
    assert math.isclose(float(img.outputs["target_position"][0]), -1.0)


def test_net_blocks_sees_a_leak() -> None:
    leak: list[bytes] = []
    assert net_blocks(lambda: leak.append(bytes(100)), cycles=500, warmup=10) >= 500
