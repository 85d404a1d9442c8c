"""The real pysoem master (SOEM inside) against the wire-level emulator over a veth pair.

No fieldbus wrapper in between: pysoem configures the emulated ESCs as it
would real drives (SII, CoE mapping read, SM/FMMU programming, DC, AL states),
then runs 10,000 process-data cycles with the CiA 402 drive model behind.
"""

from __future__ import annotations

import struct
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest

pysoem = pytest.importorskip("pysoem")

INTEROP = Path(__file__).resolve().parents[1] / "data" / "ethercat_driver_ros2"
MAXON = INTEROP / "maxon_epos4_50_5.yaml"
NAME = "maxon_epos4_50_5"
VENDOR, PRODUCT = 0x000000FB, 0x63500000
OUT = struct.Struct("<HiihiihB")  # 0x1603: controlword, target pos/vel/torque, offsets, mode (23 B)
IN = struct.Struct("<Hiihbhhii")  # 0x1A03: statusword, pos/vel/torque actual, mode display, ... (25 B)
IN_REMAPPED = 21  # 0x1A03 without its last entry (0x60BB, int32)
CSP = 8
CYCLES = 10_000

pytestmark = [pytest.mark.veth, pytest.mark.timeout(600), pytest.mark.usefixtures("generous_pysoem_timeouts")]


def _bring_to_preop(master: Any, n: int) -> None:
    assert master.config_init() == n
    assert len(master.slaves) == n


def _remap_inputs(slave: Any) -> None:
    """setup_func hook (PRE-OP, runs inside config_map): drop the last entry of 0x1A03 and assign it again."""
    slave.sdo_write(0x1C13, 0, bytes([0]))
    slave.sdo_write(0x1A03, 0, bytes([0]))
    slave.sdo_write(0x1A03, 0, bytes([8]))
    slave.sdo_write(0x1C13, 1, struct.pack("<H", 0x1A03))
    slave.sdo_write(0x1C13, 0, bytes([1]))


def _cycle(master: Any) -> int:
    master.send_processdata()
    return int(master.receive_processdata(10_000))


def _controlword(status: int) -> int:
    """CiA 402 enable sequence: shutdown -> switch on -> enable operation (fault reset on fault)."""
    if status & 0x08:
        return 0x80
    if status & 0x4F == 0x40:
        return 0x06
    if status & 0x6F == 0x21:
        return 0x07
    return 0x0F


@pytest.mark.parametrize("n", [1, 12, pytest.param(64, marks=pytest.mark.slow)])
def test_pysoem_configures_emulated_drives(ethercat_emulator: Any, n: int) -> None:
    emu = ethercat_emulator([MAXON], count=n)
    master = pysoem.Master()
    master.open(emu.iface)
    try:
        _bring_to_preop(master, n)
        for s in master.slaves:
            assert s.name == NAME
            assert (s.man, s.id) == (VENDOR, PRODUCT)
        ident = [struct.unpack("<I", master.slaves[-1].sdo_read(0x1018, sub))[0] for sub in (1, 2, 3, 4)]
        assert ident == [VENDOR, PRODUCT, 0, 0]

        # an injected abort reaches pysoem as SdoError with the code
        emu.command(cmd="abort_sdo", slave=0, index=0x1018, sub=2, code=0x08000021)
        with pytest.raises(pysoem.SdoError) as exc:
            master.slaves[0].sdo_read(0x1018, 2)
        assert exc.value.abort_code == 0x08000021
        emu.command(cmd="clear")

        master.slaves[0].setup_func = _remap_inputs
        size = master.config_map()
        assert size == n * (OUT.size + IN.size) - (IN.size - IN_REMAPPED)
        assert len(master.slaves[0].output) == OUT.size
        assert len(master.slaves[0].input) == IN_REMAPPED
        if n > 1:
            assert len(master.slaves[1].input) == IN.size
        assert master.expected_wkc == 3 * n
        assert master.config_dc()
        assert master.state_check(pysoem.SAFEOP_STATE, 2_000_000) == pysoem.SAFEOP_STATE

        master.state = pysoem.OP_STATE
        master.write_state()
        for _ in range(2000):
            _cycle(master)
            if master.state_check(pysoem.OP_STATE, 1000) == pysoem.OP_STATE:
                break
        assert master.read_state() == pysoem.OP_STATE, [hex(s.al_status) for s in master.slaves]

        wrong, lost = 0, 0
        start = None
        target = 0
        for _i in range(CYCLES):
            for s in master.slaves:
                status = struct.unpack_from("<H", s.input)[0]
                if status & 0x6F == 0x27:  # operation enabled: follow a slow ramp in CSP
                    if start is None:
                        start = struct.unpack_from("<i", s.input, 2)[0]
                        target = start
                    cw = 0x0F
                else:
                    cw = _controlword(status)
                s.output = OUT.pack(cw, target, 0, 0, 0, 0, 0, CSP)
            if start is not None:
                target += 5
            t0 = time.perf_counter()
            wkc = _cycle(master)
            timed_out = time.perf_counter() - t0 >= 0.009
            if wkc <= 0 or (timed_out and wkc < master.expected_wkc):
                # no frame (or, with 64 slaves, one of the cycle's frames) within 10 ms:
                # the emulator process was not scheduled in time
                lost += 1
            elif wkc != master.expected_wkc:
                wrong += 1
        assert wrong == 0, f"{wrong} of {CYCLES} cycles had a WKC other than {master.expected_wkc}"
        # A user-space emulator on a shared 2-core machine may miss a deadline now and then;
        # a wrong WKC never is acceptable, a rare late frame is (SOEM reports it as no frame):
        # at most 0.5 % (64 slaves with drive models answer in ~1.6 ms; a busy CI neighbour adds the rest).
        assert lost <= CYCLES // 200, f"{lost} of {CYCLES} frames came back later than 10 ms"
        assert start is not None, "the drives never reached 'operation enabled'"
        for s in master.slaves:
            status, pos = struct.unpack_from("<Hi", s.input)
            assert status & 0x6F == 0x27, hex(status)
            assert abs(pos - target) < 2000, (pos, target)
            assert pos - start > (target - start) // 2
        assert master.read_state() == pysoem.OP_STATE
    finally:
        master.state = pysoem.INIT_STATE
        master.write_state()
        master.close()


