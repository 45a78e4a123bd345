"""Message <-> core conversions. Every function is pure (no node, no I/O)."""

from __future__ import annotations

import array
import math

import numpy as np
from builtin_interfaces.msg import Duration, Time
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from geometry_msgs.msg import PointStamped, Vector3Stamped
from sensor_msgs.msg import JointState
from std_msgs.msg import Header, String
from trajectory_msgs.msg import JointTrajectory, JointTrajectoryPoint

from piezo_stage.core.errors import DataError
from piezo_stage.core.types import Doc, PerAxis
from piezo_stage_msgs_adapters import cdr
from piezo_stage_msgs_adapters.wire import (
    HOLD_GO,
    HOLD_WAIT,
    JOINTS,
    MEASURED,
    UM,
    Announcement,
    Reference,
    TrajectoryRefused,
    announcement_of,
    joint_state_axes,
    reference_of,
    trajectory_header,
)

__all__ = ["JOINTS", "UM", "ns_to_time", "time_to_ns", "header", "joint_state",
           "joint_state_to_um", "voltage_msg", "voltage_from_msg", "reference_msg",
           "reference_from_msg", "point_msg", "joint_state_cdr", "voltage_cdr",
           "reference_cdr", "point_cdr", "setpoint_from_msg", "trajectory_msg",
           "trajectory_from_msg", "model_msg", "model_from_msg", "diagnostic_array",
           "arming_state_msg", "announcement_from_msg", "trajectory_from_cdr", "clock_msg",
           "check_trajectory_size", "trajectory_max_bytes", "trajectory_take_bytes",
           "trajectory_stamp_ns", "phase_msg", "phase_from_msg", "move_msg",
           "move_from_msg", "hold_msg", "hold_from_msg", "on_target_msg",
           "on_target_from_msg", "trajectory_header", "refusal_msg", "refusal_from_msg",
           "trajectory_refusal_msg"]

FRAME = "stage"  # header.frame_id of everything the nodes publish


