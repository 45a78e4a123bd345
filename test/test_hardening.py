"""Hostile and clumsy input: bounded parsing, strict validation, outputs that never
overwrite inputs, nodes that survive any well-typed message (issue 10)."""

import os
import signal
import subprocess
import sys

import numpy as np
import pytest

from conftest import CONFIG, ROOT
from piezo_stage.benchmarks.faults import ALIAS_BOMB, scaled_model
from piezo_stage.core.errors import DataError, ModelError
from piezo_stage.io.model_file import load_model, parse_yaml
from piezo_stage.io.run_bag import status_node

MODEL = os.path.join(CONFIG, "stage_model.yaml")
GOOD = open(MODEL).read()


def cli(*args, cwd=None):
    return subprocess.run([sys.executable, "-m", "piezo_stage.cli", *map(str, args)],
                          capture_output=True, text=True, timeout=120, cwd=cwd or ROOT)


def one_line_exit_2(r):
    assert r.returncode == 2, (r.returncode, r.stderr[-500:])
    assert len(r.stderr.strip().splitlines()) == 1, r.stderr
    assert "Traceback" not in r.stderr


BOMB = ALIAS_BOMB


def test_yaml_alias_bomb_is_refused_at_once(tmp_path):
    bomb = tmp_path / "bomb.yaml"
    bomb.write_text(BOMB)
    with pytest.raises(ModelError, match="aliases"):  # refused, not expanded
        load_model(bomb)
    with pytest.raises(ModelError, match="bytes"):
        parse_yaml("x: 1\n" * 20000, "message", max_bytes=65536)


@pytest.mark.parametrize("edit, why", [
    (lambda t: t.replace("g: [0.36, 0.0006]", "g: [1.0e300, 0.0006]"), "um/V"),
    (lambda t: t.replace("voltage_limits_V: [0.0, 150.0]", "voltage_limits_V: [0, 150, 3]"),
     "min, max"),
    (lambda t: t.replace("voltage_limits_V: [0.0, 150.0]", "voltage_limits_V: [150, 0]"),
     "min < max"),
    (lambda t: t.replace("alpha: 0.030", "alpha: true"), "number"),
])
def test_model_files_are_validated(tmp_path, edit, why):
    assert "voltage_limits_V: [0.0, 150.0]" in GOOD
    bad = tmp_path / "bad.yaml"
    bad.write_text(edit(GOOD))
    with pytest.raises(ModelError, match=why):
        load_model(bad)


def test_a_polynomial_that_overflows_is_refused(tmp_path):
    import yaml
    doc = yaml.safe_load(GOOD)
    ax = doc["axes"]["x"]
    branch = ax["ascending"] if "ascending" in ax else ax
    branch.pop("f", None), branch.pop("g", None)
    branch["h"] = [1.0] * 2000
    bad = tmp_path / "big.yaml"
    bad.write_text(yaml.safe_dump(doc))
    with pytest.raises(ModelError, match="finite"):
        load_model(bad)


def test_outputs_never_overwrite_inputs_and_must_be_writable(tmp_path):
    volts = tmp_path / "v.csv"
    volts.write_text("t,vx,vy\n" + "".join(f"{k * 1e-3},{k % 50},{0}\n" for k in range(200)))
    before = volts.read_text()
    one_line_exit_2(cli("simulate", "--in", volts, "--out", volts))
    assert volts.read_text() == before
    one_line_exit_2(cli("invert", "--model", MODEL, "--in", volts, "--out", MODEL))
    one_line_exit_2(cli("identify", volts, "--out", volts))
    one_line_exit_2(cli("simulate", "--in", volts, "--out", tmp_path))  # a directory
    locked = tmp_path / "locked"
    locked.mkdir(mode=0o500)
    if not os.access(locked, os.W_OK):  # (root may write anyway)
        one_line_exit_2(cli("simulate", "--in", volts, "--out", locked / "o.csv"))


def test_missing_axis_and_divergent_output_are_errors_not_silent(tmp_path):
    import yaml
    doc = yaml.safe_load(GOOD)
    del doc["axes"]["y"]
    xonly = tmp_path / "x.yaml"
    xonly.write_text(yaml.safe_dump(doc))
    target = tmp_path / "w.csv"
    target.write_text("t,wx,wy\n" + "".join(f"{k * 1e-3},10,10\n" for k in range(50)))
    r = cli("invert", "--model", xonly, "--in", target, "--out", tmp_path / "v.csv")
    one_line_exit_2(r)
    assert "axis y" in r.stderr and not (tmp_path / "v.csv").exists()


