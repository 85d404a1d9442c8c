"""The clean cycle's shortcuts decide as the full rules do: OutputRules' and DriveFaultWatch's fast paths
against the same objects forced onto their full path, over random adversarial command sequences
(NaN, +-inf, out of the window, engaged and not, faults on stale rows)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from fieldbus.core import kernels
from fieldbus.core.drivefault import DriveFaultWatch
from fieldbus.core.output_rules import OutputRules, channel_limits
from fieldbus.core.pdo import drive_map_from_text
from fieldbus.core.pdo.image import ProcessImage
from fieldbus.core.pdo.layout import layout

MAP = """
name: joint
vendor_id: 1
product_id: 2
profile: cia402
sdo:
  - {index: 0x607D, sub_index: 1, type: int32, value: -20000}
  - {index: 0x607D, sub_index: 2, type: int32, value: 40000}
rpdo:
  - index: 0x1600
    channels:
      - {index: 0x6040, sub_index: 0, type: uint16}
      - {index: 0x607A, sub_index: 0, type: int32, factor: 10000.0, unit: rad}
      - {index: 0x6071, sub_index: 0, type: int16, factor: 1000.0, unit: N·m}
tpdo:
  - index: 0x1A00
    channels:
      - {index: 0x6041, sub_index: 0, type: uint16}
      - {index: 0x6061, sub_index: 0, type: int8}
"""

N = 4


def _rules(text: str, quick: bool) -> tuple[ProcessImage, OutputRules]:
    drive = drive_map_from_text(text, "joint.yaml")
    img = ProcessImage(layout(drive), N)
    lim = channel_limits(drive, img.layout.outputs, 0.001)
    inp = img.inputs.values
    rules = OutputRules("g", img.outputs, lim, inp["statusword"], inp["modes_of_operation_display"])
    if not quick:
        for b in rules.blocks:
            b.quick = False
    return img, rules


def _command(rng: np.random.Generator) -> float:
    k = rng.integers(0, 12)
    if k == 0:
        return math.nan
    if k == 1:
        return math.inf
    if k == 2:
        return -math.inf
    if k == 3:
        return float(rng.uniform(-50.0, 50.0))  # out of 0x607D's window (-2..4 rad) often
    return float(rng.uniform(-1.0, 1.0))


@pytest.mark.parametrize(
    ("extra", "quick_on"),
    [("", True), ("limits: off\n", True), ("limits:\n  target_position: {max_rate: 200.0}\n", False)],
    ids=["window", "no-window", "step"],
)
@pytest.mark.parametrize("native", [True, False], ids=["c-kernel", "numpy"])
def test_output_rules_fast_path_decides_as_the_full_path(
    extra: str, quick_on: bool, native: bool, monkeypatch: pytest.MonkeyPatch
) -> None:
    if native and not kernels.native:
        pytest.skip("fieldbus._codec is not built (numpy path only)")
    monkeypatch.setattr(kernels, "native", native)  # the clean cycle's test: C kernel or numpy
    fast_img, fast = _rules(MAP + extra, quick=True)
    full_img, full = _rules(MAP + extra, quick=False)
    assert [b.quick for b in fast.blocks] == [quick_on]  # the shortcut is (not) taken on this map
    rng = np.random.default_rng(35)
    clean_runs = 0
    for cycle in range(3000):
        adversarial = rng.random() < 0.3  # mostly clean streaks, so the fast path runs between refusals
        row = [_command(rng) if adversarial else float(rng.uniform(-0.05, 0.05)) for _ in range(N)]
        torque = [_command(rng) if adversarial else 0.0 for _ in range(N)]
        sw = rng.choice([0x0027, 0x0037, 0x0040], size=N).astype(np.uint16)
        for img in (fast_img, full_img):
            img.outputs["target_position"][:] = row
            img.outputs["target_torque"][:] = torque
            img.inputs["statusword"][:] = sw
            img.inputs["modes_of_operation_display"][:] = 8
        got = []
        for img, rules in ((fast_img, fast), (full_img, full)):
            hit = rules.apply()
            ev = rules.events(cycle) if hit else []
            if not hit:
                rules.settle()
            img.outputs.to_wire()
            got.append((hit, repr(ev), bytes(img.outputs.wire), rules.counts.tolist()))  # repr: NaN == NaN
        clean_runs += not got[0][0]
        assert got[0] == got[1], f"cycle {cycle}"
        for r in range(N):
            assert repr(fast.last_clamp(r)) == repr(full.last_clamp(r))
    assert 500 < clean_runs < 3000  # both paths were exercised


@pytest.mark.parametrize("native", [True, False], ids=["c-kernel", "numpy"])
def test_drive_fault_watch_fast_path_reports_as_a_plain_model(
    native: bool, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Oracle: a per-row Python model of the watch (an edge is a fresh row whose fault bit rose)."""
    if native and not kernels.native:
        pytest.skip("fieldbus._codec is not built (numpy path only)")
    monkeypatch.setattr(kernels, "native", native)  # the clean cycle's fault-bit test: C kernel or numpy
    img = ProcessImage(layout(drive_map_from_text(MAP, "joint.yaml")), N)
    watch = DriveFaultWatch("g", img, tuple(f"j{i}" for i in range(N)))
    in_fault = [False] * N
    rng = np.random.default_rng(7)
    events = 0
    for cycle in range(4000):
        faulty = rng.random() < 0.05  # mostly clean cycles: the fast path, between faults and recoveries
        sw = np.where(rng.random(N) < (0.5 if faulty else 0.0), 0x0008, 0x0027).astype(np.uint16)
        fresh = rng.random(N) < 0.9
        img.inputs["statusword"][:] = sw
        got = [f.axis for f in watch.step(fresh, cycle)]
        want = []
        for r in range(N):
            now = bool(sw[r] & 0x0008)
            if fresh[r]:
                if now and not in_fault[r]:
                    want.append(r)
                in_fault[r] = now
        assert got == want, f"cycle {cycle}"
        assert watch.in_fault.tolist() == in_fault
        events += len(got)
    assert events > 10  # faults were raised, and on stale rows held back until fresh
