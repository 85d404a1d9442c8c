"""Run an :class:`~sim_slaves.ethercat.chain.EscChain` on a network interface (AF_PACKET, ethertype 0x88A4).

    python -m sim_slaves.ethercat --iface IFACE (--map MAP.yaml [--map ...] [--count N] | --network NET [--bus NAME])
        [--pcap FILE] [--control PATH] [--app auto|loopback|none]
        [--drift-ppm X [--drift-seed N]] [--esc-delays-ns TP TF] [--cable-m M] [--dc-min-sample-us US]
        [--rt-priority N|auto|off] [--cpu N] [--lock-memory auto|on|off] [--spin-us US]
        [--after-reply yield|hold]

Slaves are the maps in the order given, the whole list repeated ``--count``
times; or, with ``--network``, the slaves of one EtherCAT bus of a network
file (``--bus``, default its only one), each with its ``emulator:`` options
(command delay, current loop, encoder, friction, thermal: see
:mod:`sim_slaves.emulator_options`) - the same drives the ``sim`` backend
builds from that file. The process prints ``ready <iface> <n> slaves`` on stdout once it
listens and runs until SIGTERM/SIGINT.

Like a real ESC on port 0, it processes every EtherCAT frame that arrives
whatever its MAC addresses (a master's source MAC may well have the locally
administered bit set already); what it skips are frames sent on the interface
(packet type PACKET_OUTGOING: its own replies and other senders on this end),
frames whose ethertype is not 0x88A4, and runts. An 802.1Q VLAN tag
(ethertype 0x8100, then 0x88A4) is processed as the ESCs do: its contents are
ignored and the reply carries it unchanged. The kernel strips the tag before
packet sockets see a frame, so the socket listens to every protocol
(ETH_P_ALL, an in-kernel filter keeps EtherCAT only) and takes the tag from
PACKET_AUXDATA. The interface is put in promiscuous mode for as long as the
runner listens: an ESC does not look at the destination MAC.

Distributed clocks (docs/dc.md, "In the emulator"): ``--drift-ppm X`` spreads
the slaves' crystal drifts evenly over ±X ppm (order shuffled by
``--drift-seed``); ``--esc-delays-ns TP TF`` sets every ESC's processing and
forwarding delay, ``--cable-m`` the cable per hop; ``--dc-min-sample-us``
the least time between two FRMW samples the clocks' loops take (default 500,
0: every one, see :class:`~sim_slaves.ethercat.dc.DcLine`).

``--control PATH`` opens a UNIX datagram socket taking one JSON object per
datagram (``slave`` is the 0-based wire position, as in ``pysoem.Master.slaves``)::

    {"cmd": "drop", "count": 1}                         lose the next frames
    {"cmd": "delay", "seconds": 0.01, "count": 1}       hold replies back
    {"cmd": "corrupt_wkc", "delta": -1, "count": 1}     falsify process-data WKCs
    {"cmd": "power_cycle", "slave": 0}                  back to INIT, registers reset
    {"cmd": "refuse_state", "slave": 0, "state": "SAFE_OP", "code": 29}
    {"cmd": "abort_sdo", "slave": 0, "index": 4120, "sub": 1, "code": 101318656}
    {"cmd": "emergency", "slave": 0, "code": 33297}
    {"cmd": "drive_fault", "slave": 0, "code": 29440}    the drive faults (0x603F = code), EMCY sent;
                                                        "axis": k (0-based) faults axis k + 1 of a multi-axis slave
    {"cmd": "mute_mailbox", "slave": 0, "stuck": false} mailbox requests dropped (stuck: SM0 stays full)
    {"cmd": "stick_eeprom", "slave": 0}                 EEPROM interface busy for ever
    {"cmd": "bit_errors", "slave": 4, "rate": 0.05, "seed": 1, "direction": "both", "frames": -1}
                                                        bit errors on the cable behind slave 4 (port 1)
    {"cmd": "flap_link", "slave": 4}                    that cable loses its link for a moment
    {"cmd": "sii", "slave": 0}                          the slave's EEPROM image (hex) and alias register
    {"cmd": "foe_power_loss", "slave": 0, "after_bytes": 5000}  power lost during an FoE write
    {"cmd": "foe_busy", "slave": 0, "answers": 3}       FoE DATA answered with BUSY
    {"cmd": "firmware", "slave": 0, "password": 4660}   the slave's firmware store (optional: set its password)
    {"cmd": "clear"}                                    undo all injections
    {"cmd": "status"}                                   states, AL status codes, frame count
    {"cmd": "timing", "reset": false}                   the runner's reply times (see ReplyTimes)
    {"cmd": "dc"}                                       every slave's DC registers and clock at one instant
    {"cmd": "dc_config", "drift_ppm": 100, "seed": 0}   drifts (±X spread, or a list), from now on;
        optional "processing_ns", "forwarding_ns", "cable_m": the line,
        "min_sample_interval_ns": FRMW samples

A sender with a bound address gets ``{"ok": true, ...}`` or ``{"ok": false, "error": ...}`` back
(:func:`send_control` does this).

Reply time (docs/emulator.md, "Reply time"): a master waits for each reply,
so the runner keeps everything it can off the path from a frame's arrival to
its reply. It sends the reply first and only then steps the drives (their
inputs travel in the next frame either way); at SCHED_FIFO it first waits up
to 50 µs so that a master sharing its CPU takes the reply (:class:`AfterReply`,
``--after-reply``). Python's garbage collector is frozen after start-up and
switched off; the runner collects in the gaps between frames instead
(:class:`IdleCollector`). Where the process has
CAP_SYS_NICE it runs at SCHED_FIFO (``--rt-priority``, default
:data:`DEFAULT_RT_PRIORITY`; ``off`` to leave the scheduler alone), so a busy
machine's other processes cannot keep it from waking up; there it polls the
socket only 50 µs after a reply before it sleeps (300 µs otherwise), so its
spin does not keep a plain master off the CPU. ``--lock-memory`` (default
``auto``: where CAP_IPC_LOCK) locks its memory and prefaults a heap (mlockall),
``--cpu N`` pins it. What was applied and what refused is printed on stderr
and returned by the ``timing`` control command, with the runner's own reply
times (:class:`ReplyTimes`).
"""

