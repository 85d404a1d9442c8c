"""A slave's ``emulator:`` mapping in a network file: kept as written and handed to the emulator, which validates it.

The core knows no emulator option. A network file's ``emulator:`` section (the
delays, limits and imperfections of an *emulated* drive; real drives ignore it)
is kept as :class:`EmulatorSection`: the mapping as the file has it, the bus's
cycle time, and the document's source positions, so that the emulator's errors
name file, line and field like every other error of the file.

The emulators register their validator as the emulator part ``emulator_options``
(:mod:`fieldbus.emulators`; ``sim_slaves.emulator_options`` holds the schema and
its table). Loading a network file runs it on every section when it is
installed; without the emulators the section is accepted and ignored.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

from fieldbus.core.yamlread import Reader
from fieldbus.core.yamlsrc import Located, PathT

PART = "emulator_options"  # the emulator part (fieldbus.emulators) that validates a section


@dataclass(frozen=True)
class EmulatorSection:
    """One slave's ``emulator:`` mapping, opaque to fieldbus: ``options`` as written (YAML values)."""

    options: Mapping[Any, Any] = field(hash=False)
    cycle_time_us: int  # the bus's cycle: options in µs become whole cycles
    doc: Located = field(compare=False, hash=False, repr=False)  # source positions of the network file
    path: PathT = ()  # where ``options`` is in ``doc``

    def reader(self) -> Reader:
        """Typed, located reading of ``options`` (errors name file, line and field: ``path`` + key)."""
        return Reader(self.doc)


def emulator_section(r: Reader, raw: Any, path: PathT, cycle_time_us: int) -> EmulatorSection:
    """The ``emulator:`` value at ``path`` as a section (a mapping; its keys are the emulator's to check)."""
    if not isinstance(raw, Mapping):
        raise r.err(path, "expected a mapping of emulator options")
    return EmulatorSection(raw, cycle_time_us, r.doc, tuple(path))
