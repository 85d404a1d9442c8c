"""``backend: sim`` is the EtherCAT backend on the in-process transport (issue 29): one EtherCAT path.

Judged with our own code on both sides (the emulated ESC chain answers the
frames); the pysoem-over-veth runs in test_cyclic_api.py are the oracle for
the backend itself.
"""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from fieldbus.commands.demo import demo_network
from fieldbus.network import Operational, open_network
from fieldbus.platform.clock import VirtualClock


@pytest.fixture
def op(tmp_path: Path) -> Iterator[Operational]:
    """Two demo joints on the sim backend, in OP, on a virtual clock."""
    with (
        demo_network("sim", 2, 1000.0, tmp_path) as setup,
        open_network(setup.net_file, backend="sim", clock=VirtualClock()) as net,
    ):
        yield net.bring_up()


def test_an_sdo_in_op_takes_a_datagram_per_cycle_as_on_hardware(op: Operational) -> None:
    """The in-OP mailbox of the ethercat backend: request into SM0, SM1 polled, answer read - never the
    whole transfer inside one exchange()."""
    request = op.submit_sdo_read("joints", "j1", 0x1000, 0)
    cycles = 0
    while not request.done() and cycles < 50:
        op.exchange()
        cycles += 1
    assert request.done() and len(request.result(0)) == 4
    assert cycles >= 3  # write the request, see SM1 full, read the answer


def test_a_power_cycled_slave_is_configured_again_by_the_ethercat_backends_steps(op: Operational) -> None:
    """The stepwise reconfiguration (INIT, SMs, PRE-OP, the SDO plan, SAFE-OP, FMMUs, OP): the slave is
    back in OP, counted once, with no recovery error."""
    backend: Any = op._net.backends[0]
    backend.chain.power_cycle(1)
    for _ in range(2000):
        op.exchange()
        if backend.recoveries and not backend.recovering:
            break
    assert backend.recoveries == 1 and not backend.recovery_errors
    assert [s.state & 0x0F for s in backend.master.slaves] == [8, 8]  # AL state OP as last read
    assert backend.master.read_state() == 8