from __future__ import annotations

import argparse
import contextlib
import gc
import json
import os
import select
import signal
import socket
import struct
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

from fieldbus.core.dc.model import EscTiming
from fieldbus.core.dc.sim import spread_drifts
from fieldbus.core.ecat import ETHERTYPE_ECAT, FrameError
from fieldbus.core.pdo.model import DriveMap
from fieldbus.errors import FieldbusError
from fieldbus.interop.device import load_device
from fieldbus.platform.rt import RtConfig, realtime
from fieldbus.platform.timing import LatencyHistogram
from fieldbus.wire.packet_socket import ETH_P_ALL, bound_packet_socket
from fieldbus.wire.pcap import PcapWriter
from fieldbus.wire.sockfilter import DROP, JEQ_K, LDH_ABS, RET_K, attach_filter
from sim_slaves.ethercat.al import AlState
from sim_slaves.ethercat.axes import app_states
from sim_slaves.ethercat.chain import ETHERTYPE_VLAN, VLAN_TAG_SIZE, AppFactory, EscChain
from sim_slaves.ethercat.dc import DC_MIN_SAMPLE_INTERVAL_NS
from sim_slaves.ethercat.esc import App, LoopbackApp
from sim_slaves.od import ObjectDictionary

PACKET_OUTGOING = 4  # sockaddr_ll packet type of a frame sent on this interface
SOL_PACKET = 263
PACKET_ADD_MEMBERSHIP = 1
PACKET_MR_PROMISC = 1
PACKET_AUXDATA = 8
PACKET_IGNORE_OUTGOING = 23  # Linux >= 4.20; PACKET_OUTGOING is checked as well
TP_STATUS_VLAN_VALID = 0x10
TP_STATUS_VLAN_TPID_VALID = 0x40
_AUXDATA = struct.Struct("<IIIHHHH")  # tpacket_auxdata: status, len, snaplen, mac, net, vlan_tci, vlan_tpid
SO_TIMESTAMPNS = 35  # linux/asm-generic/socket.h: receive time of each frame (CLOCK_REALTIME) as a cmsg
_TIMESPEC = struct.Struct("@qq")
_AUX_SPACE = socket.CMSG_SPACE(_AUXDATA.size) + socket.CMSG_SPACE(_TIMESPEC.size)
_VLAN_TAG = struct.Struct(">HH")  # TPID, TCI as on the wire
# ldh [12]; jeq #0x88A4 ? accept : drop (the kernel has taken a VLAN tag out of the data already)
_ECAT_ONLY = ((LDH_ABS, 0, 0, 12), (JEQ_K, 0, 1, ETHERTYPE_ECAT), (RET_K, 0, 0, 0x40000), (RET_K, 0, 0, DROP))
SPIN_NS = 300_000  # after a frame, poll the socket this long before sleeping in poll()
RT_SPIN_NS = 50_000  # the same at SCHED_FIFO: shorter, the spin would keep a plain master off its CPU
YIELD_NS = 50_000  # at SCHED_FIFO, sleep this long after a reply before the work after it (AfterReply)
YIELD_GAP_NS = 300_000  # ... when at least this long passed since the frame before (a paced master)
ANTICIPATE_NS = 200_000  # at SCHED_FIFO, wake this long before a paced master's next frame is due
ANTICIPATE_LATE_NS = 100_000  # ... and poll until this long after it is due before sleeping again
DEFAULT_RT_PRIORITY = 40  # SCHED_FIFO priority where CAP_SYS_NICE allows it
CAP_SYS_NICE = 23  # capability numbers (linux/capability.h)
CAP_IPC_LOCK = 14
GC_GEN0 = 700  # net allocations before a young collection (CPython's default gen-0 threshold)
GC_OLDER = 10  # collections of a generation before the next one is collected (CPython's default)


def has_capability(cap: int) -> bool:
    """True if this process's effective capability set holds ``cap`` (``/proc/self/status`` CapEff)."""
    try:
        with open("/proc/self/status") as f:
            for line in f:
                if line.startswith("CapEff:"):
                    return bool(int(line.split()[1], 16) >> cap & 1)
    except OSError:
        pass
    return False


