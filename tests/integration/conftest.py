"""Integration fixtures: a veth pair with the EtherCAT emulator on one end.

``ethercat_emulator(maps, count=..., pcap=..., app=...)`` starts
:func:`sim_slaves.ethercat.veth.emulated_segment` and returns its
:class:`~sim_slaves.ethercat.veth.Emulator` (``iface`` = the master's end).
Everything is torn down afterwards, also when the test fails. Skips only when
the machine refuses (not root, no ``ip``, ``ip link add`` refused), with the
reason.

``veth_possible`` skips a test that makes its own pair (the demo, the soak) for the same
reasons only.

``tshark`` gives ``count(pcap, display_filter)``: the frames of a capture that
tshark's filter selects (skips when tshark is not installed; scripts/test
installs it as root).
"""

from __future__ import annotations

import shutil
import subprocess
from collections.abc import Callable, Iterator
from contextlib import ExitStack
from pathlib import Path

import pytest

from sim_slaves.ethercat.veth import Emulator, VethUnavailable, delete_link, emulated_segment, make_veth_pair


@pytest.fixture
def generous_pysoem_timeouts() -> Iterator[None]:
    """SOEM's frame round-trip timeout 20 ms instead of 2 ms: the machine is shared and loaded."""
    pysoem = pytest.importorskip("pysoem")
    t = pysoem.settings.timeouts
    old = t.ret
    t.ret = 20_000
    yield
    t.ret = old


@pytest.fixture
def veth_possible() -> None:
    """For tests whose code makes its own veth pair (the demo, the soak): pysoem is there and this
    machine lets us create a pair; skips with the machine's reason otherwise."""
    pytest.importorskip("pysoem")
    try:
        master, _ = make_veth_pair()
        delete_link(master)
    except VethUnavailable as exc:
        pytest.skip(str(exc))


@pytest.fixture
def ethercat_emulator(tmp_path: Path) -> Iterator[Callable[..., Emulator]]:
    with ExitStack() as stack:

        def start(
            maps: list[Path | str], *, count: int = 1, pcap: Path | None = None, app: str = "auto"
        ) -> Emulator:
            try:
                return stack.enter_context(
                    emulated_segment(maps, count=count, pcap=pcap, app=app, workdir=tmp_path)
                )
            except VethUnavailable as exc:
                pytest.skip(str(exc))

        yield start


@pytest.fixture
def tshark() -> Callable[[Path, str], int]:
    """``count(pcap, display_filter)``: how many frames of ``pcap`` tshark's display filter selects."""
    if shutil.which("tshark") is None:
        pytest.skip("tshark is not installed (apt-get install tshark)")

    def count(pcap: Path, display_filter: str) -> int:
        res = subprocess.run(
            ["tshark", "-n", "-r", str(pcap), "-Y", display_filter],
            capture_output=True,
            text=True,
            check=True,
        )
        return len([line for line in res.stdout.splitlines() if line.strip()])

    return count
