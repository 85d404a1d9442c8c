"""Firmware over FoE on the in-process transport: our master's steps against the emulated ESC chain.

Witness: the emulator's own state (its AL states, the firmware store, SII and 0x1018:03 after a
power cycle), not our master's view. Virtual time: every wait passes on a VirtualClock, and the
transfers count datagrams, not seconds. The independent oracles (pysoem's own FoE calls, tshark)
are in test_foe_veth.py.
"""

from __future__ import annotations

import random
from typing import Any

import pytest

from fieldbus.backends.ecat_firmware import FirmwareSession, run_steps
from fieldbus.backends.ecat_mailbox import SlaveMailbox
from fieldbus.commands.demo import DEMO_MAP
from fieldbus.core.al import AL_BOOT, AL_INIT, AL_OP, AL_PREOP, AL_SAFEOP, AlStatusCode
from fieldbus.core.coe_mailbox import MailboxProtocolError, SdoTransfer
from fieldbus.core.foe import FoeError, FoeErrorCode
from fieldbus.core.pdo import load_drive_map
from fieldbus.errors import StateTransitionError
from fieldbus.testing import VirtualClock, firmware_image

pytest.importorskip("pysoem")

from fieldbus.backends.ecat_inprocess import InProcessMaster

OLD_REV = 0  # the demo map's revision


def master(n: int) -> Any:
    m = InProcessMaster([load_drive_map(DEMO_MAP)] * n, clock=VirtualClock())
    assert m.config_init() == n
    return m


def to_op(m: Any) -> None:
    m.config_map()
    assert m.state_check(AL_SAFEOP, 50_000) == AL_SAFEOP
    m.state = AL_OP
    m.write_state()
    m.send_processdata()
    m.receive_processdata()
    assert m.state_check(AL_OP, 50_000) == AL_OP


def update(m: Any, k: int, image: bytes, *, name: str = "app.efw", password: int = 0) -> FirmwareSession:
    s = FirmwareSession(m, k)
    s.enter_bootstrap()
    run_steps(s.transfer(s.foe(name, image, password=password)))
    s.leave_bootstrap()
    return s


def revisions(m: Any, k: int) -> tuple[int, int]:
    esc = m.chain.slaves[k]
    return esc.sii.revision, int(esc.od.get_value(0x1018, 3))


def test_a_firmware_write_takes_effect_at_the_next_power_cycle() -> None:
    m = master(3)
    before = FirmwareSession(m, 1).identity(od=False)
    assert before.revision == OLD_REV
    update(m, 1, firmware_image(0x00020001, 5000))
    assert int(m.chain.slaves[1].state) == AL_INIT
    assert revisions(m, 1) == (OLD_REV, OLD_REV)  # written, not yet running
    m.chain.power_cycle(1)
    assert revisions(m, 1) == (0x00020001, 0x00020001)
    m.config_init()
    assert m.state_check(AL_PREOP, 50_000) == AL_PREOP
    after = FirmwareSession(m, 1).identity()
    assert (after.revision, after.od_revision) == (0x00020001, 0x00020001)
    m.chain.power_cycle(1)  # and it stays: the next power cycle keeps the new image
    assert revisions(m, 1) == (0x00020001, 0x00020001)


def test_the_bootstrap_mailbox_is_the_one_in_the_sii() -> None:
    m = master(1)
    s = FirmwareSession(m, 0)
    lay = s.enter_bootstrap()
    sii = m.chain.slaves[0].sii
    assert (lay.out_start, lay.out_size) == sii.boot_mailbox_out != sii.mailbox_out
    assert (lay.in_start, lay.in_size) == sii.boot_mailbox_in
    # CoE has no place in BOOTSTRAP: the slave answers with a mailbox error (unsupported protocol)
    with pytest.raises(MailboxProtocolError, match="mailbox error 0x0002"):
        run_steps(
            SlaveMailbox(lay, s.port).transfer(SdoTransfer(0x1000, 0, None, mailbox_out=lay.out_size), 100)
        )


def test_boot_is_refused_with_the_standard_mailbox_in_sm0() -> None:
    m = master(1)
    s = FirmwareSession(m, 0)
    s.request(AL_INIT)  # SOEM's mailbox layout still in SM0/SM1 (config_init wrote it)
    with pytest.raises(StateTransitionError) as err:
        s.request(AL_BOOT)
    assert err.value.al_status == AlStatusCode.INVALID_BOOT_MAILBOX_CONFIG