class IdleCollector:
    """Python's garbage collection moved out of the reply path: frozen, disabled, run in idle gaps.

    :meth:`start` collects once, freezes every object alive (start-up data:
    maps, object dictionaries, the chain; never scanned again) and disables
    the automatic collector, which would otherwise run in the middle of a
    frame whenever allocations cross its threshold. The runner calls
    :meth:`gap` when no frame is waiting: it collects the young generation
    (and, as CPython's thresholds would, an older one now and then) there.
    A full collection waits for :meth:`quiet` (no frame for a whole poll
    timeout), unless garbage piles up. :meth:`stop` restores the collector.
    """

    def __init__(self) -> None:
        self.was_enabled = gc.isenabled()
        self.collections = 0

    def start(self) -> None:
        gc.collect()
        gc.freeze()
        gc.disable()

    def gap(self) -> bool:
        """Collect if the young generation is due; True if it did (time was spent: look for frames again)."""
        young, gen1, gen2 = gc.get_count()
        if young < GC_GEN0:
            return False
        if gen1 >= GC_OLDER:
            gc.collect(2 if gen2 >= GC_OLDER * GC_OLDER else 1)
        else:
            gc.collect(0)
        self.collections += 1
        return True

    def quiet(self) -> None:
        """No frames for a while: a full collection if anything is left for it."""
        if any(gc.get_count()):
            gc.collect()
            self.collections += 1

    def stop(self) -> None:
        gc.unfreeze()
        if self.was_enabled:
            gc.enable()


class AfterReply:
    """What the runner does between a reply's send and the work after it (drive step, idle work, spin).

    At SCHED_FIFO that work keeps every plain process off the runner's CPU,
    and the master woken by the reply is often placed there (the kernel puts
    a wakee near its waker): it would wait until the work is done, 100-200 µs
    with a few drives. ``yield`` (the default) waits up to :data:`YIELD_NS`
    first, so the master takes its reply (a frame arriving meanwhile ends the
    wait: the frames of one cycle follow each other), when the frame came at
    least :data:`YIELD_GAP_NS` after the one before: a master that paces its
    cycle has that time to spare, one that sends flat out would only find
    the work in front of its next frame; ``hold`` goes straight on.
    (Dropping to the plain policy for the work instead was measured: on a
    busy machine the work, and with it the next frame, then waits for
    milliseconds.) Without SCHED_FIFO both go straight on.
    """

    def __init__(self, mode: str, sock: socket.socket | None = None) -> None:
        if mode not in ("yield", "hold"):
            raise ValueError(f"after a reply: 'yield' or 'hold', not {mode!r}")
        self.mode = mode if os.sched_getscheduler(0) == os.SCHED_FIFO else "hold"
        self.sock = sock  # the port: a frame arriving ends the wait
        self.last_ns = 0  # when the frame before arrived (monotonic)

    def replied(self, arrived_ns: int) -> None:
        """The reply to the frame that arrived at ``arrived_ns`` (monotonic) is sent: let a master that
        shares the CPU take it (``yield``, a paced master)."""
        gap, self.last_ns = arrived_ns - self.last_ns, arrived_ns
        if self.mode == "yield" and gap >= YIELD_GAP_NS:
            if self.sock is not None:
                select.select([self.sock], [], [], YIELD_NS / 1e9)
            else:
                time.sleep(YIELD_NS / 1e9)


class Anticipator:
    """Learns a paced master's cycle and says when its next frame is due, so that the runner is
    already polling the socket when it comes (a wake-up from sleep is the tail of the reply time).

    A cycle starts with a frame that arrives at least :data:`YIELD_GAP_NS` after the one before;
    the period is a running mean of the starts' spacing, trusted after :data:`STEADY` starts in a
    row within an eighth of it. Times are the kernel's receive stamps [ns, CLOCK_REALTIME].
    ``lead_ns`` 0 turns it off.
    """

    STEADY = 8

    def __init__(self, lead_ns: int, late_ns: int = ANTICIPATE_LATE_NS) -> None:
        self.lead_ns = lead_ns
        self.late_ns = late_ns
        self.last_ns = 0  # the frame before
        self.start_ns = 0  # the current cycle's first frame
        self.period_ns = 0
        self.steady = 0

    def arrived(self, at_ns: int) -> None:
        """A frame arrived at ``at_ns``."""
        gap, self.last_ns = at_ns - self.last_ns, at_ns
        if gap < YIELD_GAP_NS:
            return
        if self.start_ns:
            period = at_ns - self.start_ns
            if self.period_ns and abs(period - self.period_ns) * 8 < self.period_ns:
                self.steady = min(self.steady + 1, self.STEADY)
                self.period_ns += (period - self.period_ns) // 8
            else:
                self.steady = 0
                self.period_ns = period
        self.start_ns = at_ns

    def due_ns(self, now_ns: int) -> int:
        """When the next cycle's first frame is due [ns], or 0: not steady, off, or already overdue
        by more than ``late_ns`` (the master paused: sleep until it sends)."""
        if not self.lead_ns or self.steady < self.STEADY:
            return 0
        due = self.start_ns + self.period_ns
        if now_ns > due + self.late_ns:
            return 0
        return due


def reply_timing(priority: str, cpu: int | None, lock_memory: str) -> RtConfig:
    """The real-time settings the runner asks for: ``priority`` "auto" (SCHED_FIFO at
    :data:`DEFAULT_RT_PRIORITY` if CAP_SYS_NICE), "off", or a number 1-99; ``lock_memory``
    "auto" (mlockall if CAP_IPC_LOCK), "on" or "off"."""
    lock = lock_memory == "on" or (lock_memory == "auto" and has_capability(CAP_IPC_LOCK))
    level: int | None
    if priority == "off":
        level = None
    elif priority == "auto":
        level = DEFAULT_RT_PRIORITY if has_capability(CAP_SYS_NICE) else None
    else:
        level = int(priority)
    return RtConfig(priority=level, cpu=cpu, lock_memory=lock)


