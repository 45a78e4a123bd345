"""Stops: every node kind and the launcher stop on SIGINT and SIGTERM at any moment of
their life, say what they did, and leave nothing behind; a default-QoS publisher meets
no QoS warning on either side. Real processes, each run on its own ROS_DOMAIN_ID.

``piezo-stage bench signals`` runs the long form (over 100 trials, some under load)."""

import os
import signal
import subprocess
import sys
import time

import pytest

pytest.importorskip("rclpy")
from benchmarks import signals as bench_signals  # noqa: E402
from conftest import CONFIG, ROOT  # noqa: E402
from piezo_stage.launcher.launcher import Launch, LaunchOptions  # noqa: E402

pytestmark = pytest.mark.slow
STAGE = os.path.join(CONFIG, "stage.yaml")


def test_every_node_and_the_launcher_stop_at_random_moments(ros_domains):
    """Each kind twice (SIGINT, then SIGTERM), signalled 0-3 s after start: during
    imports, rclpy.init, discovery or spinning."""
    n = 2 * len(bench_signals.KINDS)
    trials = bench_signals.stress(n, parallel=2, loaded_share=0.0, seed=7,
                                  domain0=ros_domains(2))
    bad = [t for t in trials if not t.ok]
    assert not bad, "\n".join(map(str, bad))
    # a start-up stop and a running stop both happened, and each said so
    assert any("start-up" in t.said for t in trials)
    assert any("while running" in t.said or "in order" in t.said for t in trials)


ENDS_BY_ITSELF = r"""
import signal, sys
from piezo_stage.process import signals
signals.install()
import rclpy
from rclpy.node import Node
from piezo_stage.nodes._executor import run_node

class Ends(Node):  # a node whose run ends by itself after a few passes
    def __init__(self):
        super().__init__("ends_by_itself")
        self.create_timer(0.05, lambda: rclpy.try_shutdown())

code = run_node(Ends)
held = all(signal.getsignal(s) == signal.SIG_IGN for s in (signal.SIGINT, signal.SIGTERM))
print("ended", code, held, flush=True)
sys.exit(code)
"""


