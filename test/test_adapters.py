"""Message adapters: pure conversions, SI on the wire, rejection of bad messages."""

import math

import numpy as np
import pytest

pytest.importorskip("rclpy")
import piezo_stage_msgs_adapters as A  # noqa: E402
from piezo_stage.core.errors import DataError  # noqa: E402


def test_joint_state_round_trip_in_metres():
    m = A.joint_state(1_500_000_123, {"x": 12.5, "y": -3.0}, {"x": 80.0, "y": 10.0})
    assert m.position[0] == pytest.approx(12.5e-6)
    assert list(m.name) == ["x", "y"]
    ns, w, v = A.joint_state_to_um(m, with_effort=True)
    assert ns == 1_500_000_123 and w == pytest.approx({"x": 12.5, "y": -3.0})
    assert v == {"x": 80.0, "y": 10.0}


def test_voltage_rejects_nan():
    m = A.voltage_msg(5, {"x": 1.0, "y": 2.0})
    assert A.voltage_from_msg(m) == (5, {"x": 1.0, "y": 2.0})
    m.vector.x = math.nan
    with pytest.raises(DataError):
        A.voltage_from_msg(m)


def test_trajectory_round_trip_and_rejections():
    t = np.arange(5) * 0.01
    w = {"x": np.linspace(0, 10, 5), "y": np.linspace(5, 6, 5)}
    tt, ww = A.trajectory_from_msg(A.trajectory_msg(t, w), (-10, 90))
    np.testing.assert_allclose(tt, t)
    np.testing.assert_allclose(ww["x"], w["x"])
    bad = A.trajectory_msg(t, w)
    bad.joint_names = ["x", "z"]
    with pytest.raises(DataError, match="unknown joint"):
        A.trajectory_from_msg(bad)
    bad = A.trajectory_msg(t[::-1].copy(), w)
    with pytest.raises(DataError, match="increasing"):
        A.trajectory_from_msg(bad)
    with pytest.raises(DataError, match="outside the stage range"):
        A.trajectory_from_msg(A.trajectory_msg(t, {"x": w["x"] * 100, "y": w["y"]}), (-10, 90))


def test_reference_and_setpoint_and_model():
    r = A.reference_from_msg(A.reference_msg(
        7, {"x": 1.0, "y": 2.0}, {"x": 3.0, "y": 4.0}, {"x": 5.0, "y": 6.0},
        {"x": 7.0, "y": 8.0}))
    assert (r.ns, r.ff_V, r.applied_V) == (7, {"x": 3.0, "y": 4.0}, {"x": 7.0, "y": 8.0})
    assert r.desired_um == pytest.approx({"x": 1.0, "y": 2.0})
    assert r.measured_um == pytest.approx({"x": 5.0, "y": 6.0})
    # the bag reader's decoder is the same one
    from piezo_stage_msgs_adapters.wire import reference_um
    assert reference_um(A.reference_cdr(7, r.desired_um, r.ff_V, r.measured_um,
                                        r.applied_V)) == r
    with pytest.raises(DataError):
        A.setpoint_from_msg(A.point_msg(1, {"x": 500.0, "y": 0.0}), (-10, 90))
    import os

    from conftest import CONFIG
    text = open(os.path.join(CONFIG, "stage_model.yaml")).read()
    model, _ = A.model_from_msg(A.model_msg(text))
    assert set(model.axes) == {"x", "y"}
    diag = A.diagnostic_array(1, "n", 1, "warn", {"k": 2})
    assert diag.status[0].values[0].value == "2"
    st = A.arming_state_msg(9, "/stage/stage_driver: arming", "faulted", "stale", {"k": 1})
    a = A.announcement_from_msg(st)
    assert (a.since_ns, a.state, a.reason) == (9, "faulted", "stale")
    assert st.status[0].level == bytes([2]) and st.status[0].message == "faulted"
    with pytest.raises(DataError):
        A.announcement_from_msg(A.diagnostic_array(1, "n", 0, "ok", {}))


def test_the_drivers_announcement_is_typed_key_values_read_in_one_place():
    st = A.arming_state_msg(5, "/stage/stage_driver: arming", "armed", "tracking", {
        "lookahead_s": 0.005, "voltage_limit_lo_V": 0.0, "voltage_limit_hi_V": 150.0,
        "mode": "realtime"})
    a = A.announcement_from_msg(st)
    assert (a.lookahead_s, a.limits, a.mode) == (0.005, (0.0, 150.0), "realtime")
    older = A.announcement_from_msg(A.arming_state_msg(5, "d", "armed", "", {}))
    assert (older.lookahead_s, older.limits, older.mode) == (0.0, None, "")  # no limits
    for bad in ({"voltage_limit_lo_V": "150", "voltage_limit_hi_V": "0"},
                {"voltage_limit_lo_V": "a", "voltage_limit_hi_V": "1"},
                {"lookahead_s": "nan"}, {"lookahead_s": "-1"}):
        with pytest.raises(DataError):
            A.announcement_from_msg(A.arming_state_msg(5, "d", "armed", "", bad))


