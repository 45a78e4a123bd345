"""What the launcher checks and sets before the nodes run: modes, parameters, gates, the
middleware's transports and threads."""

import os
import signal
import subprocess
import sys

import pytest

from conftest import CONFIG, cli, one_line_exit_2

MODEL = os.path.join(CONFIG, "stage_model.yaml")


def test_launch_refuses_an_unknown_mode(tmp_path):
    cfg = tmp_path / "bogus.yaml"
    cfg.write_text("/**/stage_driver:\n  ros__parameters:\n    mode: bogus\n")
    r = cli("launch", cfg, "--duration", "5")
    one_line_exit_2(r)
    assert "bogus" in r.stderr


@pytest.mark.parametrize("record", [None, "bag"])
def test_lockstep_gates_count_the_live_view_as_a_subscriber(tmp_path, record):
    """The live view subscribes to every topic, as the recorder does: with --foxglove
    every lockstep publisher waits for one subscriber more, so its gate cannot open on
    the taps before a loop node listens (a lockstep run with the live view once hung:
    the driver's first sample went out before the feedforward had matched)."""
    from piezo_stage.launcher.launcher import Launch, LaunchOptions
    cfg = os.path.join(CONFIG, "stage.yaml")
    rec = None if record is None else str(tmp_path / record)
    plain = Launch(cfg, LaunchOptions(record=rec))._gates()
    watched = Launch(cfg, LaunchOptions(record=rec, foxglove_port=0))._gates()
    for node, gates in plain.items():
        for key in ("min_subscribers", "min_record_subscribers"):
            if key in gates:
                # the trajectory node's one subscriber is the feedforward (the taps take
                # the trajectory the feedforward accepted)
                more = 0 if node == "trajectory" else 1
                assert watched[node][key] == gates[key] + more, (node, key)


@pytest.mark.slow
def test_a_bad_parameter_is_refused_at_start_naming_the_node(ros_env):
    pytest.importorskip("rclpy")
    env = ros_env
    r = subprocess.run([sys.executable, "-m", "piezo_stage.nodes.stage_driver_node",
                        "--ros-args", "-r", "__ns:=/stage", "-p", "mode:=bogus"], env=env,
                       capture_output=True, text=True, timeout=60)
    assert r.returncode == 2  # a configuration error
    assert "/stage/stage_driver: fatal:" in r.stderr and "bogus" in r.stderr


@pytest.mark.slow
def test_a_misspelled_parameter_is_refused_by_name_and_an_integer_is_a_float(tmp_path,
                                                                            ros_env):
    """kP and frequncy_hz were ignored without a word (exit 0); `kp: 1` killed the
    controller with a type error. Now the node refuses the unknown name, suggesting the
    declared one, and takes 1 as 1.0; the launcher checks the whole file first."""
    pytest.importorskip("rclpy")
    r = subprocess.run([sys.executable, "-m", "piezo_stage.nodes.controller_node",
                        "--ros-args", "-r", "__ns:=/stage", "-p", "kP:=0.3"], env=ros_env,
                       capture_output=True, text=True, timeout=60)
    assert r.returncode == 2, r.stderr
    assert r.stderr.strip().splitlines()[-1] == \
        "/stage/controller: fatal: unknown parameter 'kP' (did you mean 'kp'?)"
    cfg = tmp_path / "kp.yaml"
    cfg.write_text("/**/controller:\n  ros__parameters:\n    kp: 1\n"
                   "    voltage_limits_V: [0, 150]\n")
    p = subprocess.Popen([sys.executable, "-m", "piezo_stage.nodes.controller_node",
                          "--ros-args", "-r", "__ns:=/stage", "--params-file", str(cfg)],
                         env=ros_env, stderr=subprocess.PIPE, text=True)
    try:
        with pytest.raises(subprocess.TimeoutExpired):  # it runs
            p.wait(8)
    finally:
        p.send_signal(signal.SIGINT)
        err = p.communicate(timeout=30)[1]
    assert p.returncode == 130 and "fatal" not in err, err
    bad = tmp_path / "typo.yaml"
    bad.write_text("/**/trajectory:\n  ros__parameters:\n    frequncy_hz: 3.0\n")
    r = cli("launch", str(bad), "--duration", "5")
    one_line_exit_2(r)
    assert "trajectory: unknown parameter 'frequncy_hz' (did you mean 'frequency_hz'?)" \
        in r.stderr
    assert "stage_driver" not in r.stderr  # refused before any node started