def test_mapping_writes_refused_outside_preop(ethercat_emulator: Any) -> None:
    emu = ethercat_emulator([MAXON])
    master = pysoem.Master()
    master.open(emu.iface)
    try:
        _bring_to_preop(master, 1)
        master.config_map()
        assert master.state_check(pysoem.SAFEOP_STATE, 2_000_000) == pysoem.SAFEOP_STATE
        with pytest.raises(pysoem.SdoError) as exc:
            master.slaves[0].sdo_write(0x1C13, 0, bytes([0]))
        assert exc.value.abort_code == 0x08000022
    finally:
        master.close()


def test_refused_state_reports_al_status_code(ethercat_emulator: Any) -> None:
    emu = ethercat_emulator([MAXON], count=2)
    master = pysoem.Master()
    master.open(emu.iface)
    try:
        _bring_to_preop(master, 2)
        emu.command(cmd="refuse_state", slave=1, state="SAFE_OP", code=0x001D)
        master.config_map()
        master.state_check(pysoem.SAFEOP_STATE, 200_000)
        master.read_state()
        assert master.slaves[0].state == pysoem.SAFEOP_STATE
        assert master.slaves[1].state == pysoem.PREOP_STATE | pysoem.STATE_ERROR
        assert master.slaves[1].al_status == 0x001D
    finally:
        master.close()


def test_pcap_decodes_in_tshark(
    ethercat_emulator: Any, tmp_path: Path, tshark: Callable[[Path, str], int]
) -> None:
    pcap = tmp_path / "run.pcap"
    emu = ethercat_emulator([MAXON], count=2, pcap=pcap)
    master = pysoem.Master()
    master.open(emu.iface)
    try:
        _bring_to_preop(master, 2)
        master.slaves[0].sdo_read(0x1018, 1)
        master.config_map()
        master.config_dc()
        master.state = pysoem.OP_STATE
        master.write_state()
        for _ in range(200):
            _cycle(master)
    finally:
        master.close()
        emu.stop()

    assert tshark(pcap, "_ws.malformed || _ws.expert.severity >= error") == 0
    assert tshark(pcap, "ecat") > 400
    assert tshark(pcap, "ecat_mailbox.coe") > 0


