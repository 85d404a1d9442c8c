"""The ESC chain's lean per-frame path against its general one (the reference), frame by frame.

Two chains of demo joints (``fieldbus/data/demo_joint.yaml``) get the same
frames at the same times: one with ``lean=True`` (cached datagram offsets,
byte compares instead of numpy reductions, slice copies, the drive link in
C, the drive bank's idle and CSP cycles one C call each), one with
``lean = False`` and
``drive_bank.motion_kernel`` None while it runs (every drive path numpy).
After every frame the replies (bytes, so working counters too), the chains'
memory (every ESC register: AL state and status code, watchdog status, error
counters, the process data) and every array of the drive bank (CiA 402
state, positions, statuswords, fault codes...) must be equal; the objects
of every slave's dictionary (diagnosis history included) now and then and at
the end. The master side: the cycle frame of the in-process backend (LRW
plus the DC FRMW of 0x0910), random outputs through every CiA 402
transition, other modes, and faults: lost frames, corrupted working
counters, bit errors on a cable, a link flap, the process-data watchdog
running out, a power cycle, a drive fault, other frame layouts in between
(register reads, broadcast, a VLAN tag).

This compares the emulator with itself: the reference is its own general
path (which the veth tests judge against pysoem), not an outside oracle.
"""

from __future__ import annotations

import dataclasses
import struct
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from fieldbus.core.cia402 import State402
from fieldbus.core.dc.model import DcRegister
from fieldbus.core.ecat import Command, Datagram, build_master_frame
from fieldbus.core.pdo.load import load_drive_map
from sim_slaves import drive_bank
from sim_slaves.ethercat import AlState, EscChain, pdplan
from sim_slaves.ethercat.bringup import STATION_BASE, ProcessDataPlan, bring_up

DEMO = Path(__file__).resolve().parents[2] / "fieldbus" / "data" / "demo_joint.yaml"
OUT = struct.Struct("<Hihb")  # the demo joint's outputs: controlword, target position, target torque, mode
CYCLE_NS = 1_000_000
CSP, CSV, CST = 8, 9, 10
ENABLE = (0x00, 0x06, 0x07, 0x0F)


@contextmanager
def _kernel(kernel: Any) -> Iterator[None]:
    """``drive_bank.motion_kernel`` set to ``kernel`` for a while."""
    was = drive_bank.motion_kernel
    drive_bank.motion_kernel = kernel
    try:
        yield
    finally:
        drive_bank.motion_kernel = was


class Pair:
    """A lean chain and a reference chain fed the same frames; every step compared."""

    def __init__(self, axes: int) -> None:
        maps = [load_drive_map(DEMO)] * axes
        self.lean = EscChain.from_maps(maps)
        self.ref = EscChain.from_maps(maps)
        self.ref.lean = False
        assert self.lean.lean and not self.ref.lean and self.lean.bank.lean and not self.ref.bank.lean
        self.axes = axes
        self.now = 0
        self.frames = 0
        self.plan = self.both(bring_up)

    def both(self, call: Callable[[EscChain], Any]) -> Any:
        """``call`` on the lean chain, then on the reference (numpy drive paths); their results, equal."""
        got = call(self.lean)
        with _kernel(None):
            want = call(self.ref)
        if not isinstance(got, ProcessDataPlan):
            assert got == want
        self.check()
        return got

    def bring_up(self) -> None:
        self.plan = self.both(lambda c: bring_up(c, self.now))

    def frame(self, frame: bytes) -> bytes | None:
        """One frame through both chains at the current time; the reply (None: lost)."""
        self.frames += 1
        replies = []
        for chain, kernel in ((self.lean, drive_bank.motion_kernel), (self.ref, None)):
            with _kernel(kernel):
                replies.append(chain.process(frame, self.now))
        assert replies[0] == replies[1], f"frame {self.frames}: replies differ"
        self.check()
        return replies[0]

    def cycle(self, outputs: list[tuple[int, int, int, int]]) -> bytes | None:
        """The cycle frame as the in-process backend sends it: the LRW, then the FRMW of 0x0910."""
        self.now += CYCLE_NS
        data = b"".join(OUT.pack(*o) for o in outputs).ljust(self.plan.out_bytes, b"\0")
        lrw = Datagram(Command.LRW, 0, 0, data + bytes(self.plan.in_bytes))
        frmw = Datagram.physical(Command.FRMW, STATION_BASE, DcRegister.SYSTEM_TIME, bytes(8))
        return self.frame(build_master_frame([lrw, frmw]))

    def check(self) -> None:
        a, b = self.lean, self.ref
        where = f"after frame {self.frames}"
        assert a.memory.tobytes() == b.memory.tobytes(), f"{where}: ESC memory differs"
        for name, value in vars(a.bank).items():
            if isinstance(value, np.ndarray) and name != "_target":  # (the C cycle's scratch row: no state)
                other = getattr(b.bank, name)
                assert value.tobytes() == other.tobytes(), f"{where}: bank.{name} {value} != {other}"
        for name in ("_pending", "_last_out_ns", "_last_step_ns", "_stepped", "_code_seen"):
            assert getattr(a, name).tobytes() == getattr(b, name).tobytes(), f"{where}: chain.{name}"
        assert a._lockstep_ns == b._lockstep_ns
        assert _faults(a) == _faults(b) and a.pending_delay == b.pending_delay, where
        for sa, sb in zip(a.slaves, b.slaves, strict=True):
            assert (sa.state, sa.last_output_ns, sa.fast) == (sb.state, sb.last_output_ns, sb.fast), where

    def check_od(self) -> None:
        """Every object of every slave's dictionary (diagnosis history, the drives' objects)."""
        for sa, sb in zip(self.lean.slaves, self.ref.slaves, strict=True):
            assert _od(sa.od) == _od(sb.od), f"after frame {self.frames}: {sa.name}'s objects differ"


