"""The node set over real rclpy: separate processes, real topics, a real recorder.

Every test runs on its own random ROS_DOMAIN_ID with discovery kept on this host;
nothing depends on wall-clock speed (lockstep runs wait for each other)."""

import os
import re
import signal
import subprocess
import sys
import time

import numpy as np
import pytest

pytest.importorskip("rclpy")
from lab_nodes import REQUEST_AGAIN, SAME_AGAIN, assert_ran_each  # noqa: E402

from conftest import CONFIG, ROOT, on_a_terminal  # noqa: E402
from piezo_stage.io.bag import deserialize, iter_messages, read_bag_record  # noqa: E402
from piezo_stage.launcher.launcher import Launch, LaunchOptions  # noqa: E402

pytestmark = pytest.mark.slow  # real node processes: -m "not slow" leaves them out

STAGE = os.path.join(CONFIG, "stage.yaml")
MODEL = os.path.join(CONFIG, "stage_model.yaml")


@pytest.fixture
def env(ros_env):
    return ros_env


def topic_data(bag, suffix):
    return [(log, data) for topic, _, log, data in iter_messages(bag) if topic.endswith(suffix)]


def lockstep(tmp_path, env, name, steps=400, nodes=None, overrides=None):
    o = {"stage_driver": {"max_steps": steps, "exit_after_max_steps": True, "seed": 3},
         "feedforward": {"model_file": MODEL},
         "trajectory": {"kind": "seed", "duration_s": 1.0}}
    for k, v in (overrides or {}).items():
        o.setdefault(k, {}).update(v)
    bag = str(tmp_path / name)
    rc = Launch(STAGE, LaunchOptions(record=bag, overrides=o, nodes=nodes,
        exclusive=False), env=env).run(duration=300)
    assert rc == 0
    return bag


STALLED_STATE_READER = r"""
import os, signal, rclpy
from diagnostic_msgs.msg import DiagnosticArray
from piezo_stage.nodes._common import QOS_EVENTS
rclpy.init()
node = rclpy.create_node("stalled_state_reader")
got = []
node.create_subscription(DiagnosticArray, "/stage/state", got.append, QOS_EVENTS)
while not got:
    rclpy.spin_once(node, timeout_sec=0.1)
print("matched", flush=True)
os.kill(os.getpid(), signal.SIGSTOP)  # every thread: its reader acknowledges nothing
node.destroy_node()
rclpy.try_shutdown()
"""


def test_lockstep_sends_no_sample_before_every_reader_holds_the_state(env, capfd):
    """A loop node that took a sample before the state announced ahead of it ran the
    approach a tick late, and reruns differed: in lockstep the
    driver publishes no sample after a change announced ahead (the enable) until every
    reader of ``state`` acknowledged it. Here an outside reader of ``state`` is stopped
    (SIGSTOP) before the set is armed: the enable then waits out the bound (1 s) and
    says so, and the set still arms."""
    from ros_probe import Probe
    o = {"stage_driver": {"seed": 3}, "feedforward": {"model_file": MODEL},
         "trajectory": {"kind": "seed", "duration_s": 1.0}}
    launch = Launch(STAGE, LaunchOptions(overrides=o, arm=False, exclusive=False,
        nodes=["stage_driver", "feedforward", "controller", "trajectory"]), env=env)
    launch.start()
    reader = subprocess.Popen([sys.executable, "-c", STALLED_STATE_READER], env=env,
                              stdout=subprocess.PIPE, text=True)
    probe = Probe(int(env["ROS_DOMAIN_ID"]))
    try:
        assert reader.stdout.readline().strip() == "matched"
        for _ in range(100):
            with open(f"/proc/{reader.pid}/stat") as fh:
                if fh.read().rsplit(")", 1)[1].split()[0] == "T":
                    break
            time.sleep(0.05)
        else:
            pytest.fail("the outside reader did not stop")
        t_end = time.monotonic() + 60
        while True:  # refused until the loop closed (saying so)
            t0 = time.monotonic()
            if probe.arm(True).success:
                break
            assert t0 < t_end, probe.states[-3:]
            probe.spin(0.2)
        assert probe.wait_state("armed", 60)
        took = time.monotonic() - t0
        reader.send_signal(signal.SIGCONT)
        assert reader.wait(30) == 0
    finally:
        if reader.poll() is None:
            reader.send_signal(signal.SIGCONT)
            reader.kill()
        probe.close()
        launch.stop()
    err = capfd.readouterr().err
    assert "a reader of state did not acknowledge it within 1 s; going on" in err, err[-3000:]
    # the enable, announced ahead of its sample, waited out the bound for the stopped reader
    assert took >= 1.0, took