def test_use_sim_time_on_a_real_time_set_is_refused(tmp_path):
    from piezo_stage.core.errors import ConfigError
    from piezo_stage.launcher.launcher import Launch
    cfg = tmp_path / "rt.yaml"
    cfg.write_text("/**/stage_driver:\n  ros__parameters:\n    mode: realtime\n"
                   "/**/controller:\n  ros__parameters:\n    use_sim_time: true\n")
    with pytest.raises(ConfigError, match="use_sim_time on controller"):
        Launch(str(cfg))
    r = cli("launch", cfg, "--duration", "1")
    assert r.returncode == 2 and "use_sim_time" in r.stderr


def test_real_time_sets_publish_synchronously_over_loopback_udp(tmp_path):
    """Real time publishes synchronously (a publish is the caller's sendto on UDP: the
    asynchronous mode's writer threads cost the composed set a quarter of its
    capacity), off shared memory; lockstep keeps the transports its byte-identical
    reruns were measured with; a publication mode of the user's own is left alone."""
    from piezo_stage.launcher.launcher import Launch, LaunchOptions
    rt = tmp_path / "rt.yaml"
    rt.write_text("/**/stage_driver:\n  ros__parameters:\n    mode: realtime\n")
    from piezo_stage.launcher.launcher import LOCKSTEP_PROFILE, LOOPBACK_UDP_PROFILE
    env = {k: v for k, v in os.environ.items() if k not in (
        "RMW_FASTRTPS_PUBLICATION_MODE", "ROS_AUTOMATIC_DISCOVERY_RANGE")}
    real = Launch(str(rt), LaunchOptions(arm=False), env=env)  # the driver alone
    assert "RMW_FASTRTPS_PUBLICATION_MODE" not in real.env
    assert "RMW_FASTRTPS_PUBLICATION_MODE" not in real.node_env
    own = Launch(str(rt), LaunchOptions(
        arm=False), env=dict(env, RMW_FASTRTPS_PUBLICATION_MODE="ASYNCHRONOUS"))
    assert own.env["RMW_FASTRTPS_PUBLICATION_MODE"] == "ASYNCHRONOUS"
    # and off shared memory: a simulated set on this host gets LOCALHOST's discovery
    # over loopback UDP (rmw_fastrtps would add shared memory back under LOCALHOST)
    assert real.node_env["FASTRTPS_DEFAULT_PROFILES_FILE"] == LOOPBACK_UDP_PROFILE
    assert real.env["ROS_AUTOMATIC_DISCOVERY_RANGE"] == "SUBNET"
    lock = Launch(os.path.join(CONFIG, "stage.yaml"), env=env)
    assert "RMW_FASTRTPS_PUBLICATION_MODE" not in lock.env
    # lockstep: its transports as they were, the writers' heartbeat at 50 ms (the
    # driver's last wait for acknowledgements), a user's own profile left alone
    assert lock.node_env == {"FASTRTPS_DEFAULT_PROFILES_FILE": LOCKSTEP_PROFILE}
    assert lock.env["FASTRTPS_DEFAULT_PROFILES_FILE"] == LOCKSTEP_PROFILE
    assert lock.env["ROS_AUTOMATIC_DISCOVERY_RANGE"] == "LOCALHOST"
    own = Launch(os.path.join(CONFIG, "stage.yaml"),
                 env=dict(env, FASTRTPS_DEFAULT_PROFILES_FILE="/lab/profiles.xml"))
    assert own.node_env == {} and own.env["FASTRTPS_DEFAULT_PROFILES_FILE"] == \
        "/lab/profiles.xml"
    with open(LOCKSTEP_PROFILE) as fh:  # the file Fast DDS reads: the period as said
        assert "<heartbeatPeriod><sec>0</sec><nanosec>50000000</nanosec>" in fh.read()
    # real time too: with Fast DDS's 3 s the loop's topics were acknowledged in one burst
    # every 3 s, and the driver missed a tick or the commands came late right then
    with open(LOOPBACK_UDP_PROFILE) as fh:
        text = fh.read()
    assert '<publisher profile_name="piezo_stage_loopback_udp_writer" ' \
        'is_default_profile="true">' in text
    assert "<heartbeatPeriod><sec>0</sec><nanosec>50000000</nanosec>" in text


