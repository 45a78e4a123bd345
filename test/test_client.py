"""Moves through the node set, asked from other processes: `piezo-stage move`, `scan` and
the Python client (piezo_stage.client) against a running set, in lockstep and in real
time at this host's rate; their errors (no stage, a refused target, a timeout, a
disarmed stage) each one line with its own exit code."""

import csv
import os
import subprocess
import sys

import numpy as np
import pytest

pytest.importorskip("rclpy")
from conftest import CONFIG, realtime_twice  # noqa: E402
from piezo_stage.launcher.launcher import Launch, LaunchOptions  # noqa: E402

MODEL = os.path.join(CONFIG, "stage_model.yaml")
STAGE = os.path.join(CONFIG, "stage.yaml")


def _cli(env, *args, timeout=120):
    return subprocess.run([sys.executable, "-m", "piezo_stage", *args], env=env,
                          capture_output=True, text=True, timeout=timeout)


def _set(tmp_path, env, mode, rate=None, record=None):
    o = {"stage_driver": {"mode": mode, "min_margin": 0.0},
         "feedforward": {"model_file": MODEL}}
    return Launch(STAGE, LaunchOptions(record=record, overrides=o, trajectory=False,
        exclusive=False, rate=rate), env=env), rate or 1000.0


def _one_line(r, code, said):
    assert r.returncode == code, (r.returncode, r.stdout, r.stderr)
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and said in lines[0], r.stderr


@pytest.mark.slow
@pytest.mark.parametrize("mode", ["lockstep",
                                  pytest.param("realtime", marks=pytest.mark.realtime)])
def test_move_scan_and_the_client_against_a_running_set(tmp_path, ros_env, ros_domains,
                                                        mode):
    """Real time on a shared 2-core VM: a run the host stalls (a pause of tens of ms
    faults the set on stale commands) is run once more on a fresh domain, at the rate
    the host holds then (conftest.realtime_twice); two failures fail."""
    if mode == "lockstep":
        _client_run(tmp_path, ros_env, mode)
        return
    from piezo_stage.client import StageError
    realtime_twice(lambda env, rate, which: _client_run(tmp_path / which, env, mode, rate),
                   ros_env, ros_domains, (AssertionError, StageError), "the client")


def _client_run(tmp_path, env, mode, rate=None):
    from piezo_stage.client import MoveRefused, MoveTimeout, Stage
    from piezo_stage.io.run_bag import read_run
    tmp_path.mkdir(exist_ok=True)
    launch, rate = _set(tmp_path, env, mode, rate)
    try:
        launch.start()
        # `move` from another process: on target, its settle time and final error
        r = _cli(env, "move", "30", "20", "--timeout", "30")
        assert r.returncode == 0, (r.stdout, r.stderr)
        assert r.stdout.startswith("on target at (30, 20) um: settled in "), r.stdout
        r = _cli(env, "move", "35", "25", "--tol-um", "0.2", "--settle-ms", "10")
        assert r.returncode == 0 and "on target at (35, 25) um" in r.stdout, r

        # the client, in this process (as a notebook holds it)
        os.environ["ROS_DOMAIN_ID"] = env["ROS_DOMAIN_ID"]
        with Stage(domain_id=int(env["ROS_DOMAIN_ID"])) as stage:
            x, y = stage.position()
            assert abs(x - 35) < 0.6 and abs(y - 25) < 0.6, (x, y)
            assert stage.state() == "armed"
            done = stage.move_to(50.0, 40.0, tol_um=0.25, settle_ms=5.0, timeout=30)
            assert 0 < done.settle_s < 1.0, done
            assert all(abs(e) <= 0.25 for e in done.error_um.values()), done
            dw = stage.dwell(0.05, done.stamp_ns)
            assert dw.samples >= 0.05 * rate * 0.9, dw
            assert abs(dw.mean_um["x"] - 50) < 0.25 and abs(dw.mean_um["y"] - 40) < 0.25
            assert 0.03 < dw.std_um["x"] < 0.3  # the sensor's noise, at rest
            with pytest.raises(MoveRefused, match="outside the stage range"):
                stage.move_to(500.0, 40.0, timeout=10)
            with pytest.raises(MoveTimeout, match="not on target within 1 s"):
                stage.move_to(45.0, 40.0, tol_um=1e-4, timeout=1.0)
            stage.configure(tol_um=0.3, settle_ms=5.0)  # back to the defaults
            bag = str(tmp_path / "client_bag")
            t = np.arange(0.0, 0.5, 1e-3)
            with stage.record(bag):
                waited = stage.run(t, {"x": 40 + 5 * np.sin(2 * np.pi * 2 * t),
                                       "y": np.full(t.size, 40.0)}, timeout=60)
            assert waited >= 0.0
        run = read_run(bag)
        assert len(run.t_ns) > 0.5 * rate * 0.5
        desired = np.array(list(run.desired_um.values()))
        assert np.abs(desired[:, 0] - 40).max() > 4.5  # the sine is in the bag

        # a step scan: its points beside its bag, each at rest on its target
        scan_bag = str(tmp_path / "scan")
        r = _cli(env, "scan", "--grid", "3,2", "--size", "4,4", "--center", "40,40",
                 "--dwell-ms", "20", "--record", scan_bag)
        assert r.returncode == 0, (r.stdout, r.stderr)
        with open(scan_bag + ".points.csv") as fh:
            rows = list(csv.DictReader(fh))
        assert [(float(p["x_um"]), float(p["y_um"])) for p in rows] == [
            (38, 38), (40, 38), (42, 38), (42, 42), (40, 42), (38, 42)]
        for p in rows:
            assert abs(float(p["x_mean_um"]) - float(p["x_um"])) < 0.3, p
            assert float(p["settle_ms"]) > 0 and int(p["samples"]) > 0, p
        assert os.path.isdir(scan_bag)

        # the errors: a refused target (2), a disarmed stage (1)
        _one_line(_cli(env, "move", "500", "0"), 2, "outside the stage range")
        from std_srvs.srv import SetBool
        with Stage(domain_id=int(env["ROS_DOMAIN_ID"])) as stage:
            cli = stage.node.create_client(SetBool, "/stage/arm")
            assert cli.wait_for_service(timeout_sec=10)
            fut = cli.call_async(SetBool.Request(data=False))
            assert stage._wait(fut.done, 10) and fut.result().success
            assert stage._wait(lambda: stage.state() == "disarmed", 10)
        _one_line(_cli(env, "move", "40", "40"), 1, "disarmed")
        _one_line(_cli(env, "scan", "--grid", "2,1", "--out", str(tmp_path / "s.csv")), 1,
                  "point 1 of 2")
    finally:
        launch.stop()
    # no stage: exit 4, one line
    _one_line(_cli(env, "move", "1", "2", "--timeout", "2"), 4, "no stage at /stage")