def _faults(chain: EscChain) -> tuple[object, ...]:
    """A chain's pending fault injections, its bit-error generator by its state."""
    f = chain.faults
    rng = f.link_rng.getstate() if f.link_rng is not None else None
    return (dataclasses.replace(f, link_rng=None), rng)


def _od(od: Any) -> list[tuple[int, int, object]]:
    out: list[tuple[int, int, object]] = []
    for index in od.indices():
        for sub in od.subindices(index):
            try:
                out.append((index, sub, od.get_value(index, sub)))
            except Exception as e:  # an object without a number (a string, a domain): its error's kind
                out.append((index, sub, type(e).__name__))
    return out


def _script(rng: np.random.Generator, axes: int, cycles: int) -> Iterator[list[tuple[int, int, int, int]]]:
    """Outputs per cycle: every CiA 402 transition (enable, disable operation, shutdown, quick stop,
    disable voltage, fault reset), CSP on random targets, CSV/CST for a while, random controlwords.
    Targets as offsets from the actual position (the loop adds it, as a master holds a joint)."""
    phases: list[tuple[int, int]] = [(cw, CSP) for cw in ENABLE for _ in range(3)]
    phases += [(0x0F, CSP)] * 60 + [(0x07, CSP)] * 5 + [(0x0F, CSP)] * 20 + [(0x06, CSP)] * 5
    phases += [(cw, CSP) for cw in ENABLE[1:] for _ in range(3)] + [(0x0F, CSP)] * 20
    phases += [(0x02, CSP)] * 15 + [(0x00, CSP)] * 5 + [(0x80, CSP)] * 2
    phases += [(cw, CSV) for cw in ENABLE for _ in range(3)] + [(0x0F, CSV)] * 20
    phases += [(0x0F, CST)] * 20 + [(0x0F, CSP)] * 40 + [(0x00, CSP)] * 10
    k = loop = 0
    while k < cycles:
        loop += 1
        wild = loop % 2 == 0  # every second pass with random controlwords and modes mixed in
        for cw, mode in phases:
            if wild and rng.random() < 0.03:  # now and then a random controlword on one drive
                cws = [cw] * axes
                cws[int(rng.integers(axes))] = int(rng.integers(0, 0x10000))
            else:
                cws = [cw] * axes
            pos = rng.integers(-300, 300, axes)  # a step from where the joint is (now and then far: a fault)
            if wild and rng.random() < 0.01:
                pos = pos + rng.integers(-200000, 200000, axes)
            torque = rng.integers(-200, 200, axes)
            modes = [mode] * axes
            if (
                wild and rng.random() < 0.02
            ):  # now and then a mode of any byte (negative: manufacturer-specific)
                modes[int(rng.integers(axes))] = int(rng.integers(-128, 128))
            yield [(cws[i], int(pos[i]), int(torque[i]), modes[i]) for i in range(axes)]
            k += 1
            if k >= cycles:
                return


def _vlan(frame: bytes) -> bytes:
    return frame[:12] + b"\x81\x00\x00\x05" + frame[12:]