def loopback_app(drive: DriveMap, od: ObjectDictionary) -> App:
    """Outputs copied to inputs entry by entry (same position, same bit length)."""
    from sim_slaves.od import RXPDO_ASSIGN, TXPDO_ASSIGN

    outs = [c for p in od.assigned_pdos(RXPDO_ASSIGN) for c in p.channels if not c.is_gap]
    ins = [c for p in od.assigned_pdos(TXPDO_ASSIGN) for c in p.channels if not c.is_gap]
    pairs = [
        ((o.index, o.sub_index), (i.index, i.sub_index))
        for o, i in zip(outs, ins, strict=False)
        if o.bits == i.bits
    ]
    return LoopbackApp(pairs)


def network_slaves(path: str, bus_name: str | None) -> tuple[list[DriveMap], list[dict[str, Any] | None]]:
    """The drive maps and emulator options (``DriveParams`` keywords) of one EtherCAT bus of a network file."""
    from fieldbus.core.network import load_network
    from sim_slaves.emulator_options import drive_options

    net = load_network(path)
    buses = [b for b in net.buses if b.type == "ethercat"]
    if bus_name is not None:
        buses = [b for b in buses if b.name == bus_name]
    if len(buses) != 1:
        names = ", ".join(b.name for b in net.buses if b.type == "ethercat") or "none"
        which = (
            f"no EtherCAT bus '{bus_name}'" if bus_name else "more than one EtherCAT bus: name one with --bus"
        )
        raise FieldbusError(f"{path}: {which} (EtherCAT buses: {names})")
    slaves = buses[0].slaves
    return [s.map for s in slaves], [drive_options(s.emulator) for s in slaves]


def build_chain(
    maps: list[str],
    count: int,
    app: str,
    *,
    drift_ppm: float = 0.0,
    drift_seed: int = 0,
    dc_timing: EscTiming | None = None,
    cable_m: float = 1.0,
    dc_min_sample_interval_ns: int = DC_MIN_SAMPLE_INTERVAL_NS,
    devices: list[DriveMap] | None = None,
    drive_params: list[dict[str, Any] | None] | None = None,
) -> EscChain:
    """The chain of ``maps`` (drive maps, ESI or EDS files) repeated ``count`` times, or of ``devices``
    (already loaded, with per-slave ``drive_params``), as the options of :func:`main` say."""
    drives = devices if devices is not None else [load_device(m) for m in maps] * count
    factory: str | AppFactory | None = {"auto": "auto", "none": None, "loopback": loopback_app}[app]
    drifts = spread_drifts(len(drives), drift_ppm, drift_seed).tolist() if drift_ppm else None
    return EscChain.from_maps(
        drives,
        app=factory,
        drift_ppm=drifts,
        dc_timing=dc_timing,
        cable_m=cable_m,
        dc_min_sample_interval_ns=dc_min_sample_interval_ns,
        drive_params=drive_params,
    )


def _dc_command(chain: EscChain, msg: dict[str, Any], now_ns: int) -> dict[str, Any]:
    """``dc``: the DC status at ``now_ns``; ``dc_config``: change drifts / line first, then the status."""
    if msg.get("cmd") == "dc_config":
        drift = msg.get("drift_ppm")
        if isinstance(drift, list):
            chain.set_dc_drift([float(d) for d in drift], now_ns)
        elif drift is not None:
            drifts = spread_drifts(len(chain), float(drift), int(msg.get("seed", 0)))
            chain.set_dc_drift(drifts.tolist(), now_ns)
        if "processing_ns" in msg or "forwarding_ns" in msg or "cable_m" in msg:
            t = chain.dc_timing
            timing = EscTiming(
                processing_ns=float(msg.get("processing_ns", t.processing_ns)),
                forwarding_ns=float(msg.get("forwarding_ns", t.forwarding_ns)),
            )
            cable = msg.get("cable_m")
            chain.set_dc_line(timing, None if cable is None else float(cable))
        if "min_sample_interval_ns" in msg:
            chain.dc_line.min_sample_interval_ns = int(msg["min_sample_interval_ns"])
    line = chain.dc_line
    return {
        "ok": True,
        "frames": chain.frames,
        "dc": {
            "now_ns": now_ns,
            "slaves": chain.dc_status(now_ns),
            "samples": line.samples,
            "skipped": line.skipped,
            "min_sample_interval_ns": line.min_sample_interval_ns,
        },
    }


def handle_control(
    chain: EscChain, msg: dict[str, Any], now_ns: int | None = None, *, times: ReplyTimes | None = None
) -> dict[str, Any]:
    """Apply one control command to ``chain``; the answer to send back.

    ``now_ns``: the chain's time line (default ``time.monotonic_ns()``, the
    runner's frame clock), used by the DC commands; ``times``: the runner's
    reply times (the ``timing`` command).
    """
    cmd = msg.get("cmd")
    if cmd == "timing":
        return _timing(chain, msg, times)
    if cmd in ("dc", "dc_config"):
        return _dc_command(chain, msg, time.monotonic_ns() if now_ns is None else now_ns)
    answer = _inject(chain, cmd, msg)
    return _status(chain) if answer is None else answer


def _timing(chain: EscChain, msg: dict[str, Any], times: ReplyTimes | None) -> dict[str, Any]:
    """The ``timing`` command: the runner's reply times and settings (``reset``: start them again)."""
    if times is None:
        return {"ok": False, "error": "no reply times here"}
    answer = {
        "ok": True,
        "frames": chain.frames,
        "reply_us": times.to_json(),
        **times.settings,
        "gc": {"enabled": gc.isenabled(), "frozen": gc.get_freeze_count()},
    }
    if msg.get("reset"):
        times.reset()
    return answer


