"""What the wire carries, without ROS: the units constant and the reading of a joint
state's fields into micrometres and volts, shared by every reader (the nodes through
``convert``, the bag readers in ``piezo_stage.io``). SI units on the wire (metres,
volts; REP 103), micrometres in the core."""

from __future__ import annotations

import math

from piezo_stage.core.errors import DataError

JOINTS = ("x", "y")
UM = 1e-6  # metres per micrometre: um = m / UM, m = um * UM


def joint_state_axes(names, position, effort, what: str = "joint_states"
                     ) -> tuple[dict, dict | None]:
    """A joint state's fields -> ({joint: um} for the stage's joints it holds, {joint:
    V} from effort, or None when effort is not one value a joint). DataError when
    positions and names differ in number, a name repeats, or a value is not finite."""
    names = list(names)
    if len(position) != len(names):
        raise DataError(f"{what}: {len(names)} joint names, {len(position)} positions")
    if len(set(names)) != len(names):
        raise DataError(f"{what}: joint names repeat: {names}")
    w = {n: float(position[i]) / UM for i, n in enumerate(names) if n in JOINTS}
    v = ({n: float(effort[i]) for i, n in enumerate(names) if n in JOINTS}
         if len(effort) == len(names) else None)
    if not all(math.isfinite(x) for x in [*w.values(), *(v or {}).values()]):
        raise DataError(f"{what}: non-finite value")
    return w, v


def joint_state_um(data: bytes, what: str = "joint_states") -> tuple[int, dict, dict | None]:
    """sensor_msgs/JointState CDR bytes -> (stamp ns, {joint: um}, {joint: V} or None)."""
    from piezo_stage_msgs_adapters.cdr import decode_joint_state
    ns, _, names, position, _, effort = decode_joint_state(data)
    w, v = joint_state_axes(names, position, effort, what)
    return ns, w, v


def point_um(data: bytes) -> tuple[int, dict]:
    """geometry_msgs/PointStamped CDR bytes -> (stamp ns, {"x": um, "y": um})."""
    from piezo_stage_msgs_adapters.cdr import decode_point_stamped
    ns, _, (x, y, _) = decode_point_stamped(data)
    return ns, {"x": x / UM, "y": y / UM}
