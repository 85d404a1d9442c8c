"""Emulated CANopen drives (CiA 301 + CiA 402) on a python-can bus.

``CanopenSimulator(bus, [(drive_map, node_id), ...])`` starts the nodes on one
python-can bus instance (for example ``can.Bus(interface="virtual",
channel=...)``) and stops them again; ``CanopenNode`` is one device, sans-IO.
"""

from sim_slaves.canopen.node import CanopenNode, NmtState
from sim_slaves.canopen.simulator import CanopenSimulator

__all__ = ["CanopenNode", "CanopenSimulator", "NmtState"]
