"""Bit-level entries of the process image: the C codec, one uint64 per word (numpy), one entry at a time.

The MIT-mode CAN frame (CubeMars AK80-9 map) is mostly 12-bit fields: the
command has four (velocity, kp, kd, torque), the reply two (velocity,
current), all scaled. Three ways to code them, in one run:

- ``c``: the default, ``fieldbus._codec`` (its bit-level columns);
- ``word``: the numpy engine, every bit-level entry inside one 8-byte word
  of the row coded through that word as a little-endian uint64 (``_BitWord``);
- ``per-entry``: the numpy engine with ``_bits`` put back to one
  ``_BitField`` per entry (a handful of ufuncs per byte each entry touches).

All three give the same bytes and values (asserted before timing).
Interleaved rounds; ratios are taken within each round.

    python benchmarks/bit_fields.py [--rounds 15] [--json]
"""

from __future__ import annotations

import argparse
import json
import sys
from collections.abc import Callable
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks._common import interleaved, machine_note, table
from fieldbus import PDO_MAPS
from fieldbus.core.pdo import load_drive_map
from fieldbus.core.pdo.image import ProcessImage, _BitField, _BitWord
from fieldbus.core.pdo.layout import layout

MAP = Path(PDO_MAPS) / "cubemars_ak80_9_mit.yaml"
HOWS = ("c", "word", "per-entry")


def _image(axes: int, how: str) -> ProcessImage:
    img = ProcessImage(layout(load_drive_map(MAP)), axes, engine="c" if how == "c" else "numpy")
    if how == "per-entry":
        for d in (img.outputs, img.inputs):
            fields: list[_BitField] = []
            for b in d._bits:
                fields += [bf for bf, _ in b.fields] if isinstance(b, _BitWord) else [b]
            d._bits = list(fields)
    rng = np.random.default_rng(1)
    for name in ("position", "velocity", "kp", "kd", "torque"):
        img.outputs[name][:] = rng.uniform(-1.0, 1.0, axes) + (2.0 if name in ("kp", "kd") else 0.0)
    img.inputs.wire[:] = rng.integers(0, 256, img.inputs.wire.shape, dtype=np.uint8)
    return img


def _same(images: list[ProcessImage]) -> None:
    for img in images:
        img.outputs.to_wire()
        img.inputs.from_wire()
    a = images[0]
    for b in images[1:]:
        assert np.array_equal(a.outputs.wire, b.outputs.wire)
        assert a.inputs.values.tobytes() == b.inputs.values.tobytes()


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rounds", type=int, default=15)
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args(argv)
    groups: dict[str, dict[str, Callable[[], object]]] = {}
    for axes in (3, 12):
        imgs = {how: _image(axes, how) for how in HOWS}
        assert imgs["c"].outputs.engine == "c" and imgs["word"].outputs.engine == "numpy"
        _same(list(imgs.values()))
        for how, img in imgs.items():
            groups.setdefault(f"{axes} axes, command to_wire", {})[how] = img.outputs.to_wire
            groups.setdefault(f"{axes} axes, reply from_wire", {})[how] = img.inputs.from_wire
    res = interleaved(groups, args.rounds, 0.05)
    rows = [
        [
            g,
            *(f"{s.median_us(h):.1f}" for h in HOWS),
            f"{s.ratio('word', 'c'):.0f}",
            f"{s.ratio('per-entry', 'word'):.2f}",
        ]
        for g, s in res.items()
    ]
    if args.json:
        print(json.dumps({"machine": machine_note(), "rows": rows}))
        return 0
    print(f"# bit-level entries, MIT-mode frames ({machine_note()}), {args.rounds} rounds\n")
    print(table(["case", "c [µs]", "word [µs]", "per-entry [µs]", "word / c", "per-entry / word"], rows))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
