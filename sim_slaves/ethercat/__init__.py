"""Emulated EtherCAT slaves that real masters (SOEM / pysoem) configure over the wire.

- :class:`EscChain` - sans-IO chain of :class:`Esc` slaves: ``process(frame, now_ns)``;
- :func:`build_sii` - SII EEPROM image from a drive map;
- ``python -m sim_slaves.ethercat --iface IF --map MAP.yaml`` - the chain on an
  interface (AF_PACKET), see :mod:`sim_slaves.ethercat.runner` and docs/emulator.md.
"""

from sim_slaves.ethercat.al import AlState, AlStatusCode
from sim_slaves.ethercat.chain import EscChain
from sim_slaves.ethercat.esc import Esc, LoopbackApp
from sim_slaves.ethercat.sii import SiiImage, build_sii

__all__ = ["AlState", "AlStatusCode", "Esc", "EscChain", "LoopbackApp", "SiiImage", "build_sii"]
