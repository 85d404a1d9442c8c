"""The served bus's diagnostics (``fieldbus monitor --dds`` shows them): drive faults by name, per axis;
stalls of the cycle and the safe stop they cause.

In process on the sim emulator (``fieldbus.testing.emulate``, a virtual clock):
the server's cycle is stepped by the test, the fault injected in the emulated
drive, and the DiagnosticArray the server would publish is read back.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import pytest

pytest.importorskip("cyclonedds")

import fieldbus
from fieldbus.dds.participant import Participant
from fieldbus.dds.server import BusServer, ServeOptions
from fieldbus.testing import emulate

DEMO_JOINT = Path(fieldbus.__file__).resolve().parent / "data" / "demo_joint.yaml"


def _net(tmp_path: Path) -> Path:
    """3 CiA 402 joints of the demo's map at 1 kHz on one EtherCAT bus (sim)."""
    net = tmp_path / "robot.yaml"
    net.write_text(
        "name: robot\ncycle_time_us: 1000\nreceive_timeout_us: 500\nbuses:\n  - name: bus\n    type: ethercat\n"
        f"    interface: sim\n    slaves: [{{name: 'j{{i}}', map: {json.dumps(str(DEMO_JOINT))}, count: 3}}]\n"
    )
    return net


def _status(server: BusServer, hardware_id: str) -> Any:
    (status,) = [s for s in server.diagnostics().status if s.hardware_id == hardware_id]
    return status


def _values(server: BusServer, hardware_id: str) -> dict[str, str]:
    return {kv.key: kv.value for kv in _status(server, hardware_id).values}


def test_a_drive_fault_is_in_the_diagnostics_by_axis_code_and_name(tmp_path: Path) -> None:
    with emulate(_net(tmp_path), bring_up=False) as emu:
        server = BusServer(emu.network, Participant(231, "lo"), ServeOptions("robot"))
        server.attach(emu.bring_up())
        group = next(iter(server.groups))
        ctrl = server.groups[group].ctrl
        assert ctrl is not None
        ctrl.set_goal(fieldbus.Goal.ENABLE)
        emu.run(server.step, 300)
        assert not any(k.endswith("/drive_error") for k in _values(server, group))
        emu.drive_fault("bus", "j1", 0x7300)
        emu.run(server.step, 50)
        values = _values(server, group)
        status = _status(server, group)
    assert [k for k in values if k.endswith("/drive_error")] == ["j1/drive_error"]
    assert values["j1/drive_error"].startswith("0x7300 sensor") and values["j1/drive_error"].endswith(
        "1 fault(s)"
    )
    # the fault latches the group's safe stop (no automatic re-enable on the last command): the drive
    # stays in FAULT until the owner clears and enables, and the group's status says why
    assert values["j1/drive_state"] == "FAULT" and values["latched_by"].startswith("drive fault on j1")
    assert status.level == 2 and status.message.startswith("SAFE_STOP: drive fault on j1")


@pytest.mark.parametrize("stall_ms", [50, 150])
def test_a_stall_of_the_cycle_is_counted_and_a_safe_stop_after_it_is_put_down_to_it(
    tmp_path: Path, stall_ms: int
) -> None:
    """On a virtual clock the cycle thread goes unscheduled for ``stall_ms``: 50 ms is a stall the drives
    ride through; 150 ms is longer than their SyncManager watchdog (100 ms), the bus latches its safe
    stop, and the diagnostics (and so ``fieldbus monitor --dds``) say that the stall came first."""
    with emulate(_net(tmp_path), bring_up=False) as emu:
        server = BusServer(emu.network, Participant(231, "lo"), ServeOptions("robot"), clock=emu.clock.now_ns)
        server.attach(emu.bring_up())
        emu.run(server.step, 300)
        assert _status(server, "cycle").message == "OK"
        emu.clock.advance(stall_ms * 1_000_000)
        emu.run(server.step, 100)
        latched = emu.op.result.safe_stop
        after = emu.model.buses[0].safe_stop_after  # misses in a row that latch
        cycle = _status(server, "cycle")
    values = {kv.key: kv.value for kv in cycle.values}
    assert (
        values["stalls"] == "1"
        and stall_ms * 1000 <= int(values["longest_stall_us"]) <= stall_ms * 1000 + 2000
    )
    assert latched is (stall_ms == 150)
    if latched:  # exactly safe_stop_after cycles after the stall, every one a miss
        stall_at, gap_ms = int(values["last_stall_cycle"]), int(values["longest_stall_us"]) // 1000
        assert cycle.level == 2 and cycle.message.startswith(
            f"safe stop latched at cycle {stall_at + after}, {after} cycles after the cycle thread stalled "
            f"{gap_ms} ms before cycle {stall_at}"
        )
        assert cycle.message.endswith("run the cycle at --rt-priority")
    else:
        assert (cycle.level, cycle.message) == (1, "1 stall(s)")


