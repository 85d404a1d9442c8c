"""LRW cycles per second of the EtherCAT emulator: in-process and over veth with pysoem driving.

    python benchmarks/emulator.py [--seconds 3] [--slaves 12 64] [--rounds 1] [--enable] [--no-veth]

In-process: ``EscChain.process_into`` on the cycle frames of a SOEM-like
mapping (one LRW per segment of <= 1486 bytes), slave application cycles
included. Over veth (root only): the real pysoem master in this process,
``python -m sim_slaves.ethercat`` in a child process on the peer end; one
cycle = ``send_processdata`` + ``receive_processdata``; cycles with a WKC
other than ``expected_wkc`` are counted. Slaves: Maxon EPOS4 maps (23 output
bytes, 25 input bytes each). Applications: ``none`` (ESC only), ``auto``
(the CiA 402 drives, stepped together in ``sim_slaves.drive_bank``). The
outputs are zeros: the drives stay in SWITCH ON DISABLED; with ``--enable``
they are enabled in CSP first (controlword 0x06, 0x07, 0x0F, mode 8) and
hold position 0 while measured, as a robot standing still. With ``--rounds
K`` each figure is the median of K rounds (the rounds of one configuration
run back to back), and the range is printed beside it: on a shared VM single
rounds scatter by tens of percent.
"""

from __future__ import annotations

import argparse
import os
import statistics
import struct
import subprocess
import sys
import time
from pathlib import Path

from fieldbus.core.cia402 import State402
from fieldbus.core.ecat import Command, Datagram, build_master_frame, decode_frame
from fieldbus.core.pdo.load import load_drive_map
from fieldbus.platform import capabilities
from sim_slaves.ethercat import EscChain
from sim_slaves.ethercat.bringup import bring_up

REPO = Path(__file__).resolve().parent.parent
MAXON = REPO / "tests" / "data" / "ethercat_driver_ros2" / "maxon_epos4_50_5.yaml"


#: the Maxon map's RxPDO: controlword, target position/velocity/torque, their offsets, mode of operation
OUTPUTS = struct.Struct("<Hiihiihb")
ENABLE = (0x06, 0x07, 0x0F)  # shutdown, switch on, enable operation
ENABLE_CYCLES = 30  # cycles per controlword
CSP = 8


def outputs(controlword: int) -> bytes:
    """One drive's output bytes: ``controlword``, CSP, every target 0."""
    return OUTPUTS.pack(controlword, 0, 0, 0, 0, 0, 0, CSP)


def image_frames(frames: list[bytes], image: bytes) -> list[bytearray]:
    """``frames`` (one LRW each) carrying the bytes of ``image`` at their logical addresses."""
    out = []
    for f in frames:
        dg = decode_frame(f).datagrams[0]
        data = image[dg.address : dg.address + len(dg.data)]
        out.append(bytearray(build_master_frame([Datagram(Command.LRW, dg.idx, dg.address, data)])))
    return out


def in_process(n: int, app: str, seconds: float, enable: bool = False) -> float:
    chain = EscChain.from_maps([load_drive_map(MAXON)] * n, app="auto" if app == "auto" else None)
    plan = bring_up(chain)
    frames = [bytearray(f) for f in plan.lrw_frames()]
    work = [(bytearray(f), len(f)) for f in frames]  # processed in place: refilled from the frames each cycle
    now = 0

    def cycle(sent: list[bytearray]) -> None:
        nonlocal now
        now += 250_000
        for i, (buf, size) in enumerate(work):
            buf[:] = sent[i]
            chain.process_into(buf, size, now)

    if enable and app == "auto":
        for cw in ENABLE:
            image = (outputs(cw) * n).ljust(plan.size, b"\0")
            staged = image_frames([bytes(f) for f in frames], image)
            for _ in range(ENABLE_CYCLES):
                cycle(staged)
        frames = staged
        if not (chain.bank.state == int(State402.OPERATION_ENABLED)).all():
            raise RuntimeError("in-process: the drives did not reach OPERATION ENABLED")
    cycles = 0
    t0 = time.perf_counter()
    end = t0 + seconds
    while time.perf_counter() < end:
        for _ in range(100):
            cycle(frames)
        cycles += 100
    return cycles / (time.perf_counter() - t0)


