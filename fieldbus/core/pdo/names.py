"""Default channel names for well-known CiA 301 / CiA 402 objects.

Used when a channel has neither ``name`` nor an ethercat_driver_ros2 interface
name. Anything else is named from its address, e.g. ``x6000_01``.
"""

from __future__ import annotations

CIA402_NAMES: dict[tuple[int, int], str] = {
    (0x603F, 0): "error_code",
    (0x6040, 0): "controlword",
    (0x6041, 0): "statusword",
    (0x605A, 0): "quick_stop_option_code",
    (0x6060, 0): "modes_of_operation",
    (0x6061, 0): "modes_of_operation_display",
    (0x6062, 0): "position_demand_value",
    (0x6063, 0): "position_actual_internal_value",
    (0x6064, 0): "position_actual_value",
    (0x606B, 0): "velocity_demand_value",
    (0x606C, 0): "velocity_actual_value",
    (0x6071, 0): "target_torque",
    (0x6072, 0): "max_torque",
    (0x6074, 0): "torque_demand",
    (0x6077, 0): "torque_actual_value",
    (0x6078, 0): "current_actual_value",
    (0x6079, 0): "dc_link_circuit_voltage",
    (0x607A, 0): "target_position",
    (0x607F, 0): "max_profile_velocity",
    (0x6080, 0): "max_motor_speed",
    (0x60B0, 0): "position_offset",
    (0x60B1, 0): "velocity_offset",
    (0x60B2, 0): "torque_offset",
    (0x60B8, 0): "touch_probe_function",
    (0x60B9, 0): "touch_probe_status",
    (0x60BA, 0): "touch_probe_pos1_pos_value",
    (0x60BB, 0): "touch_probe_pos1_neg_value",
    (0x60F4, 0): "following_error_actual_value",
    (0x60FC, 0): "position_demand_internal_value",
    (0x60FD, 0): "digital_inputs",
    (0x60FE, 1): "digital_outputs",
    (0x60FF, 0): "target_velocity",
}

CONTROLWORD = 0x6040
STATUSWORD = 0x6041


def default_name(index: int, sub_index: int) -> str:
    """Name of an unnamed channel: its CiA 402 name, else ``x{index:04x}_{sub:02x}``."""
    return CIA402_NAMES.get((index, sub_index), f"x{index:04x}_{sub_index:02x}")


# CiA 402-2 data types of the objects above: what a scan assumes when the device cannot say
# (CANopen has no SDO Information; an EtherCAT slave without it).
CIA402_TYPES: dict[tuple[int, int], str] = {
    (0x603F, 0): "uint16",
    (0x6040, 0): "uint16",
    (0x6041, 0): "uint16",
    (0x605A, 0): "int16",
    (0x6060, 0): "int8",
    (0x6061, 0): "int8",
    (0x6062, 0): "int32",
    (0x6063, 0): "int32",
    (0x6064, 0): "int32",
    (0x606B, 0): "int32",
    (0x606C, 0): "int32",
    (0x6071, 0): "int16",
    (0x6072, 0): "uint16",
    (0x6074, 0): "int16",
    (0x6077, 0): "int16",
    (0x6078, 0): "int16",
    (0x6079, 0): "uint32",
    (0x607A, 0): "int32",
    (0x607F, 0): "uint32",
    (0x6080, 0): "uint32",
    (0x60B0, 0): "int32",
    (0x60B1, 0): "int32",
    (0x60B2, 0): "int16",
    (0x60B8, 0): "uint16",
    (0x60B9, 0): "uint16",
    (0x60BA, 0): "int32",
    (0x60BB, 0): "int32",
    (0x60F4, 0): "int32",
    (0x60FC, 0): "int32",
    (0x60FD, 0): "uint32",
    (0x60FE, 1): "uint32",
    (0x60FF, 0): "int32",
}