@pytest.mark.alone  # (a rerun compared byte for byte: see setup.cfg's markers)
def test_lockstep_tracks_records_everything_and_is_deterministic(tmp_path, env, capfd):
    nodes = ["stage_driver", "feedforward", "controller", "trajectory"]
    a = lockstep(tmp_path, env, "a", nodes=nodes, steps=1500)
    # the driver's last wait, for its readers' acknowledgements of the final samples:
    # the set's writers send a heartbeat every 50 ms (fastdds_lockstep.xml); with Fast
    # DDS's 3 s period it took 1.8-2.7 s
    err = capfd.readouterr().err
    acked = re.search(r"done after 1501 samples: .*; acknowledged in (\d+) ms", err)
    assert acked and int(acked.group(1)) < 1000, err[-2000:]
    # 0 messages lost: every loop sample of the run is in the bag
    for suffix in ("/joint_states", "/sim/true_position", "/reference",
                   "/command"):
        assert len(topic_data(a, suffix)) == 1501, suffix
    rec = read_bag_record(a)
    ref = {}
    for _, data in topic_data(a, "/reference"):
        m = deserialize(data, "sensor_msgs/msg/JointState")
        ref[m.header.stamp.sec * 10**9 + m.header.stamp.nanosec] = np.array(m.position[:2]) * 1e6
    meas_ns = {int(round(t * 1e9)) for t in rec.t}
    stamps = sorted(s for s in ref if s in meas_ns)[100:]
    meas = {int(round(t * 1e9)): (rec.w["x"][i], rec.w["y"][i]) for i, t in enumerate(rec.t)}
    e = np.array([np.array(meas[s]) - ref[s] for s in stamps])
    assert np.sqrt(np.mean(e ** 2)) < 0.3  # um: feedforward + PID at 10 Hz
    # every node reports on /diagnostics (rates, limit hits, model in use)
    names, keys = set(), {}
    for _, data in topic_data(a, "/diagnostics"):
        for st in deserialize(data, "diagnostic_msgs/msg/DiagnosticArray").status:
            names.add(st.name)
            keys.setdefault(st.name, set()).update(kv.key for kv in st.values)
    # the diagnostic_msgs way: "<namespace>/<node>: <task>", the device named, a message
    # that says why (never a bare "ok")
    task = {"stage_driver": "sample loop", "feedforward": "inverse feedforward",
            "controller": "feedback control", "trajectory": "trajectory",
            "recorder": "recording"}
    assert {f"/stage/{n}: {task[n]}" for n in nodes + ["recorder"]} <= names, names
    assert {"samples", "rejected", "limit_hits", "missed_ticks", "late_commands",
            "state"} <= keys["/stage/stage_driver: sample loop"]
    assert "model" in keys["/stage/feedforward: inverse feedforward"]
    last = {}
    for _, data in topic_data(a, "/diagnostics"):
        for st in deserialize(data, "diagnostic_msgs/msg/DiagnosticArray").status:
            last[st.name] = st
    for name, st in last.items():
        assert st.message and st.message.lower() != "ok", name
        assert st.hardware_id.startswith("sim seed 3"), (name, st.hardware_id)

    # one time base: lockstep runs on the driver's /clock, so every topic (diagnostics,
    # trajectory and state included) is logged in simulated time, and the rosbag2
    # reader (metadata.yaml) gives the run's simulated duration
    from rosbags.rosbag2 import Reader
    logs = [log for _, _, log, _ in iter_messages(a)]
    assert 0 <= min(logs) and max(logs) <= 1_501_000_000  # commands: for the next sample
    with Reader(a) as r:
        assert r.duration <= 1_501_000_001 and r.start_time < 1_500_000_000
        assert r.duration >= 1_000_000_000  # diagnostics at 1 Hz of simulated time too
    # same seed, same data: two runs give byte-identical loop topics
    b = lockstep(tmp_path, env, "b", nodes=nodes, steps=1500)
    for suffix in ("/joint_states", "/reference", "/command"):
        assert topic_data(a, suffix) == topic_data(b, suffix), suffix


EXTERNAL = r"""
import sys, rclpy
from rclpy.node import Node
from builtin_interfaces.msg import Duration
from trajectory_msgs.msg import JointTrajectory, JointTrajectoryPoint
rclpy.init()
n = Node('lab_node')
pub = n.create_publisher(JointTrajectory, '/stage/trajectory', 10)
msg = JointTrajectory(joint_names=['x', 'y'])
for k in range(301):
    t = k * 0.001
    msg.points.append(JointTrajectoryPoint(positions=[30e-6 + 10e-6 * (t > 0.1), 20e-6],
                      time_from_start=Duration(sec=0, nanosec=int(t * 1e9))))
bad = JointTrajectory(joint_names=['x', 'q'], points=msg.points[:2])
import time
t0 = time.time()
while pub.get_subscription_count() < 1 and time.time() - t0 < 120:  # the feedforward
    rclpy.spin_once(n, timeout_sec=0.05)
pub.publish(bad)
pub.publish(msg)
# sent once and volatile: stay until every matched reader has it (a reader whose own
# side of the match lagged the publisher's gets it resent then; leaving after 0.5 s
# lost it once and the set waited for it until the test's timeout)
from rclpy.duration import Duration as Wait
acked = pub.wait_for_all_acked(Wait(seconds=30))
n.destroy_node(); rclpy.try_shutdown()
sys.exit(0 if acked else 1)
"""


def with_lab_node(tmp_path, env, code, name, steps, args=()):
    """A lab node (Python ``code`` in its own process, given ``args``) beside a lockstep
    set that waits for its trajectory (a bad one does not count); the node must exit 0.
    -> the bag."""
    lab = subprocess.Popen([sys.executable, "-c", code, *args], env=env)
    try:
        bag = lockstep(tmp_path, env, name, steps=steps,
                       nodes=["stage_driver", "feedforward", "controller"],
                       overrides={"feedforward": {"wait_for_trajectory": True}})
        assert lab.wait(60) == 0
    finally:
        if lab.poll() is None:
            lab.kill()
    return bag


def test_the_same_trajectory_published_three_times_runs_three_times(tmp_path, env):
    """A trajectory is its publication (docs/nodes.md): one lab node publishes the same
    trajectory (the same bytes) three times, each after the last run ended; the stage
    accepts all three, the bag holds all three on trajectory/accepted, and it runs each
    (through its middle point) to its end. (Before, a repeat of the bytes taken last
    was dropped without a word.)"""
    bag = with_lab_node(tmp_path, env, SAME_AGAIN, "same_again", 30000, args=("3",))
    assert_ran_each(bag, 3)


def test_a_trajectory_named_as_a_request_runs_once_however_often_it_is_sent(tmp_path,
                                                                           env):
    """A sender that resends until it hears an answer names its trajectory as a request
    (``header.frame_id`` ``request:...``, docs/nodes.md): the same request sent twice at
    once and again after its run runs once; the next request runs. The bag holds the
    two on trajectory/accepted, and the feedforward counts the two it took already."""
    bag = with_lab_node(tmp_path, env, REQUEST_AGAIN, "request_again", 30000, args=("0",))
    assert_ran_each(bag, 2)
    names = [deserialize(data, "trajectory_msgs/msg/JointTrajectory").header.frame_id
             for _, data in topic_data(bag, "/stage/trajectory/accepted")]
    assert names == ["request:/lab@1#1", "request:/lab@1#2"], names
    last = {}
    for _, data in topic_data(bag, "/diagnostics"):
        for st in deserialize(data, "diagnostic_msgs/msg/DiagnosticArray").status:
            last[st.name] = {kv.key: kv.value for kv in st.values}
    ff = last["/stage/feedforward: inverse feedforward"]
    assert int(float(ff["trajectories_taken_already"])) == 2, ff