# --- CDR codecs of the per-sample topics: checked against rclpy's own serializer ---

W, V, D = {"x": 12.5, "y": -3.0}, {"x": 80.0, "y": 10.0}, {"x": 21.0, "y": 45.0}


def _typed_and_raw():
    """(typed message, the same message as our CDR bytes, its type) per hot topic."""
    from geometry_msgs.msg import PointStamped, Vector3Stamped
    from sensor_msgs.msg import JointState
    ns = 3_000_000_123
    return [(A.joint_state(ns, W, V), A.joint_state_cdr(ns, W, V), JointState),
            (A.joint_state(ns, W), A.joint_state_cdr(ns, W), JointState),
            (A.point_msg(ns, W), A.point_cdr(ns, W), PointStamped),
            (A.voltage_msg(ns, V), A.voltage_cdr(ns, V), Vector3Stamped),
            (A.reference_msg(ns, D, V, W, V), A.reference_cdr(ns, D, V, W, V), JointState)]


def test_cdr_encoders_give_the_messages_rclpy_reads():
    from rclpy.serialization import deserialize_message
    for typed, raw, cls in _typed_and_raw():
        assert deserialize_message(raw, cls) == typed, cls.__name__
    # other layouts (odd name lengths, velocity only, long frame) use their own templates
    from sensor_msgs.msg import JointState

    from piezo_stage_msgs_adapters import cdr
    for names, pos, vel, eff, frame in ((["a", "bb", "ccc"], [1.0, 2.0, 3.0],
                                         [4.0, 5.0, 6.0], [], "f"),
                                        (["x"], [], [], [7.5], "a_longer_frame_id_")):
        m = deserialize_message(cdr.encode_joint_state(5_000_000_006, frame, names, pos,
                                                       vel, eff), JointState)
        assert (m.header.frame_id, list(m.name), list(m.position), list(m.velocity),
                list(m.effort)) == (frame, names, pos, vel, eff)
        assert (m.header.stamp.sec, m.header.stamp.nanosec) == (5, 6)


def test_cdr_decoders_read_what_rclpy_writes():
    from rclpy.serialization import serialize_message
    (js, _, _), (js0, _, _), _, (vm, _, _), (ref, _, _) = _typed_and_raw()
    assert A.joint_state_to_um(serialize_message(js), True) == \
        A.joint_state_to_um(js, True)
    assert A.joint_state_to_um(serialize_message(js0), True)[2] is None  # no effort
    assert A.voltage_from_msg(serialize_message(vm)) == A.voltage_from_msg(vm)
    assert A.reference_from_msg(serialize_message(ref)) == A.reference_from_msg(ref)
    # a lab node's JointState: other frame, names in another order, extra joint, velocity
    from sensor_msgs.msg import JointState
    other = JointState(name=["z", "y", "x"], position=[1.0, 2e-6, 3e-6],
                       velocity=[0.0, 0.0, 0.0])
    other.header.frame_id = "piezo_base_link"
    other.header.stamp.sec, other.header.stamp.nanosec = 4, 5
    ns, w = A.joint_state_to_um(serialize_message(other))
    assert ns == 4_000_000_005 and w == pytest.approx({"x": 3.0, "y": 2.0})


def test_cdr_big_endian_and_xcdr2_are_read():
    import struct

    from piezo_stage_msgs_adapters import cdr
    # Vector3Stamped, big-endian XCDR1: stamp, frame "s", pad to 8, three doubles
    be = b"\x00\x00\x00\x00" + struct.pack(">iI", 1, 2) + struct.pack(">I", 2) + b"s\x00" \
        + b"\x00" * 2 + struct.pack(">3d", 1.5, -2.5, 0.0)
    assert A.voltage_from_msg(be) == (1_000_000_002, {"x": 1.5, "y": -2.5})
    # the same in little-endian XCDR2 (8-byte values aligned to 4: no padding here)
    le2 = b"\x00\x07\x00\x00" + struct.pack("<iI", 1, 2) + struct.pack("<I", 2) + b"s\x00" \
        + b"\x00" * 2 + struct.pack("<3d", 1.5, -2.5, 0.0)
    assert cdr.decode_vector3_stamped(le2) == (1_000_000_002, "s", (1.5, -2.5, 0.0))