def _inject(chain: EscChain, cmd: object, msg: dict[str, Any]) -> dict[str, Any] | None:
    """A fault-injection (or read-out) command on the chain or one of its slaves; its own answer, or
    None when the answer is the chain's :func:`_status`."""
    slave = int(msg.get("slave", 0))
    if cmd == "drop":
        chain.drop_frames(int(msg.get("count", 1)), process_data=bool(msg.get("pd")))
    elif cmd == "delay":
        chain.delay_frames(float(msg["seconds"]), int(msg.get("count", 1)))
    elif cmd == "corrupt_wkc":
        chain.corrupt_wkc(
            int(msg.get("delta", -1)), int(msg.get("count", 1)), all_frames=bool(msg.get("all"))
        )
    elif cmd == "power_cycle":
        chain.power_cycle(slave)
    elif cmd == "refuse_state":
        chain.refuse_state(slave, AlState[str(msg["state"]).upper()], int(msg["code"]))
    elif cmd == "abort_sdo":
        sub = msg.get("sub")
        chain.abort_sdo(slave, int(msg["index"]), None if sub is None else int(sub), int(msg["code"]))
    elif cmd == "mute_mailbox":
        chain.mute_mailbox(slave, stuck=bool(msg.get("stuck")))
    elif cmd == "stick_eeprom":
        chain.stick_eeprom(slave)
    elif cmd == "bit_errors":
        chain.bit_errors(
            slave,
            float(msg.get("rate", 0.05)),
            seed=int(msg.get("seed", 0)),
            direction=str(msg.get("direction", "both")),
            frames=int(msg.get("frames", -1)),
        )
    elif cmd == "flap_link":
        chain.flap_link(slave)
    elif cmd == "sii":
        esc = chain.slaves[slave]
        return {"ok": True, "sii": bytes(esc.sii.data).hex(), "alias": esc.alias, "loaded": esc.eeprom_loaded}
    elif cmd == "foe_power_loss":
        chain.cut_power_during_foe(slave, int(msg["after_bytes"]))
    elif cmd == "foe_busy":
        chain.foe_busy(slave, int(msg.get("answers", 1)))
    elif cmd == "firmware":
        store = chain.slaves[slave].firmware
        if "password" in msg:
            store.password = int(msg["password"])
        return {"ok": True, "frames": chain.frames, "firmware": store.status()}
    elif cmd == "emergency":
        chain.emergency(slave, int(msg["code"]), int(msg.get("register", 0)))
    elif cmd == "drive_fault":
        inject = getattr(chain.slaves[slave].app, "inject_fault", None)
        if inject is None:
            return {"ok": False, "error": f"slave {slave} has no CiA 402 drive"}
        axis = int(msg.get("axis", 0))  # 0-based axis of a multi-axis slave
        if axis:
            inject(int(msg["code"]), axis=axis)
        else:
            inject(int(msg["code"]))
        chain.emergency(slave, int(msg["code"]), 0x01)
    elif cmd == "clear":
        chain.clear_faults()
    elif cmd == "status":
        pass
    else:
        return {"ok": False, "error": f"unknown command {cmd!r}"}
    return None


def _status(chain: EscChain) -> dict[str, Any]:
    """The chain's frames and each slave's AL state, AL status code and drive states."""
    return {
        "ok": True,
        "frames": chain.frames,
        "states": [int(s.state) for s in chain.slaves],
        "al_status_codes": [s.status_code for s in chain.slaves],
        # CiA 402 State402 of each emulated drive (each axis of a multi-axis slave), -1: no drive application
        "drive_states": [st for s in chain.slaves for st in app_states(s.app)],
    }


def send_control(path: str | Path, msg: dict[str, Any], timeout_s: float = 2.0) -> dict[str, Any]:
    """Send one command to a runner's ``--control`` socket and wait for its answer."""
    with socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM) as s:
        me = os.path.join(tempfile.gettempdir(), f"fbctl-{os.getpid()}-{time.monotonic_ns()}")
        s.bind(me)
        try:
            s.settimeout(timeout_s)
            s.sendto(json.dumps(msg).encode(), str(path))
            answer: dict[str, Any] = json.loads(s.recv(65536))
            return answer
        finally:
            os.unlink(me)


def open_port0(iface: str) -> socket.socket:
    """The emulated chain's port 0 on ``iface``: a non-blocking packet socket for every EtherCAT frame.

    Every protocol (a VLAN-tagged frame reaches only such a socket with its
    tag, as PACKET_AUXDATA), an in-kernel filter for ethertype 0x88A4,
    promiscuous mode (any destination MAC), its own sends not looped back.
    The filter, promiscuous mode and ignoring outgoing frames are best
    effort: :func:`serve` checks ethertype and packet type itself.
    """
    sock = bound_packet_socket(iface, ETH_P_ALL)  # from its first frame on, this interface's only
    try:
        sock.setsockopt(SOL_PACKET, PACKET_AUXDATA, 1)
        with contextlib.suppress(OSError):
            sock.setsockopt(SOL_PACKET, PACKET_IGNORE_OUTGOING, 1)
        with contextlib.suppress(OSError):
            mreq = struct.pack("iHH8s", socket.if_nametoindex(iface), PACKET_MR_PROMISC, 0, b"")
            sock.setsockopt(SOL_PACKET, PACKET_ADD_MEMBERSHIP, mreq)
        with contextlib.suppress(OSError):
            attach_filter(sock, _ECAT_ONLY)
        with contextlib.suppress(OSError):
            sock.setsockopt(socket.SOL_SOCKET, SO_TIMESTAMPNS, 1)
        sock.setblocking(False)
    except BaseException:
        sock.close()
        raise
    return sock


