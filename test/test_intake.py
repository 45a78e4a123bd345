"""The feedforward's intake: trajectories and models taken apart off the loop's thread,
finished in order, errors handed back as values."""

import threading
import time

import pytest

from piezo_stage.core.errors import DataError, PiezoStageError
from piezo_stage.nodes._intake import Intake, warm_up


def _drain(intake, n, timeout=5.0):
    out, t_end = [], time.monotonic() + timeout
    while len(out) < n and time.monotonic() < t_end:
        out += intake.ready()
        time.sleep(0.001)
    return out


def test_items_finish_in_order_on_one_other_thread_and_errors_come_back():
    seen = []

    def decode(data):
        seen.append(threading.current_thread().name)
        if data == b"bad":
            raise DataError("bad bytes")
        return len(data)
    intake = Intake({"trajectory": decode, "model": str.upper}, (PiezoStageError,))
    for kind, data in [("trajectory", b"abc"), ("model", "m"), ("trajectory", b"bad"),
                       ("trajectory", b"de")]:
        intake.submit(kind, data)
    out = _drain(intake, 4)
    assert [k for k, _ in out] == ["trajectory", "model", "trajectory", "trajectory"]
    assert out[0][1] == 3 and out[1][1] == "M" and out[3][1] == 2
    assert isinstance(out[2][1], DataError) and "bad bytes" in str(out[2][1])
    assert set(seen) == {"intake"}


@pytest.mark.filterwarnings("ignore::pytest.PytestUnhandledThreadExceptionWarning")
def test_an_error_it_was_not_told_of_is_not_swallowed_as_a_result():
    intake = Intake({"model": lambda d: 1 / 0}, (PiezoStageError,))
    intake.start()
    intake.submit("model", "x")
    time.sleep(0.2)
    assert intake.ready() == []  # the worker died loudly (threading's excepthook)


def test_warm_up_runs_both_decoding_paths():
    from piezo_stage_msgs_adapters import trajectory_from_cdr
    calls = []

    def decode(data):
        calls.append(len(data))
        return trajectory_from_cdr(data, (0.0, 100.0), 10)
    warm_up(decode, (PiezoStageError,))
    assert len(calls) == 2
    with pytest.raises(PiezoStageError):  # the ragged one is refused, as warm_up expects
        from rclpy.serialization import serialize_message
        from trajectory_msgs.msg import JointTrajectory, JointTrajectoryPoint
        decode(serialize_message(JointTrajectory(
            joint_names=["x", "y"], points=[JointTrajectoryPoint(positions=[0.0, 0.0]),
                                            JointTrajectoryPoint(positions=[0.0])])))
