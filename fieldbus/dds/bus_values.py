"""A bus's ``BusStatus`` as the key-values of its DDS diagnostics status (``fieldbus/bus/<name>``).

Every field of the status dataclass goes in by its name (derived with
:mod:`fieldbus.core.status_fields`: a field added to ``BusStatus`` is served
without editing this module), after the bus's counters; :data:`EXCLUDED`
names the fields served elsewhere. The watcher's view (``fieldbus monitor
--dds``) shows every non-empty value it receives.
"""

from __future__ import annotations

from collections.abc import Mapping

from fieldbus.core.status_fields import as_plain
from fieldbus.dds import messages as m

# BusStatus fields not among a bus's diagnostics values, and where they are served instead
EXCLUDED = {
    "name": "the status's name, fieldbus/bus/<name>",
    "fresh": "per axis, AxisState.fresh of each group",
}


def bus_values(status: object, counters: Mapping[str, int]) -> list[m.KeyValue]:
    """The bus's ``counters`` (``BusView.counters()``), then each field of ``status`` not among them
    (text; ``None`` as ``""``, an enum by its name)."""
    values = [m.KeyValue(k, str(v)) for k, v in counters.items()]
    for k, v in as_plain(status, exclude=EXCLUDED).items():
        if k not in counters:
            values.append(m.KeyValue(k, "" if v is None else str(v)))
    return values
