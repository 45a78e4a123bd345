"""The live view (Foxglove WebSocket) against a running node set, with a plain
WebSocket client speaking Foxglove's protocol (benchmarks/foxglove_probe.py): it decodes
what it receives using only the schema the server advertised, as Foxglove does."""

import os
import socket
import subprocess
import sys

import pytest

pytest.importorskip("rclpy")
pytest.importorskip("foxglove")
pytest.importorskip("websockets")
from benchmarks.foxglove_probe import connect, decoder, receive  # noqa: E402
from conftest import CONFIG, ROOT  # noqa: E402
from piezo_stage.launcher.launcher import Launch, LaunchOptions  # noqa: E402

# real node processes in real time: -m "not slow" leaves them out, and ./dev.sh test
# runs them alone after the rest
pytestmark = [pytest.mark.slow, pytest.mark.realtime]

def free_port():
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_live_view_serves_decodable_joint_states(tmp_path, ros_env):
    port = free_port()
    env = ros_env
    # a real-time driver on the sim, disarmed: it samples the stage at 1 kHz
    la = Launch(os.path.join(CONFIG, "stage.yaml"), LaunchOptions(nodes=["stage_driver"],
        arm=False, foxglove_port=port, overrides={"stage_driver": {"mode": "realtime"}},
        exclusive=False), env=env)
    assert la.nodes[0] == "live_view" and la.node_params("live_view")["port"] == port
    la.start()
    try:
        with connect(port) as ws:
            channel, got = receive(ws, "/stage/joint_states", want=50)
        assert channel is not None, "joint_states was never advertised"
        decode = decoder(channel)
        check_parameters(env)
    finally:
        la.stop()
    assert not la.failed
    assert channel["encoding"] == "cdr" and channel["schemaEncoding"] == "ros2msg"
    assert channel["schemaName"] == "sensor_msgs/msg/JointState"
    assert len(got) >= 50
    stamps = []
    for log_ns, payload, _ in got:  # decoded with nothing but the advertised schema
        msg = decode(payload)
        assert list(msg.name) == ["x", "y"]
        assert all(abs(p) < 1e-3 for p in msg.position)  # m: a stage at rest, < 1 mm
        assert list(msg.effort) == [0.0, 0.0]             # V: disarmed, the safe voltage
        stamp = msg.header.stamp.sec * 10**9 + msg.header.stamp.nanosec
        assert stamp == log_ns                            # logged at its sample time
        stamps.append(stamp)
    assert stamps == sorted(stamps) and len(set(stamps)) == len(stamps)
    # max_rate_hz (200 by default) thins the 1 kHz topic to <= 200 per wall-clock second
    # (by arrival; the sample stamps of a real-time run follow the wall clock)
    span_s = (stamps[-1] - stamps[0]) * 1e-9
    assert len(stamps) - 1 <= 200 * span_s * 1.1 + 2, (len(stamps), span_s)
    assert len(stamps) - 1 >= 1000 * span_s / 20  # thinned, not starved


def check_parameters(env):
    """From an outside node, as `ros2 param` does: only max_rate_hz and batch_period_s
    are writable (and applied); the port refuses a set as read-only."""
    from rcl_interfaces.srv import DescribeParameters, ListParameters

    from benchmarks.probe import Probe, _param_call_raw, set_params
    os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"  # as the nodes'
    probe = Probe(int(env["ROS_DOMAIN_ID"]))
    try:
        names = _param_call_raw(probe, "/stage/live_view", "list_parameters",
                                ListParameters, names=[], depth=0).result.names
        names = [n for n in names if not n.startswith("qos_overrides")]
        from piezo_stage.nodes.declared import DECLARED, RCLPY_OWN
        assert set(names) - RCLPY_OWN == DECLARED["live_view"]  # the launcher's table
        descs = _param_call_raw(probe, "/stage/live_view", "describe_parameters",
                                DescribeParameters, names=names).descriptors
        assert {x.name for x in descs if not x.read_only} - {"use_sim_time"} == \
            {"max_rate_hz", "batch_period_s"}
        assert set_params(probe, "/stage/live_view", max_rate_hz=50.0) == [(True, "")]
        ok, why = set_params(probe, "/stage/live_view", port=1)[0]
        assert not ok and "read-only" in why.lower()
    finally:
        probe.close()


def test_launch_refuses_a_bad_port():
    r = subprocess.run([sys.executable, "-m", "piezo_stage.cli", "launch", "--foxglove",
                        "http"], capture_output=True, text=True, cwd=ROOT)
    assert r.returncode == 2 and "not a TCP port" in r.stderr
