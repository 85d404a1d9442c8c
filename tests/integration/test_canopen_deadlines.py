"""Every CANopen input has a deadline: a silent node is never fresh (issue 23, defect 3).

On python-can's virtual bus with the CanopenSimulator. Event-driven TPDOs
(type 255) are due within their event timer plus one cycle, TPDOs of type n
within n SYNCs, a node within its heartbeat consumer time; a node that could
die unnoticed is refused. The oracle of "stale" in the heartbeat test is a
listener on the same virtual channel that sees every frame the nodes send,
with the bus's own send timestamps (not the backend's bookkeeping).

Cycles are paced by sleeping one cycle time after each: a loaded machine only
makes a cycle longer, so a deadline in time passes within as many cycles or
fewer; the bounds below are in cycles.
"""

from __future__ import annotations

import itertools
import json
import math
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import pytest

can = pytest.importorskip("can")

from fieldbus.cli import main  # noqa: E402
from fieldbus.commands.demo import DEMO_MAP  # noqa: E402
from fieldbus.core.network import load_network  # noqa: E402
from fieldbus.core.pdo import load_drive_map  # noqa: E402
from fieldbus.errors import FieldbusError, PdoMapError  # noqa: E402
from fieldbus.network import CycleResult, Operational, open_network  # noqa: E402
from sim_slaves.canopen import CanopenSimulator  # noqa: E402

pytestmark = pytest.mark.timeout(120)
_channels = itertools.count()
CYCLE_US = 10_000
EVENT_MS = 20
NODES = (1, 2, 3)


@pytest.fixture
def channel() -> str:
    return f"fb-deadline-{next(_channels)}-{time.monotonic_ns()}"


def _map(tmp_path: Path, *, heartbeat_ms: int, tpdo: str) -> Path:
    """The demo joint with both TPDOs set to ``tpdo`` (a flow mapping's keys) and the given heartbeat."""
    f = tmp_path / f"joint_{heartbeat_ms}_{len(list(tmp_path.iterdir()))}.yaml"
    f.write_text(
        DEMO_MAP.read_text().replace(
            "  heartbeat_ms: 100\n",
            f"  heartbeat_ms: {heartbeat_ms}\n  pdo:\n"
            f"    - {{index: 0x1A00, {tpdo}}}\n    - {{index: 0x1A01, {tpdo}}}\n",
        )
    )
    return f


def _net(tmp_path: Path, channel: str, map_file: Path, safe_stop_after: int = 5) -> Path:
    f = tmp_path / "net.yaml"
    f.write_text(
        f"cycle_time_us: {CYCLE_US}\nreceive_timeout_us: 20000\nsafe_stop_after: {safe_stop_after}\n"
        f"buses:\n  - name: bus\n    type: canopen\n    interface: {channel}\n    can_interface: virtual\n"
        f"    slaves:\n      - {{name: 'j{{i}}', map: {json.dumps(str(map_file))}, node_id: 1, "
        f"count: {len(NODES)}}}\n"
    )
    return f


StartNodes = Callable[[Path], CanopenSimulator]


@pytest.fixture
def sim_for(channel: str) -> Iterator[StartNodes]:
    """``sim_for(map_file)``: the emulated nodes 1-3 on ``channel`` (stopped afterwards)."""
    started: list[tuple[can.BusABC, CanopenSimulator]] = []

    def start(map_file: Path) -> CanopenSimulator:
        bus = can.Bus(interface="virtual", channel=channel)
        drive = load_drive_map(map_file)
        sim = CanopenSimulator(bus, [(drive, n) for n in NODES], dt_s=CYCLE_US / 1e6)
        sim.start()
        started.append((bus, sim))
        return sim

    yield start
    for bus, sim in started:
        sim.stop()
        bus.shutdown()
        assert not sim.errors


def _paced(op: Operational) -> CycleResult:
    res = op.exchange()
    time.sleep(CYCLE_US / 1e6)
    return res