def test_a_run_shorter_than_the_report_cadence_has_every_nodes_final_report(tmp_path,
                                                                              env):
    """Every node's last /diagnostics report, with its final counts, is in the bag
    however short the run against the 1 s cadence (Diagnostics.final at the node's
    close; the recorder stops after them). A 1,500-sample lockstep run took 0.5 s on a
    fast host, and the composed feedforward's first report came after the recorder had
    stopped (a fresh clone's CI of 5df54de)."""
    nodes = ["stage_driver", "feedforward", "controller", "trajectory"]
    bag = lockstep(tmp_path, env, "short", nodes=nodes, steps=200)
    last = {}
    for _, data in topic_data(bag, "/diagnostics"):
        for st in deserialize(data, "diagnostic_msgs/msg/DiagnosticArray").status:
            last[st.name] = {kv.key: kv.value for kv in st.values}
    assert {"/stage/stage_driver: sample loop", "/stage/feedforward: inverse feedforward",
            "/stage/controller: feedback control", "/stage/trajectory: trajectory"} <= \
        set(last), sorted(last)
    commands = last["/stage/controller: feedback control"]["commands"]
    assert int(float(commands)) == len(topic_data(bag, "/command")), commands


def test_stage_follows_a_trajectory_from_another_lab_node(tmp_path, env):
    bag = with_lab_node(tmp_path, env, EXTERNAL, "ext", 4000)
    rec = read_bag_record(bag)
    # it rejected the bad trajectory, kept running, and followed the good one:
    # 30 um, then a step to 40 um; y at 20 um
    assert rec.w["x"][-50:].mean() == pytest.approx(40.0, abs=0.3)
    assert rec.w["y"][-50:].mean() == pytest.approx(20.0, abs=0.3)


def test_the_docs_minimal_lab_node_is_run_by_the_stage_and_in_the_bag(tmp_path, env):
    """docs/nodes.md's smallest outside node (default QoS, sent once as soon as one
    subscriber matched, then waiting for the acknowledgements), as the page shows it,
    against a lockstep set that waits for a trajectory: the stage runs it and the bag's
    trajectory/accepted holds it."""
    page = open(os.path.join(ROOT, "docs", "nodes.md"), encoding="utf-8").read()
    code = re.search(r"## Other labs' nodes.*?```python\n(.*?)```", page, re.S).group(1)
    bag = with_lab_node(tmp_path, env, code, "docs_lab", 1500)
    got = [deserialize(data, "trajectory_msgs/msg/JointTrajectory")
           for _, data in topic_data(bag, "/stage/trajectory/accepted")]
    assert len(got) == 1 and [round(p.positions[0] * 1e6, 6) for p in got[0].points] == \
        [20.0, 40.0, 30.0]
    rec = read_bag_record(bag)  # its last point, held
    assert rec.w["x"][-50:].mean() == pytest.approx(30.0, abs=0.3)
    assert rec.w["y"][-50:].mean() == pytest.approx(30.0, abs=0.3)


def test_recorder_killed_with_sigkill_leaves_a_readable_bag(tmp_path, env):
    bag = tmp_path / "killed"
    procs = [subprocess.Popen([sys.executable, "-m", f"piezo_stage.nodes.{n}_node",
                               "--ros-args", "-r", "__ns:=/stage", *extra], env=env)
             for n, extra in (("recorder", ["-p", f"output:={bag}", "-p", "flush_period_s:=0.2"]),
                              ("stage_driver", ["-p", "mode:=realtime"]))]
    try:
        deadline = time.time() + 60
        while time.time() < deadline:
            time.sleep(0.5)
            try:
                if sum(1 for _ in iter_messages(bag)) > 500:
                    break
            except Exception:
                pass
        procs[0].send_signal(signal.SIGKILL)
        procs[0].wait(10)
        n = sum(1 for t, *_ in iter_messages(bag) if t.endswith("/joint_states"))
        assert n > 200  # everything up to the last flushed chunk
    finally:
        for p in procs[1:]:
            p.send_signal(signal.SIGINT)
            p.wait(30)


def test_launcher_reports_a_dead_node(tmp_path, env):
    bad = tmp_path / "bad.yaml"
    bad.write_text("/**/stage_driver:\n  ros__parameters:\n    backend: replay\n")
    # (--no-arm: a file with the driver alone could never arm, and is refused without it)
    r = subprocess.run([sys.executable, "-m", "piezo_stage.cli", "launch", str(bad),
                        "--duration", "20", "--no-arm"], env=env, capture_output=True,
                       text=True, timeout=120)
    assert r.returncode != 0
    assert "stage_driver" in r.stderr


def test_ros2_launch_file_imports_where_launch_is_installed():
    pytest.importorskip("launch_ros")
    import importlib.util
    spec = importlib.util.spec_from_file_location(
        "piezo_stage_launch", os.path.join(ROOT, "launch", "piezo_stage_launch.py"))
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    assert callable(mod.generate_launch_description)


def _rows(text):
    return {line.split()[0]: [float(x) for x in line.split()[1:]] for line in text.splitlines()
            if line.split()[:1] in (["x"], ["y"]) and len(line.split()) == 4}


def test_demo_prints_what_the_readme_says(tmp_path, env):
    """The README's main command end to end, as the README runs it (defaults): the
    excitation, live identification by the identifier node, the model handed over
    without restart, tracking of the paper's 10 Hz; the rows it prints are the README's
    (a lockstep run is deterministic for its random seed; the tolerance is for another
    machine's last digits)."""
    r = subprocess.run([sys.executable, "-m", "piezo_stage.cli", "demo",
                        "--out", str(tmp_path / "demo")], env=env,
                       capture_output=True, text=True, timeout=600, cwd=ROOT)
    assert r.returncode == 0, r.stderr[-3000:]
    assert "models handed to the feedforward: 1" in r.stdout
    readme = open(os.path.join(ROOT, "README.md")).read()
    quoted = _rows(readme[readme.index("models handed to the feedforward"):])
    got = _rows(r.stdout)
    assert set(quoted) == set(got) == {"x", "y"}, (quoted, got)
    for a in ("x", "y"):
        assert np.allclose(got[a], quoted[a], atol=[0.002, 0.01, 0.004]), (a, got, quoted)
    assert (tmp_path / "demo" / "metadata.yaml").exists()
    assert "tracking.png (the whole run)" in r.stdout
    assert (tmp_path / "demo" / "tracking.png").stat().st_size > 20_000


def test_gap_node_publishes_the_live_residual(tmp_path, env):
    """The twin on the stage's own model: the live residual is the sensor noise."""
    bag = lockstep(tmp_path, env, "gapnode", steps=1500,
                   nodes=["stage_driver", "feedforward", "controller", "trajectory", "gap"],
                   overrides={"stage_driver": {"plant_config": os.path.join(
                       CONFIG, "sim_stage.yaml")}})
    res = []
    for _, data in topic_data(bag, "/gap/residual"):
        m = deserialize(data, "geometry_msgs/msg/PointStamped")
        res.append((m.point.x * 1e6, m.point.y * 1e6))
    res = np.array(res)
    assert len(res) == 1501
    assert np.sqrt(np.mean(res[100:] ** 2)) < 0.2  # um: noise 0.1 RMS, twin = stage