def test_wrong_password_and_missing_file_are_named_and_leave_the_old_firmware() -> None:
    m = master(1)
    m.chain.slaves[0].firmware.password = 0xC0DE
    s = FirmwareSession(m, 0)
    s.enter_bootstrap()
    with pytest.raises(FoeError) as err:
        run_steps(s.transfer(s.foe("app.efw", firmware_image(5), password=1)))
    assert (err.value.code, err.value.name, err.value.slave) == (0x800A, "no rights", "slave 0 (demo_joint)")
    with pytest.raises(FoeError) as err:
        run_steps(s.transfer(s.foe("other.efw", None, password=0xC0DE)))
    assert err.value.code == FoeErrorCode.NOT_FOUND
    s.leave_bootstrap()
    m.chain.power_cycle(0)
    m.config_init()
    assert m.state_check(AL_PREOP, 50_000) == AL_PREOP  # the old firmware runs
    assert revisions(m, 0) == (OLD_REV, OLD_REV)


def test_the_others_stay_in_op_and_exchange_every_cycle_while_one_is_updated() -> None:
    """12 drives in OP; drive 5 goes to BOOTSTRAP and takes a firmware image, one mailbox datagram
    between two process-data cycles. Every cycle's WKC counts the 11 others' LRW (3 each)."""
    m = master(12)
    to_op(m)
    full = m.expected_wkc
    assert full == 36
    s = FirmwareSession(m, 5)
    s.enter_bootstrap()
    steps = s.transfer(s.foe("app.efw", firmware_image(0x00020000, 20_000)))
    wkcs = []
    done = False
    while not done:
        m.send_processdata()
        wkcs.append(m.receive_processdata())
        try:
            next(steps)
        except StopIteration:
            done = True
    s.leave_bootstrap()
    states = [int(e.state) for e in m.chain.slaves]
    assert states == [AL_OP] * 5 + [AL_INIT] + [AL_OP] * 6
    assert len(wkcs) > 40 and set(wkcs) == {full - 3}  # the 11 others exchanged every cycle
    m.chain.power_cycle(5)
    assert revisions(m, 5) == (0x00020000, 0x00020000)


