"""``fieldbus register``: a Damiao register and an ODrive endpoint read and written from the CLI against the
emulators on python-can's virtual bus (the in-process path, as tests/integration/test_sdo_cli.py does).

What the CLI puts on the bus is read by a listener and decoded here from the published layouts (Damiao
``[id lo, id hi, op, reg, value LE]`` on 0x7FF, op 0x33 read / 0x55 write; ODrive RxSdo ``node << 5 | 0x04``:
opcode, uint16 endpoint, reserved, value), not by fieldbus's codec. The emulators are our own code.
"""

from __future__ import annotations

import itertools
import json
import os
import struct
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

can = pytest.importorskip("can")

from fieldbus import PDO_MAPS, open_network  # noqa: E402
from fieldbus.cli import main  # noqa: E402
from fieldbus.core.pdo import load_drive_map  # noqa: E402
from sim_slaves.damiao import DamiaoSimulator  # noqa: E402
from sim_slaves.odrive import OdriveSimulator  # noqa: E402

pytestmark = pytest.mark.timeout(120)
DAMIAO = Path(PDO_MAPS) / "damiao_dm_j4310.yaml"
_channels = itertools.count()


def _net(tmp_path: Path, bus: str, prefix: str, map_path: Path, n: int) -> tuple[Path, str]:
    channel = f"fb-reg-{os.getpid()}-{next(_channels)}"
    net = tmp_path / "net.yaml"
    net.write_text(
        "cycle_time_us: 1000\nreceive_timeout_us: 20000\nbuses:\n"
        f"  - {{name: {bus}, type: rawcan, interface: {channel}, can_interface: virtual,\n"
        f"     slaves: [{{name: '{prefix}{{i}}', map: {map_path}, node_id: 1, count: {n}}}]}}\n"
        "  - {name: io, type: sim, slaves: [{name: s, map: "
        f"{Path(PDO_MAPS) / 'generic_cia402.yaml'}}}]}}\n"
    )
    return net, channel


def _run(capsys: pytest.CaptureFixture[str], *argv: str) -> tuple[int, str, str]:
    code = main(list(argv))
    out = capsys.readouterr()
    return code, out.out, out.err


def _requests(listener: can.BusABC) -> list[bytes]:
    out = []
    while (msg := listener.recv(timeout=0)) is not None:
        if msg.arbitration_id == 0x7FF:
            out.append(bytes(msg.data))
    return out


class StubbornDamiao(DamiaoSimulator):
    """A motor that answers a CTRL_MODE write outside 1..4 but keeps its mode (one function replaced)."""

    def _register(self, data: bytes) -> can.Message | None:
        if data[2] == 0x55 and data[3] == 10 and not 1 <= struct.unpack("<I", data[4:])[0] <= 4:
            node = data[0]
            return self._reply(node, data[:4] + self.state[node].registers[10])
        return super()._register(data)


@pytest.fixture
def damiao_net(tmp_path: Path) -> Iterator[tuple[Path, str, DamiaoSimulator, can.BusABC]]:
    net, channel = _net(tmp_path, "arm", "j", DAMIAO, 2)
    drive = load_drive_map(DAMIAO)
    with (
        can.Bus(interface="virtual", channel=channel) as listener,
        can.Bus(interface="virtual", channel=channel) as sim_bus,
        StubbornDamiao(sim_bus, [(drive, 1), (drive, 2)], dt_s=0.001) as sim,
    ):
        yield net, channel, sim, listener