def _fault(pair: Pair, k: int, rng: np.random.Generator) -> None:
    """The fault (or other frame) of cycle ``k``, on both chains."""
    at = k % 97
    n = pair.axes
    if at == 11:
        pair.both(lambda c: c.drop_frames(1))
    elif at == 17:
        pair.both(lambda c: c.drop_frames(2, process_data=True))
        pair.frame(build_master_frame([Datagram.physical(Command.BRD, 0, 0x0130, bytes(2))]))
    elif at == 23:
        pair.both(lambda c: c.corrupt_wkc(-1, 2))
    elif at == 29 and n > 1:
        pair.both(lambda c: c.bit_errors(0, 0.3, seed=k, frames=6))
    elif at == 37 and n > 1:
        pair.both(lambda c: c.flap_link(n - 2))
    elif at == 41:  # the master stalls: the process-data watchdog (100 ms) runs out, then it comes back
        pair.now += 150 * CYCLE_NS
        if k % 2:  # the I/O layer's tick finds it, else the next frame
            pair.both(lambda c: c.tick(pair.now))
        pair.cycle([(0x0F, 0, 0, CSP)] * n)
        pair.bring_up()
    elif at == 53:
        slave = int(rng.integers(n))
        pair.both(lambda c: c.power_cycle(slave))
        pair.cycle([(0x0F, 0, 0, CSP)] * n)  # answered by the others only
        pair.bring_up()
    elif at == 61:
        slot = int(rng.integers(n))
        pair.both(lambda c: c.bank.drives[slot].inject_fault(0x2310))
    elif at == 67:  # other frame layouts in between: register reads, a VLAN-tagged cycle frame
        reads = [Datagram.physical(Command.FPRD, STATION_BASE + i, 0x0130, bytes(6)) for i in range(n)]
        pair.frame(build_master_frame(reads))
        pair.frame(_vlan(build_master_frame([Datagram.physical(Command.APRD, 0, 0x0440, bytes(2))])))
    elif at == 71:
        pair.both(lambda c: c.clear_faults())


@pytest.mark.parametrize(("axes", "c_paths"), [(3, True), (12, True), (3, False)])
def test_the_lean_path_answers_every_frame_as_the_reference(
    axes: int, c_paths: bool, monkeypatch: pytest.MonkeyPatch
) -> None:
    """``c_paths`` False: the lean path where the C extensions are not built (their numpy fallbacks)."""
    if not c_paths:
        monkeypatch.setattr(drive_bank, "motion_kernel", None)
        monkeypatch.setattr(pdplan, "pdlink", None)
    pair = Pair(axes)
    rng = np.random.default_rng(axes)
    lost = 0
    states: set[int] = set()
    for k, outputs in enumerate(_script(rng, axes, 1200)):
        _fault(pair, k, rng)
        actual = pair.lean.bank.position_counts.tolist()
        lost += pair.cycle([(cw, actual[i] + p, t, m) for i, (cw, p, t, m) in enumerate(outputs)]) is None
        states.update(pair.lean.bank.state.tolist())
        if k % 100 == 0:
            pair.check_od()
    pair.check_od()
    # the run went where it should: frames lost, drives through enabled, quick stop and fault
    assert lost >= 10
    want = {State402.OPERATION_ENABLED, State402.QUICK_STOP_ACTIVE, State402.FAULT}
    assert {int(s) for s in want} <= states, states
    assert all(s.state == AlState.OP for s in pair.lean.slaves)


def test_frames_of_one_length_and_header_but_other_datagrams_are_taken_apart_again() -> None:
    """The offsets cache keys on the frame's length and headers, then checks every datagram's command
    and length: a frame of the same size with other datagrams, or a tag, is laid out anew."""
    pair = Pair(3)

    def aprd(*sizes: int) -> bytes:
        return build_master_frame(
            [Datagram.physical(Command.APRD, -i, 0x0130, bytes(n)) for i, n in enumerate(sizes)]
        )

    one, two = aprd(20), aprd(4, 4)  # one datagram of 20 bytes, two of 4: the same EtherCAT length
    assert len(one) == len(two) and one[12:16] == two[12:16]
    tagged, padded = _vlan(aprd(6)), aprd(10)
    assert len(padded) == len(tagged)
    replies = [pair.frame(f) for f in (one, two, one, aprd(6), tagged, padded, tagged, two)]
    assert all(r is not None for r in replies)
    assert replies[0] == replies[2] and replies[1] == replies[7]  # register reads: the same answer again
    assert replies[1] != replies[0]
    # every frame answered as from its own layout: two datagrams, each counted by its slave
    second = replies[1]
    assert second is not None
    assert second[30:32] == second[46:48] == b"\x01\x00"  # WKC after 16 + 10 + 4 and 32 + 10 + 4 bytes


def test_the_c_paths_under_comparison_are_built() -> None:
    """The lean path's C parts (pip install -e '.[all]' builds them): without them the comparison above
    would only see the numpy fallbacks."""
    assert pdplan.pdlink is not None, "sim_slaves._pdlink is not built (python setup.py build_ext --inplace)"
    assert hasattr(drive_bank.motion_kernel, "Bank"), "sim_slaves._motion (with Bank) is not built"