def test_recorder_stopped_with_sigint_keeps_what_had_arrived(tmp_path, env):
    """The recorder takes messages in batches (batch_period_s); on SIGINT whatever had
    already arrived (acknowledged by its reader) still goes into the bag. A 30 s batch
    period makes sure the burst is still untaken when SIGINT comes."""
    code = r"""
import rclpy, sys
from rclpy.node import Node
from rclpy.duration import Duration
from geometry_msgs.msg import PointStamped
from piezo_stage.nodes._common import QOS_DATA
rclpy.init()
n = Node('burst')
pub = n.create_publisher(PointStamped, '/stage/setpoint', QOS_DATA)
while pub.get_subscription_count() < 1:
    rclpy.spin_once(n, timeout_sec=0.05)
for k in range(300):
    m = PointStamped(); m.header.stamp.sec = k + 1; m.point.x = k * 1e-7
    pub.publish(m)
print(pub.wait_for_all_acked(Duration(seconds=20)), flush=True)
sys.stdin.readline()  # stay matched until the recorder has been stopped
n.destroy_node(); rclpy.try_shutdown()
"""
    bag = tmp_path / "sigint"
    rec = subprocess.Popen([sys.executable, "-m", "piezo_stage.nodes.recorder_node",
                            "--ros-args", "-r", "__ns:=/stage", "-p", f"output:={bag}",
                            "-p", "batch_period_s:=30.0"], env=env)
    pub = subprocess.Popen([sys.executable, "-c", code], env=env, stdin=subprocess.PIPE,
                           stdout=subprocess.PIPE, text=True)
    try:
        assert pub.stdout.readline().strip() == "True"  # all 300 in the recorder's reader
        rec.send_signal(signal.SIGINT)
        assert rec.wait(30) == 130
    finally:
        pub.communicate("\n", timeout=30)
        if rec.poll() is None:
            rec.kill()
    got = [deserialize(d, "geometry_msgs/msg/PointStamped").header.stamp.sec
           for _, d in topic_data(str(bag), "/setpoint")]
    assert got == list(range(1, 301))


def test_recorder_stopped_while_it_is_built_finishes_its_bag_with_what_arrived(tmp_path,
                                                                            env):
    """A SIGINT that lands while the recorder is still being built, after its readers
    have acknowledged a burst (on a loaded host: "stopped by SIGINT
    during start-up", a bag without its summary, the burst lost): the stop is noted,
    the recorder is built whole, and its spin's first pass takes what arrived and
    finishes the bag. Here the stop is sent from the constructor's last step, right
    after a burst of 50 is acknowledged by the recorder's reader."""
    bag = tmp_path / "early"
    code = f"""
import piezo_stage.process.signals
import os, signal, sys, time
import rclpy
from rclpy.duration import Duration
from geometry_msgs.msg import PointStamped
from piezo_stage.nodes import recorder_node as R
from piezo_stage.nodes._common import QOS_DATA
built = R.Diagnostics
def last_step(*a, **kw):
    burst = rclpy.create_node("burst")
    pub = burst.create_publisher(PointStamped, "/stage/setpoint", QOS_DATA)
    while pub.get_subscription_count() < 1:
        time.sleep(0.01)
    for i in range(50):
        m = PointStamped(); m.header.stamp.sec = i + 1
        pub.publish(m)
    assert pub.wait_for_all_acked(Duration(seconds=20))
    os.kill(os.getpid(), signal.SIGINT)
    return built(*a, **kw)
R.Diagnostics = last_step
sys.exit(R.main(["--ros-args", "-r", "__ns:=/stage", "-p", "output:={bag}"]))
"""
    r = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True,
                       text=True, timeout=60)
    assert r.returncode == 130, r.stderr
    assert "stopped by SIGINT while running: bag" in r.stderr, r.stderr
    got = [deserialize(d, "geometry_msgs/msg/PointStamped").header.stamp.sec
           for _, d in topic_data(str(bag), "/setpoint")]
    assert got == list(range(1, 51))


def test_replay_honours_rate_on_the_bags_time_and_publishes_clock(tmp_path, env):
    """A lockstep bag (one time base: simulated time from 0) replayed at rate 2 takes at
    least half its duration, never less (the rate is honoured), and /clock carries the
    bag's time in order, so a node on use_sim_time follows the replay."""
    import threading

    from rosgraph_msgs.msg import Clock

    from piezo_stage.core.estimation.record import Record
    from piezo_stage.io.bag import write_record_bag
    from ros_probe import Probe
    t = np.arange(1500) / 1000.0
    v = 75 - 75 * np.cos(2 * np.pi * t)
    bag = tmp_path / "r"
    write_record_bag(bag, Record(t, {"x": v, "y": v}, {"x": 0.5 * v, "y": 0.5 * v}))
    probe = Probe(int(env["ROS_DOMAIN_ID"]))
    clocks = []
    probe.node.create_subscription(Clock, "/clock", lambda m: clocks.append(
        m.clock.sec * 10**9 + m.clock.nanosec), 100)
    stop = threading.Event()
    spinner = threading.Thread(target=lambda: [probe.ex.spin_once(timeout_sec=0.01)
                                               for _ in iter(stop.is_set, True)])
    spinner.start()
    try:
        t0 = time.monotonic()
        r = subprocess.run([sys.executable, "-m", "piezo_stage.cli", "replay", str(bag),
                            "--rate", "2"], env=env, capture_output=True, text=True,
                           timeout=60)
        took = time.monotonic() - t0
        assert r.returncode == 0, r.stderr
        assert "replayed 1500 messages" in r.stdout
        assert took >= 1.499 / 2
        time.sleep(0.5)  # the spinner takes the last ones
    finally:
        stop.set()
        spinner.join()
        probe.close()
    assert len(clocks) >= 100 and clocks == sorted(clocks)
    assert clocks[0] == 0 and 1_480_000_000 <= clocks[-1] <= 1_499_000_000
    bad = subprocess.run([sys.executable, "-m", "piezo_stage.cli", "replay", str(bag), "--rate",
                          "-1"], env=env, capture_output=True, text=True, timeout=60)
    assert bad.returncode == 2 and "--rate" in bad.stderr
    # --duration is the record's time, and the end is said in one line
    cut = subprocess.run([sys.executable, "-m", "piezo_stage.cli", "replay", str(bag),
                          "--rate", "0", "--duration", "0.5"], env=env, capture_output=True,
                         text=True, timeout=60)
    assert cut.returncode == 0, cut.stderr
    first, last = cut.stdout.splitlines()[0], cut.stdout.splitlines()[-1]
    assert first.startswith("replay: 501 messages, 0.500 s of the record"), cut.stdout
    assert last.startswith("replayed 501 messages on 1 topics: 0.500 s of the "
                           "record's 1.499 s in "), cut.stdout
    assert cut.stdout.endswith(", cut at --duration 0.5 s of the record\n"), cut.stdout
    assert "to the end" in r.stdout
    # a file that is not a bag is named for what it is
    for path, says in ((os.path.join(CONFIG, "stage_model.yaml"), "a YAML file"),
                       (bag / "metadata.yaml", "the bag's metadata.yaml (give its directory)")):
        other = subprocess.run([sys.executable, "-m", "piezo_stage.cli", "replay", str(path)],
                               env=env, capture_output=True, text=True, timeout=60)
        assert other.returncode == 2 and other.stderr.count("\n") == 1, other.stderr
        assert f"{path}: {says}" in other.stderr and "not a bag" in other.stderr