def test_damiao_registers_by_name_and_number(
    damiao_net: tuple[Path, str, DamiaoSimulator, can.BusABC], capsys: pytest.CaptureFixture[str]
) -> None:
    net, _, sim, listener = damiao_net
    code, out, _ = _run(capsys, "register", str(net), "arm", "j1", "PMAX")
    assert code == 0 and out.strip() == "arm j1 (node 2) PMAX (21) = 12.5  [float32]"
    assert _requests(listener) == [bytes([2, 0, 0x33, 21, 0, 0, 0, 0])]

    code, out, _ = _run(capsys, "register", str(net), "arm", "j0", "timeout", "1000", "--json")
    assert code == 0
    r = json.loads(out)
    assert (r["register"], r["name"], r["type"], r["value"], r["written"], r["ok"]) == (
        9, "TIMEOUT", "uint32", 1000, 1000, True
    )  # fmt: skip
    assert _requests(listener) == [
        bytes([1, 0, 0x55, 9]) + struct.pack("<I", 1000),
        bytes([1, 0, 0x33, 9, 0, 0, 0, 0]),
    ]
    assert sim.state[1].reg(9) == 1000 and sim.state[2].reg(9) == 0

    code, out, _ = _run(capsys, "register", str(net), "arm", "j0", "10", "3")
    assert code == 0 and out.strip() == "arm j0 (node 1) CTRL_MODE (10) <- 3 (0x3)  [uint32]"
    assert sim.state[1].reg(10) == 3
    code, out, _ = _run(capsys, "register", str(net), "arm", "j1", "KP_APR", "12.5")
    assert code == 0 and sim.state[2].reg(27) == 12.5
    assert _requests(listener)[-2] == bytes([2, 0, 0x55, 27]) + struct.pack("<f", 12.5)
    code, out, _ = _run(capsys, "register", str(net), "arm", "j1", "MST_ID")
    assert code == 0 and "MST_ID (7) = 18 (0x12)" in out
    _requests(listener)

    # --save: write, read back, then the save request [id, 0xAA, 0x01]; a disabled motor answers
    code, out, _ = _run(capsys, "register", str(net), "arm", "j0", "TIMEOUT", "2000", "--save")
    assert (
        code == 0 and out.strip() == "arm j0 (node 1) TIMEOUT (9) <- 2000 (0x7D0)  [uint32], saved to flash"
    )
    assert _requests(listener)[-1] == bytes([1, 0, 0xAA, 1, 0, 0, 0, 0])
    assert sim.state[1].saves == 1
    # an enabled motor does not save (nor answer): exit 1, the reason named
    listener.send(can.Message(arbitration_id=2, data=bytes([0xFF] * 7 + [0xFC]), is_extended_id=False))
    deadline = time.monotonic() + 5
    while sim.state[2].error != 1 and time.monotonic() < deadline:
        time.sleep(0.01)
    code, _, err = _run(capsys, "register", str(net), "arm", "j1", "KP_APR", "5", "--save")
    assert code == 1 and "did not answer the save to flash (a motor saves only while disabled)" in err
    assert sim.state[2].saves == 0 and sim.state[2].reg(27) == 5.0  # written to RAM, not saved


def test_damiao_errors_and_exit_codes(
    damiao_net: tuple[Path, str, DamiaoSimulator, can.BusABC], capsys: pytest.CaptureFixture[str]
) -> None:
    net, _, _sim, listener = damiao_net
    # read back another value than written: exit 3, both values named
    code, out, err = _run(capsys, "register", str(net), "arm", "j0", "CTRL_MODE", "7")
    assert code == 3 and "reads back 1 (0x1)" in out
    assert "arm j0 (node 1): CTRL_MODE (10) reads back 1 (0x1) after writing 7 (0x7)" in err
    _requests(listener)
    refused = [
        (("arm", "j0", "NOPE"), "no register 'NOPE'"),
        (("arm", "j0", "Rs", "1.0"), "register Rs (17) is read-only"),
        (("arm", "j0", "TIMEOUT", "-1"), "'-1' is not a uint32 value"),
        (("arm", "j0", "PMAX", "x"), "'x' is not a float32 value"),
        (("arm", "j0", "200", "1"), "register 200 is not in the table: give --type float32 or uint32"),
        (("arm", "j9", "PMAX"), "bus 'arm' has no motor 'j9' (motors: j0, j1)"),
        (("legs", "j0", "PMAX"), "no bus 'legs' (buses: arm, io)"),
        (("io", "s", "PMAX"), "bus 'io' is sim; registers are on rawcan buses"),
    ]
    for words, message in refused:
        code, _, err = _run(capsys, "register", str(net), *words)
        assert code == 1 and message in err, (words, err)
        assert "Traceback" not in err
    assert _requests(listener) == []  # none of them reached the bus
    # a register the motor does not have: no answer, a timeout naming it
    code, _, err = _run(capsys, "register", str(net), "arm", "j0", "200")
    assert code == 1 and "did not answer the read of register 200" in err
    # refused while a master runs on the channel
    with open_network(net) as network:
        network.bring_up()
        code, _, err = _run(capsys, "register", str(net), "arm", "j0", "PMAX")
        assert code == 1 and "in use" in err, err