def _bus(server: BusServer) -> tuple[Any, dict[str, str]]:
    bus = [s for s in server.diagnostics().status if s.name.startswith("fieldbus/bus/")]
    status = next(iter(bus))
    return status.level, {kv.key: kv.value for kv in status.values}


def test_esc_error_counters_and_the_suspect_cable_are_in_the_bus_diagnostics(tmp_path: Path) -> None:
    """With the bus option error_counters, the bus's status names the cable with bit errors (warning)."""
    with emulate(_net(tmp_path), bring_up=False, bus_options={"bus": {"error_counters": True}}) as emu:
        server = BusServer(emu.network, Participant(231, "lo"), ServeOptions("robot"))
        server.attach(emu.bring_up())
        emu.run(server.step, 100)
        assert "suspect_link" not in _bus(server)[1]
        emu.bit_errors("bus", between=("j1", "j2"), rate=0.05, seed=4)
        emu.run(server.step, 800)
        level, values = _bus(server)
    assert values["suspect_link"].startswith("cable between slave 1 (j1) port 1 and slave 2 (j2) port 0")
    assert values["j2/esc_errors"].startswith("p0 ")
    assert level in (1, b"\x01")  # WARN


def test_the_diagnostics_wait_for_a_cycle_with_time_left_and_go_out_at_most_100_cycles_late(
    tmp_path: Path,
) -> None:
    """The 1 Hz DiagnosticArray is 0.1-0.2 ms of Python: it goes out in the first cycle since it was due
    whose own work took under half the period, not on top of a slow one; never more than 100 cycles late.
    The cycle's work is timed on a clock this test moves: 0.2 ms (fast) or 0.8 ms (slow) per exchange."""
    now = [0]
    with emulate(_net(tmp_path), bring_up=False) as emu:
        server = BusServer(emu.network, Participant(231, "lo"), ServeOptions("robot"), clock=lambda: now[0])
        op = emu.bring_up()
        server.attach(op)
        work_ns = [200_000]
        exchange = op.exchange

        def timed_exchange() -> Any:
            now[0] += work_ns[0]
            return exchange()

        op.exchange = timed_exchange  # type: ignore[method-assign]
        sent: list[int] = []
        write = server.diag_writer.write
        server.diag_writer.write = lambda msg, *a: (sent.append(k), write(msg, *a))  # type: ignore[method-assign]
        k = 0

        def cycles(n: int) -> None:
            nonlocal k
            for _ in range(n):
                k += 1
                now[0] += 1_000_000 - work_ns[0]
                server.step(k)

        cycles(1500)
        assert sent == [1000]  # on time while the cycles are fast
        work_ns[0] = 800_000
        cycles(1050)  # due at 2000, every cycle slow: out at the latest, 100 cycles late
        assert sent == [1000, 2100]
        cycles(3040 - k)  # due at 3000: slow until 3040, then fast
        work_ns[0] = 200_000
        cycles(10)
        assert sent == [1000, 2100, 3041]