def received_ns(ancdata: list[tuple[int, int, bytes]]) -> int:
    """When the kernel received the frame (SO_TIMESTAMPNS, CLOCK_REALTIME ns), 0 if the cmsg is missing."""
    for level, kind, data in ancdata:
        if level == socket.SOL_SOCKET and kind == SO_TIMESTAMPNS and len(data) >= _TIMESPEC.size:
            sec, nsec = _TIMESPEC.unpack_from(data)
            return int(sec * 1_000_000_000 + nsec)
    return 0


class ReplyTimes:
    """The emulator's own reply time: from the kernel's receipt of a frame to the return of its reply's send.

    ``reply`` includes the runner's wake-up and the frame's processing, not
    the master's side; ``pickup`` is the part until the runner has the frame
    (the kernel's delivery and the runner's wake-up). ``{"cmd": "timing"}``
    on the control socket reads both (``"reset": true`` starts afresh).
    """

    def __init__(self, settings: dict[str, Any] | None = None) -> None:
        self.reply = LatencyHistogram(max_us=20_000)
        self.pickup = LatencyHistogram(max_us=20_000)
        self.over_1ms = 0
        self.settings = settings or {}  # what the runner applied (scheduling, memory, collector)

    def reset(self) -> None:
        self.reply = LatencyHistogram(max_us=20_000)
        self.pickup = LatencyHistogram(max_us=20_000)
        self.over_1ms = 0

    def add(self, received_ns: int, picked_ns: int, sent_ns: int) -> None:
        """One frame: kernel receipt, runner has it, reply sent (CLOCK_REALTIME ns)."""
        reply = sent_ns - received_ns
        self.reply.add(reply)
        self.pickup.add(picked_ns - received_ns)
        if reply > 1_000_000:
            self.over_1ms += 1

    def to_json(self) -> dict[str, Any]:
        return {**self.reply.to_json(), "over_1ms": self.over_1ms, "pickup": self.pickup.to_json()}


def vlan_tag(ancdata: list[tuple[int, int, bytes]]) -> int | None:
    """The TCI of the 802.1Q tag the kernel took out of a received frame, None if it had none.

    ``ancdata`` is ``recvmsg``'s with PACKET_AUXDATA on; a tag with another
    TPID (802.1ad) gives -1: not a frame an ESC processes.
    """
    for level, kind, data in ancdata:
        if level != SOL_PACKET or kind != PACKET_AUXDATA or len(data) < _AUXDATA.size:
            continue
        status, _len, _snap, _mac, _net, tci, tpid = _AUXDATA.unpack_from(data)
        if not status & TP_STATUS_VLAN_VALID:
            return None
        if status & TP_STATUS_VLAN_TPID_VALID and tpid != ETHERTYPE_VLAN:
            return -1
        return int(tci)
    return None


def insert_vlan_tag(buf: bytearray, n: int, tci: int) -> int:
    """Put the 802.1Q tag back after the MAC addresses of the ``n``-byte frame in ``buf``; new length."""
    buf[12 + VLAN_TAG_SIZE : n + VLAN_TAG_SIZE] = buf[12:n]
    _VLAN_TAG.pack_into(buf, 12, ETHERTYPE_VLAN, tci)
    return n + VLAN_TAG_SIZE


def serve(
    chain: EscChain,
    iface: str,
    *,
    pcap: str | None = None,
    control: str | None = None,
    timing: RtConfig | None = None,
    spin_ns: int | None = None,
    after_reply: str = "yield",
    anticipate_ns: int | None = None,
) -> None:
    """Answer frames on ``iface`` until SIGTERM/SIGINT; ``timing``: real-time settings (None: none);
    ``spin_ns``: how long to poll the socket after a reply before sleeping (default :data:`SPIN_NS`);
    ``anticipate_ns``: wake this long before a paced master's next frame (default
    :data:`ANTICIPATE_NS` at SCHED_FIFO, else 0: off, the spin would take a plain master's CPU)."""
    with realtime(timing or RtConfig(), warn=_note) as applied:
        for line in applied.applied:
            _note(f"real-time: {line}")
        fifo = os.sched_getscheduler(0) == os.SCHED_FIFO
        collector = IdleCollector()
        collector.start()
        try:
            _serve(
                chain,
                iface,
                pcap=pcap,
                control=control,
                collector=collector,
                spin_ns=(RT_SPIN_NS if fifo else SPIN_NS) if spin_ns is None else spin_ns,
                times=ReplyTimes({"realtime": applied.to_json(), "sched_fifo": fifo}),
                after=AfterReply(after_reply),
                anticipate=Anticipator(
                    (ANTICIPATE_NS if fifo else 0) if anticipate_ns is None else anticipate_ns
                ),
            )
        finally:
            collector.stop()


def _note(line: str) -> None:
    print(line, file=sys.stderr, flush=True)