def test_replay_tells_a_fast_topics_subscribers_what_keeps_it_whole(tmp_path, env):
    """A best-effort subscriber to a 1 kHz joint_states is warned by name; every fast
    topic with subscribers gets one note with the queue depth that keeps it whole."""
    from rclpy.qos import QoSProfile, ReliabilityPolicy
    from sensor_msgs.msg import JointState

    from piezo_stage.core.estimation.record import Record
    from piezo_stage.io.bag import write_record_bag
    from ros_probe import Probe
    t = np.arange(1500) / 1000.0
    v = 75 - 75 * np.cos(2 * np.pi * t)
    bag = tmp_path / "r"
    write_record_bag(bag, Record(t, {"x": v, "y": v}, {"x": 0.5 * v, "y": 0.5 * v}))
    probe = Probe(int(env["ROS_DOMAIN_ID"]))
    try:
        probe.node.create_subscription(
            JointState, "/stage/joint_states", lambda m: None,
            QoSProfile(depth=10, reliability=ReliabilityPolicy.BEST_EFFORT))
        r = subprocess.run([sys.executable, "-m", "piezo_stage.cli", "replay", str(bag),
                            "--rate", "0"], env=env, capture_output=True, text=True,
                           timeout=60)
    finally:
        probe.close()
    assert r.returncode == 0, r.stderr
    assert ("piezo-stage replay: warning: /probe subscribes to /stage/joint_states best "
            "effort") in r.stderr, r.stderr
    notes = [ln for ln in r.stderr.splitlines() if ln.startswith("piezo-stage replay: note:")]
    assert len(notes) == 1 and "/stage/joint_states streams" in notes[0], r.stderr
    assert "a subscriber keeps every one with a queue of" in notes[0]