def test_silent_event_driven_nodes_go_stale_within_their_event_timer_and_safe_stop(
    sim_for: StartNodes, channel: str, tmp_path: Path
) -> None:
    """No heartbeat, TPDOs on a 20 ms event timer: silence every node and 400 cycles used to read fresh.

    Deadline: the event timer plus one cycle (30 ms), so the cycle that starts 3 cycle times after
    the silence is stale at the latest; the policy latches safe_stop_after (5) cycles later.
    """
    drive = _map(tmp_path, heartbeat_ms=0, tpdo=f"transmission_type: 255, event_timer: {EVENT_MS}")
    sim = sim_for(drive)
    with open_network(_net(tmp_path, channel, drive)) as net:
        op = net.bring_up()
        assert net.backends[0].expected_wkc == 0  # nothing to wait for at SYNC: only the deadlines tell
        alive = [_paced(op).fresh for _ in range(20)]
        assert any(alive), "the nodes never read fresh while alive"
        for n in NODES:
            sim.bus_off(n)
        fresh, stops = [], []  # per cycle (the result object is the same every cycle)
        for _ in range(400):
            res = _paced(op)
            fresh.append(res.fresh)
            stops.append(res.safe_stop)
        deadline_cycles = math.ceil((EVENT_MS * 1000 + CYCLE_US) / CYCLE_US) + 1
        assert sum(fresh) <= deadline_cycles, f"{sum(fresh)} of 400 cycles read fresh after the silence"
        first_stale = fresh.index(False)
        assert not any(fresh[first_stale:]), "a dead bus read fresh again"
        assert stops.index(True) <= first_stale + 5 - 1  # safe_stop_after misses in a row
        assert all(stops[first_stale + 5 - 1 :])
        assert not any(res.buses[0].fresh)


def test_no_cycle_reads_fresh_after_any_deadline_of_its_node_passed(
    sim_for: StartNodes, channel: str, tmp_path: Path
) -> None:
    """heartbeat_ms 100 (consumer 150 ms) and a 20 ms event timer: node 2's heartbeat goes silent,
    then node 3 goes bus-off. Per cycle and node, a listener on the bus says stale when, at the start
    of the cycle, the newest frame of one of the node's TPDOs is older than 30 ms or its newest
    heartbeat older than 150 ms; such a node must not read fresh (it used to for ~120 ms)."""
    drive = _map(tmp_path, heartbeat_ms=100, tpdo=f"transmission_type: 255, event_timer: {EVENT_MS}")
    with can.Bus(interface="virtual", channel=channel) as listener:
        sim = sim_for(drive)
        sources = {n: (0x180 + n, 0x280 + n) for n in NODES}
        last: dict[int, float] = {}  # COB-ID -> send time (time.time) of its newest frame

        def listen() -> None:
            while (msg := listener.recv(timeout=0)) is not None:
                last[msg.arbitration_id] = msg.timestamp

        def stale_at(t: float, n: int) -> bool:
            tpdo_age = max(t - last.get(cob, t) for cob in sources[n])
            return tpdo_age > (EVENT_MS * 1000 + CYCLE_US) / 1e6 or t - last.get(0x700 + n, t) > 0.150

        with open_network(_net(tmp_path, channel, drive, safe_stop_after=100_000)) as net:
            op = net.bring_up()
            stale_cycles = wrong = 0
            for k in range(90):
                if k == 20:
                    sim.silence_heartbeat(2)
                if k == 30:
                    sim.bus_off(3)
                t0 = time.time()
                res = _paced(op)
                listen()  # every frame the backend could have taken in that cycle came before this
                fresh = res.buses[0].fresh
                for i, n in enumerate(NODES):
                    if stale_at(t0, n):
                        stale_cycles += 1
                        wrong += bool(fresh[i])
            assert wrong == 0, f"{wrong} of {stale_cycles} stale node-cycles read fresh"
            assert stale_cycles >= 40  # nodes 2 and 3 were stale for most of the last 60 cycles
            assert not fresh[2] and not fresh[1] and net.backends[0].heartbeat_lost[1]


def test_tpdos_of_type_n_are_due_within_n_syncs(sim_for: StartNodes, channel: str, tmp_path: Path) -> None:
    """Type 3 (every 3rd SYNC), no heartbeat: after the nodes go silent, the 4th cycle is stale at
    the latest (in SYNCs, whatever the machine's load); they used to read fresh for ever."""
    drive = _map(tmp_path, heartbeat_ms=0, tpdo="transmission_type: 3")
    sim = sim_for(drive)
    with open_network(_net(tmp_path, channel, drive, safe_stop_after=100_000)) as net:
        op = net.bring_up()
        assert any(_paced(op).fresh for _ in range(30))
        for n in NODES:
            sim.bus_off(n)
        fresh = [op.exchange().fresh for _ in range(50)]
        assert not any(fresh[3:]), fresh.index(False) if False in fresh else fresh


