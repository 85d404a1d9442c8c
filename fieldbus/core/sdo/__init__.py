"""SDO plans (ordered configuration writes) and abort codes. Pure data."""

from fieldbus.core.sdo.plan import SdoPlan, SdoStep, StepKind, canopen_plan, coe_plan
from fieldbus.errors import ABORT_CODES, abort_name

__all__ = ["ABORT_CODES", "SdoPlan", "SdoStep", "StepKind", "abort_name", "canopen_plan", "coe_plan"]