def test_colcon_style_prefix_install_starts_the_driver(tmp_path, env):
    """Installed the way colcon builds an ament_python package (setup.py install into a
    prefix, scripts under lib/piezo_stage, share/piezo_stage/{config,launch}, the ament
    index marker), the driver started from there, in another directory, finds its
    default plant config through the ament index and starts."""
    src, build, prefix = tmp_path / "src", tmp_path / "build", tmp_path / "install"
    build.mkdir()
    subprocess.run(f"git -C {ROOT} ls-files -z | (cd {ROOT} && xargs -0 tar -cf -) | "
                   f"(mkdir -p {src} && tar -xf - -C {src})", shell=True, check=True)
    r = subprocess.run([sys.executable, "setup.py", "-q", "egg_info", "--egg-base",
                        str(build), "build", "--build-base", str(build), "install",
                        "--prefix", str(prefix), "--record", str(build / "rec.txt"),
                        "--single-version-externally-managed"], cwd=src,
                       capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    share = prefix / "share" / "piezo_stage"
    assert (prefix / "share/ament_index/resource_index/packages/piezo_stage").exists()
    assert (share / "config" / "sim_stage.yaml").exists()
    assert (share / "launch" / "piezo_stage_launch.py").exists()
    site = next(prefix.glob("lib/python3*/site-packages"))
    e = dict(env, PYTHONPATH=str(site), AMENT_PREFIX_PATH=str(prefix))
    where = subprocess.run([sys.executable, "-c", "import piezo_stage.paths as p; "
                            "print(p.__file__); print(p.default_config('sim_stage.yaml'))"],
                           env=e, cwd=tmp_path, capture_output=True, text=True)
    assert where.stdout.split() == [str(site / "piezo_stage" / "paths.py"),
                                    str(share / "config" / "sim_stage.yaml")], where
    # the nodes and piezo-stage in lib/piezo_stage, nothing in bin/ (colcon's layout)
    from piezo_stage.nodes import NODES
    lib = prefix / "lib" / "piezo_stage"
    assert sorted(os.listdir(lib)) == sorted([*NODES, "piezo-stage"])
    assert not (prefix / "bin").exists() or not os.listdir(prefix / "bin")
    # a ROS install has no Python in the prefix: the node runs python3 from PATH
    e["PATH"] = os.path.dirname(sys.executable) + os.pathsep + e.get("PATH", "")
    _driver_starts(lib / "stage_driver", e, tmp_path)


def _driver_starts(exe, env, cwd):
    """The installed stage_driver executable starts and says so; then SIGINT."""
    assert os.access(exe, os.X_OK), exe
    proc = subprocess.Popen([str(exe), "--ros-args", "-r", "__ns:=/stage"], env=env,
                            cwd=cwd, stderr=subprocess.PIPE, text=True)
    try:
        lines = []
        for line in proc.stderr:
            lines.append(line)
            if "started disarmed" in line or "not found" in line or "rror" in line:
                break
        assert lines and "started disarmed" in lines[-1], "".join(lines)
    finally:
        proc.send_signal(signal.SIGINT)
        proc.wait(30)


def test_a_wheel_puts_only_piezo_stage_on_path_and_the_nodes_in_lib(tmp_path, env):
    """pip's install (a wheel, into a prefix): bin/ holds piezo-stage and nothing else
    (no controller, recorder, gap... shadowing other tools on PATH); the nodes are
    executables in lib/piezo_stage, where `ros2 run piezo_stage <node>` looks, and run
    with the prefix's own Python (a virtual environment's). (Before: eight node names
    in bin/, none in lib/piezo_stage.)"""
    from piezo_stage.nodes import NODES
    src, prefix = tmp_path / "src", tmp_path / "prefix"
    subprocess.run(f"git -C {ROOT} ls-files -z | (cd {ROOT} && xargs -0 tar -cf -) | "
                   f"(mkdir -p {src} && tar -xf - -C {src})", shell=True, check=True)
    # (--ignore-installed: pip would otherwise uninstall our own editable install first)
    r = subprocess.run([sys.executable, "-m", "pip", "install", "--quiet", "--no-deps",
                        "--ignore-installed",
                        "--no-build-isolation", "--disable-pip-version-check",
                        "--prefix", str(prefix), str(src)],
                       capture_output=True, text=True, cwd=tmp_path)
    assert r.returncode == 0, r.stderr
    assert os.listdir(prefix / "bin") == ["piezo-stage"]
    lib = prefix / "lib" / "piezo_stage"
    assert sorted(os.listdir(lib)) == sorted(NODES)
    assert (prefix / "share/ament_index/resource_index/packages/piezo_stage").exists()
    site = next(prefix.glob("lib/python3*/site-packages"))
    # the prefix's Python is taken over PATH's: a prefix without piezo_stage's
    # dependencies on PATH could not start the node
    # (a link to our interpreter, given our environment's packages as a venv would)
    import sysconfig
    os.symlink(sys.executable, prefix / "bin" / "python3")
    e = dict(env, PYTHONPATH=os.pathsep.join([str(site), sysconfig.get_paths()["purelib"]]),
             AMENT_PREFIX_PATH=str(prefix), PATH="/nonexistent")
    _driver_starts(lib / "stage_driver", e, tmp_path)


def test_launch_file_and_launcher_share_one_node_list_and_parameters(tmp_path):
    """The ros2 launch file builds its nodes from Launch (the same set, recorder and
    gap included, the same gating): what Launch gives each node is what our own
    processes get on their command line."""
    import ast
    src = open(os.path.join(ROOT, "launch", "piezo_stage_launch.py")).read()
    tree = ast.parse(src)
    assert any(isinstance(n, ast.ImportFrom) and n.module == "piezo_stage.launcher.launcher"
               for n in tree.body)
    assert "launch.node_params(n)" in src and "for n in launch.nodes" in src
    cfg = tmp_path / "c.yaml"
    cfg.write_text(open(STAGE).read() + "/**/gap:\n  ros__parameters:\n    window: 500\n")
    la = Launch(str(cfg), LaunchOptions(record=str(tmp_path / "bag")))
    assert la.nodes[0] == "recorder" and "gap" in la.nodes and "stage_driver" in la.nodes
    for n in la.nodes:
        cmd = la.command(n)
        for k, v in la.node_params(n).items():
            assert f"{k}:={v if not isinstance(v, bool) else str(v).lower()}" in cmd
    assert la.node_params("recorder")["output"] == str(tmp_path / "bag")
    assert la.node_params("stage_driver")["use_sim_time"] is True


def test_the_bag_holds_the_trajectories_the_stage_accepted(tmp_path, env):
    """The feedforward alone subscribes to /stage/trajectory and republishes what it
    accepted, byte for byte and latched, on /stage/trajectory/accepted, which the
    recorder takes: one accepted before the recorder started is in the bag; one sent
    once by a default-QoS publisher as soon as its one subscriber matched reached the
    stage and the bag; one refused (out of range) is in neither, and said to its sender
    on trajectory/refused (in the bag too), by the name it gave it."""
    from diagnostic_msgs.msg import DiagnosticArray
    from rclpy.qos import QoSProfile
    from trajectory_msgs.msg import JointTrajectory

    import piezo_stage_msgs_adapters as A
    from benchmarks.probe import Probe
    from piezo_stage.io.run_bag import status_node
    from piezo_stage.nodes._common import QOS_LATCHED
    probe = Probe(int(env["ROS_DOMAIN_ID"]))
    t = np.arange(0, 0.1, 1e-3)
    node = lambda name, *extra: subprocess.Popen(  # noqa: E731
        [sys.executable, "-m", f"piezo_stage.nodes.{name}_node", "--ros-args", "-r",
         "__ns:=/stage", *extra], env=env, stderr=subprocess.PIPE, text=True)
    ff = node("feedforward")
    bag = tmp_path / "accepted"
    rec = None
    # what the recorder holds, from its own diagnostics (1 Hz): the test waits for
    # that, not for a time (discovery between two nodes took over 1.5 s on CI's host
    # loaded by other work, and the recorder was stopped before it matched)
    recorded: dict = {}
    probe.node.create_subscription(DiagnosticArray, "/diagnostics", lambda m: recorded.update(
        {kv.key: kv.value for st in m.status if status_node(st.name) == "recorder"
         for kv in st.values}), 10)

    def accepted_in_bag() -> int:
        return int(recorded.get("/stage/trajectory/accepted", 0))
    try:
        latched = probe.node.create_publisher(JointTrajectory, "/stage/trajectory",
                                              QOS_LATCHED)
        assert probe.wait(lambda: latched.get_subscription_count() >= 1, 30)
        latched.publish(A.trajectory_msg(t, {"x": np.full(t.size, 5.0),
                                             "y": np.full(t.size, 5.0)}))
        probe.spin(1.0)
        rec = node("recorder", "-p", f"output:={bag}")
        # the recorder up, and the latched trajectory in its bag (its start and its
        # match with the feedforward take longer on a loaded host)
        assert probe.wait(lambda: accepted_in_bag() >= 1, 60), recorded
        plain = probe.node.create_publisher(JointTrajectory, "/stage/trajectory",
                                            QoSProfile(depth=10))
        assert probe.wait(lambda: plain.get_subscription_count() >= 1, 10)
        plain.publish(A.trajectory_msg(t, {"x": np.full(t.size, 7.0),
                                           "y": np.full(t.size, 7.0)}))
        too_far = A.trajectory_msg(t, {"x": np.full(t.size, 500.0), "y": np.full(t.size, 7.0)})
        too_far.header.frame_id = "too-far"  # its sender's name for it
        plain.publish(too_far)
        from rclpy.duration import Duration
        assert plain.wait_for_all_acked(Duration(seconds=10))
        assert probe.wait(lambda: accepted_in_bag() >= 2, 30), recorded
        probe.spin(1.0)  # (room for a third, which must not come: the refused one)
        assert plain.get_subscription_count() == 1  # the feedforward alone
    finally:
        probe.close()
        for p in (rec, ff):
            if p is not None:
                p.send_signal(signal.SIGINT)
        ff_err = ff.communicate(timeout=30)[1]
        assert rec is not None and rec.wait(30) == 130
    got = [deserialize(data, "trajectory_msgs/msg/JointTrajectory").points[0].positions[0]
           for _, data in topic_data(str(bag), "/stage/trajectory/accepted")]
    assert [round(p * 1e6, 6) for p in got] == [5.0, 7.0]
    assert not topic_data(str(bag), "/stage/trajectory")
    assert "trajectory rejected" in ff_err and "500" in ff_err, ff_err[-2000:]
    # the refusal reached its sender's topic, with the name it gave it and the reason
    refused = [A.refusal_from_msg(deserialize(data, "diagnostic_msgs/msg/DiagnosticArray"))
               for _, data in topic_data(str(bag), "/stage/trajectory/refused")]
    assert [(f, "500" in why and "range" in why) for f, _, why in refused] == \
        [("too-far", True)], refused


def test_learning_feedforward_through_the_node_set(tmp_path, env):
    """Lockstep, the effects stage (creep, an 800 Hz resonance, a 0.5 ms delay) with a
    model that knows none of them, feedforward only, 40 Hz for 0.75 s (30 periods):
    with learning the last periods' error against the true position is a fraction of
    the same run's without it, and the voltages stay within the limits."""
    from piezo_stage.io.run_bag import read_run
    out = {}
    for learn in (False, True):
        bag = lockstep(tmp_path, env, f"learn{learn}", steps=2200,
                       nodes=["stage_driver", "feedforward", "controller", "trajectory"],
                       overrides={"stage_driver": {"plant_config": os.path.join(
                           CONFIG, "sim_stage_effects.yaml")},
                           "controller": {"feedback": False},
                           "trajectory": {"kind": "sine", "frequency_hz": 40.0,
                                          "center_um": 25.0, "amplitude_um": 24.0,
                                          "duration_s": 0.75},
                           "feedforward": {"learning": learn, "learning_period_s": 0.025}})
        run = read_run(bag)
        ks = sorted(run.desired_um)
        d = np.array([run.desired_um[k] for k in ks])[:, 0]
        t_end = ks[np.flatnonzero(np.abs(np.diff(d)) > 1e-9)[-1]]  # the trajectory's end
        e = run.errors_um(t_end - int(0.1e9), t_end)  # its last 4 periods
        out[learn] = float(np.sqrt(np.mean(e ** 2)))
        assert np.all((run.v_V >= 0.0) & (run.v_V <= 150.0))
        if learn:
            diag = [kv.value for _, data in topic_data(bag, "/diagnostics")
                    for st in deserialize(data, "diagnostic_msgs/msg/DiagnosticArray").status
                    for kv in st.values if kv.key == "learning"]
            assert any("periods learned" in d for d in diag), diag[-3:]
    assert out[True] < 0.35 * out[False], out


def test_launch_seed_gives_another_run_to_hold_out(tmp_path, env):
    """docs/nodes.md's recipe: the held-out run takes another --seed, so its bag is a
    different record of the same stage (a lockstep run with the same seed is the same
    bag, byte for byte)."""
    from piezo_stage.io.bag import read_bag_record
    runs = {}
    for name, extra in (("run1", []), ("run2", ["--seed", "7"])):
        r = subprocess.run([sys.executable, "-m", "piezo_stage.cli", "launch", "--record",
                            str(tmp_path / name), "--duration", "6", *extra], env=env,
                           capture_output=True, text=True, timeout=120)
        assert r.returncode == 0, r.stderr[-2000:]
        runs[name] = read_bag_record(str(tmp_path / name))
    # each run from the sample its reference starts to move (when the trajectory reaches
    # the feedforward depends on the host's pace in lockstep too: the set holds until
    # then), up to the first model hand-over if any (the identifier hands its model over
    # at a sample that depends on the host's pace, as it runs beside the lockstep loop)
    parts = {}
    for name, rec in runs.items():
        bag = str(tmp_path / name)
        ref = []
        for _, data in topic_data(bag, "/reference"):
            m = deserialize(data, "sensor_msgs/msg/JointState")
            ref.append((m.header.stamp.sec * 10**9 + m.header.stamp.nanosec,
                        m.position[0] * 1e6))
        ref.sort()
        moves = next(ns for ns, x in ref if abs(x - ref[0][1]) > 0.5)
        # (lockstep: the bag's log times are the samples' stamps)
        logs = np.array(sorted(log for log, _ in topic_data(bag, "/stage/joint_states")))
        assert len(logs) == len(rec)
        handed = [log for log, _ in topic_data(bag, "/stage/model")]
        k0 = int(np.searchsorted(logs, moves))
        k1 = int(np.searchsorted(logs, min(handed))) if handed else len(rec)
        parts[name] = rec.w["x"][k0:k1]
    n = min(len(p) for p in parts.values())
    assert n > 300
    a, b = parts["run1"][:n], parts["run2"][:n]
    assert np.sqrt(np.mean((a - b) ** 2)) < 1.0  # of the same stage and trajectory (um)


@pytest.mark.slow
def test_launch_and_replay_show_their_progress_on_a_terminal(tmp_path, env):
    """On a terminal, launch's progress (seconds of its --duration) and replay's (seconds
    of the record) stand on one redrawn line; piped, as everywhere else, neither."""
    exe = os.path.join(os.path.dirname(sys.executable), "piezo-stage")
    said = on_a_terminal([exe, "launch", "--duration", "4"], env, tmp_path)
    assert "launch: " in said and "/4.0 [" in said and "%|" in said, said[-1500:]
    # a bag of 2 s of the record, whatever the host's pace: a played waveform's
    from piezo_stage.io.csv_table import write_table
    t = np.arange(0, 2.0, 1e-3)
    write_table(tmp_path / "wave.csv", {"t": t, "vx": 50 + 40 * np.sin(2 * np.pi * t),
                                        "vy": 50 + 40 * np.cos(2 * np.pi * t)})
    subprocess.run([exe, "play", "wave.csv", "--out", "bag"], env=env, cwd=tmp_path,
                   check=True, capture_output=True, timeout=120)
    said = on_a_terminal([exe, "replay", "bag", "--rate", "2"], env, tmp_path)
    assert "replay: " in said and "s of record" in said and "%|" in said, said[-1500:]
    piped = subprocess.run([exe, "replay", "bag", "--rate", "0"], env=env, cwd=tmp_path,
                           capture_output=True, text=True, timeout=120)
    assert "%|" not in piped.stdout + piped.stderr


def test_a_nodes_diagnostics_learn_the_device_from_the_drivers_state_bytes(ros_env):
    """The recorder learns the driver's hardware_id from the state it records (bytes),
    not only from its own subscription, which its executor may serve after its last
    report (a short lockstep run's bag once had the recorder's status naming
    "stage /stage"). Bytes that are no announcement leave what it knew."""
    import rclpy
    from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
    from rclpy.context import Context
    from rclpy.serialization import serialize_message

    from piezo_stage.nodes._loop import Diagnostics
    ctx = Context()
    rclpy.init(context=ctx, domain_id=int(ros_env["ROS_DOMAIN_ID"]))
    try:
        node = rclpy.create_node("recorder", namespace="/stage", context=ctx)
        diag = Diagnostics(node, lambda: (0, "recording", {}), "recording")
        assert diag.hw == "stage /stage"
        diag.learn_from_state(b"\x00\x01 not a message")
        assert diag.hw == "stage /stage"
        msg = DiagnosticArray(status=[DiagnosticStatus(name="/stage/stage_driver: state",
                                                       hardware_id="sim seed 3 (x, y)")])
        diag.learn_from_state(serialize_message(msg))
        assert diag.hw == "sim seed 3 (x, y)"
        node.destroy_node()
    finally:
        rclpy.shutdown(context=ctx)


def test_the_probe_waits_for_a_steady_state_and_says_what_it_saw(env):
    """Before a test injects a fault it waits for a set armed for a while (a set faulted
    again after a re-arm shows no new fault when its controller stops): here a
    publisher of the driver's state topic says armed, faulted, armed; the probe calls
    the set steady only once the last armed has held for ``hold`` s, and ``seen`` lists
    every state with its reason and time."""
    import rclpy
    from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
    from rclpy.context import Context

    from piezo_stage.nodes._common import QOS_EVENTS
    from ros_probe import Probe
    d = int(env["ROS_DOMAIN_ID"])
    ctx = Context()
    rclpy.init(context=ctx, domain_id=d)
    node = rclpy.create_node("state_source", context=ctx)
    pub = node.create_publisher(DiagnosticArray, "/stage/state", QOS_EVENTS)
    probe = Probe(d)

    def say(state, reason):
        m = DiagnosticArray()
        m.status = [DiagnosticStatus(name="stage_driver", values=[
            KeyValue(key="state", value=state), KeyValue(key="reason", value=reason)])]
        pub.publish(m)

    try:
        assert probe.wait(lambda: pub.get_subscription_count() > 0, 10)
        assert not probe.wait_steady("armed", 0.2, 0.3)  # nothing heard yet
        assert "no state seen" in probe.seen()
        say("armed", "tracking")
        assert probe.wait_state("armed", 5)
        t_armed = time.monotonic()
        say("faulted", "stale commands: none on time for 0.051 s")
        assert probe.wait_state("faulted", 5, after=1)
        assert not probe.wait_steady("armed", 0.2, 0.5)  # faulted now, however long
        say("armed", "tracking")
        assert probe.wait_state("armed", 5, after=2)
        t0 = time.monotonic()
        assert probe.wait_steady("armed", 0.4, 5)
        assert time.monotonic() - t0 >= 0.35  # held for its hold, not at once
        seen = probe.seen(0, t_armed)
        assert [s.split(" (")[0] for s in seen.split("; ")] == ["armed", "faulted", "armed"]
        assert "faulted (stale commands: none on time for 0.051 s) +" in seen, seen
        assert probe.seen(1).startswith("faulted (stale commands") and " +0.000 s;" in \
            probe.seen(1), probe.seen(1)
    finally:
        probe.close()
        node.destroy_node()
        rclpy.try_shutdown(context=ctx)


# a stand-in for the feedforward's side of the trajectory topic (a real node): it takes
# every publication on /stage/trajectory, says it holds with none, and answers on
# trajectory/accepted only if told to; it prints how many publications it got in 4 s
HOLDING_FF = r"""
import sys, time, rclpy
from diagnostic_msgs.msg import KeyValue
from trajectory_msgs.msg import JointTrajectory
from piezo_stage.nodes._common import QOS_EVENTS
answer = sys.argv[1] == "answer"
rclpy.init()
n = rclpy.create_node("feedforward", namespace="/stage")
got = []
acc = n.create_publisher(JointTrajectory, "trajectory/accepted", QOS_EVENTS)
phase = n.create_publisher(KeyValue, "feedforward/phase", QOS_EVENTS)
def take(m):
    got.append(time.monotonic())
    if answer:
        acc.publish(m)
n.create_subscription(JointTrajectory, "trajectory", take, 10)
t0 = time.monotonic()
while time.monotonic() - t0 < 6.0 and (not got or time.monotonic() - got[0] < 4.0):
    phase.publish(KeyValue(key="holding", value=""))
    rclpy.spin_once(n, timeout_sec=0.1)
print(len(got))
"""


@pytest.mark.parametrize("answer, most", [("answer", 1), ("silent", 4)])
def test_the_trajectory_node_resends_only_what_the_feedforward_did_not_take(env, answer,
                                                                              most):
    """The trajectory node (a real process) publishes its trajectory once a consumer
    listens; a feedforward that keeps saying it holds with none and never answers on
    trajectory/accepted gets it again, a second apart, at most RESENDS times more; one
    that answered it (it runs the publication, whatever its phase says next) never
    gets a second publication: a trajectory is its publication, so a resend would run
    the trajectory twice."""
    ff = subprocess.Popen([sys.executable, "-c", HOLDING_FF, answer], env=env,
                          stdout=subprocess.PIPE, text=True)
    node = subprocess.Popen([sys.executable, "-m", "piezo_stage.nodes.trajectory_node",
                             "--ros-args", "-r", "__ns:=/stage"], env=env,
                            stderr=subprocess.DEVNULL)
    try:
        out, _ = ff.communicate(timeout=60)
    finally:
        node.send_signal(signal.SIGINT)
        node.wait(30)
    got = int(out.split()[-1])
    assert (got == 1) if answer == "answer" else (2 <= got <= most), got
