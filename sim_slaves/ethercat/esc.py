"""One emulated EtherCAT slave controller (ESC): register memory, AL state, SII, mailbox, FMMU/SM.

Sans-IO: the chain hands each slave the datagrams addressed to it as
``read(ado, n, now)`` / ``write(ado, data, now)`` (physical) and
``logical(...)`` (through the FMMUs); "now" is in ns. Directions from the
master's side: outputs = SM2 (RxPDO), inputs = SM3 (TxPDO).

Memory: 0x0000-0x0FFF registers, 0x1000-0x2FFF process RAM (8 KiB).
Registers with behaviour: 0x0010 station address, 0x0012 alias, 0x0110 DL
status, 0x0120 AL control -> 0x0130 AL status / 0x0134 AL status code,
0x0400/0x0420 watchdog divider / process-data watchdog time, 0x0500-0x050F
EEPROM interface, 0x0600 FMMUs (16 B each), 0x0800 SyncManagers (8 B each),
0x0900-0x09AF distributed clocks (:class:`~sim_slaves.ethercat.dc.EscDc`, backed by the
model in :mod:`fieldbus.core.dc`; the bytes of ``mem`` in that range are not used).
"""

from __future__ import annotations

import struct
from collections.abc import Callable
from typing import Protocol

from fieldbus.core.sii import checksum_ok
from sim_slaves.ethercat.al import AL_ERROR_INDICATOR, TRANSITIONS, AlState, AlStatusCode, Check
from sim_slaves.ethercat.coe import SdoServer, emergency_payload
from sim_slaves.ethercat.dc import DC_END, DC_FIRST, EscDc
from sim_slaves.ethercat.foe import FirmwareStore, FoeServer
from sim_slaves.ethercat.mailbox import Mailbox
from sim_slaves.ethercat.pdo import ProcessImage
from sim_slaves.ethercat.sii import SM_TYPE_INPUTS, SM_TYPE_OUTPUTS, SiiImage
from sim_slaves.od import CommState, ObjectDictionary

MEM_SIZE = 0x3000
RAM_START = 0x1000
ESC_TYPE = 0x11  # ET1100-like
FEATURES = 0x000C  # DC supported, 64-bit DC
N_FMMU = 8
N_SM = 8
EEPROM_R64 = 0x0040  # EEPROM status: 8-byte reads
EEPROM_BUSY = 0x8000  # EEPROM status: a command is running
# EEPROM status error bits (ESC datasheet section II, 0x0502): checksum error in the ESC configuration
# area, EEPROM not loaded, missing acknowledge / invalid command, write command without write enable
EEPROM_CHECKSUM_ERROR, EEPROM_NOT_LOADED, EEPROM_NACK, EEPROM_WRITE_ENABLE_ERROR = (
    0x0800,
    0x1000,
    0x2000,
    0x4000,
)
EEPROM_WRITE_BUSY_READS = 2  # reads of 0x0502 that find the interface busy after a word write
ERR_FIRST, ERR_END = 0x0300, 0x0314  # error counters (fieldbus.core.esc_errors)
WD_DIVIDER_DEFAULT = 2498  # (2498 + 2) x 40 ns = 100 us
WD_PD_DEFAULT = 1000  # x 100 us = 100 ms
DEFAULT_DT_S = 0.001

_RO_RANGES = ((0x0000, 0x0010), (0x0110, 0x0112), (0x0130, 0x0136), (ERR_FIRST, ERR_END))
_U16 = struct.Struct("<H")
_U32 = struct.Struct("<I")
_SM = struct.Struct("<HHBBBB")
_FMMU = struct.Struct("<IHBBHBBB")
_COMM_STATE = {
    AlState.INIT: CommState.INIT,
    AlState.BOOT: CommState.INIT,
    AlState.PRE_OP: CommState.PRE_OPERATIONAL,
    AlState.SAFE_OP: CommState.SAFE_OPERATIONAL,
    AlState.OP: CommState.OPERATIONAL,
}