@pytest.mark.parametrize("given, wanted", [
    ({"ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST"}, "profile"),
    ({"ROS_LOCALHOST_ONLY": "1"}, "profile"),
    ({"ROS_AUTOMATIC_DISCOVERY_RANGE": "SUBNET"}, {"FASTDDS_BUILTIN_TRANSPORTS": "UDPv4"}),
    ({}, {"FASTDDS_BUILTIN_TRANSPORTS": "UDPv4"}),
    ({"ROS_AUTOMATIC_DISCOVERY_RANGE": "OFF"}, {}),
    ({"ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST",
      "FASTRTPS_DEFAULT_PROFILES_FILE": "/lab/own.xml"}, {}),
    ({"FASTDDS_BUILTIN_TRANSPORTS": "SHM"}, {}),
    ({"RMW_IMPLEMENTATION": "rmw_cyclonedds_cpp"}, {}),
])
def test_a_real_time_set_leaves_out_shared_memory_unless_told_otherwise(given, wanted):
    """The real-time transport choice on each discovery range, and a configuration of
    the user's own (a profiles file, FASTDDS_BUILTIN_TRANSPORTS, another RMW) kept."""
    from piezo_stage.launcher.launcher import LOOPBACK_UDP_PROFILE, realtime_transport_env
    if wanted == "profile":
        wanted = {"ROS_AUTOMATIC_DISCOVERY_RANGE": "SUBNET",
                  "FASTRTPS_DEFAULT_PROFILES_FILE": LOOPBACK_UDP_PROFILE}
        assert os.path.isfile(LOOPBACK_UDP_PROFILE)
    assert realtime_transport_env(given) == wanted


LOOPBACK_PROBE = """
import os, time, rclpy
from std_msgs.msg import String
def shm_mapped():  # this process's own shared-memory mappings (another test's do not count)
    with open("/proc/self/maps") as fh:
        return {line.split()[-1] for line in fh if "/dev/shm/" in line}
before = shm_mapped()
rclpy.init()
node = rclpy.create_node("transport_probe")
pub = node.create_publisher(String, "chatter", 10)
sub_seen = []
node.create_subscription(String, "chatter", lambda m: sub_seen.append(m.data), 10)
t0 = time.monotonic()
while not sub_seen and time.monotonic() - t0 < 10:
    pub.publish(String(data="x"))
    rclpy.spin_once(node, timeout_sec=0.05)
print(len(sub_seen) > 0, sorted(shm_mapped() - before))
node.destroy_node()
rclpy.try_shutdown()
"""


def test_the_loopback_udp_profile_talks_and_opens_no_shared_memory(ros_env):
    """A participant on the real-time set's profile (fastdds_loopback_udp.xml, the way
    the launcher applies it) creates no shared-memory segment or port, and still talks
    (its own subscription hears its publisher)."""
    pytest.importorskip("rclpy")
    from piezo_stage.launcher.launcher import realtime_transport_env
    env = dict(ros_env, **realtime_transport_env(ros_env))
    r = subprocess.run([sys.executable, "-c", LOOPBACK_PROBE], env=env,
                       capture_output=True, text=True, timeout=60)
    assert r.returncode == 0, r.stderr
    assert r.stdout.split("\n")[0] == "True []", r.stdout


