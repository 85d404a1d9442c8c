"""``--record FILE`` on ``fieldbus run`` and ``fieldbus soak`` (sim backend), read back with
``fieldbus.recording.load``: every cycle there, values the run reported."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from fieldbus.cli import main
from fieldbus.commands.demo import DEMO_MAP
from fieldbus.recording import load
from fieldbus.recording.schema import NO_VALUE

pytestmark = pytest.mark.timeout(300)


def test_run_records_every_cycle(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    net = tmp_path / "net.yaml"
    net.write_text(
        "cycle_time_us: 1000\nbuses:\n  - {name: arm, type: ethercat, interface: sim,\n"
        f"     slaves: [{{name: 'a{{i}}', map: {json.dumps(str(DEMO_MAP))}, count: 3}}]}}\n"
    )
    path = tmp_path / "run.mcap"
    code = main(["run", str(net), "--backend", "sim", "--cycles", "700", "--json", "--record", str(path)])
    report = json.loads(capsys.readouterr().out)
    assert code == (0 if report["missed"] == 0 else 3)
    r = load(path)
    assert r.complete and r.meta["network"] == str(net)
    assert np.array_equal(r.cycles["cycle"], np.arange(700))
    bus = r.buses["arm"]
    assert r.slaves["arm"] == ["a0", "a1", "a2"] and r.axes["arm"] == ["a0", "a1", "a2"]
    (b,) = report["buses"]
    assert int((bus["verdict"] != 0).sum()) == b["missed"]
    assert np.all(bus["wkc"][bus["verdict"] == 0] == b["expected_wkc"])
    # run's outputs keep their defaults (no controller): controlword 0 on every axis, every cycle until
    # a safe stop (a loaded machine's misses can latch one); from the frame after it, the quick stop (2)
    cw = r.groups["arm"]["outputs"]["controlword"]
    stopped = np.concatenate([[False], r.cycles["safe_stop"][:-1].astype(bool)])
    assert np.all(cw[~stopped] == 0) and np.all(np.isin(cw[stopped], (0, 2)))
    # paced by run_cycles: every cycle but the first has its wake-up latency, and they run 1 ms apart
    assert np.all(r.cycles["wakeup_ns"][1:] != NO_VALUE)
    # one-sided, so a loaded machine cannot fail them (how close to 1 ms is the machine's: benchmarks/):
    # no cycle woke before its deadline, and the cycles are paced (not run as fast as they go)
    assert np.all(r.cycles["wakeup_ns"][1:] >= 0)
    assert float(np.median(np.diff(r.cycles["t_ns"]))) > 0.8e6


def test_soak_records_every_cycle_and_its_faults(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    path = tmp_path / "soak.mcap"
    args = ["soak", "--demo", "--backend", "sim", "--axes", "3", "--cycles", "2000"]  # paced at 1 kHz
    args += ["--faults", "loss=0.01,power_cycles=1", "--seed", "1", "--json", "--record", str(path)]
    # what is checked here is the recording; the exchange-time invariant is wall-clock (test_soak and
    # benchmarks/ own it): a margin of 60 s leaves only a hung exchange a violation (seen: 171 ms at load 6)
    args += ["--margin-us", "60000000"]
    code = main(args)
    report = json.loads(capsys.readouterr().out)
    assert report["violation_count"] == 0, report["violations"]
    assert code == 0 and report["injected"]["loss"] > 5
    r = load(path)
    assert r.complete and np.array_equal(r.cycles["cycle"], np.arange(2000))
    bus = r.buses["joints"]
    assert int((bus["verdict"] != 0).sum()) == report["missed"]
    assert int((bus["verdict"] == 2).sum()) == report["injected"]["loss"]  # each lost frame: one timeout
    kinds = [e["kind"] for e in r.events]
    assert kinds.count("safe_stop") == report["safe_stops"] >= 1
    # every recovery is in the recording: the injected power cycle's, and on a loaded machine those of
    # slaves whose watchdog expired while the master was off the CPU (seen: 16 at load 11)
    assert kinds.count("recovered") >= report["recovered_power_cycles"] == 1
    # the soak's controller enabled every drive: the recording shows each one reach OPERATION ENABLED
    enabled = {
        e["slave"] for e in r.events if e["kind"] == "cia402_state" and e["new"] == "OPERATION_ENABLED"
    }
    assert enabled == {"j0", "j1", "j2"}