def test_a_node_that_ended_by_itself_is_not_killed_by_a_late_stop(ros_env):
    """The launcher's SIGINT can meet a node that has just ended by itself (the run's
    end): once its teardown is done the stop signals are ignored, so one arriving while
    the interpreter exits (which gives the default handlers back) cannot kill it. Here
    SIGINTs rain on the node from its last line to its exit: it exits 0 every time."""
    for _ in range(3):
        p = subprocess.Popen([sys.executable, "-c", ENDS_BY_ITSELF], env=ros_env,
                             stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        assert p.stdout.readline().split() == ["ended", "0", "True"]
        while p.poll() is None:
            try:
                os.kill(p.pid, signal.SIGINT)
            except ProcessLookupError:
                break
            time.sleep(0.0005)
        _, err = p.communicate(timeout=30)
        assert p.returncode == 0, (p.returncode, err[-1000:])


STOP_IN_A_CALLBACK = r"""
import os, signal, sys
from piezo_stage.process import signals
signals.set_phase("building", "/stage/builder")
import llvmlite.binding.executionengine as ee
find = ee.ExecutionEngine._find_module_ptr  # (what LLVM's callback into Python calls)
sent = []
def at_the_callback(self, ptr):  # a Ctrl-C while LLVM has called back into Python
    if not sent:
        sent.append(os.kill(os.getpid(), signal.SIGINT))
    return find(self, ptr)
ee.ExecutionEngine._find_module_ptr = at_the_callback
from numba import njit
import time
try:
    njit(lambda x: x + 1)(1)  # compiling: LLVM hands its object cache to Python
    time.sleep(2.0)
except signals.Stopped:
    print("stopped", signals.requested(), signals.count(), len(sent)); sys.exit(0)
print("not stopped")
"""


def test_a_nodes_stop_inside_a_compilers_callback_is_raised_once_back_in_python():
    """A node building its kernels (numba, through llvmlite) gets a Ctrl-C while LLVM is
    calling back into Python through ctypes, where a raised exception is printed with
    its traceback and dropped: it is sent again a moment later and raised then, once
    back in Python, still counted as one stop (a driver takes a second one as "stop at
    once"); nothing is printed."""
    r = subprocess.run([sys.executable, "-c", STOP_IN_A_CALLBACK], capture_output=True,
                       text=True, timeout=120, env=dict(os.environ, PYTHONPATH=ROOT))
    assert (r.returncode, r.stdout.strip()) == (0, f"stopped {int(signal.SIGINT)} 1 1"), \
        r.stderr
    assert "Traceback" not in r.stderr and "Exception ignored" not in r.stderr, r.stderr


COMMAND_STOP_IN_A_CALLBACK = r"""
import os, signal, sys, time
from piezo_stage.process import stopping
stopping.running()
import llvmlite.binding.executionengine as ee
find = ee.ExecutionEngine._find_module_ptr
sent = []
def at_the_callback(self, ptr):
    if not sent:
        sent.append(os.kill(os.getpid(), signal.SIGINT))
    return find(self, ptr)
ee.ExecutionEngine._find_module_ptr = at_the_callback
from numba import njit
try:
    njit(lambda x: x + 1)(1)
    time.sleep(2.0)
except KeyboardInterrupt:
    print("stopped", len(sent)); sys.exit(0)
print("not stopped")
"""


def test_a_commands_stop_inside_a_compilers_callback_is_raised_once_back_in_python():
    """The command line's own stop (a KeyboardInterrupt) landing in the same callback:
    not raised there (it would be printed and lost) but sent again a moment later and
    raised then: the command stops, nothing is printed."""
    r = subprocess.run([sys.executable, "-c", COMMAND_STOP_IN_A_CALLBACK],
                       capture_output=True, text=True, timeout=120,
                       env=dict(os.environ, PYTHONPATH=ROOT))
    assert (r.returncode, r.stdout.strip()) == (0, "stopped 1"), r.stderr
    assert "Traceback" not in r.stderr and "Exception ignored" not in r.stderr, r.stderr


def test_a_stop_caught_inside_code_run_by_exec_ends_the_command_with_its_own_code():
    """CPython keeps a KeyboardInterrupt that left ``exec``'d code marked unhandled and
    ends the interpreter by SIGINT at exit; the command's hold clears the mark (a stop
    during numba's dataclass import once exited -2 after saying it stopped)."""
    code = ("from piezo_stage.process import stopping\n"
            "try:\n    exec('raise KeyboardInterrupt')\n"
            "except KeyboardInterrupt:\n    stopping.hold()\n")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                       timeout=60)
    assert r.returncode == 0, r.stderr


def test_importlibs_own_frames_are_told_from_a_modules_top_level():
    """A stop landing in importlib's lock code is sent again (raised there it is
    dropped); one landing in a module's own top level is raised."""
    from piezo_stage.process import stopping
    seen = {}

    def tracer(frame, event, arg):
        if event == "call":
            seen.setdefault(frame.f_code.co_filename.startswith("<frozen importlib"),
                            frame)
        return None

    import importlib
    sys.modules.pop("colorsys", None)
    sys.setprofile(tracer)
    try:
        importlib.import_module("colorsys")
    finally:
        sys.setprofile(None)
    assert stopping.in_import_machinery(seen[True])
    assert not stopping.in_import_machinery(sys._getframe())


def test_a_stop_landing_in_the_first_import_of_threading_is_sent_again(monkeypatch):
    """A stop that lands while the command imports ``threading`` for the first time (the
    launcher's look, 0.11 s after start) is sent again: ``again_soon`` uses the module it
    imported whole, never the half-made one then in ``sys.modules`` (it raised
    AttributeError: no ``Timer``, a traceback instead of the stop's line)."""
    import types

    from piezo_stage.process import stopping
    monkeypatch.setitem(sys.modules, "threading", types.ModuleType("threading"))
    stopping.again_soon(0)  # signal 0: only checks that this process may be signalled


