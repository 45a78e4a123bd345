"""What the wire carries, without ROS: the units constant and the reading of a joint
state's fields into micrometres and volts, shared by every reader (the nodes through
``convert``, the bag readers in ``piezo_stage.io``). SI units on the wire (metres,
volts; REP 103), micrometres in the core."""

from __future__ import annotations

import math
from dataclasses import dataclass

from piezo_stage.core.errors import DataError, PiezoStageError
from piezo_stage.core.types import Doc
from piezo_stage_msgs_adapters.cdr import CdrReader

JOINTS = ("x", "y")
UM = 1e-6  # metres per micrometre: um = m / UM, m = um * UM


def joint_state_axes(names, position, effort, what: str = "joint_states"
                     ) -> tuple[dict, Doc | None]:
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


def joint_state_um(data: bytes, what: str = "joint_states") -> tuple[int, Doc, Doc | None]:
    """sensor_msgs/JointState CDR bytes -> (stamp ns, {joint: um}, {joint: V} or None)."""
    from piezo_stage_msgs_adapters.cdr import decode_joint_state
    ns, _, names, position, _, effort = decode_joint_state(data)
    w, v = joint_state_axes(names, position, effort, what)
    return ns, w, v


def point_um(data: bytes) -> tuple[int, Doc]:
    """geometry_msgs/PointStamped CDR bytes -> (stamp ns, {"x": um, "y": um})."""
    from piezo_stage_msgs_adapters.cdr import decode_point_stamped
    ns, _, (x, y, _) = decode_point_stamped(data)
    return ns, {"x": x / UM, "y": y / UM}


HOLD_WAIT, HOLD_GO = "wait", "go on"  # a lockstep hold's header.frame_id (watch/hold)
MEASURED = ("x_measured", "y_measured")  # the reference's joints after x, y


@dataclass(frozen=True)
class Reference:
    """The feedforward's /reference for one target sample: the desired position [um]
    and the feedforward [V] per axis, and the measurement [um] and applied voltage [V]
    it was computed from (the controller sees its own commands come back)."""

    ns: int
    desired_um: dict[str, float]
    ff_V: dict[str, float]
    measured_um: dict[str, float]
    applied_V: dict[str, float]


def reference_of(ns: int, names, position, effort) -> Reference:
    """A reference's joint-state fields (joints x, y, x_measured, y_measured; position
    [m], effort [V]) -> Reference; DataError when it is not one. The one decoder: the
    controller's (``convert.reference_from_msg``) and the bag reader's
    (``reference_um``)."""
    if list(names) != list(JOINTS + MEASURED) or len(position) != 4 or len(effort) != 4:
        raise DataError("reference: expected joints [x, y, x_measured, y_measured] with "
                        "position and effort")
    values = [float(x) for x in (*position, *effort)]
    if not all(math.isfinite(x) for x in values):
        raise DataError("reference: non-finite value")
    p, e = values[:4], values[4:]
    return Reference(int(ns), {a: p[i] / UM for i, a in enumerate(JOINTS)},
                     {a: e[i] for i, a in enumerate(JOINTS)},
                     {a: p[2 + i] / UM for i, a in enumerate(JOINTS)},
                     {a: e[2 + i] for i, a in enumerate(JOINTS)})


def reference_um(data: bytes) -> Reference:
    """A /reference as CDR bytes -> Reference."""
    from piezo_stage_msgs_adapters.cdr import decode_joint_state
    ns, _, names, position, _, effort = decode_joint_state(data)
    return reference_of(ns, names, position, effort)


@dataclass(frozen=True)
class Announcement:
    """The driver's latched ``state``: from the sample stamped ``since_ns`` on, its
    arming ``state`` and ``reason``, the look-ahead [s] it announces, its voltage
    limits (lo, hi) [V] (None: not given), its ``mode``, and every key-value as sent."""

    since_ns: int
    state: str
    reason: str
    lookahead_s: float
    limits: tuple[float, float] | None
    mode: str
    values: dict[str, str]


def announcement_of(msg) -> Announcement:
    """A diagnostic_msgs/DiagnosticArray of the driver's ``state`` (rclpy's message or
    a bag reader's: the same fields) -> Announcement, read in this one place. DataError
    when it has no status or state, a value is not a number or the limits not lo < hi."""
    if not msg.status:
        raise DataError("state: no status")
    kv = {str(k.key): str(k.value) for k in msg.status[0].values}
    if "state" not in kv:
        raise DataError("state: no 'state' value")
    try:
        lookahead = float(kv.get("lookahead_s", 0.0))
        lo, hi = kv.get("voltage_limit_lo_V"), kv.get("voltage_limit_hi_V")
        limits = None if lo is None or hi is None else (float(lo), float(hi))
    except (TypeError, ValueError) as e:
        raise DataError(f"state: a driver announcement that is not a number ({e})") from None
    if limits is not None and not (math.isfinite(limits[0]) and limits[0] < limits[1]):
        raise DataError(f"state: voltage limits {limits} are not lo < hi")
    if not (math.isfinite(lookahead) and lookahead >= 0.0):
        raise DataError(f"state: look-ahead {lookahead} s")
    stamp = msg.header.stamp
    return Announcement(int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec), kv["state"],
                        kv.get("reason", ""), lookahead, limits, kv.get("mode", ""), kv)


def trajectory_header(data: bytes) -> tuple[str, int]:
    """(header.frame_id, header.stamp [ns]) of a trajectory's CDR bytes, what its sender
    names it by; ("", 0) where the bytes do not hold a header."""
    try:
        r = CdrReader(data)
        stamp = r.stamp()
        return r.string(), stamp
    except DataError:
        return "", 0


class TrajectoryRefused(PiezoStageError):
    """A trajectory refused: the reason, and what its sender names it by (its header's
    frame_id and stamp [ns], ``trajectory_header``), for the refusal it is told."""

    def __init__(self, reason: str, data: bytes) -> None:
        super().__init__(reason)
        self.frame_id, self.stamp_ns = trajectory_header(data)
