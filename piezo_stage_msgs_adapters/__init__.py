"""Pure functions between ROS 2 messages (common_interfaces only) and core data.

The only code in the project that touches message types. SI units on the wire
(metres, volts, seconds; REP 103), micrometres in the core: conversions happen here.

``wire`` (units and joint-state reading) and ``cdr`` (the codecs of the per-sample
topics) need no ROS: the bag readers use them. The message functions of ``convert``
load the message types when first asked for (``piezo_stage_msgs_adapters.joint_state``
and the like): each is named below, so a type checker sees the node <-> message seam
with its types, and a name that is no adapter is an AttributeError.
"""

from typing import TYPE_CHECKING

from piezo_stage_msgs_adapters.wire import (
    JOINTS,
    MEASURED,
    UM,
    Announcement,
    Reference,
    TrajectoryRefused,
)

if TYPE_CHECKING:  # at run time loaded on first use (__getattr__): no ROS to import us
    from piezo_stage_msgs_adapters.convert import (
        ARM_LEVEL,
        FRAME,
        announcement_from_msg,
        arming_state_msg,
        check_trajectory_size,
        clock_msg,
        diagnostic_array,
        header,
        hold_from_msg,
        hold_msg,
        joint_state,
        joint_state_cdr,
        joint_state_to_um,
        model_from_msg,
        model_msg,
        move_from_msg,
        move_msg,
        ns_to_time,
        on_target_from_msg,
        on_target_msg,
        phase_from_msg,
        phase_msg,
        point_cdr,
        point_msg,
        reference_cdr,
        reference_from_msg,
        reference_msg,
        refusal_from_msg,
        refusal_msg,
        setpoint_from_msg,
        time_to_ns,
        trajectory_from_cdr,
        trajectory_from_msg,
        trajectory_header,
        trajectory_max_bytes,
        trajectory_msg,
        trajectory_refusal_msg,
        trajectory_stamp_ns,
        trajectory_take_bytes,
        voltage_cdr,
        voltage_from_msg,
        voltage_msg,
    )

__all__ = [
    "JOINTS", "MEASURED", "UM", "Announcement", "Reference", "TrajectoryRefused",
    "ARM_LEVEL", "FRAME",
    "announcement_from_msg", "arming_state_msg", "check_trajectory_size", "clock_msg",
    "diagnostic_array", "header", "hold_from_msg", "hold_msg", "joint_state",
    "joint_state_cdr", "joint_state_to_um",
    "model_from_msg", "model_msg", "move_from_msg", "move_msg", "ns_to_time",
    "on_target_from_msg", "on_target_msg", "phase_from_msg", "phase_msg",
    "point_cdr", "point_msg", "reference_cdr", "reference_from_msg", "reference_msg",
    "refusal_from_msg", "refusal_msg", "setpoint_from_msg", "time_to_ns",
    "trajectory_from_cdr", "trajectory_from_msg", "trajectory_header",
    "trajectory_max_bytes", "trajectory_msg", "trajectory_refusal_msg", "trajectory_stamp_ns",
    "trajectory_take_bytes", "voltage_cdr", "voltage_from_msg", "voltage_msg",
]
# what __getattr__ loads from convert (the TYPE_CHECKING list above)
CONVERT = frozenset(__all__) - {"JOINTS", "MEASURED", "UM", "Announcement", "Reference",
                                "TrajectoryRefused"}


def __getattr__(name: str) -> object:
    if name not in CONVERT:
        raise AttributeError(f"module 'piezo_stage_msgs_adapters' has no attribute {name!r}")
    import importlib
    value = getattr(importlib.import_module("piezo_stage_msgs_adapters.convert"), name)
    globals()[name] = value  # once: later look-ups (``msgs.name`` each sample) find it here
    return value