def test_a_stop_landing_in_a_finalizer_is_not_lost():
    """A Ctrl-C that lands while an object's ``__del__`` runs (llvmlite's, as numba
    compiles) is sent again once the finalizer is done: the command stops with its
    line and 130, nothing printed as "Exception ignored"."""
    code = (
        "import sys, os, signal, time, threading\n"
        "from piezo_stage.process import stopping\n"
        "stopping.install(); stopping.running()\n"
        "class Slow:\n"
        "    def __del__(self):\n"
        "        t0 = time.monotonic()\n"
        "        while time.monotonic() - t0 < 0.3: pass\n"
        "threading.Timer(0.1, os.kill, (os.getpid(), signal.SIGINT)).start()\n"
        "try:\n"
        "    x = Slow(); del x\n"
        "    time.sleep(5)\n"
        "    print('not stopped')\n"
        "except KeyboardInterrupt:\n"
        "    stopping.hold(); print('stopped after the finalizer')\n")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                       timeout=60)
    assert r.stdout.strip() == "stopped after the finalizer", (r.stdout, r.stderr)
    assert "Exception ignored" not in r.stderr and "Traceback" not in r.stderr, r.stderr


def test_a_killed_launcher_leaves_no_node_behind(tmp_path, ros_env):
    """SIGKILL cannot be caught: the nodes' parent-death signal stops them (each as on
    SIGTERM: the recorder finishes its bag)."""
    bag = tmp_path / "bag"
    la = subprocess.Popen([sys.executable, "-m", "piezo_stage", "launch", STAGE,
                           "--namespace", "/killed", "--duration", "60", "--record",
                           str(bag)], env=ros_env, stderr=subprocess.PIPE, text=True)
    try:
        for line in la.stderr:
            if "armed: tracking" in line:
                break
        processes = Launch(STAGE, LaunchOptions(record=str(bag))).processes()
        assert len(bench_signals.left_behind("/killed")) == len(processes)
        la.kill()
        la.wait()
        deadline = time.monotonic() + 10
        while bench_signals.left_behind("/killed") and time.monotonic() < deadline:
            time.sleep(0.1)
        assert bench_signals.left_behind("/killed") == []
    finally:
        for pid in bench_signals.left_behind("/killed"):
            os.kill(pid, signal.SIGKILL)
    from piezo_stage.io.bag import iter_messages
    assert sum(1 for t, *_ in iter_messages(str(bag)) if t.endswith("/joint_states")) > 0


OUTSIDE = r"""
import sys, time, rclpy
from rclpy.node import Node
from trajectory_msgs.msg import JointTrajectory, JointTrajectoryPoint
rclpy.init()
n = Node('lab_default_qos')
pub = n.create_publisher(JointTrajectory, '/stage/trajectory', 10)  # default QoS
t0 = time.monotonic()
while pub.get_subscription_count() < 1 and time.monotonic() - t0 < 20:
    rclpy.spin_once(n, timeout_sec=0.05)
m = JointTrajectory(); m.joint_names = ['x', 'y']
for k in range(5):
    p = JointTrajectoryPoint(); p.positions = [20e-6 + k * 1e-6, 20e-6]
    p.time_from_start.nanosec = k * 1_000_000; m.points.append(p)
pub.publish(m)
from rclpy.duration import Duration
acked = pub.wait_for_all_acked(Duration(seconds=30))  # sent once: stay until it is had
n.destroy_node(); rclpy.try_shutdown()
sys.exit(0 if acked else 1)
"""


# the same lab node, on the graph before the set starts: it publishes 2 s after the
# feedforward matches
OUTSIDE_FIRST = OUTSIDE.replace("< 20:", "< 40:").replace("m = JointTrajectory()",
                                                         "time.sleep(2.0)\nm = JointTrajectory()")


def _node(kind, env, log):
    return subprocess.Popen([sys.executable, "-m", f"piezo_stage.nodes.{kind}_node",
                             "--ros-args", "-r", "__ns:=/stage", "--params-file", STAGE],
                            env=env, stderr=log, stdout=log)


def _wait_for(path, text, timeout=30.0, count=1):
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        with open(path) as fh:
            if fh.read().count(text) >= count:
                return True
        time.sleep(0.1)
    return False