PRIORITY_PROBE = """
import os, sys, rclpy
from std_msgs.msg import String
from piezo_stage.nodes._loop import set_realtime_priority
rclpy.init()
node = rclpy.create_node("priority_probe")
node.create_publisher(String, "chatter", 10)
class Log:
    def warning(self, text):
        print("WARN", text)
got = set_realtime_priority(int(sys.argv[1]), Log(), main_thread=sys.argv[2] == "1")
for tid in sorted(os.listdir("/proc/self/task")):
    name = open(f"/proc/self/task/{tid}/comm").read().strip()
    policy = os.sched_getscheduler(int(tid))
    prio = os.sched_getparam(int(tid)).sched_priority
    print(got, int(tid) == os.getpid(), name, int(policy == os.SCHED_FIFO), prio)
node.destroy_node()
rclpy.try_shutdown()
"""


@pytest.mark.parametrize("main_thread", [True, False])
def test_fast_dds_writer_threads_run_below_the_threads_that_hold_their_mutex(ros_env,
                                                                             main_thread):
    """Fast DDS's asynchronous writer threads poll a writer's mutex in a loop while
    another thread holds it: at that thread's own SCHED_FIFO priority two of them once
    filled both cores and the holder never ran again (a controller at 188 % CPU, deaf
    to signals, its launcher gone). They now sit one level below the node's other
    threads, or at normal priority where the main thread stays there (the recorder)."""
    pytest.importorskip("rclpy")
    env = dict(ros_env, RMW_FASTRTPS_PUBLICATION_MODE="ASYNCHRONOUS")
    r = subprocess.run([sys.executable, "-c", PRIORITY_PROBE, "45", str(int(main_thread))],
                       env=env, capture_output=True, text=True, timeout=60)
    assert r.returncode == 0, r.stderr
    rows = [line.split() for line in r.stdout.splitlines() if not line.startswith("WARN")]
    if "WARN" in r.stdout or rows[0][0] == "0":
        pytest.skip("SCHED_FIFO is not permitted here")
    asyn = [row for row in rows if row[2].startswith("dds.asyn")]
    rest = [row for row in rows if not row[2].startswith("dds.asyn") and
            (main_thread or row[1] == "False")]
    assert asyn and rest
    if main_thread:
        assert all(row[3:] == ["1", "44"] for row in asyn), asyn
    else:
        assert all(row[3] == "0" for row in asyn), asyn
        assert [row[3] for row in rows if row[1] == "True"] == ["0"]
    assert all(row[3:] == ["1", "45"] for row in rest), rest


A_SET_RUNNING = """
import sys, time, rclpy
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from piezo_stage.nodes._common import QOS_EVENTS
rclpy.init()
node = rclpy.create_node("stage_driver", namespace="/lookns")
pub = node.create_publisher(DiagnosticArray, "/lookns/state", QOS_EVENTS)
pub.publish(DiagnosticArray(status=[DiagnosticStatus(name="state", values=[
    KeyValue(key="host", value="labhost"), KeyValue(key="pid", value="4242")])]))
print("up", flush=True)
end = time.monotonic() + 60
while time.monotonic() < end and not sys.stdin.closed:
    rclpy.spin_once(node, timeout_sec=0.1)
"""


