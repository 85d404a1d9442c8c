"""Every cycle the master ran, kept for assertions and for comparing two runs bit for bit.

A :class:`Trace` is filled by the emulation after each ``exchange()`` (the
user's loop does not change): per cycle whether every bus was fresh, the
safe-stop latch, per bus the verdict, working counter and per-slave
freshness, and per axis group the inputs (as decoded this cycle) and the
outputs (as they stand after the cycle: on the cycle a safe stop latches,
the safe outputs that the next cycle sends). Arrays grow in chunks; the
cycle index is the position in them (0 = the first cycle after bring-up).
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

import numpy as np
import numpy.typing as npt

from fieldbus.errors import FieldbusError

if TYPE_CHECKING:
    from fieldbus.network import CycleResult, Network, Operational

CHUNK = 4096  # cycles added to the arrays at a time


def _zeros(shape: tuple[int, ...], dtype: Any) -> npt.NDArray[Any]:
    """Zeros, padding bytes of a structured dtype included (``np.zeros`` may leave those as they were),
    so that two equal traces are equal byte for byte."""
    dt = np.dtype(dtype)
    out: npt.NDArray[Any] = (
        np.zeros(int(np.prod(shape)) * dt.itemsize, dtype=np.uint8).view(dt).reshape(shape)
    )
    return out


class Trace:
    """Per-cycle record of an :class:`~fieldbus.network.Operational` (see the module)."""

    def __init__(self, op: Operational, network: Network) -> None:
        self._op = op
        self.bus_names = tuple(st.name for st in op.result.buses)
        self.group_names = tuple(op.groups)
        self._group_bus: dict[str, int] = {}
        self._group_rows: dict[str, npt.NDArray[np.intp]] = {}
        for name, g in op.groups.items():
            bus_name = next(b.bus.name for b in network.backends if g in b.groups)
            self._group_bus[name] = self.bus_names.index(bus_name)
            rows = np.arange(g.first, g.first + len(g.slaves))  # a multi-axis slave: a row per axis
            self._group_rows[name] = np.repeat(rows, g.image.n_axes // len(g.slaves))
        self.n = 0
        self._cap = 0
        self._fresh = np.zeros(0, dtype=bool)
        self._stop = np.zeros(0, dtype=bool)
        self._verdict = np.zeros((0, len(self.bus_names)), dtype=np.int8)
        self._wkc = np.zeros((0, len(self.bus_names)), dtype=np.int32)
        self._slave_fresh = [np.zeros((0, st.fresh.size), dtype=bool) for st in op.result.buses]
        self._inputs = {
            k: np.zeros((0, g.image.n_axes), g.image.inputs.values.dtype) for k, g in op.groups.items()
        }
        self._outputs = {
            k: np.zeros((0, g.image.n_axes), g.image.outputs.values.dtype) for k, g in op.groups.items()
        }

    def _grow(self) -> None:
        cap = self._cap + CHUNK

        def grown(a: npt.NDArray[Any]) -> npt.NDArray[Any]:
            out = _zeros((cap, *a.shape[1:]), a.dtype)
            out[: self.n] = a[: self.n]
            return out

        self._fresh, self._stop = grown(self._fresh), grown(self._stop)
        self._verdict, self._wkc = grown(self._verdict), grown(self._wkc)
        self._slave_fresh = [grown(a) for a in self._slave_fresh]
        self._inputs = {k: grown(a) for k, a in self._inputs.items()}
        self._outputs = {k: grown(a) for k, a in self._outputs.items()}
        self._cap = cap

    def note_events(self, events: list[Any]) -> None:
        """The cycle's events (kept in the result; nothing more to keep here)."""

    def close(self) -> None:
        """The network closed: the trace stays readable."""

    def capture(self, result: CycleResult, t0_ns: int = 0) -> None:
        """Keep this cycle (an observer of the network: called at the end of every ``exchange()``)."""
        if self.n == self._cap:
            self._grow()
        k = self.n
        self._fresh[k] = result.fresh
        self._stop[k] = result.safe_stop
        for j, st in enumerate(result.buses):
            self._verdict[k, j] = int(st.verdict)
            self._wkc[k, j] = st.wkc
            self._slave_fresh[j][k] = st.fresh
        for name, g in self._op.groups.items():
            # field by field: a whole-record copy may carry bytes between the fields along
            for dst, src in (
                (self._inputs[name][k], g.image.inputs.values),
                (self._outputs[name][k], g.image.outputs.values),
            ):
                for field in src.dtype.names or ():
                    dst[field] = src[field]
        self.n = k + 1

    # -- reading -----------------------------------------------------------------------------
    def __len__(self) -> int:
        return self.n

    def mark(self) -> int:
        """The index the next cycle will have: ``since=trace.mark()`` before injecting a fault."""
        return self.n

    @property
    def fresh(self) -> npt.NDArray[np.bool_]:
        """Per cycle: every slave of every bus delivered fresh inputs."""
        return self._fresh[: self.n]

    @property
    def safe_stop(self) -> npt.NDArray[np.bool_]:
        """Per cycle: the safe stop was latched after the cycle."""
        return self._stop[: self.n]

    def _bus(self, bus: str) -> int:
        if bus not in self.bus_names:
            raise FieldbusError(f"no bus '{bus}' in this trace (have: {', '.join(self.bus_names)})")
        return self.bus_names.index(bus)

    def verdict(self, bus: str) -> npt.NDArray[np.int8]:
        """Per cycle, bus ``bus``'s verdict (``fieldbus.core.wkc.Verdict``: 0 OK, 1 SHORT, 2 TIMEOUT)."""
        return self._verdict[: self.n, self._bus(bus)]

    def wkc(self, bus: str) -> npt.NDArray[np.int32]:
        """Per cycle, bus ``bus``'s working counter (CAN: frames that came; -1 before the first)."""
        return self._wkc[: self.n, self._bus(bus)]

    def slave_fresh(self, bus: str) -> npt.NDArray[np.bool_]:
        """Per cycle and slave of bus ``bus`` (wire / node order): its inputs were fresh."""
        return self._slave_fresh[self._bus(bus)][: self.n]

    def _group(self, group: str) -> None:
        if group not in self._inputs:
            raise FieldbusError(
                f"no axis group '{group}' in this trace (have: {', '.join(self.group_names)})"
            )

    def inputs(self, group: str) -> npt.NDArray[Any]:
        """Per cycle and axis, group ``group``'s inputs in engineering units (a structured array)."""
        self._group(group)
        return self._inputs[group][: self.n]

    def outputs(self, group: str) -> npt.NDArray[Any]:
        """Per cycle and axis, group ``group``'s outputs as they stood after the cycle."""
        self._group(group)
        return self._outputs[group][: self.n]

    def group_fresh(self, group: str) -> npt.NDArray[np.bool_]:
        """Per cycle and axis of group ``group``: that axis's slave delivered fresh inputs."""
        self._group(group)
        return self._slave_fresh[self._group_bus[group]][: self.n][:, self._group_rows[group]]

    def group_bus(self, group: str) -> str:
        """The bus that group ``group`` is on."""
        self._group(group)
        return self.bus_names[self._group_bus[group]]

    def arrays(self) -> dict[str, npt.NDArray[Any]]:
        """Everything kept, by name (``fresh``, ``safe_stop``, ``<bus>.verdict``, ``<group>.inputs``, ...).

        Two runs of a scenario on a virtual clock give equal arrays, bit for bit: inputs and
        outputs come as packed copies (no padding bytes between fields, whose contents numpy
        leaves undefined), so ``a.tobytes() == b.tobytes()`` compares the values themselves.
        """
        from numpy.lib.recfunctions import repack_fields

        out: dict[str, npt.NDArray[Any]] = {"fresh": self.fresh, "safe_stop": self.safe_stop}
        for b in self.bus_names:
            out[f"{b}.verdict"] = self.verdict(b)
            out[f"{b}.wkc"] = self.wkc(b)
            out[f"{b}.slave_fresh"] = self.slave_fresh(b)
        for g in self.group_names:
            out[f"{g}.inputs"] = repack_fields(self.inputs(g))
            out[f"{g}.outputs"] = repack_fields(self.outputs(g))
        return out