def test_default_qos_publisher_works_without_warnings_and_a_restart_gets_the_latched(
        tmp_path, ros_env):
    ff_log, tr_log = tmp_path / "ff.log", tmp_path / "tr.log"
    with open(ff_log, "w") as ffh, open(tr_log, "w") as trh:
        traj = _node("trajectory", ros_env, trh)
        ff = _node("feedforward", ros_env, ffh)
        try:
            # the built-in node's latched trajectory (1001 points), then the lab's
            assert _wait_for(ff_log, "trajectory of 1001 points accepted")
            time.sleep(1.0)  # a lab node joining later, not in the fetch's moment
            out = subprocess.run([sys.executable, "-c", OUTSIDE], env=ros_env,
                                 capture_output=True, text=True, timeout=60)
            assert out.returncode == 0, out.stderr
            assert "incompatible" not in out.stderr.lower(), out.stderr
            assert _wait_for(ff_log, "trajectory of 5 points accepted")
            # a restarted feedforward gets the latched trajectory again
            ff.send_signal(signal.SIGINT)
            assert ff.wait(30) == 130
            ff = _node("feedforward", ros_env, ffh)
            assert _wait_for(ff_log, "trajectory of 1001 points accepted", count=2)
        finally:
            for p in (ff, traj):
                p.send_signal(signal.SIGINT)
                p.wait(30)
    for log in (ff_log, tr_log):
        assert "incompatible" not in log.read_text().lower(), log.read_text()


def test_a_fetch_is_for_named_outside_latched_publishers_and_none_beside_volatile_ones():
    """What a latched fetch is opened for, from the graph's endpoint records (rclpy's
    own TopicEndpointInfo): an outside latched publisher; not our trajectory node in
    the namespace (it resends), nor a latched publisher the graph cannot name yet (it
    may be that node), and a volatile one on the topic is reported."""
    from rclpy.qos import DurabilityPolicy, QoSProfile
    from rclpy.topic_endpoint_info import TopicEndpointInfo, TopicEndpointTypeEnum

    from piezo_stage.nodes._common import UNKNOWN_NODE
    from piezo_stage.nodes._latched import fetchable

    def pub(name, ns, durability, gid):
        return TopicEndpointInfo(
            node_name=name, node_namespace=ns, topic_type="trajectory_msgs/msg/JointTrajectory",
            endpoint_type=TopicEndpointTypeEnum.PUBLISHER, endpoint_gid=[gid] * 16,
            qos_profile=QoSProfile(depth=1, durability=durability))
    latched, volatile = DurabilityPolicy.TRANSIENT_LOCAL, DurabilityPolicy.VOLATILE
    ours, lab = pub("trajectory", "/stage", latched, 1), pub("lab", "/", latched, 2)
    unnamed = pub(UNKNOWN_NODE, "_NODE_NAMESPACE_UNKNOWN_", latched, 3)
    assert fetchable([ours, lab, unnamed], "/stage") == ({bytes([2] * 16)}, False)
    assert fetchable([ours, unnamed], "/stage") == (set(), False)
    assert fetchable([pub("trajectory", "/other", latched, 4)], "/stage")[0] == \
        {bytes([4] * 16)}  # another namespace's trajectory node is outside this set
    assert fetchable([lab, pub("lab2", "/", volatile, 5)], "/stage") == \
        ({bytes([2] * 16)}, True)


def test_a_default_qos_publisher_already_on_the_graph_sees_no_warning_and_the_set_starts(
        tmp_path, ros_env):
    """A lab node with a default-QoS trajectory publisher is running when the set
    starts. The set's own trajectory node sends its latched trajectory again to each
    subscription that matches after its send, so no node opens a transient-local fetch
    for it: no incompatible-QoS warning on either side, and the feedforward gets both
    trajectories (once, a volatile publisher on the topic kept the feedforward from
    ever fetching the set's own, and the set never armed)."""
    ff_log, tr_log, lab_log = tmp_path / "ff.log", tmp_path / "tr.log", tmp_path / "lab.log"
    with open(ff_log, "w") as ffh, open(tr_log, "w") as trh, open(lab_log, "w") as lab_h:
        lab = subprocess.Popen([sys.executable, "-c", OUTSIDE_FIRST], env=ros_env,
                               stderr=lab_h, stdout=lab_h)
        time.sleep(1.5)  # on the graph first
        traj = _node("trajectory", ros_env, trh)
        ff = _node("feedforward", ros_env, ffh)
        try:
            assert _wait_for(ff_log, "trajectory of 1001 points accepted"), ff_log.read_text()
            assert _wait_for(ff_log, "trajectory of 5 points accepted"), ff_log.read_text()
            assert lab.wait(60) == 0, lab_log.read_text()
        finally:
            for p in (ff, traj, lab):
                p.send_signal(signal.SIGINT)
                p.wait(30)
    for log in (ff_log, tr_log, lab_log):
        assert "incompatible" not in log.read_text().lower(), log.read_text()