@pytest.mark.slow
def test_the_look_for_a_running_set_begun_early_names_it_or_answers_none(ros_env):
    """The one-set-per-namespace look a command begins before it reads its config
    (launcher/running.py's Look): it names a set whose driver announced itself, answers
    None on an empty namespace, ends at once when cancelled, and is used by the
    launch it was begun for (another namespace's is cancelled and looked for anew);
    its answer is in before its node leaves the graph."""
    pytest.importorskip("rclpy")
    from piezo_stage.launcher.launcher import Launch, LaunchOptions
    from piezo_stage.launcher.running import Look, begin_look, running_set
    d = int(ros_env["ROS_DOMAIN_ID"])
    p = subprocess.Popen([sys.executable, "-c", A_SET_RUNNING], env=ros_env, text=True,
                         stdin=subprocess.PIPE, stdout=subprocess.PIPE)
    try:
        assert p.stdout.readline().strip() == "up"
        # (30 s for the names to show: a loaded host's discovery; found, it answers then)
        assert Look("/lookns", d, wait_s=30.0).result() == "labhost, pid 4242"
        assert Look("/elsewhere", d).result() is None
        # the answer is reported before the look's node is torn down, as returned
        said: list = []
        assert running_set("/lookns", d, wait_s=30.0, report=said.append) == \
            "labhost, pid 4242" and said == ["labhost, pid 4242"]
    finally:
        p.kill()
        p.wait()
    look = Look("/elsewhere", d)
    look.cancel()
    assert look.done() and look.result() is None
    with begin_look("/stage", ros_env) as early:
        launch = Launch(os.path.join(CONFIG, "stage.yaml"), env=ros_env, look=early)
        assert launch._look_for_this_set() is early
        other = Launch(os.path.join(CONFIG, "stage.yaml"), LaunchOptions(
            namespace="/stage2"), env=ros_env, look=early)
        fresh = other._look_for_this_set()
        assert fresh is not early and fresh.namespace == "/stage2" and early.done()
        fresh.cancel()
    with begin_look("/stage", dict(ros_env, ROS_DOMAIN_ID="x")) as none:
        assert none is None


def test_every_override_the_launcher_writes_is_the_value_rcl_reads():
    """A node's overrides go on its command line as ``-p name:=VALUE`` rules, which rcl
    reads as YAML: the empty string (``model_file: ""`` in config/stage.yaml) was
    written ``model_file:=`` and refused, and "true" or "1.5" would have become a bool
    or a float. Each value here goes through rcl's own parser and comes back as given."""
    pytest.importorskip("rclpy")
    import rclpy
    from rclpy.context import Context

    from piezo_stage.launcher.launcher import _fmt
    values = {"empty": "", "word": "true", "number": "1.5", "quote": "it's",
              "colon": "a: b", "comma": "x,y", "path": "/lab/model.yaml", "hash": "a #b",
              "tilde": "~", "flag": False, "rate": 2000.0, "limits": [0.0, 150.0],
              "names": ["a", ""]}
    rules = [x for k, v in values.items() for x in ("-p", f"{k}:={_fmt(v)}")]
    ctx = Context()
    rclpy.init(args=["n", "--ros-args", *rules], context=ctx)
    try:
        node = rclpy.create_node("overrides", context=ctx, start_parameter_services=False,
                                 automatically_declare_parameters_from_overrides=True)
        got = {k: node.get_parameter(k).value for k in values}
        node.destroy_node()
    finally:
        rclpy.try_shutdown(context=ctx)
    assert {k: list(v) if isinstance(v, (list, tuple)) else v for k, v in got.items()} \
        == values


def test_a_look_whose_teardown_hangs_is_killed_and_the_launch_goes_on(tmp_path, ros_env):
    """Fast DDS can deadlock while it destroys a participant that is discovering others
    (launcher/running.py's Look): a look torn down in the launcher's own thread, while
    a set that had just ended left the domain, once froze the launcher at a whole CPU.
    The look is a process of its own: one that hangs after its answer (HANG_ENV, the
    deadlock's stand-in) is killed ``LOOK_TEARDOWN_S`` after it, and a launch beside
    it arms, runs and ends; no look process is left."""
    pytest.importorskip("rclpy")
    import time

    from piezo_stage.launcher.running import HANG_ENV, LOOK_TEARDOWN_S, Look
    d = int(ros_env["ROS_DOMAIN_ID"])
    old = os.environ.get(HANG_ENV)
    os.environ[HANG_ENV] = "1"
    try:
        look = Look("/hangs", d, wait_s=0.5)
    finally:
        if old is None:
            del os.environ[HANG_ENV]
    assert look.result() is None and look._proc.pid != os.getpid()
    t0 = time.monotonic()
    look.close()
    assert time.monotonic() - t0 < LOOK_TEARDOWN_S + 2.0
    assert look._proc.returncode == -signal.SIGKILL  # it hung: killed
    fine = Look("/hangs", d, wait_s=0.5)  # without the stand-in: it ends by itself
    assert fine.result() is None
    fine.close()
    assert fine._proc.returncode == 0
    r = subprocess.run([sys.executable, "-m", "piezo_stage.cli", "launch", "--duration",
                        "0.3"], env=dict(ros_env, **{HANG_ENV: "1"}), capture_output=True,
                       text=True, timeout=120)
    assert r.returncode == 0, r.stderr[-1500:]
    left = subprocess.run(["pgrep", "-f", f"piezo_stage.launcher.running /stage {d} "],
                          capture_output=True, text=True)
    assert left.stdout.strip() == "", left.stdout


