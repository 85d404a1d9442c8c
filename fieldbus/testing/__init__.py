"""Test a controller against emulated drives: networks brought up as written, faults by name, virtual time.

    from fieldbus.testing import emulate, assert_safe_stop_latched

    with emulate("robot.yaml") as emu:           # every bus emulated, the master in OP
        emu.run(controller.step, cycles=1000)    # the controller's own loop, on emu.clock
        since = emu.trace.mark()
        emu.lose_cycles("legs", 12)
        emu.run(controller.step, cycles=50)
        assert_safe_stop_latched(emu.trace, within=12, since=since)

The pytest plugin (installed with fieldbus, entry point ``pytest11``) gives
the same as a fixture, ``fieldbus_emulation``: ``emu = fieldbus_emulation("robot.yaml")``,
torn down after the test, skipped with the machine's reason where it refuses
(a veth pair without root). See docs/testing.md.
"""

from fieldbus.core.firmware_image import firmware_image
from fieldbus.platform.clock import Clock, VirtualClock, WallClock
from fieldbus.testing.checks import (
    EmulationAssertion,
    assert_all_enabled,
    assert_drive_states,
    assert_event,
    assert_inputs_held,
    assert_no_event,
    assert_no_miss,
    assert_no_safe_stop,
    assert_no_target_jump,
    assert_safe_stop_latched,
)
from fieldbus.testing.emulation import Emulation, emulate
from fieldbus.testing.provider import EmulationError, EmulationUnavailable, FaultNotSupported
from fieldbus.testing.trace import Trace, TraceEvent

__all__ = [
    "Clock",
    "Emulation",
    "EmulationAssertion",
    "EmulationError",
    "EmulationUnavailable",
    "FaultNotSupported",
    "Trace",
    "TraceEvent",
    "VirtualClock",
    "WallClock",
    "assert_all_enabled",
    "assert_drive_states",
    "assert_event",
    "assert_inputs_held",
    "assert_no_event",
    "assert_no_miss",
    "assert_no_safe_stop",
    "assert_no_target_jump",
    "assert_safe_stop_latched",
    "emulate",
    "firmware_image",
]