def test_a_node_that_could_die_unnoticed_is_refused_with_the_fix(
    tmp_path: Path, channel: str, capsys: pytest.CaptureFixture[str]
) -> None:
    """Event-driven TPDOs without an event timer and no heartbeat: nothing would ever tell that the
    node went silent. The network file is refused at its map entry, naming both fixes."""
    drive = _map(tmp_path, heartbeat_ms=0, tpdo="transmission_type: 255")
    net_file = _net(tmp_path, channel, drive)
    with pytest.raises(PdoMapError) as err:
        load_network(net_file)
    e = err.value
    assert e.file == str(net_file) and e.line == 10 and e.path == "buses[0].slaves[0].map"
    assert "0x1A00 is event driven (transmission type 255) without an event_timer" in e.message
    assert "set event_timer (ms) on an event-driven TPDO under canopen.pdo" in e.message
    assert "canopen.heartbeat_ms" in e.message
    assert main(["validate", str(net_file)]) == 1
    assert "a silent node would go unnoticed" in capsys.readouterr().err
    # either fix is accepted
    load_network(_net(tmp_path, channel, _map(tmp_path, heartbeat_ms=50, tpdo="transmission_type: 255")))
    load_network(
        _net(
            tmp_path, channel, _map(tmp_path, heartbeat_ms=0, tpdo="transmission_type: 255, event_timer: 10")
        )
    )


def test_switching_the_heartbeat_consumer_off_cannot_leave_a_node_unwatched(
    tmp_path: Path, channel: str
) -> None:
    """heartbeat_consumer_ms=0 is refused where the heartbeat was a node's only deadline; the refused
    backend leaves no frame log (file or writer thread) behind."""
    drive = _map(tmp_path, heartbeat_ms=100, tpdo="transmission_type: 255")
    log = tmp_path / "bus.log"
    threads = threading.active_count()
    with pytest.raises(FieldbusError, match=r"node 1 \(j0, heartbeat consumer 0 ms\): a silent node"):
        open_network(_net(tmp_path, channel, drive), heartbeat_consumer_ms=0, can_log=str(log))
    assert not log.exists() and threading.active_count() == threads
    open_network(_net(tmp_path, channel, DEMO_MAP), heartbeat_consumer_ms=0).close()  # SYNC TPDOs: fine


def test_error_frames_are_counted_and_never_read_as_data(
    sim_for: StartNodes, channel: str, tmp_path: Path
) -> None:
    """socketcan hands error frames over as 11-bit frames whose id is the error class: class 0x082
    (bus error + lost arbitration) used to read as an EMCY of node 2. Bus-off (0x040) is counted."""
    sim_for(DEMO_MAP)
    with (
        can.Bus(interface="virtual", channel=channel) as injector,
        open_network(_net(tmp_path, channel, DEMO_MAP)) as net,
    ):
        op = net.bring_up()
        backend = net.backends[0]
        for _ in range(3):
            op.exchange()
        for cls in (0x082, 0x040):
            injector.send(
                can.Message(arbitration_id=cls, is_error_frame=True, is_extended_id=False, data=bytes(8))
            )
        for _ in range(3):
            op.exchange()
        assert not backend.emergencies and backend.emcy_count == 0
        assert backend.error_frames == 2 and backend.bus_off == 1
        assert backend.last_error == "bus-off (error frame class 0x040)"


def test_late_and_extra_tpdos_are_counted_and_never_taken(
    sim_for: StartNodes, channel: str, tmp_path: Path
) -> None:
    """A copy of node 1's TPDO1 after a cycle that had it is extra; after a cycle that missed it, late.
    Neither lands in the inputs (its position would read 12 345 counts)."""
    sim = sim_for(DEMO_MAP)
    net_file = _net(tmp_path, channel, DEMO_MAP).read_text().replace("20000", "50000")
    (tmp_path / "net50.yaml").write_text(net_file)
    bogus = can.Message(
        arbitration_id=0x181,
        is_extended_id=False,
        data=(0x0237).to_bytes(2, "little") + (12345).to_bytes(4, "little"),
    )
    with (
        can.Bus(interface="virtual", channel=channel) as injector,
        open_network(tmp_path / "net50.yaml") as net,
    ):
        op = net.bring_up()
        backend = net.backends[0]
        wire = op["bus"].inputs.wire
        for _ in range(5):
            assert op.exchange().fresh
        injector.send(bogus)  # node 1 answered this cycle already: extra
        time.sleep(0.005)
        assert op.exchange().fresh
        assert backend.extra_frames == 1 and backend.late_frames == 0
        sim.drop_tpdos(1, 1)  # node 1's TPDO1 of the next cycle is lost
        assert list(op.exchange().buses[0].fresh) == [False, True, True]
        injector.send(bogus)  # turns up after that cycle: late
        time.sleep(0.005)
        res = op.exchange()
        assert res.fresh and backend.late_frames == 1 and backend.extra_frames == 1
        assert int.from_bytes(bytes(wire[0, 2:6]), "little", signed=True) != 12345