def test_100_transfers_interrupted_at_random_points_all_recover_by_running_the_update_again() -> None:
    """Fixed seed. Each trial stops a firmware write after a random number of datagrams: the master
    stops (Ctrl-C, cable: the slave stays in BOOTSTRAP) or the slave loses power (it comes back in
    INIT without valid firmware and refuses PRE-OP, AL 0x0014). Recovery is what docs/firmware.md
    says: rescan, run the update again, power-cycle. Every slave then runs the new image."""
    rng = random.Random(37)
    m = master(4)
    kinds = {"stop": 0, "power": 0}
    mid_transfer = 0  # trials cut while the image was half written
    revision = 0x00010000
    for trial in range(100):
        k = rng.randrange(4)
        revision += 1
        image = firmware_image(revision, rng.randrange(1, 6000), seed=trial)
        s = FirmwareSession(m, k)
        s.enter_bootstrap()
        steps = s.transfer(s.foe("app.efw", image))
        cut = rng.randrange(1, 3 * (len(image) // 500 + 2) + 1)  # each message: write, poll, read
        for _ in range(cut):
            try:
                next(steps)
            except StopIteration:
                break
        kind = rng.choice(("stop", "power"))
        kinds[kind] += 1
        esc = m.chain.slaves[k]
        mid_transfer += not esc.firmware.valid
        if kind == "power":
            m.chain.power_cycle(k)
            if not esc.firmware.valid:
                m.config_init()  # the rescan the command makes
                assert int(esc.state) & 0x0F == AL_INIT and esc.status_code == AlStatusCode.NO_VALID_FIRMWARE
        else:
            assert int(esc.state) == AL_BOOT  # left in BOOTSTRAP
        # recovery: run the command again (rescan, update), then power-cycle
        m.config_init()
        update(m, k, image)
        m.chain.power_cycle(k)
        m.config_init()
        assert m.state_check(AL_PREOP, 50_000) == AL_PREOP, f"trial {trial}"
        assert revisions(m, k) == (revision, revision), f"trial {trial}"
    assert min(kinds.values()) > 30 and mid_transfer > 60


def test_a_configuration_file_goes_in_preop_through_the_standard_mailbox() -> None:
    m = master(2)
    assert m.state_check(AL_PREOP, 50_000) == AL_PREOP
    s = FirmwareSession(m, 0)
    lay = s.enter_preop()
    assert (lay.out_start, lay.out_size) == m.chain.slaves[0].sii.mailbox_out
    config = b"0x6072,0,1000\n" * 40
    run_steps(s.transfer(s.foe("config.csv", config)))
    assert run_steps(s.transfer(s.foe("config.csv", None))) == config
    with pytest.raises(FoeError) as err:  # firmware is not taken outside BOOTSTRAP
        run_steps(s.transfer(s.foe("app.efw", firmware_image(2))))
    assert err.value.code == FoeErrorCode.BOOTSTRAP_ONLY
    assert m.chain.slaves[0].firmware.valid


def test_the_emulator_cuts_the_power_in_the_middle_of_a_write() -> None:
    """The fault hook behind Emulation.firmware_power_loss: the slave takes 3000 bytes, then its
    power goes; the master's steps find no answer and end (a bounded number of datagrams)."""
    from fieldbus.errors import BusTimeoutError

    m = master(2)
    m.chain.cut_power_during_foe(1, 3000)
    s = FirmwareSession(m, 1)
    s.enter_bootstrap()
    t = s.foe("app.efw", firmware_image(9, 10_000))
    with pytest.raises(BusTimeoutError, match="in 2000 datagrams"):
        run_steps(s.transfer(t))
    esc = m.chain.slaves[1]
    assert t.done == 2500 and int(esc.state) == AL_INIT and not esc.firmware.valid  # packet 6 never ACKed
    assert esc.station_address == 0  # powered up again: registers reset
    m.config_init()
    assert esc.status_code == AlStatusCode.NO_VALID_FIRMWARE  # PRE-OP refused


def test_a_device_without_a_bootstrap_mailbox_is_named_and_refuses_boot() -> None:
    from fieldbus.errors import FieldbusError

    m = master(1)
    esc = m.chain.slaves[0]
    esc.sii.write_word(0x15, 0)  # bootstrap receive mailbox size 0: no BOOTSTRAP
    s = FirmwareSession(m, 0)
    with pytest.raises(FieldbusError, match=r"no bootstrap mailbox \(words 0x14-0x17\)"):
        s.enter_bootstrap()
    with pytest.raises(StateTransitionError) as err:  # asked anyway: the ESC refuses
        s.request(AL_BOOT)
    assert err.value.al_status == AlStatusCode.BOOTSTRAP_NOT_SUPPORTED


def test_bringing_up_a_network_with_a_drive_left_without_firmware_names_it(tmp_path: Any) -> None:
    """A drive whose update was cut by a power loss: the network's bring-up stops with the drive,
    its AL status code 0x0014 and its name, instead of a bare timeout."""
    from fieldbus.network import open_network

    net_file = tmp_path / "net.yaml"
    net_file.write_text(
        "cycle_time_us: 1000\nbuses:\n"
        f"  - {{name: bus, type: ethercat, interface: none0, slaves: [{{name: 'j{{i}}', map: '{DEMO_MAP}', count: 3}}]}}\n"
    )
    with open_network(net_file, backend="ethercat", transport="in-process") as net:
        chain = net.backends[0].master.chain  # type: ignore[attr-defined]
        chain.slaves[1].firmware.valid = False  # as test_the_emulator_cuts_the_power... leaves it
        with pytest.raises(StateTransitionError) as err:
            net.bring_up()
    assert err.value.al_status == 0x0014
    assert "position 1" in str(err.value) and "no valid firmware" in str(err.value)


def test_the_testing_kit_cuts_a_drives_power_mid_update_and_the_bring_up_names_it(tmp_path: Any) -> None:
    """fieldbus.testing's hook (Emulation.firmware_power_loss), an update through the bus's own master
    before bring-up, then bring-up: it stops at PRE-OP naming the drive and AL status code 0x0014."""
    from fieldbus.errors import BusTimeoutError, FieldbusError
    from fieldbus.testing import FaultNotSupported, emulate

    net_file = tmp_path / "net.yaml"
    net_file.write_text(
        "cycle_time_us: 1000\nbuses:\n"
        f"  - {{name: arm, type: ethercat, interface: enp3s0, slaves: [{{name: 'j{{i}}', map: '{DEMO_MAP}', count: 3}}]}}\n"
        f"  - {{name: co, type: canopen, interface: can0, can_interface: socketcan, receive_timeout_us: 2000,\n"
        f"     slaves: [{{name: 'c{{i}}', map: '{DEMO_MAP}', node_id: 1, count: 1}}]}}\n"
    )
    with emulate(net_file, bring_up=False) as emu:
        with pytest.raises(FieldbusError, match="count >= 1"):
            emu.firmware_power_loss("arm", "j1", 0)
        with pytest.raises(FaultNotSupported, match="firmware_power_loss"):
            emu.firmware_power_loss("co", "c0", 100)
        emu.firmware_power_loss("arm", "j1", 1000)
        m = emu.network.backend("arm").master  # type: ignore[attr-defined]
        assert m.config_init() == 3  # the scan the update starts with
        s = FirmwareSession(m, 1)
        s.enter_bootstrap()
        with pytest.raises(BusTimeoutError):
            run_steps(s.transfer(s.foe("app.efw", firmware_image(3, 5000))))
        with pytest.raises(StateTransitionError) as err:
            emu.bring_up()
    assert err.value.al_status == AlStatusCode.NO_VALID_FIRMWARE and "position 1 (j1)" in str(err.value)