def ns_to_time(ns: int) -> Time:
    ns = int(ns)
    return Time(sec=ns // 1_000_000_000, nanosec=ns % 1_000_000_000)


def time_to_ns(t: Time) -> int:
    return int(t.sec) * 1_000_000_000 + int(t.nanosec)


def header(ns: int, frame_id: str = FRAME) -> Header:
    return Header(stamp=ns_to_time(ns), frame_id=frame_id)


def _finite(vals, what):
    if not all(math.isfinite(v) for v in vals):
        raise DataError(f"{what}: NaN or inf")


def joint_state(ns: int, w_um: PerAxis[float], v_applied=None) -> JointState:
    """Measured position [um] -> sensor_msgs/JointState (names x, y; metres). The
    voltage applied during that sample [V], when given, goes in ``effort`` (the
    actuator's drive effort), so position and drive arrive in one message."""
    # array('d') takes the generated setters' fast path (lists are checked per element)
    return JointState(header=header(ns), name=list(JOINTS),
                      position=array.array("d", (float(w_um[a]) * UM for a in JOINTS)),
                      effort=array.array("d", (float(v_applied[a]) for a in JOINTS))
                      if v_applied else array.array("d"))


def _register_layouts() -> None:
    """The loop's own joint states and references are decoded in one unpack (cdr)."""
    cdr.known_joint_state_layout(FRAME, JOINTS, (len(JOINTS), 0, len(JOINTS)))
    cdr.known_joint_state_layout(FRAME, JOINTS + MEASURED, (4, 0, 4))


def joint_state_cdr(ns: int, w_um: PerAxis[float], v_applied=None) -> bytes:
    """The same message as ``joint_state``, as the CDR bytes a raw publisher sends."""
    return cdr.encode_joint_state(ns, FRAME, JOINTS, [float(w_um[a]) * UM for a in JOINTS],
                                  (), [float(v_applied[a]) for a in JOINTS]
                                  if v_applied else ())


def _joint_state_fields(msg):
    """(ns, names, position, effort) of a JointState message or its CDR bytes."""
    if isinstance(msg, (bytes, bytearray, memoryview)):
        ns, _, names, pos, _, eff = cdr.decode_joint_state(msg)
        return ns, names, pos, eff
    return time_to_ns(msg.header.stamp), list(msg.name), msg.position, msg.effort


def joint_state_to_um(msg, with_effort=False):
    """JointState (message or CDR bytes) -> (stamp ns, {axis: um}) or, with_effort,
    (ns, um dict, V dict or None)."""
    ns, names, position, effort = _joint_state_fields(msg)
    if len(position) != len(names) or not set(JOINTS) <= set(names):
        raise DataError(f"joint_states: expected joints x, y with positions, got {names}")
    w, v = joint_state_axes(names, position, effort)
    return (ns, w, v) if with_effort else (ns, w)


def voltage_msg(ns: int, v: PerAxis[float]) -> Vector3Stamped:
    """Voltages [V] per axis -> geometry_msgs/Vector3Stamped (x, y in volts; z unused)."""
    m = Vector3Stamped(header=header(ns))
    m.vector.x, m.vector.y = float(v["x"]), float(v["y"])
    return m


def voltage_cdr(ns: int, v: PerAxis[float]) -> bytes:
    """The same message as ``voltage_msg``, as CDR bytes."""
    return cdr.encode_vector3_stamped(ns, FRAME, float(v["x"]), float(v["y"]), 0.0)


def voltage_from_msg(msg) -> tuple[int, Doc]:
    """Vector3Stamped (message or CDR bytes) -> (ns, {axis: V}). Raises DataError on
    NaN/inf (the driver rejects such commands) or malformed bytes."""
    if isinstance(msg, (bytes, bytearray, memoryview)):
        ns, _, (x, y, _) = cdr.decode_vector3_stamped(bytes(msg))
    else:
        ns, x, y = time_to_ns(msg.header.stamp), msg.vector.x, msg.vector.y
    v = {"x": float(x), "y": float(y)}
    _finite(v.values(), "voltage command")
    return ns, v




def reference_msg(ns: int, desired_um: PerAxis[float], ff_V: PerAxis[float],
                  measured_um: PerAxis[float],
                  applied_V: PerAxis[float]) -> JointState:
    """Internal /reference for a target sample: joints x, y with position = desired
    position [m] and effort = feedforward [V], and joints x_measured, y_measured with
    position = the measurement it was computed from [m] and effort = the voltage the
    driver applied for that measurement [V] (so the controller sees its own commands
    come back), all for one step in one message."""
    return JointState(header=header(ns), name=list(JOINTS + MEASURED),
                      position=array.array("d", [float(desired_um[a]) * UM for a in JOINTS]
                                           + [float(measured_um[a]) * UM for a in JOINTS]),
                      effort=array.array("d", [float(ff_V[a]) for a in JOINTS]
                                         + [float(applied_V[a]) for a in JOINTS]))


def reference_cdr(ns: int, desired_um: PerAxis[float], ff_V: PerAxis[float],
                  measured_um: PerAxis[float],
                  applied_V: PerAxis[float]) -> bytes:
    """The same message as ``reference_msg``, as CDR bytes."""
    return cdr.encode_joint_state(
        ns, FRAME, JOINTS + MEASURED,
        [float(desired_um[a]) * UM for a in JOINTS] + [float(measured_um[a]) * UM
                                                      for a in JOINTS],
        (), [float(ff_V[a]) for a in JOINTS] + [float(applied_V[a]) for a in JOINTS])


def reference_from_msg(msg) -> Reference:
    """Reference (message or CDR bytes) -> Reference (wire.reference_of: the one
    decoder, the bag reader's too); DataError when it is not one."""
    return reference_of(*_joint_state_fields(msg))


def point_msg(ns: int, w_um: PerAxis[float]) -> PointStamped:
    m = PointStamped(header=header(ns))
    m.point.x, m.point.y = float(w_um["x"]) * UM, float(w_um["y"]) * UM
    return m


def point_cdr(ns: int, w_um: PerAxis[float]) -> bytes:
    """The same message as ``point_msg``, as CDR bytes."""
    return cdr.encode_point_stamped(ns, FRAME, float(w_um["x"]) * UM, float(w_um["y"]) * UM,
                                    0.0)


def setpoint_from_msg(msg: PointStamped, range_um=None) -> Doc:
    w = {"x": msg.point.x / UM, "y": msg.point.y / UM}
    _finite(w.values(), "setpoint")
    if range_um is not None:
        lo, hi = range_um
        for a, x in w.items():
            if not lo <= x <= hi:
                raise DataError(f"setpoint {a} = {x:.3f} um outside the stage range "
                                f"[{lo:g}, {hi:g}] um")
    return w


MAX_MOVE_ID = 200  # characters of a move's id


def move_msg(move_id: str, w_um: PerAxis[float], ns: int = 0) -> PointStamped:
    """A move request (geometry_msgs/PointStamped on ``move``): the target in metres,
    ``header.frame_id`` the move's id (the stage's own frame is implied), the stamp
    when it was asked."""
    m = PointStamped(header=header(ns, str(move_id)))
    m.point.x, m.point.y = float(w_um["x"]) * UM, float(w_um["y"]) * UM
    return m


def move_from_msg(msg: PointStamped, range_um=None) -> tuple[str, Doc]:
    """A move request -> (its id, {axis: um}); DataError when the target is not finite,
    leaves the stage range, or the id is longer than MAX_MOVE_ID."""
    if len(msg.header.frame_id) > MAX_MOVE_ID:
        raise DataError(f"move: an id of over {MAX_MOVE_ID} characters")
    return msg.header.frame_id, setpoint_from_msg(msg, range_um)


def on_target_msg(s) -> DiagnosticArray:
    """A move's on-target state (core/loop/ontarget.py TargetState) on the latched
    ``on_target`` topic: header.stamp the sample judged; one status named
    ``on_target`` whose message is the state (on_target: level 0, moving: 1,
    refused: 2, with the reason),
    ``hardware_id`` the move's id, and per axis its state, the filtered error and the
    target [um], with the settle time [ms] once on target."""
    values = {"move_id": s.move_id, "state": s.state, "started_ns": s.started_ns,
              "settle_ms": "" if s.settle_s is None else f"{s.settle_s * 1e3:.3f}",
              "reason": s.reason}
    for a, st in s.axes.items():
        values[a] = st
        values[f"error_{a}_um"] = f"{s.error_um.get(a, float('nan')):.4f}"
        values[f"target_{a}_um"] = f"{s.target_um[a]:.4f}"
    level = {"on_target": 0, "moving": 1}.get(s.state, 2)
    return diagnostic_array(s.stamp_ns, "on_target", level, s.state, values, s.move_id)


def on_target_from_msg(msg: DiagnosticArray):
    """``on_target`` -> TargetState (DataError when it is not one)."""
    from piezo_stage.core.loop.ontarget import TargetState
    try:
        st = msg.status[0]
        kv = {v.key: v.value for v in st.values}
        axes = [a for a in JOINTS if a in kv]
        settle = float(kv["settle_ms"]) * 1e-3 if kv.get("settle_ms") else None
        return TargetState(kv["move_id"], kv["state"], {a: kv[a] for a in axes}, settle,
                           {a: float(kv[f"error_{a}_um"]) for a in axes},
                           {a: float(kv[f"target_{a}_um"]) for a in axes},
                           time_to_ns(msg.header.stamp), int(kv["started_ns"]),
                           kv.get("reason", ""))
    except (IndexError, KeyError, ValueError) as e:
        raise DataError(f"on_target: not an on-target state ({e})") from None


def trajectory_msg(t_s, w_um: PerAxis[np.ndarray]) -> JointTrajectory:
    """(t [s], {axis: um}) -> JointTrajectory (joint_names x, y; metres)."""
    msg = JointTrajectory(joint_names=list(JOINTS))
    for k, t in enumerate(t_s):
        ns = int(round(float(t) * 1e9))
        msg.points.append(JointTrajectoryPoint(
            positions=[float(w_um[a][k]) * UM for a in JOINTS],
            time_from_start=Duration(sec=ns // 1_000_000_000, nanosec=ns % 1_000_000_000)))
    return msg


def trajectory_from_msg(msg: JointTrajectory, range_um=None, max_points=None):
    """JointTrajectory -> (t [s], {axis: um}); DataError with the reason if the message
    names unknown or repeated joints, has more than ``max_points`` points, points
    without one position per joint, negative or non-increasing times, NaN, or leaves
    the stage range."""
    names = list(msg.joint_names)
    unknown = [n for n in names if n not in JOINTS]
    if unknown or not names:
        raise DataError(f"trajectory: unknown joint name(s) {unknown or names}; use x, y")
    if len(set(names)) != len(names):
        raise DataError(f"trajectory: joint names repeat: {names}")
    if not msg.points:
        raise DataError("trajectory: no points")
    if max_points is not None and len(msg.points) > max_points:
        raise DataError(f"trajectory: {len(msg.points)} points, more than the "
                        f"{max_points} accepted (max_trajectory_points)")
    bad = next((k for k, p in enumerate(msg.points) if len(p.positions) != len(names)), None)
    if bad is not None:
        raise DataError(f"trajectory: point {bad} has {len(msg.points[bad].positions)} "
                        f"positions for {len(names)} joints")
    t = np.array([p.time_from_start.sec + p.time_from_start.nanosec * 1e-9
                  for p in msg.points])
    pos = np.array([list(p.positions) for p in msg.points], dtype=float)
    return _trajectory(names, t, pos, range_um)


# A point of JOINTS in CDR: its time_from_start (8 bytes) and four sequences
# (positions, velocities, accelerations, effort), each a 4-byte length, up to 4 bytes of
# alignment and 8 bytes a joint: 104 bytes; 128 leaves room. Header and names: 64 kB.
POINT_BYTES, HEAD_BYTES = 128, 65536
assert 8 + 4 * (8 + 8 * len(JOINTS)) <= POINT_BYTES


def trajectory_max_bytes(max_points: int) -> int:
    """The most CDR bytes a valid trajectory of ``max_points`` points can take."""
    return POINT_BYTES * int(max_points) + HEAD_BYTES


def trajectory_take_bytes(max_points: int) -> int:
    """The memory taking and decoding the largest admitted trajectory needs: its bytes
    twice (the middleware's copy, then Python's) and 3 doubles a point decoded."""
    return 2 * trajectory_max_bytes(max_points) + 24 * int(max_points)


def check_trajectory_size(data: bytes, max_points=None) -> None:
    """DataError when a trajectory's CDR bytes are more than ``max_points`` points can
    take (velocities, accelerations and efforts included), from its length alone."""
    if max_points is not None and len(data) > trajectory_max_bytes(max_points):
        raise DataError(f"trajectory: {len(data)} bytes, more than {max_points} points "
                        "take (max_trajectory_points)")


def trajectory_stamp_ns(data: bytes) -> int:
    """A trajectory's header.stamp [ns] from its CDR bytes (0: start now)."""
    return cdr.CdrReader(data).stamp()


def trajectory_from_cdr(data: bytes, range_um=None, max_points=None):
    """The same as ``trajectory_from_msg`` from the message's CDR bytes, without a
    Python object per point (a 200,000-point trajectory in milliseconds, not seconds),
    and with the size checked before anything is decoded."""
    check_trajectory_size(data, max_points)
    out = cdr.decode_joint_trajectory(data, max_points)
    if out is None:  # points of different layouts: the ordinary way
        from rclpy.serialization import deserialize_message
        try:
            msg = deserialize_message(data, JointTrajectory)
        except Exception as e:  # noqa: BLE001 - rclpy's error types vary by cause
            raise DataError(f"trajectory: not a valid JointTrajectory ({e})") from None
        return trajectory_from_msg(msg, range_um, max_points)
    names, t, pos = out
    unknown = [n for n in names if n not in JOINTS]
    if unknown or not names:
        raise DataError(f"trajectory: unknown joint name(s) {unknown or names}; use x, y")
    if len(set(names)) != len(names):
        raise DataError(f"trajectory: joint names repeat: {names}")
    if not len(t):
        raise DataError("trajectory: no points")
    if max_points is not None and len(t) > max_points:
        raise DataError(f"trajectory: {len(t)} points, more than the {max_points} "
                        "accepted (max_trajectory_points)")
    return _trajectory(names, t, pos, range_um)


def _trajectory(names, t, pos, range_um):
    """Checks common to both decodings: times, finiteness, range."""
    if t[0] < 0:
        raise DataError("trajectory: negative time_from_start")
    if np.any(np.diff(t) <= 0):
        raise DataError("trajectory: time_from_start is not strictly increasing")
    pos = pos / UM
    if not np.all(np.isfinite(pos)):
        raise DataError("trajectory: NaN or inf position")
    if range_um is not None:
        lo, hi = range_um
        if pos.min() < lo or pos.max() > hi:
            raise DataError(f"trajectory: positions {pos.min():.2f}..{pos.max():.2f} um "
                            f"outside the stage range [{lo:g}, {hi:g}] um")
    return t, {n: pos[:, i] for i, n in enumerate(names)}


def model_msg(yaml_text: str) -> String:
    return String(data=yaml_text)


def model_from_msg(msg: String):
    """std_msgs/String with a model file's YAML -> (StageModel, effects)."""
    from piezo_stage.core.model.model_doc import model_from_dict, parse_yaml
    return model_from_dict(parse_yaml(msg.data, "model message", max_bytes=65536),
                           "model message")


def refusal_msg(ns: int, frame_id: str, stamp_ns: int, reason: str) -> DiagnosticArray:
    """A trajectory the feedforward refused, on the ``trajectory/refused`` topic (as
    ``on_target`` answers a refused move): header.stamp when it was refused; one status
    named ``trajectory``, level 2, its message the reason, ``hardware_id`` the
    trajectory's ``header.frame_id``; key-values ``frame_id``, ``stamp_ns`` (its
    header.stamp) and ``reason``."""
    return diagnostic_array(ns, "trajectory", 2, reason, {
        "frame_id": frame_id, "stamp_ns": int(stamp_ns), "reason": reason}, frame_id)


def trajectory_refusal_msg(ns: int, e: BaseException) -> DiagnosticArray:
    """``refusal_msg`` for the error a trajectory was refused with: named as its sender
    names it where the error knows (``TrajectoryRefused``), else by nothing."""
    frame_id, stamp = (e.frame_id, e.stamp_ns) if isinstance(e, TrajectoryRefused) \
        else ("", 0)
    return refusal_msg(ns, frame_id, stamp, str(e))


def refusal_from_msg(msg: DiagnosticArray) -> tuple[str, int, str]:
    """``trajectory/refused`` -> (frame_id, stamp_ns, reason); DataError when it is not
    one."""
    try:
        kv = {v.key: v.value for v in msg.status[0].values}
        return kv["frame_id"], int(kv["stamp_ns"]), kv["reason"]
    except (IndexError, KeyError, ValueError):
        raise DataError("trajectory/refused: not a refusal") from None


def phase_msg(phase: str, follows: str = "") -> KeyValue:
    """The feedforward's phase as data (diagnostic_msgs/KeyValue): ``key`` the phase
    (holding, approaching, tracking, done), ``value`` what it follows ("trajectory of
    N points stamped S", "setpoint" or "")."""
    return KeyValue(key=str(phase), value=str(follows))


def phase_from_msg(msg: KeyValue) -> tuple[str, str]:
    """-> (phase, what it follows)."""
    return msg.key, msg.value


def hold_msg(last_ns: int | None) -> Header:
    """The live watch's hold of a lockstep set (std_msgs/Header on ``watch/hold``):
    ``frame_id`` "wait" and ``stamp`` the last sample the set takes before it waits (the
    window's last, while it is diagnosed); "go on" (stamp 0) when it may go on."""
    if last_ns is None:
        return Header(stamp=ns_to_time(0), frame_id=HOLD_GO)
    return Header(stamp=ns_to_time(last_ns), frame_id=HOLD_WAIT)


def hold_from_msg(msg: Header) -> int | None:
    """-> the last sample's stamp before the wait [ns], or None: go on."""
    if msg.frame_id == HOLD_WAIT:
        return time_to_ns(msg.stamp)
    if msg.frame_id == HOLD_GO:
        return None
    raise DataError(f"watch/hold: frame_id {msg.frame_id!r}: not {HOLD_WAIT!r} or "
                    f"{HOLD_GO!r}")


ARM_LEVEL = {"armed": 0, "approaching": 0, "arming": 1, "disarmed": 1, "faulted": 2}


def arming_state_msg(since_ns: int, name: str, state: str, reason: str, values: Doc,
                     hardware_id: str = "") -> DiagnosticArray:
    """The driver's arming state (latched ``state`` topic): header.stamp is the first
    sample stamp the state applies to; one status whose message is the state, with
    ``state``, ``reason`` and the driver's loop figures as key-values."""
    return diagnostic_array(since_ns, name, ARM_LEVEL.get(state, 2), state,
                            {"state": state, "reason": reason, **values}, hardware_id)


def announcement_from_msg(msg: DiagnosticArray) -> Announcement:
    """The driver's ``state`` -> Announcement (wire.announcement_of: the one reader,
    the bag reader's too); DataError if malformed."""
    return announcement_of(msg)


def clock_msg(ns: int):
    """rosgraph_msgs/Clock at ``ns`` (simulated time, for nodes on use_sim_time)."""
    from rosgraph_msgs.msg import Clock
    return Clock(clock=ns_to_time(ns))


def diagnostic_array(ns: int, name: str, level: int, message: str, values: Doc,
                     hardware_id: str = "") -> DiagnosticArray:
    """One DiagnosticStatus (level: 0 OK, 1 WARN, 2 ERROR, 3 STALE) in an array."""
    st = DiagnosticStatus(level=bytes([int(level)]), name=name, message=message,
                          hardware_id=hardware_id,
                          values=[KeyValue(key=str(k), value=str(v)) for k, v in values.items()])
    return DiagnosticArray(header=header(ns), status=[st])


_register_layouts()
