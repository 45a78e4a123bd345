"""The fast trajectory decoder gives exactly what rclpy's own decoder gives, for every
generated message (layouts with and without velocities, accelerations and efforts,
points of equal and of different layouts, 1 to 3 joints, any times), and refuses
the same ones with a DataError. Truncated bytes are refused, never an other error."""

import numpy as np
import pytest

pytest.importorskip("rclpy")
hypothesis = pytest.importorskip("hypothesis")
from hypothesis import HealthCheck, given, settings  # noqa: E402
from hypothesis import strategies as st  # noqa: E402
from rclpy.serialization import deserialize_message, serialize_message  # noqa: E402
from trajectory_msgs.msg import JointTrajectory, JointTrajectoryPoint  # noqa: E402

from piezo_stage.core.errors import DataError  # noqa: E402
from piezo_stage_msgs_adapters import cdr, trajectory_from_cdr, trajectory_from_msg  # noqa: E402

FLOAT = st.floats(-1e-4, 1e-4, allow_nan=False, width=64)


@st.composite
def trajectories(draw):
    names = draw(st.sampled_from([["x"], ["y"], ["x", "y"], ["y", "x"], ["x", "y", "z"],
                                  ["x", "x"], []]))
    k = len(names)
    uniform = draw(st.booleans())  # every point the same layout (as planners send)
    base = [draw(st.sampled_from([k, k, 0, 1, 2])) for _ in range(4)]
    n = draw(st.integers(0, 9))
    msg = JointTrajectory()
    msg.header.frame_id = draw(st.sampled_from(["", "stage", "s" * 7]))
    msg.joint_names = names
    t = 0
    for _ in range(n):
        # not uniform: mostly the common layout, now and then another (a point with
        # velocities late in the trajectory is what a 3-point look cannot see)
        odd = not uniform and draw(st.integers(0, 3)) == 0
        counts = [draw(st.sampled_from([k, 0, 1, 2])) for _ in range(4)] if odd else base
        p = JointTrajectoryPoint()
        p.positions = [draw(FLOAT) for _ in range(counts[0])]
        p.velocities = [draw(FLOAT) for _ in range(counts[1])]
        p.accelerations = [draw(FLOAT) for _ in range(counts[2])]
        p.effort = [draw(FLOAT) for _ in range(counts[3])]
        t += draw(st.sampled_from([1_000_000, 1_000_000, 0, 999_999_999, 1_500_000_000]))
        p.time_from_start.sec, p.time_from_start.nanosec = divmod(t, 1_000_000_000)
        msg.points.append(p)
    return msg


def _outcome(f):
    try:
        t, w = f()
        return "ok", t, {a: w[a] for a in sorted(w)}
    except DataError:
        return "refused", None, None


def _same(a, b):
    assert a[0] == b[0], (a, b)
    if a[0] == "ok":
        np.testing.assert_array_equal(a[1], b[1])
        assert sorted(a[2]) == sorted(b[2])
        for k in a[2]:
            np.testing.assert_array_equal(a[2][k], b[2][k])


@settings(max_examples=3000, deadline=None, derandomize=True,
          suppress_health_check=[HealthCheck.too_slow])
@given(trajectories())
def test_fast_decoder_agrees_with_rclpy(msg):
    data = serialize_message(msg)
    ref = _outcome(lambda: trajectory_from_msg(deserialize_message(data, JointTrajectory)))
    _same(_outcome(lambda: trajectory_from_cdr(data)), ref)


@settings(max_examples=2000, deadline=None, derandomize=True,
          suppress_health_check=[HealthCheck.too_slow])
@given(trajectories())
def test_every_uniform_layout_takes_the_fast_path(msg):
    """Points of one layout, one position per joint (what planners and our trajectory
    node send) are decoded from strided views, never by the slow way: a 60,001-point
    trajectory took 0.4 s through rclpy, and a feedforward that spent that long on it
    while armed let the driver fault on stale commands. (The decoder once returned
    None for every message when the first point carried padding the others did not.)"""
    layouts = {(len(p.positions), len(p.velocities), len(p.accelerations), len(p.effort))
               for p in msg.points}
    if len(layouts) != 1 or any(lay[0] != len(msg.joint_names) for lay in layouts):
        return
    out = cdr.decode_joint_trajectory(serialize_message(msg))
    assert out is not None, layouts
    names, t, pos = out
    assert names == list(msg.joint_names)
    np.testing.assert_array_equal(t, [p.time_from_start.sec + p.time_from_start.nanosec * 1e-9
                                      for p in msg.points])
    np.testing.assert_array_equal(pos.reshape(len(msg.points), -1),
                                  np.array([list(p.positions) for p in msg.points]).reshape(
                                      len(msg.points), -1))


@settings(max_examples=500, deadline=None, derandomize=True)
@given(trajectories(), st.integers(1, 400))
def test_truncated_bytes_are_refused_never_crash(msg, cut):
    data = serialize_message(msg)
    if cut >= len(data) - 4:
        return
    try:
        trajectory_from_cdr(data[:len(data) - cut])
    except DataError:
        pass


def test_the_issues_misread_layout():
    """Later points carrying velocities: times [0, .001, .002, .003] were once read
    as [0, .001, .002, 1.055e9 s]."""
    msg = JointTrajectory(joint_names=["x", "y"])
    for i in range(4):
        p = JointTrajectoryPoint(positions=[1e-5, 2e-5])
        if i == 3:
            p.velocities = [0.0, 0.0]
        p.time_from_start.nanosec = i * 1_000_000
        msg.points.append(p)
    t, w = trajectory_from_cdr(serialize_message(msg))
    np.testing.assert_allclose(t, [0, 0.001, 0.002, 0.003])
    np.testing.assert_allclose(w["y"], 20.0)


def test_a_huge_trajectory_is_refused_on_its_count_before_decoding():
    msg = JointTrajectory(joint_names=["x", "y"])
    p = JointTrajectoryPoint(positions=[1e-5, 2e-5])
    msg.points = [p] * 2001
    with pytest.raises(DataError, match="2001 points"):
        trajectory_from_cdr(serialize_message(msg), max_points=2000)


def test_our_own_trajectories_decode_on_the_fast_path():
    import piezo_stage_msgs_adapters as A
    for n in (1, 2, 3, 4, 5, 60001):
        t = np.arange(n) * 1e-3
        data = serialize_message(A.trajectory_msg(t, {"x": np.full(n, 20.0),
                                                      "y": np.sin(t) + 20.0}))
        out = cdr.decode_joint_trajectory(data)
        assert out is not None, n
        np.testing.assert_allclose(out[1], t, atol=1e-12)