def _serve(
    chain: EscChain,
    iface: str,
    *,
    pcap: str | None,
    control: str | None,
    collector: IdleCollector,
    spin_ns: int,
    times: ReplyTimes,
    after: AfterReply,
    anticipate: Anticipator,
) -> None:
    sock = open_port0(iface)
    after.sock = sock
    ctl = _control_socket(control) if control else None
    writer = PcapWriter(pcap) if pcap else None
    stop = _stop_on_signals()
    poller = select.poll()
    poller.register(sock.fileno(), select.POLLIN)
    if ctl is not None:
        poller.register(ctl.fileno(), select.POLLIN)
    buf = bytearray(2048)
    view = memoryview(buf)
    into = [view[: len(buf) - VLAN_TAG_SIZE]]  # room to put a VLAN tag back
    recv_into = sock.recvmsg_into
    send = sock.send
    clock = time.monotonic_ns
    wall = time.time_ns  # the clock of the kernel's receive timestamps
    dc_line = chain.dc_line
    print(f"ready {iface} {len(chain)} slaves", flush=True)
    try:
        while not stop:
            spin_until = _wait_for_frame(sock, poller, anticipate)
            if spin_until < 0:  # nothing came: the chain's time goes on, garbage may be collected
                chain.tick(clock())
                collector.quiet()
                continue
            if ctl is not None:
                _serve_control(chain, ctl, times)
            while True:
                try:
                    n, anc, _flags, addr = recv_into(into, _AUX_SPACE)
                except BlockingIOError:
                    if dc_line.pending:  # idle: the queued DC loop samples of the last FRMWs
                        dc_line.flush()
                        continue
                    if chain.idle():  # idle: copy plans after a configuration change
                        continue
                    if collector.gap():  # idle: garbage collection, never while a frame waits
                        continue
                    # busy-wait briefly for the master's next frame: a poll() wake-up costs more
                    if not spin_until:
                        spin_until = clock() + spin_ns
                    if clock() < spin_until:
                        continue
                    break
                spin_until = 0
                if addr[2] == PACKET_OUTGOING or n < 16 or buf[12] << 8 | buf[13] != ETHERTYPE_ECAT:
                    continue
                arrived = picked = 0
                if anc:
                    tci = vlan_tag(anc)
                    if tci is not None:
                        if tci < 0:
                            continue
                        n = insert_vlan_tag(buf, n, tci)
                    arrived = received_ns(anc)
                    picked = wall()
                    anticipate.arrived(arrived)
                _reply(chain, buf, view, n, clock(), send, writer, after, times, arrived, picked)
    finally:
        sock.close()
        if writer is not None:
            writer.close()
        if ctl is not None:
            ctl.close()
            if control and os.path.exists(control):
                os.unlink(control)


def _control_socket(path: str) -> socket.socket:
    """The fault-injection commands' UNIX datagram socket at ``path`` (replacing a stale one), non-blocking."""
    if os.path.exists(path):
        os.unlink(path)
    ctl = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    ctl.bind(path)
    ctl.setblocking(False)
    return ctl


class _Stop:
    """Set by SIGTERM / SIGINT: the serve loop ends after the frame in hand."""

    def __init__(self) -> None:
        self.asked = False

    def __bool__(self) -> bool:
        return self.asked

    def __call__(self, _sig: int, _frame: object) -> None:
        self.asked = True


def _stop_on_signals() -> _Stop:
    stop = _Stop()
    signal.signal(signal.SIGTERM, stop)
    signal.signal(signal.SIGINT, stop)
    return stop


def _wait_for_frame(sock: socket.socket, poller: select.poll, anticipate: Anticipator) -> int:
    """Wait for the master's next frame: a paced master's, sleeping until shortly before it is due;
    otherwise up to 20 ms in poll(). Returns until when to poll for it (monotonic ns; 0: the default
    spin), -1 when nothing came."""
    wall = time.time_ns
    due = anticipate.due_ns(wall())
    if due:  # a paced master: sleep until shortly before its frame, then poll for it
        ahead = due - anticipate.lead_ns - wall()
        if ahead > 0:
            select.select([sock], [], [], ahead / 1e9)
        return time.monotonic_ns() + max(0, due + anticipate.late_ns - wall())
    return 0 if poller.poll(20) else -1


def _reply(
    chain: EscChain,
    buf: bytearray,
    view: memoryview,
    n: int,
    now: int,
    send: Any,
    writer: PcapWriter | None,
    after: AfterReply,
    times: ReplyTimes,
    arrived: int,
    picked: int,
) -> None:
    """The chain processes the ``n``-byte frame in ``buf`` (``view``: a view of it) at ``now`` (monotonic ns) and sends its reply
    (held back by a delay fault), written to the pcap too; the reply time goes to ``times`` (from the
    kernel's receipt ``arrived``, runner pickup ``picked``; 0: not known), then the slaves' cycles run."""
    if writer is not None:
        writer.write(bytes(view[:n]), time.time())
    try:
        m = chain.process_into(buf, n, now, cycles=False)
    except FrameError as e:
        print(f"dropped malformed frame: {e}", file=sys.stderr, flush=True)
        return
    if not m:
        return
    delay = chain.take_delay()
    if delay:
        time.sleep(delay)
    send(view[:m])
    if arrived and not delay:
        times.add(arrived, picked, time.time_ns())
    after.replied(now)
    if writer is not None:
        writer.write(bytes(view[:m]), time.time())
    chain.run_cycles(now)


def _serve_control(chain: EscChain, ctl: socket.socket, times: ReplyTimes | None = None) -> None:
    while True:
        try:
            data, sender = ctl.recvfrom(65536)
        except BlockingIOError:
            return
        try:
            answer = handle_control(chain, json.loads(data), times=times)
        except (ValueError, KeyError, IndexError, TypeError) as e:
            answer = {"ok": False, "error": f"{type(e).__name__}: {e}"}
        if sender:
            with contextlib.suppress(OSError):
                ctl.sendto(json.dumps(answer).encode(), sender)