def test_a_lost_frame_costs_the_receive_timeout_not_a_scheduler_tick(
    ethercat_emulator: Any, tmp_path: Path
) -> None:
    """SOEM's recv waits whole ticks (4-10 ms measured) on a blocking socket; the backend makes it
    non-blocking, so receive() on a dropped frame returns at the timeout (500 µs here)."""
    import fieldbus
    from fieldbus.backends import soem_socket
    from fieldbus.commands.demo import DEMO_MAP

    emu = ethercat_emulator([DEMO_MAP], count=4)
    net_file = tmp_path / "net.yaml"
    net_file.write_text(
        "cycle_time_us: 1000\nreceive_timeout_us: 500\nsafe_stop_after: 100000\nbuses:\n"
        f"  - {{name: bus, type: ethercat, interface: {emu.iface}, slaves: [{{name: 'j{{i}}', map: '{DEMO_MAP}', count: 4}}]}}\n"
    )
    with fieldbus.open_network(net_file) as net:
        op = net.bring_up()
        backend = net.backends[0]
        assert backend.sockets and all(soem_socket.is_nonblocking(fd) for fd in backend.sockets)  # type: ignore[attr-defined]
        for _ in range(50):
            op.exchange()
        lost: list[float] = []
        receive = backend.receive

        def timed() -> int | None:
            t0 = time.perf_counter_ns()
            wkc = receive()
            if wkc is None:
                lost.append((time.perf_counter_ns() - t0) / 1e3)
            return wkc

        backend.receive = timed  # type: ignore[method-assign]
        for _ in range(40):
            emu.command(cmd="drop", count=1, pd=True)
            op.exchange()
            op.exchange()
        assert len(lost) >= 38, lost
        lost.sort()
        # the wait ends at the timeout: the median within 100 µs of it; the worst within a scheduler hiccup of
        # this shared machine, far below the 4 ms tick a blocking recv waits
        assert 500 <= lost[len(lost) // 2] <= 600, lost
        assert lost[-1] < 2500, lost


def test_a_redundant_port_gets_its_own_nonblocking_socket_and_the_timeout_holds(
    ethercat_emulator: Any, tmp_path: Path
) -> None:
    """SOEM opens a second packet socket for ``redundant_interface``; both are found and set
    non-blocking. The ring is open at the second port (nothing answers there), as after a cable
    break: process data still arrives through the first port, and a lost frame still costs
    the receive timeout, not SOEM's tick-long recv."""
    import fieldbus
    from fieldbus.backends import soem_socket
    from fieldbus.commands.demo import DEMO_MAP
    from sim_slaves.ethercat.veth import VethUnavailable, delete_link, make_veth_pair

    emu = ethercat_emulator([DEMO_MAP], count=2)
    try:
        spare, _ = make_veth_pair()
    except VethUnavailable as exc:
        pytest.skip(str(exc))
    try:
        net_file = tmp_path / "net.yaml"
        net_file.write_text(
            "cycle_time_us: 2000\nreceive_timeout_us: 1000\nsafe_stop_after: 100000\nbuses:\n"
            f"  - {{name: bus, type: ethercat, interface: {emu.iface}, redundant_interface: {spare},"
            f" slaves: [{{name: 'j{{i}}', map: '{DEMO_MAP}', count: 2}}]}}\n"
        )
        with fieldbus.open_network(net_file) as net:
            op = net.bring_up()
            backend = net.backends[0]
            sockets = backend.sockets  # type: ignore[attr-defined]
            assert len(sockets) == 2 and all(soem_socket.is_nonblocking(fd) for fd in sockets)
            # With the ring open SOEM waits on both ports until its timer, spinning, so every reply is
            # handed over at the timeout; one handed over more than the 200 us slack past it (the
            # scheduler's doing) is judged late, a miss, its WKC kept in late_wkc. Either way the
            # process data came back through the first port with every slave's count. What is not
            # asserted tightly is timing: on a loaded 2-CPU machine the emulator, sharing the CPU the
            # spin leaves, answers after the timeout now and then (measured quiet: 2 % lost, 2 % late).
            fresh = late = 0
            for _ in range(100):
                res = op.exchange()
                fresh += res.fresh
                late += backend.late_wkc == backend.expected_wkc
            assert fresh + late >= 80 and fresh >= 50, (
                f"fresh {fresh}, late {late}, lost {100 - fresh - late}"
            )
            lost_us: list[float] = []
            for _ in range(10):
                # a reply handed over late leaves its frame possibly still queued at the emulator,
                # which would take the drop meant for the next one: start from a cycle answered in time
                assert any(op.exchange().fresh for _ in range(20))
                emu.command(cmd="drop", count=1, pd=True)
                backend.send()
                t0 = time.perf_counter_ns()
                assert backend.receive() is None
                lost_us.append((time.perf_counter_ns() - t0) / 1e3)
                op.exchange()
            lost_us.sort()
            # SOEM waits on both ports until its timer; the blocking recv would take 4-10 ms
            assert lost_us[len(lost_us) // 2] < 1000 + 100, lost_us
            assert any(op.exchange().fresh for _ in range(20))
    finally:
        delete_link(spare)
