"""The backend contract: one bus, driven through bring-up phases and the cycle.

Template method (as python-can's ``recv`` over ``_recv_internal``): the
:class:`~fieldbus.network.Network` applies the working-counter policy, CiA 402
safe stop and statistics; a backend only moves bytes and runs bus-specific
bring-up. Directions are named from the master's side: ``outputs`` are the
RxPDOs (master -> drive), ``inputs`` the TxPDOs (drive -> master).

Process data live in one buffer per bus, ``iomap``: the outputs of every slave
in wire order, then their inputs, each slave's image starting on a byte (the
layout SOEM's ``config_map`` produces for byte-sized slaves). Groups of
consecutive slaves with the same map get one :class:`ProcessImage` whose wire
rows are views into ``iomap``: packing writes straight into it.
"""

from __future__ import annotations

import abc
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from fieldbus.core.network import Bus, Slave
from fieldbus.core.pdo.image import ProcessImage
from fieldbus.core.pdo.layout import MapLayout, layout
from fieldbus.errors import FieldbusError


@dataclass(frozen=True)
class SlaveArea:
    """Byte offsets of one slave's outputs and inputs in the bus ``iomap``."""

    slave: Slave
    layout: MapLayout
    out_offset: int
    in_offset: int

    @property
    def out_size(self) -> int:
        return self.layout.outputs.size

    @property
    def in_size(self) -> int:
        return self.layout.inputs.size


@dataclass
class AxisGroup:
    """Consecutive slaves of one bus sharing a drive map: one process image, one row per axis."""

    name: str
    slaves: tuple[Slave, ...]
    image: ProcessImage
    first: int  # index of the first slave on its bus


class Backend(abc.ABC):
    """One bus. Phases: ``open`` -> ``configure`` (PRE-OP, SDO plans) -> ``safe_op`` -> ``op``.

    Bring-up methods block (outside the cycle). ``send`` / ``receive`` are the
    hot path: no allocation that outlives the call, no blocking longer than the
    bus's receive timeout.
    """

    kind = "abstract"
    pdo_align = 1  # 1: EtherCAT bit packing inside a slave; 8: one CAN frame per PDO

    def __init__(self, bus: Bus, **options: object) -> None:
        """``options`` are backend specific (for example fault hooks of the sim backend)."""
        self.bus = bus
        self.options = options
        self.areas: list[SlaveArea] = []
        out = 0
        layouts = [layout(s.map, pdo_align=self.pdo_align) for s in bus.slaves]
        for s, lay in zip(bus.slaves, layouts, strict=True):
            self.areas.append(SlaveArea(s, lay, out, -1))
            out += lay.outputs.size
        total_out = out
        for i, area in enumerate(self.areas):
            self.areas[i] = SlaveArea(area.slave, area.layout, area.out_offset, out)
            out += area.layout.inputs.size
        self.out_bytes = total_out
        self.in_bytes = out - total_out
        self.iomap: npt.NDArray[np.uint8] = np.zeros(max(out, 1), dtype=np.uint8)
        self.groups = self._make_groups()

    # -- process image ---------------------------------------------------------
    def _make_groups(self) -> list[AxisGroup]:
        runs: list[list[int]] = []
        for i, area in enumerate(self.areas):
            if runs and self.areas[runs[-1][0]].slave.map is area.slave.map:
                runs[-1].append(i)
            else:
                runs.append([i])
        groups = []
        for run in runs:
            first = self.areas[run[0]]
            n = len(run)
            lay = first.layout
            out = self.iomap[first.out_offset : first.out_offset + n * lay.outputs.size].reshape(
                n, lay.outputs.size
            )
            inp = self.iomap[first.in_offset : first.in_offset + n * lay.inputs.size].reshape(
                n, lay.inputs.size
            )
            name = self.bus.name if len(runs) == 1 else f"{self.bus.name}.{first.slave.name}"
            slaves = tuple(self.areas[i].slave for i in run)
            groups.append(AxisGroup(name, slaves, ProcessImage(lay, n, out_wire=out, in_wire=inp), run[0]))
        return groups

    @property
    def n_slaves(self) -> int:
        return len(self.areas)

    @property
    def expected_wkc(self) -> int:
        """Working counter a complete cycle returns (EtherCAT rule; CAN backends override)."""
        from fieldbus.core.wkc import expected_wkc

        return expected_wkc([a.layout for a in self.areas])

    def slave_index(self, name: str) -> int:
        for i, a in enumerate(self.areas):
            if a.slave.name == name:
                return i
        raise FieldbusError(f"no slave '{name}' on bus '{self.bus.name}'")

    # -- bring-up (blocking, outside the cycle) -----------------------------------
    @abc.abstractmethod
    def open(self) -> None:
        """Open the interface and find the slaves (checks identity against the maps)."""

    @abc.abstractmethod
    def configure(self) -> None:
        """PRE-OP / PRE-OPERATIONAL: apply every slave's SDO plan and read it back."""

    @abc.abstractmethod
    def safe_op(self) -> None:
        """Map process data and go to SAFE-OP (inputs valid, outputs ignored by the drives)."""

    @abc.abstractmethod
    def op(self) -> None:
        """Go to OP / OPERATIONAL; raise :class:`StateTransitionError` with the reason on failure."""

    # -- cycle ----------------------------------------------------------------------
    @abc.abstractmethod
    def send(self) -> None:
        """Put this cycle's outputs (``iomap`` output area) on the bus."""

    @abc.abstractmethod
    def receive(self) -> int | None:
        """Wait up to the receive timeout; fill the ``iomap`` input area.

        Returns the working counter (CAN: the number of expected frames that
        arrived) or None on timeout. Inputs may be partly written on a miss:
        the Network only decodes them when the policy calls the cycle fresh.
        """

    def arrived(self) -> npt.NDArray[np.bool_] | None:
        """Per-slave arrival of this cycle's inputs when the bus can tell (CAN); else None."""
        return None

    def recover_step(self) -> bool:
        """One non-blocking recovery step for slaves not in OP (after a miss). True: all in OP."""
        return True

    # -- shut-down ----------------------------------------------------------------------
    @abc.abstractmethod
    def stop(self) -> None:
        """Leave OP (SAFE-OP/INIT or NMT pre-operational). Must not raise on a dead bus."""

    @abc.abstractmethod
    def close(self) -> None:
        """Release the interface. Idempotent."""

    # -- acyclic access ---------------------------------------------------------------
    def sdo_read(self, slave: int, index: int, sub_index: int) -> bytes:
        raise FieldbusError(f"{self.kind} backend has no SDO access")

    def sdo_write(self, slave: int, index: int, sub_index: int, data: bytes) -> None:
        raise FieldbusError(f"{self.kind} backend has no SDO access")
