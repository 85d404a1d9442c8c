"""The pytest plugin of :mod:`fieldbus.testing` (entry point ``pytest11``: loaded by pytest on its own).

Fixture ``fieldbus_emulation``: a function ``start(network, **options) -> Emulation``
taking :func:`fieldbus.testing.emulate`'s options. Every emulation a test
starts is torn down after it (network closed, emulators, processes and veth
pairs stopped), also when the test fails. Where the machine refuses (no root
for a veth pair, a missing extra) the test is skipped with the reason.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from contextlib import ExitStack
from pathlib import Path
from typing import Any

import pytest

from fieldbus.testing.emulation import Emulation, emulate
from fieldbus.testing.provider import EmulationUnavailable


@pytest.fixture
def fieldbus_emulation(tmp_path: Path) -> Iterator[Callable[..., Emulation]]:
    """``start(network, **options)``: emulators for ``network`` and the master in OP (see ``emulate``)."""
    with ExitStack() as stack:
        count = 0

        def start(network: Any, **options: Any) -> Emulation:
            nonlocal count
            count += 1
            options.setdefault("workdir", tmp_path / f"emulation-{count}")
            Path(options["workdir"]).mkdir(parents=True, exist_ok=True)
            try:
                return stack.enter_context(emulate(network, **options))
            except EmulationUnavailable as exc:
                pytest.skip(f"fieldbus emulation unavailable here: {exc}")

        yield start