def _parser() -> argparse.ArgumentParser:
    """The runner's command line (``python -m sim_slaves.ethercat``)."""
    p = argparse.ArgumentParser(prog="python -m sim_slaves.ethercat", description=__doc__.split("\n\n")[0])
    p.add_argument("--iface", required=True, help="network interface, e.g. one end of a veth pair")
    p.add_argument(
        "--map",
        action="append",
        help="drive map YAML, or a vendor ESI (FILE.xml[#DEVICE]) or EDS (repeatable, wire order)",
    )
    p.add_argument("--network", help="instead of --map: the slaves of an EtherCAT bus of this network file")
    p.add_argument("--bus", help="with --network: which EtherCAT bus (default: its only one)")
    p.add_argument("--count", type=int, default=1, help="repeat the list of maps this many times")
    p.add_argument("--pcap", help="write requests and replies to this pcap file")
    p.add_argument("--control", help="UNIX datagram socket path for fault-injection commands (JSON)")
    p.add_argument("--app", choices=("auto", "loopback", "none"), default="auto", help="slave application")
    p.add_argument("--drift-ppm", type=float, default=0.0, help="DC: spread clock drifts over ±X ppm")
    p.add_argument("--drift-seed", type=int, default=0, help="DC: seed of the order of the drifts")
    p.add_argument(
        "--esc-delays-ns",
        type=float,
        nargs=2,
        metavar=("TP", "TF"),
        help="DC: ESC processing and forwarding delay (default 320 280)",
    )
    p.add_argument("--cable-m", type=float, default=1.0, help="DC: cable per hop in metres (5 ns/m)")
    p.add_argument(
        "--rt-priority",
        default="auto",
        help=f"SCHED_FIFO priority 1-99, 'off', or 'auto' (default: {DEFAULT_RT_PRIORITY} where CAP_SYS_NICE)",
    )
    p.add_argument("--cpu", type=int, help="pin the runner to this CPU")
    p.add_argument(
        "--after-reply",
        choices=("yield", "hold"),
        default="yield",
        help="at SCHED_FIFO, after a reply: wait up to 50 us first (default) or go straight on",
    )
    p.add_argument(
        "--spin-us",
        type=float,
        help="after a reply, poll the socket this long before sleeping (default 300, 50 at SCHED_FIFO)",
    )
    p.add_argument(
        "--anticipate-us",
        type=float,
        help="wake this long before a paced master's next frame is due and poll for it "
        f"(default {ANTICIPATE_NS // 1000} at SCHED_FIFO, else 0: off)",
    )
    p.add_argument(
        "--lock-memory",
        choices=("auto", "on", "off"),
        default="auto",
        help="mlockall and a prefaulted heap (default: where CAP_IPC_LOCK)",
    )
    p.add_argument(
        "--dc-min-sample-us",
        type=float,
        default=DC_MIN_SAMPLE_INTERVAL_NS / 1000,
        help="DC: least time between FRMW samples the clocks' loops take (0: every one)",
    )
    return p


def _checked(
    p: argparse.ArgumentParser, args: argparse.Namespace
) -> tuple[list[DriveMap] | None, list[dict[str, Any] | None] | None]:
    """The options checked together (``p.error`` on a bad mix); the slaves of ``--network`` if given."""
    devices: list[DriveMap] | None = None
    params: list[dict[str, Any] | None] | None = None
    if args.count < 1:
        p.error("--count must be >= 1")
    if bool(args.map) == bool(args.network):
        p.error("give either --map (one or more) or --network")
    if args.network and args.count != 1:
        p.error("--count repeats --map; a network file lists its slaves itself")
    if args.bus and not args.network:
        p.error("--bus needs --network")
    if args.network:
        try:
            devices, params = network_slaves(args.network, args.bus)
        except FieldbusError as exc:
            p.error(str(exc))
    if args.drift_ppm < 0 or args.cable_m < 0 or args.dc_min_sample_us < 0:
        p.error("--drift-ppm, --cable-m and --dc-min-sample-us must be >= 0")
    if args.rt_priority not in ("auto", "off") and not (
        args.rt_priority.isdigit() and 1 <= int(args.rt_priority) <= 99
    ):
        p.error("--rt-priority takes 1-99, 'auto' or 'off'")
    return devices, params


def main(argv: list[str] | None = None) -> int:
    p = _parser()
    args = p.parse_args(argv)
    devices, params = _checked(p, args)
    timing = EscTiming(*args.esc_delays_ns) if args.esc_delays_ns else None
    chain = build_chain(
        args.map or [],
        args.count,
        args.app,
        drift_ppm=args.drift_ppm,
        drift_seed=args.drift_seed,
        dc_timing=timing,
        cable_m=args.cable_m,
        dc_min_sample_interval_ns=round(args.dc_min_sample_us * 1000),
        devices=devices,
        drive_params=params,
    )
    serve(
        chain,
        args.iface,
        pcap=args.pcap,
        control=args.control,
        timing=reply_timing(args.rt_priority, args.cpu, args.lock_memory),
        spin_ns=None if args.spin_us is None else round(args.spin_us * 1000),
        after_reply=args.after_reply,
        anticipate_ns=None if args.anticipate_us is None else round(args.anticipate_us * 1000),
    )
    return 0
