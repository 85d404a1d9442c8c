"""The EtherCAT emulator's control commands (``sim_slaves.ethercat.runner.handle_control``) for CANopen.

So a fault-injection harness (``fieldbus soak``, the shared tests) drives both
emulators the same way. States are reported in EtherCAT AL terms (8 = the
node is OPERATIONAL, 2 = PRE-OPERATIONAL, 4 = STOPPED, 1 = booting).
"""

from __future__ import annotations

from typing import Any

from sim_slaves.canopen.simulator import CanopenSimulator

NMT_TO_AL = {0x05: 0x08, 0x7F: 0x02, 0x04: 0x04, 0x00: 0x01}


def handle_control(sim: CanopenSimulator, msg: dict[str, Any]) -> dict[str, Any]:
    """drop, drop_frame, power_cycle, abort_sdo, emergency, heartbeat, bus_off, clear, status."""
    ids = sorted(sim.nodes)
    cmd = msg.get("cmd")
    count = int(msg.get("count", 1))
    if cmd == "drop":
        targets = [ids[int(msg["slave"])]] if "slave" in msg else ids
        for n in targets:
            sim.drop_tpdos(n, count * len(sim.node(n).drive.bus_map.tpdo))
    elif cmd == "drop_frame":  # one TPDO of one node
        sim.drop_tpdos(ids[int(msg.get("slave", 0))], 1)
    elif cmd == "power_cycle":
        sim.power_cycle(ids[int(msg["slave"])])
    elif cmd == "abort_sdo":
        sub = msg.get("sub")
        sim.abort_sdo(
            ids[int(msg["slave"])], int(msg["index"]), None if sub is None else int(sub), int(msg["code"])
        )
    elif cmd == "emergency":
        sim.send_emergency(ids[int(msg.get("slave", 0))], int(msg["code"]), int(msg.get("register", 1)))
    elif cmd == "bus_off":  # off=True: the node leaves the bus; off=False: it recovers and boots
        sim.bus_off(ids[int(msg.get("slave", 0))], bool(msg.get("off", True)))
    elif cmd == "heartbeat":
        sim.silence_heartbeat(ids[int(msg.get("slave", 0))], bool(msg.get("silent", True)))
    elif cmd == "clear":
        sim.clear_faults()
    elif cmd != "status":
        return {"ok": False, "error": f"unknown command {cmd!r}"}
    return {
        "ok": True,
        "states": [NMT_TO_AL.get(int(sim.node(n).state), 0) for n in ids],
        "drive_states": [int(getattr(sim.node(n).app, "state", -1)) for n in ids],
    }