def test_no_stage_is_said_once_discovery_had_its_time_not_after_the_timeout(ros_env):
    """`move` where no set runs: exit 4, one line, once discovery had its seconds (a
    set's nodes announce themselves twice a second), not after the move's whole
    timeout (it took the 10 s default to say so)."""
    import time
    t0 = time.monotonic()
    _one_line(_cli(ros_env, "move", "1", "2", "--timeout", "60"), 4, "no stage at /stage")
    assert time.monotonic() - t0 < 30.0  # (DISCOVERY_S and a start, not 60 s)


def test_move_and_scan_refuse_bad_input_before_any_stage(tmp_path, ros_env):
    _one_line(_cli(ros_env, "move", "1"), 2, "")
    _one_line(_cli(ros_env, "move", "1", "2", "--tol-um", "0"), 2, "--tol-um")
    _one_line(_cli(ros_env, "scan", "--grid", "0,3"), 2, "--grid")
    _one_line(_cli(ros_env, "scan", "--out", "/dev/null"), 2, "not a regular file")


def test_scan_points_are_a_serpentine():
    from piezo_stage.cli.scan import points
    assert points((3, 2), (4, 2), (10, 20)) == [(8, 19), (10, 19), (12, 19), (12, 21),
                                                (10, 21), (8, 21)]
    assert points((1, 1), (4, 2), (10, 20)) == [(10, 20)]
    z = points((50, 1), (24.5, 0.0), (42.25, 40.0))
    assert z[0] == (30.0, 40.0) and z[-1] == (54.5, 40.0) and len(z) == 50


@pytest.mark.slow
def test_the_moves_page_runs_as_written(tmp_path, ros_env):
    """docs/moves.md's Python, cell by cell as a notebook would run it, against the set
    it starts with; the motion-time model from `bench settle --out` is read back and
    predicts a settle time."""
    import re
    page = open(os.path.join(CONFIG, "..", "docs", "moves.md")).read()
    blocks = re.findall(r"```python\n(.*?)```", page, flags=re.S)
    assert len(blocks) == 2
    launch, _ = _set(tmp_path, ros_env, "lockstep")
    try:
        launch.start()
        r = subprocess.run([sys.executable, "-c", blocks[0]], cwd=tmp_path, env=ros_env,
                           capture_output=True, text=True, timeout=120)
        assert r.returncode == 0, r.stderr
        lines = r.stdout.splitlines()
        assert lines[0].startswith("armed ("), lines
        assert lines[1].endswith("ms {'x': ") is False and " ms {" in lines[1], lines
        assert os.path.isdir(tmp_path / "bags" / "sine")
        r = _cli(ros_env, "bench", "settle", "--steps", "4", "--moves", "8", "--out",
                 str(tmp_path / "motion.json"), timeout=600)
        assert r.returncode == 0, r.stderr
        assert "target default stage: composite settles in <= 0.3 x" in r.stdout
        r = subprocess.run([sys.executable, "-c", blocks[1]], cwd=tmp_path, env=ros_env,
                           capture_output=True, text=True, timeout=120)
        assert r.returncode == 0, r.stderr
        assert re.fullmatch(r"\d+\.\d ms\n", r.stdout), r.stdout
    finally:
        launch.stop()


