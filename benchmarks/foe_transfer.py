"""An FoE firmware write over veth: our master's bounded mailbox steps beside SOEM's ``ecx_FOEwrite``.

    python benchmarks/foe_transfer.py [--size 100000] [--rounds 10] [--json]

The real pysoem master in this process, two emulated drives (``python -m
sim_slaves.ethercat``) on the peer end of a veth pair (root only). Slave 1 is
put in BOOTSTRAP once (SOEM's way: ``amend_mbx`` with the SII's bootstrap
mailbox, 512 bytes); every round writes the same image with both, in a
shuffled order, each after a BOOT -> INIT -> BOOT bounce (a fresh mailbox):

- ``pysoem``: ``slave.foe_write`` (SOEM polls SM1 inside one blocking call);
- ``steps``: :class:`fieldbus.backends.ecat_firmware.FirmwareSession` - one
  datagram per step (write SM0, poll SM1's status, read SM1), each waiting at
  most one reply, run back to back as ``fieldbus firmware`` does outside OP.

Reported: the median time per contender, the paired ratio steps / pysoem
(per round, then the median), and the emulator's frame count per contender
(frames per FoE packet). Compare ratios within one run: the machine is shared.
"""

from __future__ import annotations

import argparse
import json
import os
import random
import statistics
import struct
import time
from typing import Any

from fieldbus.commands.demo import DEMO_MAP
from fieldbus.testing import firmware_image


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--size", type=int, default=100_000, help="image payload bytes")
    ap.add_argument("--rounds", type=int, default=10)
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args()

    import pysoem

    from fieldbus.backends.ecat_firmware import FirmwareSession, run_steps
    from fieldbus.backends.ecat_mailbox import MailboxLayout
    from sim_slaves.ethercat.veth import emulated_segment

    image = firmware_image(0x00020000, args.size)
    times: dict[str, list[float]] = {"pysoem": [], "steps": []}
    frames: dict[str, list[int]] = {"pysoem": [], "steps": []}
    ratios: list[float] = []
    pysoem.settings.timeouts.ret = 20_000
    with emulated_segment([DEMO_MAP], count=2, app="none") as emu:
        master = pysoem.Master()
        master.open(emu.iface)
        try:
            assert master.config_init() == 2
            slave = master.slaves[1]
            session = FirmwareSession(master, 1)
            o_start, o_size = struct.unpack("<HH", slave.eeprom_read(0x14))
            i_start, i_size = struct.unpack("<HH", slave.eeprom_read(0x16))
            session.request(0x01)
            slave.amend_mbx("out", o_start, o_size)
            slave.amend_mbx("in", i_start, i_size)
            session.layout = MailboxLayout(o_start, o_size, i_start, i_size)
            rng = random.Random(0)

            def bounce() -> None:
                session.request(0x01)
                session.request(0x03)

            def pysoem_write() -> None:
                assert slave.foe_write("app.efw", 0, image, 5_000_000) > 0

            def steps_write() -> None:
                run_steps(session.transfer(session.foe("app.efw", image)))

            contenders = {"pysoem": pysoem_write, "steps": steps_write}
            for _ in range(args.rounds):
                order = list(contenders)
                rng.shuffle(order)
                this: dict[str, float] = {}
                for name in order:
                    bounce()
                    before = emu.command(cmd="status")["frames"]
                    t0 = time.perf_counter()
                    contenders[name]()
                    this[name] = time.perf_counter() - t0
                    frames[name].append(emu.command(cmd="status")["frames"] - before - 1)
                    times[name].append(this[name])
                ratios.append(this["steps"] / this["pysoem"])
        finally:
            master.close()
    packets = args.size // (512 - 12) + 2
    out: dict[str, Any] = {
        "bytes": len(image),
        "packets": packets,
        "median_s": {k: statistics.median(v) for k, v in times.items()},
        "ratio_steps_over_pysoem": statistics.median(ratios),
        "frames_per_packet": {k: statistics.median(v) / packets for k, v in frames.items()},
        "load": [f"{x:.2f}" for x in os.getloadavg()],
    }
    if args.json:
        print(json.dumps(out))
        return
    for k in times:
        print(
            f"{k:7s} median {out['median_s'][k] * 1e3:8.1f} ms  "
            f"{out['frames_per_packet'][k]:.2f} frames/packet"
        )
    print(f"steps / pysoem (paired, median of {args.rounds}): {out['ratio_steps_over_pysoem']:.2f}")
    print(f"load average {' '.join(out['load'])}")


if __name__ == "__main__":
    main()
