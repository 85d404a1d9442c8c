"""In-process sim backend: the EtherCAT backend on its in-process transport, with fault hooks.

``backend: sim`` (or ``open_network(path, backend="sim")``) runs
:class:`~fieldbus.backends.ethercat.EthercatBackend` - its bring-up checks,
IO map copies, working-counter policy, stepwise recovery and in-OP mailbox,
the code that runs on hardware - with ``transport="in-process"``: pysoem's
API on the emulated ESC chain (:mod:`.ecat_inprocess`), found through
:mod:`fieldbus.emulators`. No network card, root or veth; frames, working
counters, AL states, the CoE mailbox and the SII are the emulator's.

Options (``open_network(path, backend="sim", **options)``):

- ``chain_maps``: drive maps the emulated slaves are built from, in wire
  order (default: the network's maps) - a different list makes an identity
  mismatch;
- ``error_counters``: read the ESC error counters in OP (as the ethercat
  backend: True, or N for one read in every N free cycles; :mod:`fieldbus.core.esc_errors`).
- ``clock``: the emulator's time, a :class:`~fieldbus.platform.clock.Clock`
  or a ``() -> ns`` function (default the wall clock). On a virtual clock
  (:class:`~fieldbus.platform.clock.VirtualClock`) runs are deterministic,
  and the master's waits pass on that clock: a lost frame costs the receive
  timeout, a delayed reply its delay.

Fault hooks: :attr:`SimBackend.chain` is the emulated chain (``drop_frames``,
``delay_frames``, ``corrupt_wkc``, ``power_cycle``, ``refuse_state``,
``abort_sdo``, ``emergency``); :meth:`SimBackend.corrupt_inputs` and
:meth:`SimBackend.delay_cycles` here. A delayed reply longer than the
receive timeout counts as lost, as it would on the wire. The public face of
these is :mod:`fieldbus.testing`.

Bus type ``ethercat`` run with ``backend="sim"``, or a bus of type ``sim``.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np

from fieldbus.backends.ethercat import EthercatBackend
from fieldbus.core.network import Bus
from fieldbus.errors import FieldbusError
from fieldbus.platform.clock import Clock


class _TimeSource:
    """A ``() -> ns`` function as a (real-time) :class:`~fieldbus.platform.clock.Clock`."""

    def __init__(self, now_ns: Callable[[], int]) -> None:
        self.now_ns = now_ns

    def sleep(self, seconds: float) -> None:
        time.sleep(seconds)


class SimBackend(EthercatBackend):
    """An EtherCAT bus emulated in-process: the ethercat backend on transport ``in-process``."""

    kind = "sim"

    def __init__(self, bus: Bus, **options: object) -> None:
        if bus.type not in ("ethercat", "sim"):
            raise FieldbusError(
                f"bus '{bus.name}': is {bus.type}: the sim backend emulates EtherCAT segments "
                "(CAN buses run on python-can's virtual interface: fieldbus demo --backend canopen|rawcan)"
            )
        clock = options.get("clock")
        if callable(clock) and not isinstance(clock, Clock):  # a bare () -> ns function: the chain's time
            options = {**options, "clock": _TimeSource(clock)}
        maps = options.get("chain_maps")  # any sequence of drive maps, as a list for the transport
        if maps is not None:
            if not isinstance(maps, Sequence):
                raise FieldbusError(f"bus '{bus.name}': option chain_maps is not a sequence of drive maps")
            options = {**options, "chain_maps": list(maps)}
        # as on the ethercat backend: the ESC error counters read in OP, one datagram in a free cycle
        options = {**options, "error_counters": options.get("error_counters", False)}
        super().__init__(bus, **{**options, "transport": "in-process"})
        self._corrupt: dict[int, int] = {}  # slave -> cycles its inputs still arrive inverted

    @property
    def chain(self) -> Any:
        """The emulated ESC chain (its fault hooks: see the module)."""
        return self.master.chain

    def corrupt_inputs(self, slave: int, cycles: int = 1) -> None:
        """Slave ``slave``'s inputs (0-based on this bus) arrive with every bit inverted for ``cycles``
        process-data cycles, with a good working counter: fresh, wrong data."""
        self._corrupt[slave] = self._corrupt.get(slave, 0) + cycles
        self.on_inputs = self._invert_inputs

    def delay_cycles(self, seconds: float, cycles: int = 1) -> None:
        """The process-data replies of the next ``cycles`` cycles come back ``seconds`` late (recovery
        and SDO frames in between are not held back, as ``chain.delay_frames`` would hold them)."""
        self.master.hold_processdata(seconds, cycles)

    def clear_injections(self) -> None:
        """Undo :meth:`corrupt_inputs` and :meth:`delay_cycles` (the chain's own: ``chain.clear_faults()``)."""
        self._corrupt.clear()
        self.on_inputs = None
        self.master.hold_processdata(0.0, 0)

    def _invert_inputs(self) -> None:
        """After a reply's inputs arrived (``on_inputs``): the slaves of :meth:`corrupt_inputs` inverted."""
        for slave, left in list(self._corrupt.items()):
            row = self.in_row(slave)
            np.bitwise_xor(row, 0xFF, out=row)
            if left <= 1:
                del self._corrupt[slave]
            else:
                self._corrupt[slave] = left - 1
        if not self._corrupt:
            self.on_inputs = None