@pytest.mark.parametrize("line, why", [("internal_rate_hz: 1.0e9", "internal_rate_hz"),
                                       ("effects: {delay: {enabled: true, delay_s: 1.0e6}}",
                                        "delay_s"),
                                       ("effects: {delay: {enabled: 'yes'}}", "enabled")])
def test_plant_configs_are_range_checked(tmp_path, line, why):
    cfg = tmp_path / "plant.yaml"
    cfg.write_text(f"piezo_stage_plant: 1\nmodel: {MODEL}\n{line}\n")
    volts = tmp_path / "v.csv"
    volts.write_text("t,vx,vy\n0,0,0\n0.001,1,1\n0.002,2,2\n")
    r = cli("simulate", "--in", volts, "--out", tmp_path / "o.csv", "--config", cfg)
    one_line_exit_2(r)
    assert why in r.stderr


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
    from piezo_stage.launch.launcher import Launch
    cfg = os.path.join(CONFIG, "stage.yaml")
    rec = None if record is None else str(tmp_path / record)
    plain = Launch(cfg, record=rec)._gates()
    watched = Launch(cfg, record=rec, foxglove_port=0)._gates()
    for node, gates in plain.items():
        for key in ("min_subscribers", "min_record_subscribers"):
            if key in gates:
                # the trajectory node's one subscriber is the feedforward (the taps take
                # the trajectory the feedforward accepted)
                more = 0 if node == "trajectory" else 1
                assert watched[node][key] == gates[key] + more, (node, key)

def test_trajectory_messages_are_checked_point_by_point():
    pytest.importorskip("trajectory_msgs")
    from builtin_interfaces.msg import Duration
    from trajectory_msgs.msg import JointTrajectory, JointTrajectoryPoint

    import piezo_stage_msgs_adapters as A

    def traj(names, points):
        return JointTrajectory(joint_names=names, points=[JointTrajectoryPoint(
            positions=p, time_from_start=Duration(sec=s, nanosec=0)) for s, p in points])
    with pytest.raises(DataError, match="point 1 has 1 positions"):
        A.trajectory_from_msg(traj(["x", "y"], [(0, [1e-6, 1e-6]), (1, [1e-6])]))
    with pytest.raises(DataError, match="repeat"):
        A.trajectory_from_msg(traj(["x", "x"], [(0, [1e-6, 1e-6])]))
    with pytest.raises(DataError, match="negative"):
        A.trajectory_from_msg(traj(["x"], [(-1, [1e-6]), (1, [1e-6])]))
    with pytest.raises(DataError, match="more than"):
        A.trajectory_from_msg(traj(["x"], [(k, [1e-6]) for k in range(11)]), max_points=10)