def test_the_stamped_fast_path_reads_as_the_general_reader_does():
    """decode_point_stamped's one-pass read of little-endian XCDR1 gives what
    CdrReader gives, on rclpy's bytes (frames of every padding) and on bytes cut,
    lengthened or with a length field that lies (refused the same way)."""
    import random

    from geometry_msgs.msg import Vector3Stamped
    from rclpy.serialization import serialize_message

    from piezo_stage_msgs_adapters import cdr

    def general(b):
        r = cdr.CdrReader(b)
        return r.stamp(), r.string(), r.doubles(3)

    def outcome(f, b):
        try:
            return f(b)
        except DataError as e:
            return type(e)
    rng = random.Random(7)
    for k in range(40):
        m = Vector3Stamped()
        m.header.frame_id = "f" * (k % 11)  # every padding before the doubles
        m.header.stamp.sec, m.header.stamp.nanosec = k - 3, 999_999_999 - k
        m.vector.x, m.vector.y, m.vector.z = rng.uniform(-1e3, 1e3), -0.5 * k, 1e-9 * k
        good = serialize_message(m)
        assert cdr.decode_vector3_stamped(good) == general(good) == (
            (k - 3) * 1_000_000_000 + 999_999_999 - k, m.header.frame_id,
            (m.vector.x, m.vector.y, m.vector.z))
        lie = bytearray(good)
        lie[12:16] = (rng.choice([0, 1, len(good), 2 ** 31])).to_bytes(4, "little")
        for bad in (good[:rng.randrange(len(good))], good + b"\x00" * 8, bytes(lie),
                    memoryview(good)):
            assert outcome(cdr.decode_vector3_stamped, bad) == outcome(general, bad)


def test_cdr_rejects_malformed_and_non_finite():
    raw = A.joint_state_cdr(1, W, V)
    for bad in (b"", b"\x00\x01", raw[:30], raw[:-8], b"\x01\x01\x00\x00" + raw[4:],
                b"\x00\x02\x00\x00" + raw[4:]):  # empty, truncated, unknown encapsulation
        with pytest.raises(DataError):
            A.joint_state_to_um(bad, True)
    assert int.from_bytes(raw[24:28], "little") == 2  # the name count
    huge = raw[:24] + (10 ** 6).to_bytes(4, "little") + raw[28:]
    with pytest.raises(DataError, match="sequence longer"):
        A.joint_state_to_um(huge)
    with pytest.raises(DataError, match="NaN"):
        A.voltage_from_msg(A.voltage_cdr(1, {"x": math.nan, "y": 0.0}))
    with pytest.raises(DataError, match="reference"):
        A.reference_from_msg(raw)  # a joint_states message is not a reference


def test_trajectory_from_cdr_agrees_with_the_message_path_and_bounds_size():
    from builtin_interfaces.msg import Duration
    from rclpy.serialization import serialize_message
    from trajectory_msgs.msg import JointTrajectory, JointTrajectoryPoint
    t = np.arange(7) * 1e-3
    cases = [A.trajectory_msg(t, {"x": 10 + t, "y": 20 - t}),                    # regular
             JointTrajectory(joint_names=["y", "x"], points=[JointTrajectoryPoint(  # odd ones
                 positions=[1e-6 * k, 2e-6], velocities=[0.0] * (k % 2),
                 time_from_start=Duration(sec=k)) for k in range(4)]),
             JointTrajectory(joint_names=["x"], points=[JointTrajectoryPoint(        # vel.
                 positions=[1e-6 * k], velocities=[0.1],
                 time_from_start=Duration(sec=k, nanosec=7)) for k in range(5)])]
    for msg in cases:
        a, b = A.trajectory_from_cdr(serialize_message(msg)), A.trajectory_from_msg(msg)
        np.testing.assert_array_equal(a[0], b[0])
        assert a[1].keys() == b[1].keys()
        for k in a[1]:
            np.testing.assert_array_equal(a[1][k], b[1][k])
    big = serialize_message(A.trajectory_msg(np.arange(200_000) * 1e-3,
                                             {"x": np.zeros(200_000), "y": np.zeros(200_000)}))
    assert len(A.trajectory_from_cdr(big)[0]) == 200_000
    with pytest.raises(DataError, match="bytes"):
        A.trajectory_from_cdr(big, max_points=1000)


def test_the_watchs_hold_round_trip_and_a_foreign_frame_refused():
    """watch/hold (std_msgs/Header): "wait" with the last sample's stamp, "go on"."""
    assert A.hold_from_msg(A.hold_msg(29_000_000_000 - 1_000_000)) == 28_999_000_000
    assert A.hold_from_msg(A.hold_msg(None)) is None
    with pytest.raises(DataError, match="frame_id"):
        A.hold_from_msg(A.header(5, "stage"))