@pytest.mark.parametrize("argv,code", [(["lifecycle", "stage_driver", "--timeout", "1"], 2),
                                       (["move", "1", "1", "--timeout", "1"], 4)])
def test_a_commands_teardown_that_hangs_ends_with_the_commands_own_code(ros_env, argv,
                                                                       code):
    """A command that talks to a set tears its participant down after its outcome is
    said, bounded (process/teardown.py): Fast DDS can deadlock there with the GIL held.
    One whose teardown hangs (HANG_ENV, the deadlock's stand-in) has said its line, says
    one more, and exits with its own code within the bound; one whose teardown ends
    says nothing of it."""
    import time

    from piezo_stage.process.signals import MIDDLEWARE_TEARDOWN_S
    from piezo_stage.process.teardown import HANG_ENV
    plain = subprocess.run([sys.executable, "-m", "piezo_stage.cli", *argv], env=ros_env,
                           capture_output=True, text=True, timeout=60)
    assert plain.returncode == code and "teardown" not in plain.stderr, plain.stderr
    t0 = time.monotonic()
    hung = subprocess.run([sys.executable, "-m", "piezo_stage", *argv],
                          env=dict(ros_env, **{HANG_ENV: "1"}), capture_output=True,
                          text=True, timeout=60)
    took = time.monotonic() - t0
    lines = hung.stderr.strip().splitlines()
    assert hung.returncode == code, hung.stderr
    assert lines[0] == plain.stderr.strip().splitlines()[0]  # its outcome, said first
    assert lines[-1].endswith(f"the middleware's teardown did not end within "
                              f"{MIDDLEWARE_TEARDOWN_S:g} s (Fast DDS); exited without it, "
                              f"with the command's code ({code})"), lines
    assert took < 1.0 + MIDDLEWARE_TEARDOWN_S + 20.0  # its own wait, the bound, start-up


def test_compose_is_a_launch_option_refused_in_one_line_when_unknown():
    r = cli("launch", "--compose", "bogus", "--duration", "1")
    one_line_exit_2(r)
    assert "--compose" in r.stderr and "bogus" in r.stderr


@pytest.mark.slow
@pytest.mark.parametrize("extra,says", [
    ([], "controller + feedforward + stage_driver composed in one process"),
    (["--compose", "none"], "each node in its own process"),
    # the whole config as overrides: its empty strings (model_file, plant_config) went
    # on the command line as '-p model_file:=', which rcl refused, and the set died
    (["--params", os.path.join(CONFIG, "stage.yaml")],
     "controller + feedforward + stage_driver composed in one process")])
