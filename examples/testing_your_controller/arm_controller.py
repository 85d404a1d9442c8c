"""A user's 3-axis arm controller: enable the joints, follow a sine, stop safely, report drive faults.

It knows nothing of tests: it is handed the network in OP and steps once per
cycle (``step(k)``, as :func:`fieldbus.run_cycles` calls it).
"""

from __future__ import annotations

import math

import numpy as np

import fieldbus

FAULT_MASK, FAULT = 0x004F, 0x0008  # statusword bits of the FAULT state (CiA 402-2)


class ArmController:
    """CSP on every joint of group ``group``: ``start + A sin(2 pi f t)`` once all are enabled.

    ``fault_codes`` keeps, per axis, the last error code (0x603F) its drive reported in FAULT.
    After a safe stop it holds until :meth:`resume`.
    """

    AMPLITUDE_RAD = 0.3
    FREQUENCY_HZ = 0.5

    def __init__(self, op: fieldbus.Operational, group: str = "arm", rate_hz: float = 1000.0) -> None:
        self.op = op
        image = op[group]
        self.inputs, self.outputs = image.inputs, image.outputs
        n = image.n_axes
        self.dt = 1.0 / rate_hz
        self.cia402 = fieldbus.Cia402Controller(n, mode=fieldbus.Mode.CSP, timeout_cycles=int(5 * rate_hz))
        self.cia402.set_goal(fieldbus.Goal.ENABLE)
        self.start = np.zeros(n)
        self.t = 0.0  # trajectory time, s: runs while every joint is enabled
        self.following = False
        self.prev_target = np.zeros(n)
        self.max_error_rad = 0.0  # tracking error while following: |actual - target sent a cycle before|
        self.fault_codes: dict[int, int] = {}
        self.stopped = False  # the network latched a safe stop: outputs are the drives' quick stop

    def step(self, k: int) -> None:
        result = self.op.exchange()
        if result.safe_stop:
            self.stopped = True
            self.following = False
            return
        if not result.fresh:
            return  # inputs held: keep the last targets, the policy counts the miss
        position = self.inputs["position_actual_value"]
        target = self.outputs["target_position"]
        for axis, word in enumerate(self.inputs["statusword"]):
            if int(word) & FAULT_MASK == FAULT:
                self.fault_codes[axis] = int(self.inputs["error_code"][axis])
        self.cia402.step(
            self.inputs["statusword"],
            self.outputs["controlword"],
            self.inputs["modes_of_operation_display"],
            self.outputs["modes_of_operation"],
        )
        if not self.cia402.all_reached:
            self.following = False
            target[:] = position  # follow the joints while enabling: no jump on enable
            return
        if not self.following:  # (again) all enabled: the sine starts where the joints are
            self.following = True
            self.start[:] = position
            self.t = 0.0
        else:
            self.max_error_rad = max(self.max_error_rad, float(np.abs(position - self.prev_target).max()))
        self.t += self.dt
        target[:] = self.start + self.AMPLITUDE_RAD * math.sin(2 * math.pi * self.FREQUENCY_HZ * self.t)
        self.prev_target[:] = target

    def resume(self) -> None:
        """After a safe stop: release the latch and enable the joints again."""
        self.op.clear_safe_stop()
        self.stopped = False
        self.cia402.set_goal(fieldbus.Goal.ENABLE)
