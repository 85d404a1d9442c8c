"""Mode objects by SDO over veth with the real pysoem master: homing and CSP -> CSV -> CSP, seen on the wire.

The demo joint's map with 0x6060/0x6061 removed from its PDOs, two axes, the EtherCAT emulator in a
child process on a veth pair (``fieldbus.testing.emulate(..., ethercat="veth")``, wall clock). The
mode requests go out as CoE SDO downloads of 0x6060 on the cycle's acyclic channel. Judged by tshark
(an independent decoder) on a capture of the master's side: one SDO download of 0x6060 per axis and
switch, and uploads of 0x6061. The emulator runs on the wall clock: the check is on states and frames.
"""

from __future__ import annotations

import json
import shutil
import subprocess
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest
import yaml

import fieldbus
from fieldbus import AcyclicModes, Cia402Controller, Goal, Homing, HomingPhase, Mode
from fieldbus.testing import emulate

DEMO_MAP = Path(fieldbus.__file__).resolve().parent / "data" / "demo_joint.yaml"


def _network(tmp_path: Path) -> Path:
    doc = yaml.safe_load(DEMO_MAP.read_text())
    for section in ("rpdo", "tpdo"):
        for pdo in doc[section]:
            pdo["channels"] = [c for c in pdo["channels"] if c["index"] not in (0x6060, 0x6061)]
    doc["homing"] = {"method": 37, "offset": 0, "timeout_ms": 3000}
    m = tmp_path / "joint_no_modes.yaml"
    m.write_text(yaml.safe_dump(doc, sort_keys=False))
    net = tmp_path / "net.yaml"
    net.write_text(
        "cycle_time_us: 2000\nreceive_timeout_us: 20000\nsafe_stop_after: 200\nbuses:\n"
        f"  - {{name: arm, type: ethercat, interface: eth9, slaves: [{{name: 'j{{i}}', "
        f"map: {json.dumps(str(m))}, count: 2}}]}}\n"
    )
    return net


@pytest.mark.veth
@pytest.mark.timeout(300)
def test_veth_homes_and_switches_modes_by_sdo(
    tmp_path: Path, tshark: Callable[[Path, str], int], request: pytest.FixtureRequest
) -> None:
    if shutil.which("dumpcap") is None:
        pytest.skip("dumpcap is not installed (apt-get install tshark)")
    request.getfixturevalue("veth_possible")
    with emulate(_network(tmp_path), ethercat="veth", receive_timeout_us=20000) as emu:
        _day(emu, tmp_path, tshark)


def _day(emu: Any, tmp_path: Path, tshark: Callable[[Path, str], int]) -> None:
    op = emu.op
    img = op["arm"]
    assert "modes_of_operation" not in img.outputs.names
    iface = emu.network.backend("arm").bus.interface
    pcap = tmp_path / "modes.pcapng"
    cap = subprocess.Popen(
        ["dumpcap", "-q", "-i", iface, "-w", str(pcap)], stdout=subprocess.DEVNULL, stderr=subprocess.PIPE
    )
    try:
        time.sleep(1.0)  # dumpcap opens the interface
        ctrl = Cia402Controller(2, mode=Mode.CSP)
        ctrl.set_goal(Goal.ENABLE)
        modes = AcyclicModes.for_group(op, "arm")
        homing = Homing.from_maps(ctrl, [s.map for s in op.groups["arm"].slaves], op.cycle_time_us)

        def run_until(done: Callable[[], bool], cycles: int = 4000) -> None:
            hit = [False]

            def step(_k: int) -> bool:
                if op.exchange().fresh:
                    ctrl.step_image(img, modes=modes)
                    hit[0] = done()
                return hit[0]

            emu.run(step, cycles=cycles)
            assert hit[0], f"not done: {ctrl.state}, display {modes.display}"

        run_until(lambda: ctrl.all_reached)
        homing.start()

        def homed() -> bool:
            homing.step(img.inputs["statusword"], img.outputs["controlword"])
            return homing.done and ctrl.all_reached

        run_until(homed)
        assert list(homing.phase) == [HomingPhase.DONE] * 2
        for mode in (Mode.CSV, Mode.CSP):
            ctrl.request_mode(mode)
            run_until(lambda m=mode: ctrl.all_reached and bool((modes.display == m).all()))
        assert list(modes.writes) == [5, 5]  # CSP, HM, CSP, CSV, CSP
        time.sleep(0.5)
    finally:
        cap.terminate()
        cap.wait(timeout=10)
    # tshark decodes the CoE SDO requests: downloads of 0x6060 (master -> slave), uploads of 0x6061
    assert tshark(pcap, "ecat_mailbox.coe.sdoidx == 0x6061") >= 10
    wanted = "ecat_mailbox.coe.sdoreq && ecat_mailbox.coe.sdoidx == 0x6060"
    fields = ["-T", "fields", "-e", "ecat.adp", "-e", "ecat_mailbox.coe.sdodata"]
    res = subprocess.run(
        ["tshark", "-n", "-r", str(pcap), "-Y", wanted, *fields], capture_output=True, text=True, check=True
    )
    # per slave (its configured address) the values downloaded in frame order; a frame is captured as
    # it leaves and as it comes back, a mailbox write may be repeated: consecutive repeats are one
    order: dict[int, list[int]] = {}
    for line in res.stdout.splitlines():
        adp, data = (int(x, 0) for x in line.split("\t"))
        seq = order.setdefault(adp, [])
        if not seq or seq[-1] != data:
            seq.append(data)
    assert len(order) == 2, order
    csp, hm, csv = int(Mode.CSP), int(Mode.HOMING), int(Mode.CSV)
    assert all(seq == [csp, hm, csp, csv, csp] for seq in order.values()), order