def test_launch_compose_runs_the_loop_as_asked_and_says_so(tmp_path, ros_env, extra,
                                                           says):
    """`launch --compose` chooses which of the loop's nodes share a process (the
    launcher's COMPOSE): the first line names it, and the set apart (none) arms, runs
    its samples and ends as the composed one does."""
    bag = tmp_path / "bag"
    r = subprocess.run([sys.executable, "-m", "piezo_stage.cli", "launch", "--duration",
                        "0.5", "--record", str(bag), *extra], env=ros_env,
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr[-1500:]
    first = next(line for line in r.stdout.splitlines() if line.startswith("launch:"))
    assert f"; {says};" in first, first
    from piezo_stage.io.bag import iter_messages
    states = sum(1 for _ in iter_messages(str(bag), topics=["/stage/joint_states"]))
    assert states >= 500, states  # 0.5 s of samples at 1 kHz after arming, and more


@pytest.mark.slow
@pytest.mark.parametrize("argv", [["lifecycle", "stage_driver", "--timeout", "4"],
                                  ["move", "1", "1", "--timeout", "4"],
                                  ["scan", "--grid", "2,2", "--timeout", "4", "--out", "OUT"],
                                  ["look"]])
def test_commands_that_talk_to_a_set_open_no_shared_memory(ros_env, argv, tmp_path):
    """`lifecycle`, `move`, `scan` and a launch's look for a running set keep off Fast
    DDS's shared-memory transport (as a real-time set does): with stale shared-memory
    ports on a host, Fast DDS wrote its port errors into `lifecycle`'s output, whose
    lines a test compared (a CI-host flake), and a participant opening a port whose
    mutex a killed process left locked waited in create_node. Here no set runs, so each
    waits for one while its process's maps are read."""
    pytest.importorskip("rclpy")
    env = {k: v for k, v in ros_env.items() if k not in (
        "FASTRTPS_DEFAULT_PROFILES_FILE", "FASTDDS_BUILTIN_TRANSPORTS")}
    look = None
    if argv == ["look"]:  # the launcher's, a process of its own (launcher/running.py)
        from piezo_stage.launcher.running import Look
        old = dict(os.environ)
        os.environ.clear()
        os.environ.update(env)
        try:
            look = Look("/noset", int(env["ROS_DOMAIN_ID"]), wait_s=3.0)
        finally:
            os.environ.clear()
            os.environ.update(old)
        p = look._proc
    else:
        argv = [str(tmp_path / "scan.csv") if a == "OUT" else a for a in argv]
        p = subprocess.Popen([sys.executable, "-m", "piezo_stage.cli", *argv], env=env,
                             stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    import time
    seen, t0 = set(), time.monotonic()
    try:
        while p.poll() is None and time.monotonic() - t0 < 3.0:
            try:
                with open(f"/proc/{p.pid}/maps") as fh:
                    seen |= {ln.split()[-1] for ln in fh if "/dev/shm/fastrtps" in ln}
                libs = open(f"/proc/{p.pid}/maps").read()
            except OSError:
                break
            time.sleep(0.05)
        assert "librmw_fastrtps" in libs or "rmw_fastrtps" in libs, "no participant yet"
    finally:
        if look is not None:
            look.cancel()
        else:
            p.kill()
            p.communicate()
    assert not seen, seen


def test_the_suites_shared_memory_sweep_takes_only_what_no_process_holds(tmp_path):
    """conftest's sweep at the suite's start: a Fast DDS file that a process has open or
    mapped stays, as does one just made; one nobody holds goes; others are not its to
    judge."""
    import mmap

    from conftest import stale_fastdds_shm
    for name in ("fastrtps_open", "fastrtps_mapped", "fastrtps_port7000_el",
                 "sem.fastrtps_port7000_mutex", "lttng-ust-wait-6"):
        (tmp_path / name).write_bytes(b"\0" * 4096)
    for name in ("fastrtps_port7001", "sem.fastrtps_port7001_mutex"):
        (tmp_path / name).write_bytes(b"\0" * 4096)
    held = open(tmp_path / "fastrtps_open", "rb")
    port = open(tmp_path / "fastrtps_port7001", "rb")  # its mutex stays with it
    with open(tmp_path / "fastrtps_mapped", "r+b") as fh:
        mapped = mmap.mmap(fh.fileno(), 4096)
    try:
        assert stale_fastdds_shm(str(tmp_path), older_than_s=0.0) == [
            "fastrtps_port7000_el", "sem.fastrtps_port7000_mutex"]
        assert stale_fastdds_shm(str(tmp_path), older_than_s=60.0) == []  # just made
    finally:
        held.close()
        mapped.close()
        port.close()
    assert stale_fastdds_shm(str(tmp_path), older_than_s=0.0) == [
        "fastrtps_mapped", "fastrtps_open", "fastrtps_port7000_el", "fastrtps_port7001",
        "sem.fastrtps_port7000_mutex", "sem.fastrtps_port7001_mutex"]


@pytest.mark.slow
def test_a_short_runs_bag_ends_with_the_recorders_own_last_report(tmp_path, ros_env):
    """A lockstep run shorter than the 1 s diagnostics cadence: the recorder's report
    in its bag was the first one, made before the driver's state named the device
    ("stage /stage"; a flake of test_nodes' lockstep test). The recorder now writes its
    own last report into the bag as it finishes it: the last there counts every message
    before it and names the device."""
    from piezo_stage.io.bag import deserialize, iter_messages
    bag = tmp_path / "bag"
    r = subprocess.run([sys.executable, "-m", "piezo_stage.cli", "launch", "--duration",
                        "0.2", "--record", str(bag)], env=ros_env, capture_output=True,
                       text=True, timeout=120)
    assert r.returncode == 0, r.stderr[-1500:]
    total, last = 0, None
    for topic, _, _, data in iter_messages(str(bag)):
        total += 1
        if topic == "/diagnostics":
            for st in deserialize(data, "diagnostic_msgs/msg/DiagnosticArray").status:
                if st.name == "/stage/recorder: recording":
                    last = (total, st)
    assert last is not None
    at, st = last
    assert at == total, "messages after the recorder's last report"
    assert f": {total - 1} messages on " in st.message, (st.message, total)
    assert st.hardware_id.startswith("sim seed"), st.hardware_id


def test_the_command_lines_compositions_are_the_launchers():
    from piezo_stage.cli._common import COMPOSITIONS
    from piezo_stage.launcher.launcher import COMPOSE
    assert set(COMPOSITIONS) == set(COMPOSE)


@pytest.mark.parametrize("node, name, content, said", [
    ("feedforward", "model_file", "typo", "unknown key(s) ['ascendng'] (did you mean "
     "'ascending'?)"),
    ("feedforward", "model_file", None, "no such file or directory"),
    ("stage_driver", "plant_config", "typo", "not a plant config"),
    ("trajectory", "csv_path", "t,wx\n0,1\n", "missing column(s) wy"),
    ("recorder", "model_file", None, "no such file or directory"),
])
def test_every_file_a_set_reads_is_checked_before_any_node_starts(tmp_path, node, name,
                                                                 content, said):
    """A file a parameter names (a model, the plant, a trajectory CSV, a recorder's
    metadata file) that its node would refuse is refused before any node starts, in one
    line naming the node, the parameter and the file's own error, exit 2, as a
    misspelled parameter is (before: the launcher started the nodes and the set died
    with exit 1 on "fatal: ... unknown key(s) ['ascendng']")."""
    path = tmp_path / ("f.csv" if name == "csv_path" else "f.yaml")
    if content == "typo":
        path.write_text(open(MODEL).read().replace("ascending:  {alpha: 0.030",
                                                   "ascendng:  {alpha: 0.030"))
    elif content is not None:
        path.write_text(content)
    params = tmp_path / "p.yaml"
    extra = "    kind: csv\n" if node == "trajectory" else ""
    params.write_text(f"/**/{node}:\n  ros__parameters:\n    {name}: {path}\n{extra}")
    args = ["launch", "--params", params, "--duration", "5"]
    if node == "recorder":
        args += ["--record", tmp_path / "bag"]
    r = cli(*args)
    one_line_exit_2(r)
    assert f"{node}: {name}: {path}" in r.stderr and said in r.stderr, r.stderr
    assert not (tmp_path / "bag").exists()


@pytest.mark.parametrize("managed", [False, True])
def test_a_duration_counts_from_arming_managed_or_not(managed):
    """`launch --duration S` is S seconds of the stage's own samples from its first
    arming, whether the launcher or an outside manager (`--managed`) brings the driver
    up (with --managed it counted from the launch)."""
    from piezo_stage.launcher.launcher import Launch, LaunchOptions
    launch = Launch(os.path.join(CONFIG, "stage.yaml"), LaunchOptions(managed=managed, armed_s=5.0,
        exclusive=False))
    drv = launch.overrides["stage_driver"]
    assert launch.armed_s == 5.0 and drv["max_steps_from_arming"] is True
    assert drv["max_steps"] == int(round(5.0 * launch.rate_hz()))