def _ip(*args: str) -> None:
    subprocess.run(["ip", *args], capture_output=True, check=False)


def over_veth(n: int, app: str, seconds: float, enable: bool = False) -> tuple[float, int]:
    import pysoem

    master_if, slave_if = f"fbbm{os.getpid() % 1000}", f"fbbs{os.getpid() % 1000}"
    _ip("link", "del", master_if)
    _ip("link", "add", master_if, "type", "veth", "peer", "name", slave_if)
    for name in (master_if, slave_if):
        _ip("link", "set", name, "arp", "off")
        _ip("link", "set", name, "up")
    cmd = [sys.executable, "-m", "sim_slaves.ethercat", "--iface", slave_if, "--map", str(MAXON)]
    proc = subprocess.Popen(
        [*cmd, "--count", str(n), "--app", app], cwd=REPO, stdout=subprocess.PIPE, text=True
    )
    try:
        assert proc.stdout is not None and proc.stdout.readline().startswith("ready")
        m = pysoem.Master()
        m.open(master_if)
        try:
            assert m.config_init() == n
            m.config_map()
            m.config_dc()
            m.state = pysoem.OP_STATE
            m.write_state()
            for _ in range(1000):
                m.send_processdata()
                m.receive_processdata(10_000)
                if m.state_check(pysoem.OP_STATE, 1000) == pysoem.OP_STATE:
                    break
            if enable and app == "auto":
                for cw in ENABLE:
                    for slave in m.slaves:
                        slave.output = outputs(cw)
                    for _ in range(ENABLE_CYCLES):
                        m.send_processdata()
                        m.receive_processdata(10_000)
                words = [struct.unpack_from("<H", slave.input)[0] for slave in m.slaves]
                if any(w & 0x6F != 0x27 for w in words):
                    raise RuntimeError(
                        f"over veth: not every drive is OPERATION ENABLED: {[hex(w) for w in words]}"
                    )
            expected = m.expected_wkc
            cycles = bad = 0
            t0 = time.perf_counter()
            end = t0 + seconds
            while time.perf_counter() < end:
                for _ in range(100):
                    m.send_processdata()
                    if m.receive_processdata(10_000) != expected:
                        bad += 1
                cycles += 100
            return cycles / (time.perf_counter() - t0), bad
        finally:
            m.close()
    finally:
        proc.terminate()
        proc.wait(5)
        _ip("link", "del", master_if)


def _figure(rates: list[float]) -> str:
    """The median of the rounds, and their range when there are several."""
    mid = statistics.median(rates)
    if len(rates) == 1:
        return f"{mid:,.0f}"
    return f"{mid:,.0f} ({min(rates) / 1000:.1f}k-{max(rates) / 1000:.1f}k)"


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--seconds", type=float, default=3.0)
    p.add_argument("--slaves", type=int, nargs="+", default=[12, 64])
    p.add_argument("--rounds", type=int, default=1, help="rounds per figure (median and range printed)")
    p.add_argument("--enable", action="store_true", help="drives enabled in CSP, holding position")
    p.add_argument("--no-veth", action="store_true")
    args = p.parse_args()
    veth = not args.no_veth and not capabilities.missing(capabilities.CAP_NET_ADMIN, capabilities.CAP_NET_RAW)
    print(f"cpus: {os.cpu_count()}, python {sys.version.split()[0]}")
    print(
        f"{'slaves':>6} {'app':>5} {'in-process [cycles/s]':>28} {'veth+pysoem [cycles/s]':>28} {'bad WKC':>8}"
    )
    for n in args.slaves:
        for app in ("none", "auto"):
            rates = [in_process(n, app, args.seconds, args.enable) for _ in range(args.rounds)]
            if veth:
                runs = [over_veth(n, app, args.seconds, args.enable) for _ in range(args.rounds)]
                vtxt, btxt = _figure([r for r, _ in runs]), str(sum(b for _, b in runs))
            else:
                vtxt, btxt = ("(--no-veth)" if args.no_veth else "(needs root)"), "-"
            print(f"{n:>6} {app:>5} {_figure(rates):>28} {vtxt:>28} {btxt:>8}", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