def test_odrive_endpoints_and_firmware_0_5(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    net, channel = _net(tmp_path, "legs", "a", Path(PDO_MAPS) / "odrive_s1.yaml", 2)
    drive = load_drive_map(Path(PDO_MAPS) / "odrive_s1.yaml")
    timeout_ep, enable_ep = 0x1B0, 0x1B1  # as the emulated firmware build numbers them
    with (
        can.Bus(interface="virtual", channel=channel) as listener,
        can.Bus(interface="virtual", channel=channel) as sim_bus,
        OdriveSimulator(
            sim_bus, [(drive, 1), (drive, 2)], dt_s=0.001, watchdog=(timeout_ep, enable_ep)
        ) as sim,
    ):
        code, out, _ = _run(
            capsys, "register", str(net), "legs", "a1", hex(timeout_ep), "0.25", "--type", "float32"
        )
        assert code == 0 and out.strip() == "legs a1 (node 2) endpoint 432 <- 0.25  [float32]"
        assert sim.endpoint(2, timeout_ep) == 0.25 and sim.endpoint(1, timeout_ep) == 0.0
        sdo = [
            bytes(m.data)
            for m in iter(lambda: listener.recv(timeout=0), None)
            if m.arbitration_id == 2 << 5 | 4
        ]
        assert sdo == [
            struct.pack("<BHB", 1, timeout_ep, 0) + struct.pack("<f", 0.25),
            struct.pack("<BHB", 0, timeout_ep, 0) + bytes(4),
        ]
        code, out, _ = _run(
            capsys, "register", str(net), "legs", "a1", str(enable_ep), "true", "--type", "bool"
        )
        assert code == 0 and sim.endpoint(2, enable_ep, "<I") == 1
        code, out, _ = _run(capsys, "register", str(net), "legs", "a1", str(enable_ep), "--json")
        assert code == 0 and json.loads(out)["value"] == 1
        code, _, err = _run(capsys, "register", str(net), "legs", "a0", "0x1B0", "1")
        assert code == 1 and "give --type float32, uint32, int32 or bool" in err
        code, _, err = _run(capsys, "register", str(net), "legs", "a0", "watchdog")
        assert code == 1 and "neither an endpoint id" in err
        code, _, err = _run(capsys, "register", str(net), "legs", "a0", "0x1B0", "--save")
        assert code == 1 and "--save stores a Damiao motor's registers" in err
        # an endpoint this firmware build does not have: no TxSdo, a bounded wait, a named time-out
        code, _, err = _run(capsys, "register", str(net), "legs", "a1", "999", "--type", "uint32")
        assert code == 1 and "a1 (node 2) did not answer the read of endpoint 999 within 200 ms" in err
    old, _ = _net(tmp_path, "legs", "a", Path(PDO_MAPS) / "odrive_3_6.yaml", 1)
    code, _, err = _run(capsys, "register", str(old), "legs", "a0", "0x1B0")
    assert code == 1 and "ODrive firmware 0.5 has no endpoint access over CAN" in err


def test_help_has_examples_and_exit_codes(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as exc:
        main(["register", "--help"])
    assert exc.value.code == 0
    out = capsys.readouterr().out
    assert "fieldbus register robot.yaml arm j0 TIMEOUT 1000" in out
    assert "3  the write was answered but the register reads back another value" in out


def test_clear_fault_sends_the_damiao_clear_frame_and_leaves_the_motor_disabled(
    damiao_net: tuple[Path, str, DamiaoSimulator, can.BusABC], capsys: pytest.CaptureFixture[str]
) -> None:
    net, _, sim, listener = damiao_net
    sim.inject_error(2, 0xE)  # overload
    code, out, _ = _run(capsys, "register", str(net), "arm", "j1", "--clear-fault", "--json")
    r = json.loads(out)
    assert code == 0 and (r["motor"], r["cleared"], r["code"]) == ("j1", True, 0)  # 0: disabled, no fault
    frames = []
    while (msg := listener.recv(timeout=0)) is not None:
        frames.append((msg.arbitration_id, bytes(msg.data)))
    assert (2, bytes([0xFF] * 7 + [0xFB])) in frames  # the clear-error frame on ESC_ID, by the manual
    assert sim.state[2].error == 0 and not sim.motor(2).enabled
    code, _, err = _run(capsys, "register", str(net), "arm", "j1", "PMAX", "--clear-fault")
    assert code != 0 and "--clear-fault takes no REG" in err
