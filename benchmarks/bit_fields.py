"""Bit-level entries of the process image: one uint64 per 8-byte word against one entry at a time.

The MIT-mode CAN frame (CubeMars AK80-9 map) is mostly 12-bit fields: the
command has four (velocity, kp, kd, torque), the reply two (velocity,
current). ``ProcessImage`` codes every bit-level entry that lies inside one
8-byte word of the row through that word as a little-endian uint64
(``_BitWord``); the contender ``per-entry`` is the same image with its
``_bits`` list put back to one ``_BitField`` per entry (the path every entry
took before, and still takes when it crosses a word). Both give the same
bytes and values (asserted before timing). Interleaved rounds; the ratio is
taken within each round.

    python benchmarks/bit_fields.py [--rounds 15] [--json]
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks._common import interleaved, machine_note, table
from fieldbus import PDO_MAPS
from fieldbus.core.pdo import load_drive_map
from fieldbus.core.pdo.image import ProcessImage, _BitField, _BitWord
from fieldbus.core.pdo.layout import layout

MAP = Path(PDO_MAPS) / "cubemars_ak80_9_mit.yaml"


def _image(axes: int, per_entry: bool) -> ProcessImage:
    img = ProcessImage(layout(load_drive_map(MAP)), axes)
    for d in (img.outputs, img.inputs):
        if per_entry:
            fields: list[_BitField] = []
            for b in d._bits:
                fields += [bf for bf, _ in b.fields] if isinstance(b, _BitWord) else [b]
            d._bits = list(fields)
    rng = np.random.default_rng(1)
    for name in ("position", "velocity", "kp", "kd", "torque"):
        img.outputs[name][:] = rng.uniform(-1.0, 1.0, axes) + (2.0 if name in ("kp", "kd") else 0.0)
    img.inputs.wire[:] = rng.integers(0, 256, img.inputs.wire.shape, dtype=np.uint8)
    return img


def _same(a: ProcessImage, b: ProcessImage) -> None:
    for img in (a, b):
        img.outputs.to_wire()
        img.inputs.from_wire()
    assert np.array_equal(a.outputs.wire, b.outputs.wire)
    assert a.inputs.values.tobytes() == b.inputs.values.tobytes()


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rounds", type=int, default=15)
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args(argv)
    groups = {}
    for axes in (3, 12):
        word, entry = _image(axes, False), _image(axes, True)
        _same(word, entry)
        for name, img in (("word", word), ("per-entry", entry)):
            groups.setdefault(f"{axes} axes, command to_wire", {})[name] = img.outputs.to_wire
            groups.setdefault(f"{axes} axes, reply from_wire", {})[name] = img.inputs.from_wire
    res = interleaved(groups, args.rounds, 0.05)
    rows = [
        [
            g,
            f"{s.median_us('word'):.1f}",
            f"{s.median_us('per-entry'):.1f}",
            f"{s.ratio('per-entry', 'word'):.2f}",
        ]
        for g, s in res.items()
    ]
    if args.json:
        print(json.dumps({"machine": machine_note(), "rows": rows}))
        return 0
    print(f"# bit-level entries, MIT-mode frames ({machine_note()}), {args.rounds} rounds\n")
    print(table(["case", "word [µs]", "per-entry [µs]", "per-entry / word"], rows))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