class App(Protocol):
    """The slave's application: called once per process-data exchange with the OD and the cycle time [s]."""

    def step(self, od: ObjectDictionary, dt_s: float) -> None: ...


class LoopbackApp:
    """Test application: copies each output (RxPDO) value to the input (TxPDO) entry at the same position."""

    def __init__(self, pairs: list[tuple[tuple[int, int], tuple[int, int]]]) -> None:
        self.pairs = pairs

    def step(self, od: ObjectDictionary, dt_s: float) -> None:
        for (oi, os_), (ii, is_) in self.pairs:
            od.set_value(ii, is_, od.get_value(oi, os_))


class Esc:
    """One slave. ``position`` is 0-based in wire order of a chain of ``chain_length``.

    ``dc``: its distributed-clock unit (default: no drift, placed at the
    master; :class:`~sim_slaves.ethercat.chain.EscChain` places it on the line).
    """

    def __init__(
        self,
        sii: SiiImage,
        od: ObjectDictionary,
        *,
        position: int = 0,
        chain_length: int = 1,
        app: App | None = None,
        name: str = "",
        dc: EscDc | None = None,
    ) -> None:
        self.sii = sii
        # the EEPROM is as large as word 0x3E says ((Kbit + 1) x 128 bytes), erased (0xFF) past the image
        size = min((sii.word(0x3E) + 1) * 128, 0x20000) if sii.word(0x3E) != 0xFFFF else len(sii.data)
        if len(sii.data) < size:
            sii.data += b"\xff" * (size - len(sii.data))
        self.od = od
        self.app = app
        self.name = name or sii.name
        self.position = position
        self.chain_length = chain_length
        self.dc = dc or EscDc()
        mbx_out = sii.mailbox_out[1] if sii.protocols else 0
        mbx_in = sii.mailbox_in[1] if sii.protocols else 0
        #: files and firmware (FoE), kept over power cycles; the bootstrap mailbox from SII words 0x14-0x17
        self.firmware = FirmwareStore()
        self.mailbox = Mailbox(SdoServer(od, mbx_in), mbx_out, mbx_in, FoeServer(self.firmware))
        self.refuse: dict[AlState, int] = {}  # fault hook: refuse entering a state with this AL status code
        # fault hooks (kept over a power cycle, until cleared): a mailbox that never answers ("silent":
        # requests are taken and dropped; "stuck": SM0 stays full, so later writes are refused), and an
        # EEPROM interface that stays busy
        self.mailbox_fault: str | None = None
        self.eeprom_stuck = False
        self._eeprom_busy_reads = 0
        self.links_down: set[int] = set()  # fault hook: ports whose physical link is down
        self.cycles = 0
        self.mem: bytearray | memoryview = bytearray(MEM_SIZE)
        #: called when what the process-data path depends on changes (FMMU, SM, AL state, layout, power)
        self.on_change: Callable[[], None] | None = None
        #: True: the chain runs this slave's process data (no :meth:`cycle`); see ``sync_hook``
        self.fast = False
        #: fast slaves: called as (self, False) before and (self, True) after a mailbox request is served,
        #: so the object dictionary agrees with the process data for the SDO server
        self.sync_hook: Callable[[Esc, bool], None] | None = None
        self.power_on()

    # -- power / reset --

    def power_on(self) -> None:
        """Power-on reset: registers to defaults, state INIT, mailbox empty, FMMU/SM cleared."""
        mem = self.mem
        mem[:] = bytes(MEM_SIZE)
        mem[0x0000] = ESC_TYPE
        mem[0x0001] = 0x02
        _U16.pack_into(mem, 0x0002, 0x0003)
        mem[0x0004] = N_FMMU
        mem[0x0005] = N_SM
        mem[0x0006] = (MEM_SIZE - RAM_START) // 1024
        mem[0x0007] = 0x0F  # ports 0 and 1: MII
        _U16.pack_into(mem, 0x0008, FEATURES)
        # the ESC loads its configuration area at power-up: a wrong checksum leaves it unloaded (no alias,
        # no PDI: the application never runs, the AL state stays INIT) and says so in 0x0502 and 0x0110
        self.eeprom_loaded = checksum_ok(bytes(self.sii.data[:16]))
        if self.eeprom_loaded:
            _U16.pack_into(mem, 0x0012, self.sii.word(0x0004))  # configured station alias from SII
        _U16.pack_into(mem, 0x0110, self._dl_status())
        mem[0x0120] = AlState.INIT
        mem[0x0130] = AlState.INIT
        mem[0x0140] = self.sii.word(0x0000) & 0xFF if self.eeprom_loaded else 0
        _U16.pack_into(mem, 0x0400, WD_DIVIDER_DEFAULT)
        _U16.pack_into(mem, 0x0410, WD_PD_DEFAULT)
        _U16.pack_into(mem, 0x0420, WD_PD_DEFAULT)
        _U16.pack_into(mem, 0x0502, self._eeprom_status())
        self._eeprom_busy_reads = 0
        self.dc.power_on()
        self.state = AlState.INIT
        self.error = False
        self.status_code = 0
        self.sm: list[tuple[int, int, int, int]] = [(0, 0, 0, 0)] * N_SM  # start, length, control, activate
        self.lmap: tuple[tuple[int, int, int, bool], ...] = ()  # log start, log end, phys start, is-write
        self.pd_active = False
        self.outputs_active = False  # OP only: in SAFE-OP the output SyncManager takes no writes
        self.sm0_full = False
        self.sm1_full = False
        self.sm1_buf = b""
        self._repeat_bit = 0
        self.mailbox.reset()
        self._use_mailbox(boot=False)
        self._take_firmware()
        self.image = ProcessImage(self.od, self.name)
        self.last_output_ns: int | None = None
        self.last_step_ns: int | None = None
        self.outputs_written = False
        self.touched = False
        self._changed()

    def _take_firmware(self) -> None:
        """Power on: a firmware image written completely becomes the running one; report its revision
        (SII word 0x0C, 0x1018:03)."""
        revision = self.firmware.power_on()
        if revision is not None:
            self.sii.write_word(0x0C, revision & 0xFFFF)
            self.sii.write_word(0x0D, revision >> 16)
            if self.od.has(0x1018, 3):
                self.od.set_value(0x1018, 3, revision)

    def _use_mailbox(self, *, boot: bool) -> None:
        """The standard mailbox (SII words 0x18-0x1B) or, in BOOTSTRAP, the bootstrap one (0x14-0x17)."""
        if not self.sii.protocols:
            return
        out, inp = (
            (self.sii.boot_mailbox_out, self.sii.boot_mailbox_in)
            if boot
            else (
                self.sii.mailbox_out,
                self.sii.mailbox_in,
            )
        )
        self.mailbox.size_out, self.mailbox.size_in = out[1], inp[1]
        self.mailbox.boot = boot

    def use_memory(self, mem: memoryview) -> None:
        """Keep registers and RAM in ``mem`` (``MEM_SIZE`` bytes, e.g. a row of the chain's array)."""
        mem[:] = self.mem
        self.mem = mem

    def _changed(self) -> None:
        if self.on_change is not None:
            self.on_change()

    def _dl_status(self) -> int:
        """DL status: PDI operational (EEPROM loaded), port 0 link + communication; port 1 too unless last."""
        last = self.position == self.chain_length - 1
        port1 = 0x0400 if last else 0x0820  # closed loop / link + open with communication
        raw = (0x0001 if self.eeprom_loaded else 0) | 0x0010 | 0x0200 | port1 | 0x1000 | 0x4000
        for p in self.links_down:  # no link: no communication, the port's loop closed
            raw = (raw & ~(0x0010 << p) & ~(0x0200 << 2 * p)) | (0x0100 << 2 * p)
        return raw

    # -- error counters (0x0300-0x0313) --

    def count_error(self, port: int, kind: str) -> None:
        """One error on ``port``: "invalid" frame (CRC), "rx" (symbol), "forwarded" or "lost" link (u8, stops at 255)."""
        reg = {
            "invalid": 0x0300 + 2 * port,
            "rx": 0x0301 + 2 * port,
            "forwarded": 0x0308 + port,
            "lost": 0x0310 + port,
        }[kind]
        if self.mem[reg] < 0xFF:
            self.mem[reg] += 1

    def set_link(self, port: int, up: bool) -> None:
        """Port ``port``'s physical link comes up or goes down (a lost link is counted there)."""
        if up:
            self.links_down.discard(port)
        elif port not in self.links_down:
            self.links_down.add(port)
            self.count_error(port, "lost")
        _U16.pack_into(self.mem, 0x0110, self._dl_status())

    def _clear_counters(self, ado: int, end: int) -> None:
        """A write into 0x0300-0x0313 clears counters (the value is ignored): any of 0x0300-0x030B clears
        those twelve, 0x030C and 0x030D themselves, any of 0x0310-0x0313 the lost-link counters."""
        for lo, hi in ((0x0300, 0x030C), (0x030C, 0x030D), (0x030D, 0x030E), (0x0310, 0x0314)):
            if ado < hi and end > lo:
                self.mem[lo:hi] = bytes(hi - lo)

    # -- addressing --

    @property
    def station_address(self) -> int:
        return int(self.mem[0x0010] | self.mem[0x0011] << 8)

    @property
    def alias(self) -> int:
        return int(self.mem[0x0012] | self.mem[0x0013] << 8)

    @property
    def alias_enabled(self) -> bool:
        return bool(self.mem[0x0103] & 0x01)

    # -- physical access --

    def read(self, ado: int, n: int, now_ns: int) -> bytes | None:
        """Register/RAM read by the master; None when the ESC denies it (no WKC)."""
        end = ado + n
        if end > MEM_SIZE:
            return bytes(n)
        if end > RAM_START:
            return self._read_ram(ado, n)
        if self._eeprom_busy_reads and ado < 0x0504 and end > 0x0502:
            self._eeprom_busy_reads -= 1
            if not self._eeprom_busy_reads:
                stuck = EEPROM_BUSY if self.eeprom_stuck else 0
                _U16.pack_into(self.mem, 0x0502, self._eeprom_status() | stuck)
        if ado < DC_END and end > DC_FIRST:
            return self._read_dc(ado, end, now_ns)
        return bytes(self.mem[ado:end])

    def _read_dc(self, ado: int, end: int, now_ns: int) -> bytes:
        out = bytearray(self.mem[ado:end])
        lo, hi = max(ado, DC_FIRST), min(end, DC_END)
        out[lo - ado : hi - ado] = self.dc.read(lo, hi - lo, now_ns)
        return bytes(out)

    def write(self, ado: int, data: bytes | memoryview, now_ns: int) -> bool:
        """Register/RAM write by the master; False when the ESC denies it (no WKC)."""
        n = len(data)
        end = ado + n
        if end > MEM_SIZE:
            return True
        if ado >= RAM_START:
            return self._write_ram(ado, data)
        mem = self.mem
        old = bytes(mem[ado:end])
        mem[ado:end] = data
        for s, e in _RO_RANGES:
            if s < end and ado < e:
                lo, hi = max(s, ado), min(e, end)
                mem[lo:hi] = old[lo - ado : hi - ado]
        if ado < ERR_END and end > ERR_FIRST:
            self._clear_counters(ado, end)
        if ado < 0x0122 and end > 0x0120:
            self._al_control(now_ns)
        if ado < 0x0504 and end > 0x0502:
            self._eeprom_command()
        if ado < 0x0600 + 16 * N_FMMU and end > 0x0600:
            self._fmmu_written()
        if ado < 0x0800 + 8 * N_SM and end > 0x0800:
            self._sm_written()
        if ado < DC_END and end > DC_FIRST:
            lo, hi = max(ado, DC_FIRST), min(end, DC_END)
            self.dc.write(lo, data[lo - ado : hi - ado], now_ns)
        return True

    # -- mailbox RAM --

    def _read_ram(self, ado: int, n: int) -> bytes | None:
        end = ado + n
        if self.mailbox.size_in:
            s1, l1, _, _ = self.sm[1]
            if l1 and ado < s1 + l1 and end > s1:
                if not self.sm1_full:
                    return None
                data = bytes(self.mem[ado:end])
                if end >= s1 + l1:  # last byte read: buffer released
                    self.sm1_full = False
                    self._load_sm1()
                return data
        return bytes(self.mem[ado:end])

    def _write_ram(self, ado: int, data: bytes | memoryview) -> bool:
        end = ado + len(data)
        if self.mailbox.size_out:
            s0, l0, _, _ = self.sm[0]
            if l0 and ado < s0 + l0 and end > s0:
                if self.sm0_full:
                    return False
                self.mem[ado:end] = data
                if end >= s0 + l0:
                    self._mailbox_written(bytes(self.mem[s0 : s0 + l0]))
                return True
            s1, l1, _, _ = self.sm[1]
            if l1 and ado < s1 + l1 and end > s1:
                return False  # the master cannot write the slave's send mailbox
        self.mem[ado:end] = data
        return True

    def _mailbox_active(self) -> bool:
        return self.state in (AlState.PRE_OP, AlState.SAFE_OP, AlState.OP, AlState.BOOT)

    def _mailbox_written(self, buf: bytes) -> None:
        if not self._mailbox_active():
            return
        self.sm0_full = True
        self._sm_status()
        if self.mailbox_fault is not None:
            self.sm0_full = self.mailbox_fault == "stuck"  # "silent": taken, never answered
            self._sm_status()
            return
        hook = self.sync_hook if self.fast else None
        if hook is not None:
            hook(self, False)
        self.mailbox.receive(buf, _COMM_STATE[self.state])
        if hook is not None:
            hook(self, True)
        self.sm0_full = False  # the application took it at once
        self._load_sm1()

    def _load_sm1(self) -> None:
        """Put the next queued answer into SM1 if it is free."""
        if not self.sm1_full and self.mailbox.pending:
            s1, l1, _, _ = self.sm[1]
            buf = self.mailbox.pending.popleft()
            self.mem[s1 : s1 + l1] = buf[:l1].ljust(l1, b"\x00")
            self.sm1_buf = buf
            self.sm1_full = True
        self._sm_status()

    def _repeat(self) -> None:
        """Repeat request: deliver the last answer again."""
        if self.sm1_buf:
            s1, l1, _, _ = self.sm[1]
            if self.sm1_full:
                self.mailbox.pending.appendleft(bytes(self.mem[s1 : s1 + l1]))
            self.mem[s1 : s1 + l1] = self.sm1_buf[:l1].ljust(l1, b"\x00")
            self.sm1_full = True
        self.mem[0x080F] = (self.mem[0x080F] & ~0x02) | self._repeat_bit
        self._sm_status()

    def _sm_status(self) -> None:
        self.mem[0x0805] = 0x08 if self.sm0_full else 0x00
        self.mem[0x080D] = 0x08 if self.sm1_full else 0x00

    def clear_faults(self) -> None:
        """Undo this slave's fault hooks: states taken again, mailbox and EEPROM working."""
        self.refuse.clear()
        if self.mailbox_fault == "stuck":
            self.sm0_full = False
            self._sm_status()
        self.mailbox_fault = None
        if self.eeprom_stuck:
            self.eeprom_stuck = False
            _U16.pack_into(self.mem, 0x0502, self._eeprom_status())
        if self.links_down:
            self.links_down.clear()
            _U16.pack_into(self.mem, 0x0110, self._dl_status())

    def send_emergency(self, error_code: int, error_register: int = 0, data: bytes = b"") -> None:
        """Queue a CoE emergency message for the master (when the mailbox is in use)."""
        if self.mailbox.size_in:
            self.mailbox.send_coe(emergency_payload(error_code, error_register, data))
            if self._mailbox_active():
                self._load_sm1()

    # -- SyncManagers and FMMUs --

    def _sm_written(self) -> None:
        mem = self.mem
        old01 = self.sm[:2]
        sms = []
        for i in range(N_SM):
            start, length, ctrl, _status, act, _pdi = _SM.unpack_from(mem, 0x0800 + 8 * i)
            sms.append((start, length, ctrl, act))
            mem[0x0807 + 8 * i] = 0
        self.sm = sms
        rep = mem[0x080E] & 0x02
        if [(*x[:3], x[3] & 1) for x in sms[:2]] != [(*x[:3], x[3] & 1) for x in old01]:
            self._reset_mailbox_buffers()
        elif rep != self._repeat_bit:
            self._repeat_bit = rep
            self._repeat()
        self._repeat_bit = rep
        self._sm_status()
        self._update_lmap()

    def _reset_mailbox_buffers(self) -> None:
        self.sm0_full = False
        self.sm1_full = False
        self.sm1_buf = b""
        self.mem[0x080F] = 0

    def _fmmu_written(self) -> None:
        self._update_lmap()

    def _fmmus(self) -> list[tuple[int, int, int, int, int]]:
        """Active FMMUs: (logical start, length, physical start, type, activate)."""
        out = []
        for i in range(N_FMMU):
            log, length, _sb, _eb, phys, _pb, kind, act = _FMMU.unpack_from(self.mem, 0x0600 + 16 * i)
            if act & 0x01 and length and kind & 0x03:
                out.append((log, length, phys, kind, act))
        return out

    def _update_lmap(self) -> None:
        self.lmap = tuple(
            (log, log + length, phys, bool(kind & 0x02)) for log, length, phys, kind, _ in self._fmmus()
        )
        self._changed()

    # -- process data (hot path) --

    def logical(self, cmd: int, laddr: int, buf: bytearray, doff: int, n: int) -> int:
        """LRD (10) / LWR (11) / LRW (12) through the FMMUs; WKC increment: LRD/LWR 1, LRW read 1 + write 2."""
        if not self.pd_active:
            return 0
        inc = 0
        lend = laddr + n
        mem = self.mem
        for ls, le, ps, wr in self.lmap:
            if ls >= lend or le <= laddr:
                continue
            s = ls if ls > laddr else laddr
            e = le if le < lend else lend
            po = ps + s - ls
            fo = doff + s - laddr
            if wr:
                if cmd != 10 and self.outputs_active:
                    mem[po : po + e - s] = buf[fo : fo + e - s]
                    inc |= 2
            elif cmd != 11:
                buf[fo : fo + e - s] = mem[po : po + e - s]
                inc |= 1
        if inc:
            self.touched = True
            if inc & 2:
                self.outputs_written = True
                if cmd == 11:
                    return 1  # LWR counts a write as 1; LRW as 2
        return inc

    def cycle(self, now_ns: int) -> None:
        """After a frame exchanged process data: outputs -> OD (in OP), app step, OD -> inputs."""
        img = self.image
        if self.outputs_written:
            self.outputs_written = False
            self.last_output_ns = now_ns
            if self.state == AlState.OP:
                img.outputs.to_od(self.mem, self.sm[2][0])
        if self.app is not None:
            last = self.last_step_ns
            dt = DEFAULT_DT_S if last is None else (now_ns - last) * 1e-9
            self.app.step(self.od, dt if 1e-6 < dt < 0.1 else (1e-6 if dt <= 1e-6 else 0.1))
        self.last_step_ns = now_ns
        if img.inputs.size:
            img.inputs.from_od(self.mem, self.sm[3][0])
        self.touched = False
        self.cycles += 1

    def check_watchdog(self, now_ns: int) -> None:
        """Process-data watchdog: no output write for longer than 0x0420 x (0x0400 + 2) x 40 ns in OP."""
        if self.state != AlState.OP or self.last_output_ns is None:
            return
        _start, length, ctrl, act = self.sm[2]
        if not (length and act & 0x01 and ctrl & 0x40):
            return
        mem = self.mem
        wd = (mem[0x0420] | mem[0x0421] << 8) * ((mem[0x0400] | mem[0x0401] << 8) + 2) * 40
        if wd and now_ns - self.last_output_ns > wd:
            self._fail(AlStatusCode.SYNC_MANAGER_WATCHDOG, AlState.SAFE_OP)

    # -- AL state machine --

    def _al_control(self, now_ns: int) -> None:
        if not self.eeprom_loaded:
            return  # no PDI (configuration area not loaded): nobody answers AL control, the state stays INIT
        raw = self.mem[0x0120] | self.mem[0x0121] << 8
        req = raw & 0x0F
        if raw & AL_ERROR_INDICATOR:
            self.error = False
            self.status_code = 0
        elif self.error and req > self.state:
            self._publish()
            return  # error not acknowledged: no way up
        try:
            target = AlState(req)
        except ValueError:
            self._fail(AlStatusCode.UNKNOWN_STATE)
            return
        if target == self.state:
            self._publish()
            return
        check = TRANSITIONS.get((self.state, target))
        if check is None:
            self._fail(AlStatusCode.INVALID_STATE_CHANGE)
            return
        refused = self.refuse.get(target)
        if refused is not None:
            self._fail(refused)
            return
        if check is Check.MAILBOX and not self.firmware.valid:
            self._fail(AlStatusCode.NO_VALID_FIRMWARE)  # a firmware write did not complete: BOOTSTRAP only
            return
        if check is Check.MAILBOX and not self._mailbox_config_ok():
            self._fail(AlStatusCode.INVALID_MAILBOX_CONFIG)
            return
        if check is Check.BOOT_MAILBOX:
            if not self.sii.boot_mailbox_out[1] or not self.sii.boot_mailbox_in[1]:
                self._fail(AlStatusCode.BOOTSTRAP_NOT_SUPPORTED)
                return
            if not self._mailbox_config_ok(boot=True):
                self._fail(AlStatusCode.INVALID_BOOT_MAILBOX_CONFIG)
                return
        if check is Check.PROCESS_DATA:
            code = self._process_data_config()
            if code:
                self._fail(code)
                return
        self._enter(target, now_ns)

    def _fail(self, code: int, state: AlState | None = None) -> None:
        """Set the error indicator and status code; optionally fall back to ``state``."""
        self.error = True
        self.status_code = code
        if state is not None:
            self._enter(state, None, keep_error=True)
        self._publish()

    def _enter(self, target: AlState, now_ns: int | None, *, keep_error: bool = False) -> None:
        if self.state == AlState.OP and target != AlState.OP:
            lost = getattr(self.app, "connection_lost", None)
            if callable(lost):
                lost()  # a CiA 402 drive stops by itself when the ESC leaves OP (watchdog, master)
        if target in (AlState.INIT, AlState.BOOT):
            self.mailbox.reset()
            self._reset_mailbox_buffers()
            self._sm_status()
            self._use_mailbox(boot=target == AlState.BOOT)
        self.state = target
        self.pd_active = target in (AlState.SAFE_OP, AlState.OP)
        self.outputs_active = target == AlState.OP
        if target == AlState.OP:
            self.last_output_ns = now_ns
        if not keep_error:
            self._publish()
        self._changed()

    def _publish(self) -> None:
        _U16.pack_into(self.mem, 0x0130, int(self.state) | (AL_ERROR_INDICATOR if self.error else 0))
        _U16.pack_into(self.mem, 0x0134, self.status_code)

    def _mailbox_config_ok(self, *, boot: bool = False) -> bool:
        if not self.mailbox.size_out:
            return True
        sii = self.sii
        (o_start, o_len), (i_start, i_len) = (
            (sii.boot_mailbox_out, sii.boot_mailbox_in) if boot else (sii.mailbox_out, sii.mailbox_in)
        )
        s0, s1 = self.sm[0], self.sm[1]
        return (
            s0[0] == o_start
            and s0[1] == o_len
            and s0[2] & 0x0F == 0x06
            and bool(s0[3] & 0x01)
            and s1[0] == i_start
            and s1[1] == i_len
            and s1[2] & 0x0F == 0x02
            and bool(s1[3] & 0x01)
        )

    def _process_data_config(self) -> int:
        """PRE-OP -> SAFE-OP: re-layout from the OD, then check SM2/SM3 and any FMMUs set (0 = fine)."""
        if self.image.version != self.od.mapping_version:
            self.image = ProcessImage(self.od, self.name)
            self._changed()
        fmmus = self._fmmus()
        for sm_index, sm_type, size, write, code in (
            (2, SM_TYPE_OUTPUTS, self.image.outputs.size, True, AlStatusCode.INVALID_OUTPUT_CONFIG),
            (3, SM_TYPE_INPUTS, self.image.inputs.size, False, AlStatusCode.INVALID_INPUT_CONFIG),
        ):
            start, length, ctrl, act = self.sm[sm_index]
            expected = [s.start for s in self.sii.sms if s.type == sm_type]
            if size == 0:
                if length and act & 0x01:
                    return code
                continue
            if length != size or not act & 0x01 or (expected and start != expected[0]):
                return code
            if bool(ctrl & 0x04) != write or ctrl & 0x03:
                return code
            if not any(bool(kind & 0x02) == write for _l, _f, _p, kind, _ in fmmus):
                # no FMMU for this direction yet: SOEM's ecx_reconfig_slave requests SAFE-OP first
                # and programs the FMMUs after; ESCs accept that (only a wrong FMMU is refused)
                continue
            covered = bytearray(size)
            for _log, flen, phys, kind, _ in fmmus:
                if bool(kind & 0x02) != write:
                    continue
                lo, hi = max(phys, start), min(phys + flen, start + size)
                covered[lo - start : hi - start] = b"\x01" * max(0, hi - lo)
            if not all(covered):
                return code
        return 0

    # -- EEPROM interface --

    def _eeprom_status(self, errors: int = 0) -> int:
        loaded = 0 if self.eeprom_loaded else EEPROM_CHECKSUM_ERROR | EEPROM_NOT_LOADED
        return EEPROM_R64 | loaded | errors

    def _eeprom_command(self) -> None:
        """0x0502 written: NOP clears the error bits; read (1) 8 bytes into 0x0508; write (2) the word in
        0x0508 only with write enable (bit 0) in the same write, else error bit 14; reload (4; 3 as SOEM's
        EC_ECMD_RELOAD) checks the configuration area's checksum again; anything else error bit 13. A
        command while busy is ignored. A write keeps the interface busy for a few status reads."""
        mem = self.mem
        if self._eeprom_busy_reads:
            _U16.pack_into(mem, 0x0502, self._eeprom_status() | EEPROM_BUSY)
            return
        ctrl = mem[0x0502] | mem[0x0503] << 8
        cmd = (ctrl >> 8) & 0x07
        addr = _U32.unpack_from(mem, 0x0504)[0] & 0xFFFF
        errors = 0
        if cmd == 1:  # read: 8 bytes (status bit 6 advertises it)
            mem[0x0508:0x0510] = self.sii.read(addr, 8)
        elif cmd == 2:
            if not ctrl & 0x01:
                errors = EEPROM_WRITE_ENABLE_ERROR
            elif 2 * addr + 2 > len(self.sii.data):
                errors = EEPROM_NACK  # past the EEPROM's end: no acknowledge
            else:
                self.sii.write_word(addr, mem[0x0508] | mem[0x0509] << 8)
                self._eeprom_busy_reads = EEPROM_WRITE_BUSY_READS
        elif cmd in (3, 4):
            self.eeprom_loaded = checksum_ok(bytes(self.sii.data[:16]))
            _U16.pack_into(mem, 0x0110, self._dl_status())
        elif cmd != 0:
            errors = EEPROM_NACK
        if self.eeprom_stuck:
            _U16.pack_into(mem, 0x0502, self._eeprom_status(errors) | EEPROM_BUSY)  # fault hook: never done
            return
        busy = EEPROM_BUSY if self._eeprom_busy_reads else 0
        _U16.pack_into(mem, 0x0502, self._eeprom_status(errors) | busy)
