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
    ns, d, f, w = A.reference_from_msg(A.reference_msg(7, {"x": 1.0, "y": 2.0},
                                                       {"x": 3.0, "y": 4.0}, {"x": 5.0, "y": 6.0}))
    assert (ns, f) == (7, {"x": 3.0, "y": 4.0}) and d == pytest.approx({"x": 1.0, "y": 2.0})
    assert w == pytest.approx({"x": 5.0, "y": 6.0})
    with pytest.raises(DataError):
        A.setpoint_from_msg(A.point_msg(1, {"x": 500.0, "y": 0.0}), (-10, 90))
    import os
    from conftest import CONFIG
    text = open(os.path.join(CONFIG, "stage_model.yaml")).read()
    model, _ = A.model_from_msg(A.model_msg(text))
    assert set(model.axes) == {"x", "y"}
    diag = A.diagnostic_array(1, "n", 1, "warn", {"k": 2})
    assert diag.status[0].values[0].value == "2"