@pytest.mark.slow
def test_the_example_node_runs_on_a_stage_that_recovered_from_a_fault(tmp_path, ros_env):
    """examples/publish_trajectory.py on a lockstep set that was e-stopped, disarmed and
    armed again: the latched state topic replays that fault to the example as it joins,
    and the example takes it for the present only if it began after the sample it saw
    last before publishing. (It exited 1 "the stage faulted" here while the stage was
    armed and would have run its trajectory.) While it waits it takes no samples."""
    from ros_probe import Probe
    launch, _ = _set(tmp_path, ros_env, "lockstep")
    probe = Probe(int(ros_env["ROS_DOMAIN_ID"]))
    try:
        launch.start()
        assert probe.wait_state("armed", 60)
        n = len(probe.states)
        assert probe.estop().success and probe.wait_state("faulted", 10, after=n)
        assert probe.arm(False).success and probe.wait_state("disarmed", 10, after=n)
        n = len(probe.states)
        assert probe.wait(lambda: probe.arm(True).success, 10)
        assert probe.wait_state("armed", 30, after=n)
        p = subprocess.Popen([sys.executable, os.path.join(CONFIG, "..", "examples",
                                                           "publish_trajectory.py"),
                              "--points", "0,20,20 1,25,25 30,30,30", "--start-in", "0",
                              "--timeout", "120"],
                             env=ros_env, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                             text=True)
        try:
            first = p.stdout.readline()
            assert first.startswith("published 3 points"), (first, p.stderr.read())
            # while it waits for the stage it takes none of the stage's samples (they
            # come at the control rate): its node subscribes to the state, not to them
            def topics():
                try:
                    return {t for t, _ in probe.node.get_subscriber_names_and_types_by_node(
                        "publish_trajectory", "/")}
                except Exception:  # (not on the graph yet)
                    return set()
            assert probe.wait(lambda: "/stage/state" in topics(), 10), topics()
            probe.spin(0.5)
            assert "/stage/joint_states" not in topics(), topics()
            out, err = p.communicate(timeout=150)
        finally:
            p.kill()
        assert p.returncode == 0, (first, out, err)
        assert "done: final error x" in out, out
    finally:
        probe.close()
        launch.stop()


@pytest.mark.parametrize("sig", ["SIGINT", "SIGTERM"])
def test_the_example_node_stopped_by_a_signal_says_so_in_one_line(ros_env, sig):
    """Ctrl-C or SIGTERM while examples/publish_trajectory.py waits for a set (none runs
    here): one line, exit 128 + the signal; no traceback (rclpy's own handler shut the
    context down under spin_once, and the ExternalShutdownException it raised came out
    as a traceback, exit 1)."""
    import signal
    import time
    p = subprocess.Popen([sys.executable, os.path.join(CONFIG, "..", "examples",
                                                       "publish_trajectory.py")],
                         env=ros_env, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                         text=True)
    time.sleep(2.0)  # in its wait for the feedforward, on most hosts
    p.send_signal(getattr(signal, sig))
    out, err = p.communicate(timeout=30)
    r = subprocess.CompletedProcess(p.args, p.returncode, out, err)
    _one_line(r, 128 + getattr(signal, sig), f"stopped by {sig} before the stage finished")


@pytest.mark.slow
def test_a_refused_trajectory_is_answered_to_its_sender(tmp_path, ros_env):
    """A trajectory the stage refuses (a point at 500 um, outside its range) is answered
    on trajectory/refused with the name its sender gave it and the reason: the example
    node says so in one line and exits 2 at once, the client's run raises
    TrajectoryRefused with the reason (before: nothing but a counter on /diagnostics,
    and the sender waited out its timeout)."""
    import time

    from piezo_stage.client import Stage, TrajectoryRefused
    launch, _ = _set(tmp_path, ros_env, "lockstep")
    try:
        launch.start()
        t0 = time.monotonic()
        r = subprocess.run([sys.executable, os.path.join(CONFIG, "..", "examples",
                                                         "publish_trajectory.py"),
                            "--points", "0,20,20 0.5,500,20", "--start-in", "0",
                            "--timeout", "60"],
                           env=ros_env, capture_output=True, text=True, timeout=90)
        _one_line(r, 2, "the stage refused the trajectory")
        assert "500" in r.stderr and "range" in r.stderr, r.stderr
        assert time.monotonic() - t0 < 30  # at once, not after its 60 s timeout
        with Stage(domain_id=int(ros_env["ROS_DOMAIN_ID"])) as stage:
            with pytest.raises(TrajectoryRefused, match="range"):
                stage.run([0.0, 0.5], {"x": [20.0, 500.0], "y": [20.0, 20.0]},
                          timeout=60)
    finally:
        launch.stop()
