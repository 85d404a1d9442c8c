"""What a recording reads of a running network, as protocols (``fieldbus.network`` satisfies them).

The network starts recordings (``op.record()``), so the recording does not
import the network: it names here the parts of ``Operational``,
``CycleResult`` and ``BusStatus`` it reads, read-only. Times in ns.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import TYPE_CHECKING, Any, Protocol

import numpy as np
import numpy.typing as npt

if TYPE_CHECKING:
    from fieldbus.backends.base import Backend
    from fieldbus.core.network import NetworkConfig


class BusStatus(Protocol):
    """One bus in one cycle (updated in place each cycle)."""

    @property
    def fresh(self) -> npt.NDArray[np.bool_]: ...  # per slave: inputs decoded this cycle
    @property
    def verdict(self) -> int: ...  # fieldbus.core.safety.Verdict
    @property
    def wkc(self) -> int: ...
    @property
    def consecutive_misses(self) -> int: ...
    @property
    def safe_stop(self) -> bool: ...
    @property
    def dc_time_ns(self) -> int | None: ...
    @property
    def dc_sync_error_ns(self) -> int | None: ...
    @property
    def ran(self) -> bool: ...
    @property
    def recovering(self) -> bool: ...
    @property
    def recoveries(self) -> int: ...
    @property
    def recovery_error(self) -> str | None: ...


class CycleResult(Protocol):
    """What one ``exchange()`` returned (the same object every cycle)."""

    @property
    def buses(self) -> Sequence[BusStatus]: ...
    @property
    def cycle(self) -> int: ...
    @property
    def fresh(self) -> bool: ...
    @property
    def safe_stop(self) -> bool: ...
    @property
    def exchange_ns(self) -> int: ...


class BusView(Protocol):
    """One running bus: its backend."""

    @property
    def backend(self) -> Backend: ...


class NetworkView(Protocol):
    """The network an ``Operational`` runs: its loaded file."""

    @property
    def model(self) -> NetworkConfig: ...


class Operational(Protocol):
    """A network in OP, as a recording reads it and hooks into its cycle."""

    @property
    def buses(self) -> Sequence[BusView]: ...
    @property
    def result(self) -> CycleResult: ...
    @property
    def network(self) -> NetworkView: ...
    @property
    def cycle_time_us(self) -> int: ...
    def add_observer(self, observer: Any) -> None: ...
    def remove_observer(self, observer: Any) -> None: ...