@pytest.mark.slow
def test_nodes_survive_malformed_messages_and_keep_their_model(tmp_path, ros_env):
    """An outside node sends a ragged trajectory, foreign and ragged JointStates, an
    alias bomb, a one-axis model and an absurd one: the feedforward and the identifier
    keep running, count them, and the feedforward keeps its model."""
    pytest.importorskip("rclpy")
    from diagnostic_msgs.msg import DiagnosticArray
    from sensor_msgs.msg import JointState
    from std_msgs.msg import String
    from trajectory_msgs.msg import JointTrajectory, JointTrajectoryPoint

    from piezo_stage.nodes._common import QOS_DATA, QOS_EVENTS
    from ros_probe import Probe
    env = ros_env
    d = int(env["ROS_DOMAIN_ID"])
    procs = [subprocess.Popen([sys.executable, "-m", f"piezo_stage.nodes.{n}_node",
                               "--ros-args", "-r", "__ns:=/stage", *extra], env=env)
             for n, extra in (("feedforward", ["-p", f"model_file:={MODEL}", "-p",
                                               "max_trajectory_points:=1000"]),
                              ("identifier", []),
                              ("recorder", ["-p", f"output:={tmp_path / 'bag'}"]))]
    probe = Probe(d)
    try:
        diag = {}
        probe.node.create_subscription(DiagnosticArray, "/diagnostics", lambda m: diag.update(
            {status_node(st.name): {kv.key: kv.value for kv in st.values}
             for st in m.status}), 10)
        js = probe.node.create_publisher(JointState, "/stage/joint_states", QOS_DATA)
        tr = probe.node.create_publisher(JointTrajectory, "/stage/trajectory", 10)
        # (keep last 20: nine models a little apart, none overwritten before it is taken)
        mo = probe.node.create_publisher(String, "/stage/model", QOS_EVENTS)
        # both nodes up (their diagnostics) and matched: the count alone can be reached
        # by the feedforward's own subscriptions before the identifier's has matched
        # (joint_states: the feedforward, the identifier and the recorder, all three)
        assert probe.wait(lambda: js.get_subscription_count() >= 3 and
                          tr.get_subscription_count() >= 1 and
                          mo.get_subscription_count() >= 1 and
                          {"feedforward", "identifier"} <= set(diag), 60), sorted(diag)
        probe.spin(1.0)  # both ends of each match established
        for _ in range(3):
            js.publish(JointState(name=["a", "b"], position=[1.0, 2.0]))
            js.publish(JointState(name=["x", "y"], position=[1e-6]))
            probe.spin(0.1)
        tr.publish(JointTrajectory(joint_names=["x", "y"], points=[
            JointTrajectoryPoint(positions=[1e-6])]))
        import piezo_stage_msgs_adapters as A
        tr.publish(A.trajectory_msg(np.arange(5000) * 1e-3, {"x": np.full(5000, 10.0),
                                                             "y": np.full(5000, 10.0)}))
        js.publish(JointState(name=["x", "y", "x"], position=[1e-6, 1e-6, 9e-6],
                              effort=[1.0, 1.0, 1.0]))
        for sec in (-1, 10 ** 6):  # before 1970; 10^15 ns ahead: counted, nobody dies
            m = JointState(name=["x", "y"], position=[1e-6, 1e-6], effort=[1.0, 1.0])
            m.header.stamp.sec = sec
            js.publish(m)
        import yaml
        xonly = yaml.safe_load(GOOD)
        del xonly["axes"]["y"]
        from rclpy.serialization import serialize_message
        whole = serialize_message(A.trajectory_msg(np.arange(50) * 1e-3,
                                                   {"x": np.full(50, 10.0),
                                                    "y": np.full(50, 10.0)}))
        tr.publish(whole[:len(whole) // 2])  # truncated CDR: refused, not fatal
        hostile = [BOMB, yaml.safe_dump(xonly),
                   GOOD.replace("g: [0.36, 0.0006]", "g: [1.0e300, 0.0006]"),
                   "[" * 20000 + "]" * 20000,                       # nested 20,000 deep
                   GOOD + "effects: {dynamics: {f_hz: 1.0e-9, zeta: -1}}\n",
                   GOOD + "effects: {delay: {delay_s: 1.0e9}}\n",
                   GOOD + "effects: {dynamics: {kind: resonance, fn_hz: 800, zeta: -1}}\n",
                   scaled_model(GOOD, 0.001), scaled_model(GOOD, -1.0)]
        # one at a time: the feedforward keeps the newest model message only (a model
        # overwritten by a newer one before it was taken is not taken)
        for k, text in enumerate(hostile, 1):
            mo.publish(String(data=text))
            assert probe.wait(lambda: int(diag.get("feedforward", {}).get(
                "rejected_models", 0)) >= k, 30), (k, diag.get("feedforward"))
        assert probe.wait(lambda: int(diag.get("identifier", {}).get("bad_messages", 0)) >= 2,
                          30), sorted(diag.get("identifier", {}).items())
        ff = diag["feedforward"]
        assert probe.wait(lambda: int(diag["feedforward"]["rejected_trajectories"]) >= 3,
                          30)  # ragged, over max_trajectory_points, truncated
        assert int(diag["identifier"]["bad_messages"]) >= 3  # the repeated joint too
        ff = diag["feedforward"]
        assert ff["model"] == MODEL
        assert probe.wait(lambda: int(diag.get("recorder", {}).get("bad_stamps", 0)) >= 1,
                          30), diag.get("recorder")
        assert all(p.poll() is None for p in procs)  # nobody died
    finally:
        probe.close()
        for p in procs:
            p.send_signal(signal.SIGINT)
        for p in procs:
            assert p.wait(30) == 130  # a stop by a signal: an ended run, said so


def test_csv_with_a_byte_order_mark_or_semicolons_reads(tmp_path):
    from piezo_stage.io.csv_table import read_table
    a = tmp_path / "bom.csv"
    a.write_bytes("\ufefft,vx,vy\n0,1,2\n0.001,1,2\n".encode("utf-8"))
    b = tmp_path / "semi.csv"
    b.write_text("t;vx;vy\n0;1;2\n0.001;1;2\n")
    for p in (a, b):
        cols = read_table(p, ["t", "vx", "vy"])
        np.testing.assert_array_equal(cols["vy"], [2.0, 2.0])


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


@pytest.mark.parametrize("effects, why", [
    ({"dynamics": {"f_hz": 1e-9, "zeta": -1}}, "unknown parameter"),
    ({"delay": {"delay_s": 1e9}}, "delay_s"),
    ({"dynamics": {"kind": "resonance", "fn_hz": 800, "zeta": -1}}, "zeta"),
    ({"creep": {"gamma": 0.03, "tau_s": [0.1] * 20}}, "time constants"),
    ({"warp": {}}, "unknown effect"),
    ({"delay": {"delay_s": 1e-3, "axes": ["z"]}}, "axes"),
])
def test_every_effect_key_and_range_is_checked(effects, why):
    import yaml

    from piezo_stage.core.errors import ModelError
    from piezo_stage.io.model_file import model_from_dict
    doc = yaml.safe_load(GOOD)
    doc["effects"] = effects
    with pytest.raises(ModelError, match=why):
        model_from_dict(doc)


@pytest.mark.parametrize("k", [0.001, -1.0, 2.5])
def test_an_implausible_model_change_is_refused(k):
    import yaml

    from piezo_stage.core.duhem import check_model_change
    from piezo_stage.core.errors import ModelError
    from piezo_stage.io.model_file import model_from_dict
    running, _ = model_from_dict(yaml.safe_load(GOOD))
    new, _ = model_from_dict(yaml.safe_load(scaled_model(GOOD, k)))
    with pytest.raises(ModelError, match="stroke"):
        check_model_change(new, running, 100.0)
    check_model_change(running, running, 100.0)  # the same stage again: fine
    same, _ = model_from_dict(yaml.safe_load(scaled_model(GOOD, 1.2)))
    check_model_change(same, running, 100.0)  # a refit 20 % off: fine


def test_deeply_nested_yaml_is_one_line_exit_2(tmp_path):
    deep = tmp_path / "deep.yaml"
    deep.write_text("[" * 20000 + "]" * 20000)
    inp = tmp_path / "v.csv"
    inp.write_text("t,vx,vy\n0,0,0\n0.001,1,1\n")
    out = tmp_path / "w.csv"
    for args in (["simulate", "--in", inp, "--out", out, "--model", deep],
                 ["simulate", "--in", inp, "--out", out, "--config", deep],
                 ["launch", deep, "--duration", "1"]):
        r = cli(*args)
        assert r.returncode == 2, (args, r.stderr[-300:])
        assert "nested deeper" in r.stderr and len(r.stderr.strip().splitlines()) == 1


@pytest.mark.parametrize("args", [
    ["excite", "--rate", "0"], ["excite", "--rate", "-5"], ["excite", "--rate", "nan"],
    ["excite", "--rate", "inf"], ["excite", "--rate", "1e9"], ["loop", "--freq", "0"],
    ["loop", "--freq", "nan"], ["loop", "--cycles", "-1"], ["tune", "--latency", "inf"],
    ["launch", "--duration", "-1"], ["replay", "x", "--rate", "-0.5"],
])
def test_numeric_arguments_are_range_checked(args, tmp_path):
    out = ["--out", tmp_path / "o.csv"] if args[0] == "excite" else []
    r = cli(*args, *out, cwd=tmp_path)
    assert r.returncode == 2 and len(r.stderr.strip().splitlines()) == 1, r.stderr
    assert "outside" in r.stderr and "Traceback" not in r.stderr


def test_devices_are_neither_read_nor_replaced(tmp_path):
    import stat
    inp = tmp_path / "v.csv"
    inp.write_text("t,vx,vy\n0,0,0\n0.001,1,1\n")
    r = cli("simulate", "--in", "/dev/zero", "--out", tmp_path / "o.csv")
    assert r.returncode == 2 and "not a regular file" in r.stderr
    r = cli("simulate", "--in", inp, "--out", "/dev/null")
    assert r.returncode == 2 and "not a regular file" in r.stderr
    assert stat.S_ISCHR(os.stat("/dev/null").st_mode)  # still the device


def test_echoed_text_is_escaped_and_cut(tmp_path):
    esc = tmp_path / "esc.csv"
    esc.write_text("\x1b[31mtime\x1b[0m,vx,vy\n0,0,0\n")
    r = cli("simulate", "--in", esc, "--out", tmp_path / "o.csv")
    assert r.returncode == 2 and "\x1b" not in r.stderr and "\\x1b" in r.stderr
    binary = tmp_path / "bin.csv"
    binary.write_bytes(bytes(range(1, 256)) * 400)  # 100 kB, no newline
    r = cli("simulate", "--in", binary, "--out", tmp_path / "o.csv")
    assert r.returncode == 2 and len(r.stderr.strip().splitlines()) == 1
    assert len(r.stderr) < 700, len(r.stderr)


def test_trajectory_parameters_the_loop_cannot_follow_are_refused():
    from piezo_stage.core.errors import ConfigError
    from piezo_stage.core.trajectory import generate
    with pytest.raises(ConfigError, match="Nyquist"):
        generate("sine", 1.0, 1e-3, 1e9)
    with pytest.raises(ConfigError, match="points"):
        generate("sine", 1e6, 1e-3, 10.0)
    t, w = generate("sine", 1.0, 1e-3, 500.0)  # two points a period: still taken
    assert len(t) == 1001


def test_use_sim_time_on_a_real_time_set_is_refused(tmp_path):
    from piezo_stage.core.errors import ConfigError
    from piezo_stage.launch.launcher import Launch
    cfg = tmp_path / "rt.yaml"
    cfg.write_text("/**/stage_driver:\n  ros__parameters:\n    mode: realtime\n"
                   "/**/controller:\n  ros__parameters:\n    use_sim_time: true\n")
    with pytest.raises(ConfigError, match="use_sim_time on controller"):
        Launch(str(cfg))
    r = cli("launch", cfg, "--duration", "1")
    assert r.returncode == 2 and "use_sim_time" in r.stderr


@pytest.mark.parametrize("plays, why", [
    ({"thresholds_V": [0, 10], "weights_um_per_V": [0.1]}, "same length"),
    ({"thresholds_V": [-1, 10], "weights_um_per_V": [0.1, 0.1]}, ">= 0"),
    ({"thresholds_V": [0, 10], "weights_um_per_V": [0.1, float("nan")]}, "not finite"),
    ({"thresholds_V": list(range(201)), "weights_um_per_V": [0.0] * 201}, "more than 200"),
    ({"thresholds_V": [0, 10], "weights_um_per_V": [1e4, 1e4]}, "weights sum"),
    ({"thresholds_V": [0, 10]}, "missing weights_um_per_V"),
    ({"thresholds_V": [0], "weights_um_per_V": [0.1], "start": 1}, "unknown key"),
])
def test_play_operators_in_a_model_file_are_checked(plays, why):
    """A model file's play operators (return-point memory) round-trip through the
    document, and a bad block is refused naming the key."""
    import yaml

    from piezo_stage.core.errors import ModelError
    from piezo_stage.io.model_file import model_from_dict, model_to_dict
    doc = yaml.safe_load(GOOD)
    doc["axes"]["x"]["play_operators"] = {"thresholds_V": [0.0, 20.0],
                                          "weights_um_per_V": [0.05, -0.01]}
    model, _ = model_from_dict(doc)
    p = model.plays["x"]
    assert list(p.initial_V) == [model.axes["x"].initial.v] * 2  # at rest by default
    again, _ = model_from_dict(yaml.safe_load(yaml.safe_dump(model_to_dict(model))))
    assert again.plays == model.plays and "y" not in again.plays
    doc["axes"]["x"]["play_operators"] = plays
    with pytest.raises(ModelError, match=why):
        model_from_dict(doc)


def test_real_time_sets_publish_asynchronously_and_lockstep_does_not(tmp_path):
    """In real time Fast DDS publishes from its own thread (a publish hands off rather
    than sends); lockstep keeps the synchronous mode its byte-identical reruns were
    measured with."""
    from piezo_stage.launch.launcher import Launch
    rt = tmp_path / "rt.yaml"
    rt.write_text("/**/stage_driver:\n  ros__parameters:\n    mode: realtime\n")
    from piezo_stage.launch.launcher import LOCKSTEP_PROFILE, LOOPBACK_UDP_PROFILE
    env = {k: v for k, v in os.environ.items() if k not in (
        "RMW_FASTRTPS_PUBLICATION_MODE", "ROS_AUTOMATIC_DISCOVERY_RANGE")}
    real = Launch(str(rt), env=env, arm=False)  # the driver alone
    assert real.env["RMW_FASTRTPS_PUBLICATION_MODE"] == "ASYNCHRONOUS"
    assert real.node_env["RMW_FASTRTPS_PUBLICATION_MODE"] == "ASYNCHRONOUS"
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
    from piezo_stage.launch.launcher import LOOPBACK_UDP_PROFILE, realtime_transport_env
    if wanted == "profile":
        wanted = {"ROS_AUTOMATIC_DISCOVERY_RANGE": "SUBNET",
                  "FASTRTPS_DEFAULT_PROFILES_FILE": LOOPBACK_UDP_PROFILE}
        assert os.path.isfile(LOOPBACK_UDP_PROFILE)
    assert realtime_transport_env(given) == wanted


LOOPBACK_PROBE = """
import os, time, rclpy
from std_msgs.msg import String
before = set(os.listdir("/dev/shm"))
rclpy.init()
node = rclpy.create_node("transport_probe")
pub = node.create_publisher(String, "chatter", 10)
sub_seen = []
node.create_subscription(String, "chatter", lambda m: sub_seen.append(m.data), 10)
t0 = time.monotonic()
while not sub_seen and time.monotonic() - t0 < 10:
    pub.publish(String(data="x"))
    rclpy.spin_once(node, timeout_sec=0.05)
print(len(sub_seen) > 0, sorted(set(os.listdir("/dev/shm")) - before))
node.destroy_node()
rclpy.try_shutdown()
"""


def test_the_loopback_udp_profile_talks_and_opens_no_shared_memory(ros_env):
    """A participant on the real-time set's profile (fastdds_loopback_udp.xml, the way
    the launcher applies it) creates no shared-memory segment or port, and still talks
    (its own subscription hears its publisher)."""
    pytest.importorskip("rclpy")
    from piezo_stage.launch.launcher import realtime_transport_env
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


HEAP_PROBE = """
import resource, sys
from piezo_stage.nodes._loop import reserve_heap
class Log:
    def warning(self, m): print("WARN", m)
if sys.argv[1] == "1":
    assert reserve_heap(64 << 20, Log()) == 64 << 20
wire = b"\\1" * (24 << 20)
faults = []
for _ in range(3):  # a 24 MB message taken three times: copied, as rclpy takes one
    before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
    taken = bytearray(wire)
    faults.append(resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before)
    del taken
print(*faults)
"""


@pytest.mark.parametrize("reserved", [False, True])
def test_a_reserved_heap_takes_a_large_message_without_page_faults(reserved):
    """rclpy takes a message with the GIL held; on fresh pages a 11.2 MB trajectory
    held the feedforward's loop 20-25 ms (a stale-command fault at 50 ms), on faulted
    ones 1-2 ms. In real time the feedforward reserves its heap (nodes/_loop.py
    reserve_heap): a message up to the reserve then costs no page fault, from the
    first take on."""
    r = subprocess.run([sys.executable, "-c", HEAP_PROBE, str(int(reserved))],
                       capture_output=True, text=True, timeout=60)
    assert r.returncode == 0, r.stderr
    if r.stdout.startswith("WARN"):
        pytest.skip(r.stdout.strip())
    faults = [int(x) for x in r.stdout.split()]
    pages = (24 << 20) // 4096
    if reserved:
        assert max(faults) < pages // 20, faults  # (a few for the allocator's own)
    else:  # glibc maps a block this large afresh: every page of the first take faults
        assert faults[0] > pages // 2, faults


def test_the_trajectory_byte_bound_admits_every_valid_layout_and_no_more():
    """The size check runs on the bytes before anything is decoded: a valid trajectory
    of max points (velocities, accelerations, efforts on every point) passes, one point
    more of the same layout does not."""
    pytest.importorskip("trajectory_msgs")
    from rclpy.serialization import serialize_message
    from trajectory_msgs.msg import JointTrajectory, JointTrajectoryPoint

    import piezo_stage_msgs_adapters as A
    full = [1e-6, 1e-6]
    pt = JointTrajectoryPoint(positions=full, velocities=full, accelerations=full,
                              effort=full)
    n = 1000
    msg = JointTrajectory(joint_names=["x", "y"], points=[pt] * n)
    msg.header.frame_id = "f" * 60000
    data = serialize_message(msg)
    A.check_trajectory_size(data, n)
    per_point = (len(serialize_message(JointTrajectory(joint_names=["x", "y"],
                                                       points=[pt] * (n + 1)))) -
                 len(serialize_message(JointTrajectory(joint_names=["x", "y"],
                                                       points=[pt] * n))))
    assert per_point <= A.convert.POINT_BYTES
    with pytest.raises(DataError, match="bytes, more than"):
        A.check_trajectory_size(b"\0" * (A.trajectory_max_bytes(n) + 1), n)
