"""Real time against real processes: arming, faults, recovery, shutdown.

Each test runs the node set in real time on its own ROS_DOMAIN_ID, injects a fault the
way it happens in a lab (a node killed, stopped and continued, NaN commands, an
e-stop), and then checks the recorded bag: the applied voltage never steps beyond the
slew limit, reaches the safe voltage in time, and the set re-arms through the approach
without a jump."""

import dataclasses
import math
import os
import signal
import socket
import subprocess
import sys
import time

import numpy as np
import pytest

pytest.importorskip("rclpy")
from lab_nodes import SAME_AGAIN, assert_ran_each  # noqa: E402

from conftest import CONFIG, realtime_rate_hz, realtime_twice  # noqa: E402
from piezo_stage.io.run_bag import (
    read_run,  # noqa: E402
    status_node,
)
from piezo_stage.launcher.launcher import Launch, LaunchOptions  # noqa: E402
from ros_probe import Probe  # noqa: E402

# real node processes in real time: -m "not slow" leaves them out, and ./dev.sh test
# runs them alone after the rest
pytestmark = [pytest.mark.slow, pytest.mark.realtime]

MODEL = os.path.join(CONFIG, "stage_model.yaml")
# the rate the sets run at: the highest this host holds with margin (conftest's
# realtime_rate_hz, found once), and its sample period
RATE, DT_NS = 1000.0, 1_000_000
SLEW_V_PER_S = 1.0e5  # config/sim_stage.yaml's amplifier slew limit
RAMP, STALE = 500.0, 0.05
LATE_STALE = 0.15  # s: the late-commands test's stale timeout (see _late_run)


@pytest.fixture
def domain(ros_env):
    global RATE, DT_NS
    RATE = realtime_rate_hz(ros_env)  # skips where the host holds no rate with margin
    DT_NS = int(round(1e9 / RATE))
    return int(ros_env["ROS_DOMAIN_ID"]), ros_env


def realtime_config(tmp_path, extra="", stale=STALE, rate=None):
    """The real-time set's parameters at this host's rate (judged there: its margin was
    measured already, so the set's own start-up check is left out), or at ``rate``."""
    RATE = rate or globals()["RATE"]
    cfg = tmp_path / "rt.yaml"
    cfg.write_text(
        "/**/stage_driver:\n  ros__parameters:\n    mode: realtime\n"
        f"    control_rate_hz: {RATE}\n    min_margin: 0.0\n"
        f"    stale_timeout_s: {stale}\n    safe_ramp_V_per_s: {RAMP}\n{extra}"
        "/**/feedforward:\n  ros__parameters:\n    model_file: " + MODEL + "\n"
        f"    control_rate_hz: {RATE}\n"
        f"/**/controller:\n  ros__parameters:\n    kp: 0.2\n    control_rate_hz: {RATE}\n"
        "/**/trajectory:\n  ros__parameters:\n    kind: seed\n    duration_s: 60.0\n")
    return str(cfg)


def assert_never_beyond_slew(t, v):
    dt_ticks = np.maximum(np.round(np.diff(t) / DT_NS), 1)[:, None]
    assert np.all(np.abs(np.diff(v, axis=0)) <= SLEW_V_PER_S * DT_NS * 1e-9 * dt_ticks
                  + 1e-9)


def safe_within(t, v, t_fault_ns):
    """(seconds from t_fault to the first sample at 0 V on both axes after it, the
    highest voltage held in between: what the ramp starts from)."""
    after = np.flatnonzero((t >= t_fault_ns) & np.all(v == 0.0, axis=1))
    assert after.size, "never reached the safe voltage"
    held = np.abs(v[(t >= t_fault_ns) & (t <= t[after[0]])]).max()
    return (t[after[0]] - t_fault_ns) * 1e-9, held


class HostTooSlow(Exception):
    """The host paused the loop longer than a judgement can allow for: the run says
    nothing either way. ``run_twice_at_most`` runs it again, and skips with this reason
    when the second is no better; never a pass."""


def host_pause_s(t, a_ns, b_ns, dt_ns=None) -> float:
    """The host's pace as the bag shows it: the longest gap between the driver's
    samples in [a_ns, b_ns] beyond its one tick [s] (0 when it kept time)."""
    dt_s = (DT_NS if dt_ns is None else dt_ns) * 1e-9
    lo = max(int(np.searchsorted(t, a_ns, side="right")) - 1, 0)  # the sample before
    hi = min(int(np.searchsorted(t, b_ns, side="left")), len(t) - 1)  # and the one after
    gaps = np.diff(t[lo:hi + 1]) * 1e-9
    return max(0.0, float(gaps.max(initial=0.0)) - dt_s)


def judged_within(took, bound, pause, what):
    """``took <= bound``, with the host's pause in the window added to the bound; a
    pause of stale_timeout_s or more leaves nothing to judge (HostTooSlow)."""
    if pause >= STALE:
        raise HostTooSlow(f"{what}: the host paused the driver {pause * 1e3:.0f} ms "
                          f"(stale_timeout_s is {STALE * 1e3:.0f} ms)")
    assert took <= bound + pause, (what, took, bound, pause)


def test_the_host_pace_is_read_from_the_samples_and_a_long_pause_judges_nothing():
    t = np.arange(0, 100) * 1_000_000
    t[60:] += 30_000_000  # the host stopped the driver 30 ms after sample 59
    assert host_pause_s(t, 0, 50_000_000, 1_000_000) == 0.0
    assert host_pause_s(t, 55_000_000, 95_000_000, 1_000_000) == pytest.approx(0.030)
    assert host_pause_s(t, 62_000_000, 65_000_000, 1_000_000) == pytest.approx(0.030)
    judged_within(0.070, 0.055, 0.030, "a fault")  # within the bound plus the pause
    with pytest.raises(AssertionError):
        judged_within(0.090, 0.055, 0.030, "a fault")
    with pytest.raises(HostTooSlow, match="paused the driver 60 ms"):
        judged_within(0.001, 0.055, 0.060, "a fault")
    # a fault 10 ms after that 30 ms pause: the host's (30 >= half of 50 ms); a fault
    # with the samples on time before it, or no fault at all, is the failure it is
    from types import SimpleNamespace
    run = SimpleNamespace(t_ns=t, states=[(0, "armed"), (100_000_000, "faulted")])
    with pytest.raises(HostTooSlow, match="paused the driver 30 ms"):
        paused_by_the_host(run, AssertionError("stale"))
    run.states[-1] = (50_000_000, "faulted")
    with pytest.raises(AssertionError, match="stale"):
        paused_by_the_host(run, AssertionError("stale"))
    with pytest.raises(AssertionError, match="no fault"):
        paused_by_the_host(SimpleNamespace(t_ns=t, states=[]), AssertionError("no fault"))


def never_faulted(states):
    """The states after arming, ``(state, reason, ...)``: tracking throughout, no fault.
    (Until the set left out Fast DDS's shared-memory transport in real time, see
    launcher.realtime_transport_env, a participant joining the graph now and then held a
    node's publishes ~0.334 s, the port health check of Fast-DDS issue 6535, and the
    driver faulted on stale commands: about 3 % of joins, 2026-11-25.)"""
    assert states and states[0][0] == "armed", states
    assert not [s for s in states if s[0] == "faulted"], states


def test_a_capacity_run_that_faulted_is_not_the_hosts_rate(domain):
    """host_rate on real sets: a capacity run at 1 kHz made to fault (a stale timeout of
    one sample period, which no host holds) gives no rate, and 500 Hz is measured on a
    run of its own: the rate chosen is never the one whose run faulted, and its figures
    name the fault. (The suite's capacity run at 1 kHz once faulted on stale commands on
    CI's host, and its last report chose 1 kHz for the four tests that then faulted.)"""
    from piezo_stage.launcher.host_rate import host_rate, measure
    _, env = domain
    runs: list = []
    tight = {"stage_driver": {"stale_timeout_s": 0.001}}
    rate, why = host_rate(env, runs=runs, measure_at=lambda r: measure(
        env, r, overrides=tight if r == 1000.0 else None))
    assert [r.rate_hz for r in runs[:2]] == [1000.0, 500.0], why
    assert "stale commands" in runs[0].faulted and runs[0].capacity is None, why
    assert why.startswith("the capacity run at 1000 Hz faulted ("), why
    assert rate in (None, 500.0, 250.0), why
    if not runs[1].faulted:  # measured at 500 Hz: its readings, judged as the set judges
        assert runs[1].readings and "at 500 Hz this host sustains" in why, why


def test_arming_is_refused_with_the_missing_link_and_e_stop_stays_latched(tmp_path, domain):
    d, env = domain
    launch = Launch(realtime_config(tmp_path), LaunchOptions(arm=False,
        nodes=["stage_driver", "feedforward", "controller"], exclusive=False), env=env)
    probe = Probe(d)
    drv = subprocess.Popen(launch.command("stage_driver"), env=env)
    others = []
    try:
        assert probe.wait_state("disarmed", 30)
        r = probe.arm(True)
        assert not r.success
        assert "no controller" in r.message and "no feedforward" in r.message, r.message
        # NaN commands from an outside node are rejected and never count as fresh
        for _ in range(20):
            probe.command(math.nan, math.nan, time.time_ns() + 5_000_000)
            probe.spin(0.005)
        assert probe.state == "disarmed" and probe.effort == [0.0, 0.0]
        others = [subprocess.Popen(launch.command(n), env=env)
                  for n in ("feedforward", "controller")]
        assert probe.wait(lambda: probe.arm(True).success, 30)  # once the loop closes
        assert probe.wait_state("armed", 10)
        # a streamed setpoint from an outside node: approached (not jumped to), and its
        # latency reported (it cannot be previewed): the look-ahead plus under a period
        from diagnostic_msgs.msg import DiagnosticArray
        from geometry_msgs.msg import PointStamped

        from piezo_stage.nodes._common import QOS_DATA
        diag = {}
        probe.node.create_subscription(DiagnosticArray, "/diagnostics", lambda m: diag.update(
            {kv.key: kv.value for st in m.status if status_node(st.name) == "feedforward"
             for kv in st.values}), 10)
        sp = probe.node.create_publisher(PointStamped, "/stage/setpoint", QOS_DATA)
        probe.wait(lambda: sp.get_subscription_count() > 0, 5)
        m = PointStamped()
        m.point.x, m.point.y = 30e-6, 20e-6
        sp.publish(m)
        assert probe.wait(lambda: probe.effort and probe.effort[0] > 40.0, 5)
        # lookahead_s (5 ms) plus under a period after the sample the feedforward answers
        # when the setpoint is taken; a sample taken just before the setpoint arrived
        # but answered after makes it shorter, by up to the loop's lag
        # (the look-ahead is a whole number of periods: 5 ms at 1 kHz, 8 ms at 250 Hz)
        dt_ms = 1e3 / RATE
        la_ms = dt_ms * math.ceil(5.0 / dt_ms - 1e-6)
        assert probe.wait(lambda: 3.0 <= float(diag.get("setpoint_latency_median_ms", 0))
                          <= la_ms + max(5.0, 1.5 * dt_ms), 5), \
            diag.get("setpoint_latency_median_ms")
        n = len(probe.states)
        assert probe.estop().success and probe.wait_state("faulted", 5, after=n)
        probe.spin(0.5)
        assert probe.effort == [0.0, 0.0]
        r = probe.arm(True)
        assert not r.success and "latched" in r.message        # no re-arm past an e-stop
        probe.spin(0.3)
        assert probe.state == "faulted"
        assert probe.arm(False).success and probe.wait_state("disarmed", 5, after=n)
        assert probe.wait(lambda: probe.arm(True).success, 10)
        assert probe.wait_state("armed", 10, after=n)
    finally:
        probe.close()
        for p in others + [drv]:
            p.send_signal(signal.SIGINT)
        for p in others + [drv]:
            assert p.wait(30) == 130


def run_twice_at_most(run, tmp_path, domain, ros_domains):
    """``run(dir, domain)``; when an assertion of it fails, or the host paused it too
    long to judge (HostTooSlow), once more on a fresh domain at the rate the host holds
    now (conftest.realtime_twice: measured again; a host that slowed since its last
    measurement is judged where it holds). Two failures fail; a second run the host
    paused too long is skipped with its figures."""
    def attempt(env, rate, which):
        global RATE, DT_NS
        RATE, DT_NS = rate, int(round(1e9 / rate))
        try:
            run(tmp_path / which, (int(env["ROS_DOMAIN_ID"]), env))
        except HostTooSlow as e:
            if which == "first":
                raise
            pytest.skip(f"the host was too slow to judge this twice: {e}")
    realtime_twice(attempt, domain[1], ros_domains, (AssertionError, HostTooSlow),
                   run.__name__)


def test_faults_ramp_to_safe_and_the_set_re_arms_through_the_approach(tmp_path, domain,
                                                                       ros_domains):
    """Controller killed, controller stopped 1 s, feedforward killed, NaN commands while
    faulted; then the launcher's shutdown. The bag is the judge. Real time on a shared
    2-core VM: a run the host stalls (it stops the whole guest for up to tens of ms,
    see bench realtime's host pauses) is run once more; two failures fail."""
    run_twice_at_most(_faults_run, tmp_path, domain, ros_domains)


def _faults_run(tmp_path, domain):
    tmp_path.mkdir()
    d, env = domain
    bag = str(tmp_path / "faults")
    launch = Launch(realtime_config(tmp_path), LaunchOptions(record=bag,
        nodes=["stage_driver", "feedforward", "controller", "trajectory"], exclusive=False,
        compose="none"), env=env)  # (each node killed on its own)
    probe = Probe(d)
    faults = []
    try:
        launch.start()
        assert probe.wait_state("armed", 60)
        for node, how in (("controller", "kill"), ("controller", "stop"),
                          ("feedforward", "kill")):
            probe.spin(1.0)
            # each fault meets a set armed for 0.5 s at least: a restarted controller
            # still behind can fault it again, and a controller stopped while the set is
            # faulted shows no new fault
            n = len(probe.states)
            assert probe.wait_steady("armed", 0.5, 30), (node, how, probe.seen(n - 3))
            n, t_inject = len(probe.states), time.monotonic()
            faults.append(time.time_ns())
            p = launch.procs[node]
            if how == "kill":
                p.send_signal(signal.SIGKILL)
                p.wait(10)
            else:
                p.send_signal(signal.SIGSTOP)
            assert probe.wait_state("faulted", 5, after=n), \
                (node, how, probe.seen(n - 1, t_inject))
            assert probe.wait(lambda: probe.effort == [0.0, 0.0], 5)  # ramped to safe
            if how == "stop":
                for _ in range(30):  # NaN while faulted: never fresh, never applied
                    probe.command(math.nan, 1e6, time.time_ns() + 5_000_000)
                    probe.spin(0.005)
                assert probe.state == "faulted" and probe.effort == [0.0, 0.0]
                probe.spin(1.0 - 0.15)
                p.send_signal(signal.SIGCONT)
            else:
                launch.procs[node] = subprocess.Popen(launch.command(node), env=env)
            assert probe.wait_state("armed", 30, after=n), \
                (node, how, probe.seen(n - 1, t_inject))
        probe.spin(1.0)
    finally:
        probe.close()
        launch.stop()
    assert all(launch.stopped_cleanly(n) for n in launch.procs
               if n != "controller" and n != "feedforward")
    run = read_run(bag)
    t, v, true, states, ref = run.t_ns, run.v_V, run.true_um, run.states, run.desired_um
    assert_never_beyond_slew(t, v)
    assert [s for _, s in states].count("faulted") >= 3
    for t_fault in faults:  # safe voltage within stale + V / ramp (+ 5 ms), plus
        took, held = safe_within(t, v, t_fault)  # any pause of the host in between
        judged_within(took, STALE + held / RAMP + 0.005,
                      host_pause_s(t, t_fault, t_fault + int(took * 1e9)),
                      "to the safe voltage after a fault")
    # no jump at any (re-)arm: through each approach and the first 0.3 s of tracking
    # the true position stays within 1 um of the path asked for; never above the
    # trajectory's 45 um (no overshoot after a stall)
    # (issue 9: from the enable to the end of the approach, within 1 um of the path)
    # (each approach that reached armed: one under way when the run ended has no end,
    # and one a fault cut short, say a restarted controller still behind, its commands
    # arriving after their ticks, was no approach the stage followed to its end)
    windows = [(s, a) for (s, name), (a, after) in zip(states, states[1:])
               if name == "approaching" and after == "armed"]
    assert len(windows) >= 4
    volts = dict(zip(t.tolist(), v))
    # set aside the samples in or 50 ms after a stall of the loop (a missed tick or a
    # tick without its command: the host stopped us, which no control law prevents; the
    # bench reports both figures), and require most of each approach to remain
    # (a tick without a reference before the bag's first one is the recorder still
    # matching the topic, which it may do late: not a stall of the loop)
    first_ref = min(ref)
    stalls = [int(b) for a, b in zip(t[:-1], t[1:]) if b - a > 1.5 * DT_NS] + \
        [int(k) for k in t if int(k) not in ref and k > first_ref]
    stalls = np.array(sorted(stalls), dtype=np.int64)

    def disturbed(k):
        i = np.searchsorted(stalls, k, side="right")
        return i > 0 and k - stalls[i - 1] <= 50_000_000
    for s0, s1 in windows:  # (where 0 V is applied and the stage is still above the
        # asked position, the path is unreachable: the lower limit, not a control error)
        ks = [k for k in ref if s0 <= k <= s1 and k in true and not (
            volts[k].min() <= 0.05 and (true[k] > ref[k]).any())]
        kept = [k for k in ks if not disturbed(k)]
        if len(kept) < 0.5 * len(ks):
            raise HostTooSlow(f"the host stalled the loop through most of an approach "
                              f"({len(ks) - len(kept)} of {len(ks)} samples)")
        e = [np.abs(true[k] - ref[k]).max() for k in kept]
        assert max(e, default=0.0) <= 1.0, (s0, max(e), len(e))
    assert np.array(list(true.values())).max() <= 45.0 + 0.5
    assert list(v[-1]) == [0.0, 0.0] and states[-1][1] == "disarmed"  # shutdown ramp


def test_a_node_dying_under_launch_ends_the_run_at_the_safe_voltage(tmp_path, domain):
    """The launcher stops the producers, then waits for the driver to ramp down."""
    d, env = domain
    bag = str(tmp_path / "dies")
    launch = Launch(realtime_config(tmp_path), LaunchOptions(record=bag,
        nodes=["stage_driver", "feedforward", "controller", "trajectory"], exclusive=False,
        compose="none"), env=env)  # (the controller killed alone)
    probe = Probe(d)
    try:
        launch.start()
        assert probe.wait_state("armed", 60)
        probe.spin(1.0)
        # killed where the stage is high on its path: the ramp then starts from a real
        # voltage (killed at a low point, 4.4 V once, it was hard to tell from rest)
        assert probe.wait(lambda: max(probe.effort or [0.0]) > 20.0, 5), probe.effort
        launch.procs["controller"].send_signal(signal.SIGKILL)
        launch.wait(30)  # returns when a node has died
    finally:
        probe.close()
        launch.stop()
    assert any("controller" in f for f in launch.failed)
    assert launch.stopped_cleanly("stage_driver")
    run = read_run(bag)
    t, v, states = run.t_ns, run.v_V, run.states
    assert_never_beyond_slew(t, v)
    assert list(v[-1]) == [0.0, 0.0]
    # the ramp starts where the driver left the armed state: on its own stale fault, or
    # on the launcher's disarm when the launcher saw the death first (it looks every
    # 50 ms, the stale timeout is 50 ms too: either may come first, both are safe ends)
    t_armed = [s for s, name in states if name == "armed"][-1]
    t_end = min(s for s, name in states if name in ("faulted", "disarmed") and s > t_armed)
    k = t >= t_end
    ticks = np.maximum(np.round(np.diff(t[k]) / DT_NS), 1)[:, None]
    assert np.all(np.abs(np.diff(v[k], axis=0)) <= RAMP * DT_NS * 1e-9 * ticks + 1e-9)
    assert v[k].max() > 5.0  # from a real voltage, not from rest


def test_controller_gains_and_feedback_are_live_and_read_only_ones_refused(tmp_path, domain):
    """Parameters set from an outside node take effect (the node re-reads them), bad
    values and read-only ones are refused with the reason."""
    from ros_probe import get_params, set_params
    d, env = domain
    launch = Launch(realtime_config(tmp_path), LaunchOptions(nodes=["controller"],
        exclusive=False), env=env)
    proc = subprocess.Popen(launch.command("controller"), env=env)
    probe = Probe(d)
    try:
        assert set_params(probe, "/stage/controller", kp=0.5, ki=90.0) == [(True, ""),
                                                                          (True, "")]
        assert get_params(probe, "/stage/controller", "kp", "ki") == [0.5, 90.0]
        assert set_params(probe, "/stage/controller", feedback=False)[0][0]
        ok, why = set_params(probe, "/stage/controller", kp=-1.0)[0]
        assert not ok and why
        ok, why = set_params(probe, "/stage/controller", voltage_limits_V=[0.0, 500.0])[0]
        assert not ok and "read-only" in why.lower()
        assert get_params(probe, "/stage/controller", "kp") == [0.5]
        # the law itself uses them: its diagnostics report the gains it computes with
        from diagnostic_msgs.msg import DiagnosticArray
        seen = {}
        probe.node.create_subscription(DiagnosticArray, "/diagnostics", lambda m: seen.update(
            {kv.key: kv.value for st in m.status if status_node(st.name) == "controller"
             for kv in st.values}), 10)
        assert probe.wait(lambda: seen.get("kp") == "0.5", 5.0), seen
        assert seen["ki"] == "90.0" and seen["feedback"] == "False"
    finally:
        probe.close()
        proc.send_signal(signal.SIGINT)
        assert proc.wait(30) == 130


LIVE = {"controller": {"kp", "ki", "kd", "feedback"},
        "feedforward": {"compensate_effects", "learning", "learning_period_s",
                        "learning_gain", "on_target_tol_um", "on_target_window_ms",
                        "on_target_filter_ms"},
        "identifier": {"method", "structure", "auto_cycles"},
        "recorder": {"batch_period_s"},
        "live_view": {"max_rate_hz", "batch_period_s"},
        "trajectory": {"kind", "frequency_hz", "duration_s", "center_um", "amplitude_um",
                       "dt_s", "csv_path", "excite_s", "excite_center_um",
                       "excite_amplitude_um", "excite_y_hz", "lines", "scan_size_um",
                       "scan_center_um", "corner", "slow", "fast_axis"}}


def test_every_parameter_of_every_node_is_live_or_read_only(tmp_path, domain):
    """Asked of the running nodes from an outside node (as `ros2 param` does): the
    writable parameters are exactly the live ones (plus rclpy's own use_sim_time);
    every other one refuses a set as read-only; a live one takes effect (the node
    reports the value it uses), and an unknown choice is refused with the reason."""
    from diagnostic_msgs.msg import DiagnosticArray
    from rcl_interfaces.srv import DescribeParameters, ListParameters

    from piezo_stage.nodes.declared import DECLARED, RCLPY_OWN
    from ros_probe import _param_call_raw, set_params
    d, env = domain
    nodes = ["stage_driver", "feedforward", "controller", "trajectory", "identifier", "gap"]
    # parameters, not timing: every node at normal priority, so none is starved of the
    # CPU it needs to answer the parameter services on a loaded host
    calm = {n: {"thread_priority": 0} for n in ("stage_driver", "feedforward", "controller",
                                                "recorder")}
    launch = Launch(realtime_config(tmp_path), LaunchOptions(record=str(tmp_path / "bag"),
        nodes=nodes, arm=False, overrides=calm, exclusive=False), env=env)
    launch.start()
    probe = Probe(d)
    seen = {}
    probe.node.create_subscription(DiagnosticArray, "/diagnostics", lambda m: seen.update(
        {status_node(st.name): {kv.key: kv.value for kv in st.values} for st in m.status}),
        50)
    try:
        for node in nodes + ["recorder"]:
            names = _param_call_raw(probe, f"/stage/{node}", "list_parameters",
                                    ListParameters, names=[], depth=0).result.names
            names = [n for n in names if not n.startswith("qos_overrides")]
            assert set(names) - RCLPY_OWN == DECLARED[node], node  # the launcher's table
            descs = _param_call_raw(probe, f"/stage/{node}", "describe_parameters",
                                    DescribeParameters, names=names).descriptors
            writable = {x.name for x in descs if not x.read_only} - {"use_sim_time"}
            assert writable == LIVE.get(node, set()), (node, writable)
            ro = sorted({x.name for x in descs if x.read_only})
            if ro:  # a read-only one refuses, saying so (its value's type kept)
                from ros_probe import get_params
                value = get_params(probe, f"/stage/{node}", ro[0])[0]
                ok, why = set_params(probe, f"/stage/{node}", **{ro[0]: value})[0]
                assert not ok and "read-only" in why.lower(), (node, ro[0], why)
        assert set_params(probe, "/stage/identifier", method="afsa") == [(True, "")]
        ok, why = set_params(probe, "/stage/identifier", method="bogus")[0]
        assert not ok and "fast, afsa, afsa-bat" in why
        assert set_params(probe, "/stage/recorder", batch_period_s=0.02) == [(True, "")]
        assert probe.wait(lambda: seen.get("identifier", {}).get("method") == "afsa" and
                          seen.get("recorder", {}).get("batch_period_s") == "0.02", 5.0), seen
    finally:
        probe.close()
        launch.stop()


def test_outside_stamps_and_a_refit_model_while_armed_never_fault_or_jump(tmp_path, domain):
    """While the set tracks in real time an outside node sends joint states stamped
    10^15 ns ahead of the clock and before 1970, then a refit model (f and g x 1.2):
    nobody faults or refuses to arm (not even when the outside node's publishers join,
    see never_faulted), the strays are counted and
    dropped, the refit is taken, and the jump between the two models' answers (14 V
    here) is eased out at 1 V a tick. Before: the far stamp faulted the driver for
    good; the new model stepped the output."""
    from sensor_msgs.msg import JointState
    from std_msgs.msg import String

    from benchmarks.faults import scaled_model
    from piezo_stage.nodes._common import QOS_DATA, QOS_EVENTS
    d, env = domain
    bag = str(tmp_path / "outside")
    launch = Launch(realtime_config(tmp_path), LaunchOptions(record=bag,
        nodes=["stage_driver", "feedforward", "controller", "trajectory"],
        exclusive=False), env=env)
    probe = Probe(d)
    try:
        launch.start()
        assert probe.wait_state("armed", 60)
        armed_at = len(probe.states) - 1
        js = probe.node.create_publisher(JointState, "/stage/joint_states", QOS_DATA)
        mo = probe.node.create_publisher(String, "/stage/model", QOS_EVENTS)
        assert probe.wait(lambda: js.get_subscription_count() >= 3 and
                          mo.get_subscription_count() >= 1, 10)
        probe.spin(1.0)
        now_s = time.time_ns() // 10 ** 9
        for sec in (now_s + 10 ** 6, -1, now_s + 10 ** 6 + 1):  # 10^15 ns ahead; 1969
            m = JointState(name=["x", "y"], position=[1e-6, 1e-6], effort=[1.0, 1.0])
            m.header.stamp.sec = sec
            js.publish(m)
            probe.spin(0.2)
        probe.spin(1.0)
        # the probe's own publishers joined the graph just now: no fault for that
        never_faulted(probe.states[armed_at:])
        model_at = len(probe.states)
        with open(MODEL) as fh:
            refit = scaled_model(fh.read(), 1.2)
        t_model = time.time_ns()
        mo.publish(String(data=refit))
        probe.spin(2.0)
        assert probe.states[model_at:] == [], probe.states[model_at - 1:]
        assert all(p.poll() is None for p in launch.procs.values())
    finally:
        probe.close()
        launch.stop()
    run = read_run(bag)
    ff = run.diagnostics["feedforward"]
    assert int(ff["stray_stamps"]) >= 2 and int(ff["models"]) == 2 and \
        int(ff["rejected_models"]) == 0, ff
    real = (run.t_ns > 0) & (run.t_ns < time.time_ns())  # the driver's, not the strays
    assert (~real).sum() == 3
    t, v = run.t_ns[real], run.v_V[real]
    assert_never_beyond_slew(t, v)
    # the feedforward's answers, target tick by target tick: after the model, no jump
    # beyond what the trajectory itself asks per tick plus the 1 V a tick of the
    # hand-over. A stall of the driver is not the hand-over: the feedforward's inverse
    # is synced to the voltages really applied, so after a sample where the driver
    # held its voltage (its commands late) the next answers jump by what the stage
    # really did (7.1 V once at a reversal, after a 4 ms host stall). Those ticks and
    # the five after each are not judged; held samples over 5 % of the ticks leave the
    # test unjudged (a skip that says so, never a pass).
    from piezo_stage.io.bag import iter_messages
    from piezo_stage_msgs_adapters import reference_from_msg
    ff_at, applied = {}, {}
    for topic, _, _, data in iter_messages(bag):
        if topic.endswith("/reference"):
            r = reference_from_msg(data)
            ff_at[r.ns] = (r.ff_V["x"], r.ff_V["y"])
            applied[r.ns] = (r.applied_V["x"], r.applied_V["y"])
    ks = np.array(sorted(ff_at))
    ffs = np.array([ff_at[k] for k in ks])
    held = np.r_[False, np.all(np.diff([applied[k] for k in ks], axis=0) == 0, axis=1)]
    near = np.convolve(held, np.ones(6), mode="full")[:ks.size] > 0  # and 5 after
    next_tick = np.diff(ks) == DT_NS
    jump = np.abs(np.diff(ffs, axis=0)).max(axis=1)
    after = next_tick & (ks[1:] >= t_model) & (ks[1:] <= t_model + 1_000_000_000)
    before = next_tick & (ks[1:] >= t_model - 1_000_000_000) & (ks[1:] < t_model)
    assert after.sum() > 0.5 * RATE and before.sum() > 0.5 * RATE
    if near[1:][after | before].mean() > 0.05:
        pytest.skip(f"the driver held its voltage on {int(held.sum())} samples (its "
                    "commands late): the hand-over cannot be judged in this run")
    calm = ~near[1:]
    assert jump[after & calm].max() <= jump[before & calm].max() + 1.2, (
        jump[after & calm].max(), jump[before & calm].max())


def _tracking_figures(run, span, over_um=0.3, apart_ms=3.0, trim=0.0025):
    """Tracking against the true position over ``span`` (ns): samples, the RMS error
    without the worst ``trim`` of samples, and the longest spell [ms] of error over
    ``over_um`` (samples over it at most ``apart_ms`` apart belong to one spell)."""
    e = run.errors_um(*span)
    t = np.asarray(run.errors_t_ns(*span), np.int64)
    sq = np.sort(np.mean(e ** 2, axis=1))
    kept = sq[:max(1, int(len(sq) * (1.0 - trim)))]
    bad = t[np.abs(e).max(axis=1) > over_um]
    longest = 0.0
    if bad.size:
        breaks = np.flatnonzero(np.diff(bad) > apart_ms * 1e6)
        starts = np.concatenate([[0], breaks + 1])
        ends = np.concatenate([breaks, [bad.size - 1]])
        longest = float(np.max(bad[ends] - bad[starts]) * 1e-6) + 1.0
    return {"n": int(len(e)), "rms_trimmed_um": float(np.sqrt(np.mean(kept))),
            "rms_um": float(np.sqrt(np.mean(e ** 2))), "longest_spell_ms": longest}


def test_the_joining_figures_tell_a_stall_from_held_ticks():
    """The joining test's figures on made-up tracking: 0.03 um RMS over 20 s at 1 kHz;
    fifteen single held ticks of 4 um double the plain RMS but leave the trimmed one and
    every spell short; a 0.33 s stall (2 um) is a 330 ms spell and lifts the trimmed RMS
    past the test's limit."""
    class Tracking:  # what _tracking_figures reads of a run
        def __init__(self, e):
            self.e, self.t = e, np.arange(len(e), dtype=np.int64) * 1_000_000

        def errors_um(self, a, b):
            return self.e

        def errors_t_ns(self, a, b):
            return self.t

    rng = np.random.default_rng(0)
    quiet = rng.normal(0.0, 0.03, (20_000, 2))
    held, stall = quiet.copy(), quiet.copy()
    held[rng.choice(20_000, 15, replace=False)] += 4.0
    stall[5_000:5_330] += 2.0
    q, h, s = (_tracking_figures(Tracking(e), (0, 0)) for e in (quiet, held, stall))
    assert h["rms_um"] > 2.0 * q["rms_um"] + 0.03  # the plain RMS would fail it
    assert h["rms_trimmed_um"] <= 2.0 * q["rms_trimmed_um"] + 0.03
    assert h["longest_spell_ms"] <= 25.0 and q["longest_spell_ms"] <= 25.0
    assert s["longest_spell_ms"] == pytest.approx(330.0, abs=2.0)
    assert s["rms_trimmed_um"] > 2.0 * q["rms_trimmed_um"] + 0.03


SECOND_RATE_HZ = 200.0


def test_nodes_joining_cost_no_fault_and_a_namespace_holds_one_set(tmp_path, domain,
                                                                   ros_domains):
    """While the set tracks in real time, ten outside nodes join and leave (latched and
    default-QoS trajectory publishers, joint_states subscribers, plain nodes), a second
    launch on /stage is refused (exit 2, naming the running set) and a second stage's
    driver starts and stops in /stage2: no fault at all, the RMS tracking error meanwhile
    stays near its quiet figure, and no spell of error lasts over 25 ms (or twice the
    longest of the quiet seconds, on a host whose pace alone makes longer ones). None of
    /stage2's topics reach this set's bag. The launcher's stop is a disarm, never a
    fault. (Before: "stale commands: none for 0.334 s" on
    about 3 % of joins, the shared-memory port health check of Fast-DDS issue 6535: the
    set now leaves that transport out in real time, see never_faulted.) Real time on a
    shared 2-core VM, as the faults test: a run the host starves is run once more on a
    fresh domain; two failures fail. (Starved: the set at SCHED_FIFO takes 1.3 cores
    here, and on a slow host all of both, so the kernel's fair server takes its 50 ms a
    second back from it for the normal-priority processes, and the driver faults on
    stale commands once a second; host_cpu says how much of the host the guest had.)"""
    run_twice_at_most(_joining_run, tmp_path, domain, ros_domains)


def host_cpu():
    """The host's CPU counters now (/proc/stat: busy, idle and stolen jiffies)."""
    with open("/proc/stat") as fh:
        f = [int(x) for x in fh.readline().split()[1:]]
    return {"busy": sum(f[:3]) + sum(f[5:7]), "idle": f[3] + f[4], "steal": f[7]}


def host_cpu_since(before):
    """Shares of the host's time since ``before`` (host_cpu): busy, stolen (by the
    hypervisor), idle."""
    now = host_cpu()
    d = {k: now[k] - before[k] for k in now}
    total = max(sum(d.values()), 1)
    return ", ".join(f"{k} {100.0 * v / total:.0f} %" for k, v in d.items())


def _joining_run(tmp_path, domain):
    tmp_path.mkdir()
    import rclpy
    from rclpy.context import Context
    from sensor_msgs.msg import JointState
    from trajectory_msgs.msg import JointTrajectory

    from piezo_stage.nodes._common import QOS_DATA, QOS_LATCHED
    d, env = domain
    bag = str(tmp_path / "joined")
    # at half the host's rate: ten processes joining and a second set starting beside
    # the first take the margin a set alone leaves (at the host's rate on a 2-core VM
    # whose capacity run chose 500 Hz, tracking while they joined was 2.5-5 x quiet);
    # judged from 250 Hz up (below it the seed trajectory is not tracked to these
    # figures, and a spell of 25 ms is three samples). The host's rate is measured again
    # as this test starts: the suite's one measurement came minutes before, and a fresh
    # clone's CI (of 5df54de) ran this test at 500 Hz on a host that had slowed
    # meanwhile (29-45 ms spells of error with nobody joining)
    from conftest import _REALTIME
    rate, why = _REALTIME(env, fresh=True)  # (the suite's summary lists it)
    if rate is None or rate / 2 < 250.0:
        pytest.skip(f"the host's real-time rate is now {rate or 0:g} Hz ({why}): joining "
                    "is judged at half of it, from 250 Hz up (a host that holds 500 Hz "
                    "with margin)")
    cfg = realtime_config(tmp_path, rate=rate / 2)
    launch = Launch(cfg, LaunchOptions(record=bag,
        nodes=["stage_driver", "feedforward", "controller", "trajectory"]), env=env)
    # the second stage as this 2-core host can hold it beside the first: its driver, at
    # 200 Hz and normal priority. One real-time set at 1 kHz takes 1.3 cores here, two
    # thirds of the host at SCHED_FIFO; with a whole second set starting beside it (four
    # more processes importing) the driver lost 50-55 ms at once and faulted on stale
    # commands in 5 of 33 runs, at the same priorities or not (docs/realtime.md)
    second = Launch(cfg, LaunchOptions(namespace="/stage2", nodes=["stage_driver"], overrides={
        "stage_driver": {"control_rate_hz": SECOND_RATE_HZ, "thread_priority": 0}}), env=env)
    probe = Probe(d)
    cpu0 = host_cpu()
    try:
        launch.start()
        assert probe.wait_state("armed", 60)
        armed_at = len(probe.states) - 1
        probe.spin(1.0)  # the approach
        quiet = [time.time_ns()]
        probe.spin(3.0)  # tracking with nobody joining: the quiet figure
        quiet.append(time.time_ns())
        for k in range(10):
            ctx = Context()
            rclpy.init(context=ctx, domain_id=d)
            node = rclpy.create_node(f"lab_node_{k}", context=ctx)
            if k % 3 == 0:
                node.create_publisher(JointTrajectory, "/stage/trajectory", QOS_LATCHED)
            elif k % 3 == 1:
                node.create_publisher(JointTrajectory, "/stage/trajectory", 10)
            else:
                node.create_subscription(JointState, "/stage/joint_states", lambda m: None,
                                         QOS_DATA)
            probe.spin(0.4)
            node.destroy_node()
            rclpy.try_shutdown(context=ctx)
        # a second launch on /stage is refused before it starts anything, naming the set
        r = subprocess.run([sys.executable, "-m", "piezo_stage", "launch", cfg,
                            "--duration", "5"], env=env, capture_output=True, text=True,
                           timeout=60)
        assert r.returncode == 2 and r.stderr.count("\n") == 1, r.stderr
        assert f"/stage is already running ({socket.gethostname()}, pid {os.getpid()})" \
            in r.stderr, r.stderr
        # a second stage on the domain: its own set, its own topics
        second.start()
        probe.spin(4.0)  # its nodes start (imports, discovery), arm and track
        second.stop()
        probe.spin(1.0)
        joined = [quiet[1], time.time_ns()]
        cpu = host_cpu_since(cpu0)
        assert not [s for s in probe.states[armed_at:] if s[0] == "faulted"], (
            probe.states[armed_at:], cpu)
        never_faulted(probe.states[armed_at:])
    finally:
        probe.close()
        second.stop()
        launch.stop()
    run = read_run(bag)
    # the stop by duration: a disarm and the ramp, never a fault
    assert run.states[-1][1] == "disarmed" and "faulted" not in [s for _, s in run.states]
    assert list(run.v_V[-1]) == [0.0, 0.0]
    # tracking while others joined, against the quiet seconds before. A stall (the
    # shared-memory health check held every publish ~0.33 s) is a long spell of error:
    # none may last over 25 ms. Single held ticks (a command later than the 5 ms
    # look-ahead, or a host pause, while processes start on this 2-core host: a few um
    # for a millisecond or a few) happen in quiet real-time runs too (docs/realtime.md);
    # 6-26 such samples in 20,000 took the plain RMS past this limit in 4 of 11 runs
    # (0.09-0.13 um against 0.027 um quiet), so the RMS compared leaves out the worst
    # 0.25 % of samples, far fewer than a stall's
    figs = [_tracking_figures(run, span, apart_ms=3e3 / (rate / 2))  # 3 sample periods
            for span in (quiet, joined)]
    assert figs[0]["n"] > rate and figs[1]["n"] > 2.5 * rate, (figs, cpu)  # 3 s, 9 s at rate/2
    # judged against the same run's quiet seconds: on this 2-core VM a 250 Hz set had
    # spells of 17-45 ms with nobody joining (fresh clones' CI of 5df54de and 8e53da8:
    # joined 33-77 ms), so a fixed 25 ms judged the host's pace; the stall this guards
    # against (0.33 s) is beyond the limit however noisy the host
    limit_ms = min(150.0, max(25.0, 2.0 * figs[0]["longest_spell_ms"]))
    assert figs[1]["longest_spell_ms"] <= limit_ms, (figs, cpu)
    assert figs[1]["rms_trimmed_um"] <= 2.0 * figs[0]["rms_trimmed_um"] + 0.03, (figs, cpu)
    from piezo_stage.io.bag import iter_messages
    topics = {topic for topic, _, _, _ in iter_messages(bag)}
    assert not any(t.startswith("/stage2/") for t in topics), topics  # its own set only
    assert second.stopped_cleanly("stage_driver")


def test_no_trajectory_set_holds_and_follows_outside_publishers(tmp_path, domain, capfd,
                                                                ros_domains):
    """`launch --no-trajectory`: the set arms and holds position with no trajectory node;
    a latched publisher and then a default-QoS one, both joining mid-run, are followed;
    one stamped in the past is refused with the reason; examples/publish_trajectory.py
    (a future stamp) runs to its end and exits 0; no QoS warning on any side, no fault,
    and the bag holds the three the stage ran. (Twice at most: a fresh clone's run once
    faulted on a 58 ms host pause.)"""
    def _outside_run(folder, dom):
        _outside(folder, dom, capfd)
    run_twice_at_most(_outside_run, tmp_path, domain, ros_domains)


def _outside(tmp_path, domain, capfd):
    tmp_path.mkdir()
    from rclpy.qos import QoSProfile
    from trajectory_msgs.msg import JointTrajectory

    import piezo_stage_msgs_adapters as A
    from piezo_stage.io.bag import iter_messages
    from piezo_stage.nodes._common import QOS_LATCHED
    d, env = domain
    capfd.readouterr()  # a first run's output is its own: its fault is not this run's
    bag = str(tmp_path / "outside")
    launch = Launch(realtime_config(tmp_path), LaunchOptions(record=bag, trajectory=False,
        exclusive=False), env=env)
    assert "trajectory" not in launch.nodes and "feedforward" in launch.nodes
    probe = Probe(d)
    t = np.arange(0, 1.0, 1e-3)
    ends = []
    failed = None
    try:
        launch.start()
        assert probe.wait_state("armed", 60)
        probe.spin(1.0)
        for qos, um in ((QOS_LATCHED, 20.0), (QoSProfile(depth=10), 30.0)):
            pub = probe.node.create_publisher(JointTrajectory, "/stage/trajectory", qos)
            # the feedforward alone takes trajectories (the recorder its accepted ones)
            assert probe.wait(lambda: pub.get_subscription_count() >= 1, 10)
            pub.publish(A.trajectory_msg(t, {"x": np.full(t.size, um),
                                             "y": np.full(t.size, um)}))
            probe.spin(2.5)  # the approach, then the 1 s trajectory; its last point held
            ends.append((time.time_ns(), um))
            assert probe.state == "armed", probe.states[-3:]
        # one stamped 5 s ago: refused with the reason (the stage stays where it is)
        old = A.trajectory_msg(t, {"x": np.full(t.size, 35.0), "y": np.full(t.size, 35.0)})
        old.header.stamp.sec = time.time_ns() // 10**9 - 5
        pub.publish(old)
        probe.spin(0.5)
        # the example outside node: rclpy and common_interfaces only, waits for the end
        r = subprocess.run([sys.executable, os.path.join(CONFIG, "..", "examples",
                                                         "publish_trajectory.py")],
                           env=env, capture_output=True, text=True, timeout=60)
        assert r.returncode == 0, (r.stdout, r.stderr)
        assert "final error x" in r.stdout, r.stdout
    except AssertionError as e:
        failed = e
    finally:
        probe.close()
        launch.stop()
    run = read_run(bag)
    err = capfd.readouterr().err
    sys.stderr.write(err)  # still this test's output, shown where it fails
    if failed is not None:
        paused_by_the_host(run, failed)
    # no fault, the example node's joining included; the last state is the launcher's
    # stop, a disarm
    names = [s for _, s in run.states]
    try:
        never_faulted([(n,) for n in names[names.index("armed"):-1]])
        assert "faulted" not in err and names[-1] == "disarmed", err[-2000:]
    except AssertionError as e:
        paused_by_the_host(run, e)
    assert_never_beyond_slew(run.t_ns, run.v_V)
    from rclpy.serialization import deserialize_message
    held = [deserialize_message(data, JointTrajectory) for topic, _, _, data
            in iter_messages(bag) if topic == "/stage/trajectory/accepted"]
    assert len(held) == 3, [(len(m.points), round(m.points[-1].positions[0] * 1e6, 3))
                            for m in held]  # 1000 at 20 and 30; 5 at 30 (the example);
    # the one stamped in the past was refused: not run, so not in the bag
    assert int(run.diagnostics["feedforward"]["rejected_trajectories"]) == 1
    for end_ns, um in ends:  # the 0.3 s before each end: at that trajectory's point
        k = (run.t_ns > end_ns - 300_000_000) & (run.t_ns < end_ns)
        assert k.sum() > 0.1 * RATE and np.abs(run.w_um[k] - um).max() < 1.0, (um, run.w_um[k][-1])
    assert "incompatible" not in err.lower(), err[-2000:]
    assert "s in the past" in err



def test_the_same_trajectory_from_three_outside_processes_runs_three_times(
        tmp_path, domain, ros_domains):
    """A trajectory is its publication: three outside processes, one after another, each
    publish the same trajectory (the same bytes) to a real-time set and wait for its
    run's end; the stage accepts, records and runs all three to their end, no fault.
    (Before, the second and later were dropped as the bytes taken last, without a
    word.)"""
    def _same_run(folder, dom):
        folder.mkdir()
        d, env = dom
        bag = str(folder / "same")
        launch = Launch(realtime_config(folder), LaunchOptions(record=bag, trajectory=False,
            exclusive=False), env=env)
        probe = Probe(d)
        failed = None
        try:
            launch.start()
            assert probe.wait_state("armed", 60)
            for _ in range(3):
                r = subprocess.run([sys.executable, "-c", SAME_AGAIN, "1"], env=env,
                                   capture_output=True, text=True, timeout=120)
                assert r.returncode == 0, r.stderr[-2000:]
            assert probe.state == "armed", probe.states[-3:]
        except AssertionError as e:
            failed = e
        finally:
            probe.close()
            launch.stop()
        run = read_run(bag)
        if failed is not None:
            paused_by_the_host(run, failed)
        names = [s for _, s in run.states]
        never_faulted([(n,) for n in names[names.index("armed"):-1]])
        assert_ran_each(bag, 3)
    run_twice_at_most(_same_run, tmp_path, domain, ros_domains)


# an outside node between the real controller (its output remapped to command_raw) and
# the driver: forwards each command at once until FLAG exists, then DELAY s after it came
DELAYING_RELAY = r"""
import os, sys, time, collections
import rclpy
from rclpy.qos import QoSProfile, ReliabilityPolicy
from geometry_msgs.msg import Vector3Stamped
flag, delay = sys.argv[1], float(sys.argv[2])
try:  # like the loop's nodes: starved at normal priority, it lagged up to 29 ms
    os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(40))
except OSError:
    pass
rclpy.init()
n = rclpy.create_node("delaying_relay")
qos = QoSProfile(depth=5000, reliability=ReliabilityPolicy.RELIABLE)
pub = n.create_publisher(Vector3Stamped, "/stage/command", qos)
queue = collections.deque()
n.create_subscription(Vector3Stamped, "/stage/command_raw",
                      lambda m: queue.append((time.monotonic(), m)), qos, raw=True)
late = False
try:
    while rclpy.ok():
        rclpy.spin_once(n, timeout_sec=0.0005)
        late = late or os.path.exists(flag)
        now = time.monotonic()
        while queue and (not late or now - queue[0][0] >= delay):
            pub.publish(queue.popleft()[1])
except KeyboardInterrupt:
    pass
"""


class _ControllerBehindARelay(Launch):
    """The controller in a process of its own (not composed with the feedforward), its
    commands remapped to the relay's input."""

    def __init__(self, config_path, options: LaunchOptions, env=None):
        super().__init__(config_path, dataclasses.replace(options, compose="none"), env=env)

    def command(self, node):
        cmd = super().command(node)
        return cmd + ["-r", "command:=command_raw"] if node == "controller" else cmd


def test_a_real_controllers_commands_late_fault_and_ramp_to_safe(tmp_path, domain,
                                                                 ros_domains):
    """The real controller's commands delayed 70 ms on their way to a driver with a
    40 ms look-ahead and a 150 ms stale timeout (a relay node in between): each arrives
    about 30 ms after the tick it is stamped for, is counted and
    dropped, and the stream faults the set within stale_timeout_s + 1 tick of the last
    one on time ("late commands: ... ms behind ..."), then ramps to the safe voltage
    within the slew limit. Real time: run once more on a host that starved it."""
    run_twice_at_most(_late_run, tmp_path, domain, ros_domains)


def paused_by_the_host(run, failed, stale=STALE):
    """A run that faulted where it should not: HostTooSlow when the driver's own samples
    show the host paused it for half of ``stale`` (its stale_timeout_s) or more in the
    200 ms before the first fault (the loop then finds its last command that old), else
    ``failed`` itself."""
    faults = [s for s, n in run.states if n == "faulted"]
    pause = host_pause_s(run.t_ns, faults[0] - 200_000_000, faults[0]) if faults else 0.0
    if pause >= 0.5 * stale:
        raise HostTooSlow(f"faulted, the host having paused the driver {pause * 1e3:.0f} ms "
                          f"(stale_timeout_s {stale * 1e3:.0f} ms): {failed}") from failed
    raise failed


class _NotArmed(Exception):
    pass


def _late_run(tmp_path, domain):
    tmp_path.mkdir()
    d, env = domain
    bag, flag = str(tmp_path / "late"), str(tmp_path / "late.flag")
    # the relay (stock rclpy) adds milliseconds of its own (up to 27 ms seen at a 20 ms
    # look-ahead, and past 25 ms in a slow hour of a busy host): a 40 ms
    # look-ahead takes them in, and a 70 ms delay is 30 ms past it; the first delayed
    # command then comes 70 ms and the relay's own after the last on time, within a
    # 150 ms stale timeout (at 50 ms it was a race with "stale commands")
    launch = _ControllerBehindARelay(
        realtime_config(tmp_path, "    lookahead_s: 0.040\n", LATE_STALE), LaunchOptions(
            record=bag, exclusive=False,
            nodes=["stage_driver", "feedforward", "controller", "trajectory"]), env=env)
    relay = subprocess.Popen([sys.executable, "-c", DELAYING_RELAY, flag, "0.070"], env=env)
    probe = Probe(d)
    try:
        launch.start()
        assert probe.wait_state("armed", 60), probe.states[-3:]
        k0 = len(probe.states)
        probe.spin(1.5)
        # (any fault while it should have stayed armed, also one it re-armed from)
        early = None if probe.state == "armed" and not any(
            s == "faulted" for s, _, _ in probe.states[k0:]) else probe.states[-3:]
        if early:  # before anything was delayed: judged once the set stopped
            raise _NotArmed()
        open(flag, "w").close()
        switched_ns = time.time_ns()
        k = len(probe.states)
        assert probe.wait_state("faulted", 5, after=k), probe.seen(k - 3)
        reason = next(r for s, r, _ in probe.states[k:] if s == "faulted")
        probe.spin(1.0)
    except _NotArmed:
        pass
    finally:
        probe.close()
        launch.stop()
        relay.send_signal(signal.SIGINT)
        relay.wait(10)
    if early:  # the host's pace, or a failure
        paused_by_the_host(read_run(bag), AssertionError(
            f"not armed before the test began: {early}"), LATE_STALE)
    assert reason.startswith("late commands: ") and "ms behind for" in reason, reason
    assert "arrived after their tick, dropped" in reason, reason
    run = read_run(bag)
    # the first fault after the switch (a tick's stamp may precede the wall clock read
    # at the switch by a tick or so; one before it is the early case above)
    fault_ns = min(s for s, n in run.states if n == "faulted" and s > switched_ns - 5_000_000)
    # the relay switches within a millisecond of the flag: the last command on time
    # came by then, and the fault within stale_timeout_s and one tick after it
    took = (fault_ns - switched_ns) * 1e-9
    assert took > 0, took
    judged_within(took, LATE_STALE + 0.001 + 0.005,
                  host_pause_s(run.t_ns, switched_ns, fault_ns), "late commands to a fault")
    k = run.t_ns >= fault_ns
    v0 = np.abs(run.v_V[k][0]).max()
    done = run.t_ns[k][np.all(np.abs(run.v_V[k]) < 1e-9, axis=1)]
    assert done.size, "never reached the safe voltage"
    judged_within((done[0] - fault_ns) * 1e-9, v0 / RAMP + 0.01,
                  host_pause_s(run.t_ns, fault_ns, int(done[0])), "the ramp to safe")
    assert_never_beyond_slew(run.t_ns, run.v_V)


def test_a_core_taken_before_the_start_refuses_at_start_or_runs_without_a_fault(
        tmp_path, domain, capfd):
    """A busy loop takes one core before the set starts; the set runs with `--rate auto`
    and the driver's own start-up check (a 2 x margin): each refusal runs it again at
    the lower rate the refusal names, never at the same or a higher one, and it either
    ends refused at start (never armed, never faulted, the safe voltage throughout,
    each refusal one line with the capacity it measured) or runs its 8 s armed with no
    fault. (Here: refused at 1,000, 500 and 250 Hz, 1.09-1.99 x, 2026-12-02.)"""
    import re
    d, env = domain
    cfg = tmp_path / "rt.yaml"
    cfg.write_text("/**/stage_driver:\n  ros__parameters:\n    mode: realtime\n"
                   f"    stale_timeout_s: {STALE}\n    safe_ramp_V_per_s: {RAMP}\n"
                   "/**/feedforward:\n  ros__parameters:\n    model_file: " + MODEL + "\n"
                   "/**/controller:\n  ros__parameters:\n    kp: 0.2\n"
                   "/**/trajectory:\n  ros__parameters:\n    kind: seed\n"
                   "    duration_s: 60.0\n")
    bag = str(tmp_path / "hogged")
    capfd.readouterr()
    hog = subprocess.Popen([sys.executable, "-c", "while True: pass"])
    try:
        time.sleep(0.5)
        launch = Launch(str(cfg), LaunchOptions(record=bag, exclusive=False, armed_s=8.0,
            nodes=["stage_driver", "feedforward", "controller", "trajectory"],
            rate="auto"), env=env)
        launch.quiet_stop = True
        rc = launch.run(launch.wall_bound())
    finally:
        hog.kill()
        hog.wait()
    err = capfd.readouterr().err
    sys.stderr.write(err)
    refusals = re.findall(r"this host sustains ([\d,]+) samples/s = ([\d.]+) x the "
                          r"(\d+) Hz rate", err)
    again = [float(r) for r in re.findall(r"running again at (\d+) Hz", err)]
    tried = [1000.0] + again
    assert all(a > b for a, b in zip(tried, tried[1:])), tried
    assert [float(r[2]) for r in refusals] == tried[:len(refusals)], (refusals, tried)
    run = read_run(bag)  # the last attempt's (a refused one's bag is removed)
    states = [s for _, s in run.states]
    assert "faulted" not in states, run.states
    if rc != 0:  # refused at start, every attempt
        assert len(refusals) == len(tried), (refusals, tried)
        assert all(float(m) < 2.0 for _, m, _ in refusals)
        assert "armed" not in states and "approaching" not in states
        assert np.all(run.v_V == 0.0)
    else:
        assert len(refusals) == len(tried) - 1
        assert "armed" in states


def test_rate_auto_takes_an_outside_trajectory_only_in_the_set_that_runs(tmp_path, domain,
                                                                          ros_domains):
    """`launch --rate auto --no-trajectory` started at a rate no host of this kind holds
    (4 x the one this host holds with margin), with examples/publish_trajectory.py
    started at the same moment: the driver refuses, the launcher runs the set again at
    a lower rate, and the publisher, which waits for the feedforward's subscription,
    meets only the set that runs (the feedforward takes outside inputs once the driver
    has armed): its trajectory is accepted once, runs to its end within tolerance, and
    the bag holds it once, with no fault. Before, a publisher that met a refused
    attempt lost its trajectory with it. (Twice at most, as the other real-time sets.)"""
    def _auto_run(folder, dom):
        _rate_auto_outside(folder, dom)
    run_twice_at_most(_auto_run, tmp_path, domain, ros_domains)


def _rate_auto_outside(tmp_path, domain):
    import re

    from rclpy.serialization import deserialize_message
    from trajectory_msgs.msg import JointTrajectory

    from piezo_stage.io.bag import iter_messages
    tmp_path.mkdir()
    d, env = domain
    # refused: the host holds RATE with 3 x (host_rate), so 4 x RATE with under 1.5 x
    start_hz = {1000.0: 5000.0, 500.0: 2000.0, 250.0: 1000.0}[RATE]
    cfg = realtime_config(tmp_path, rate=start_hz)
    text = open(cfg).read().replace("min_margin: 0.0", "min_margin: 2.0")
    open(cfg, "w").write(text)
    bag = str(tmp_path / "auto")
    launch = subprocess.Popen(
        [sys.executable, "-m", "piezo_stage.cli", "launch", "--params", cfg, "--rate",
         "auto", "--no-trajectory", "--record", bag, "--duration", "120"],
        env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
        start_new_session=True)
    pub = subprocess.Popen(
        [sys.executable, os.path.join(CONFIG, "..", "examples", "publish_trajectory.py"),
         "--timeout", "90"], env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
        text=True)
    try:
        t_end = time.monotonic() + 200.0
        while pub.poll() is None and time.monotonic() < t_end:
            if launch.poll() is not None:  # the launch ended (refused): nothing to wait for
                pub.send_signal(signal.SIGINT)
                break
            time.sleep(0.2)
        pub_out, pub_err = pub.communicate(timeout=30)
    finally:
        if pub.poll() is None:
            pub.kill()
        if launch.poll() is None:
            launch.send_signal(signal.SIGINT)
        out, err = launch.communicate(timeout=60)
    pub = subprocess.CompletedProcess(pub.args, pub.returncode, pub_out, pub_err)
    sys.stderr.write(err)  # this test's output, shown where it fails
    again = [float(r) for r in re.findall(r"running again at (\d+) Hz", err)]
    assert again and again[0] < start_hz, err[-3000:]
    # each try run again is said once, with what becomes of its bag; no node of a
    # refused try says it was stopped by a SIGINT the user never sent
    assert f"its bag replaces the {start_hz:g} Hz try's in {bag}" in err, err[-3000:]
    tries = err[:err.rindex("running again at")]  # (the last stop is this test's SIGINT)
    assert "stopped by SIGINT" not in tries, tries[-3000:]
    last = re.search(r"stage_driver refused to arm at .*", err)
    if last:  # every run refused: the host held no rate with margin then
        assert launch.returncode == 1 and pub.returncode != 0, (launch.returncode, err)
        raise HostTooSlow(last.group(0))
    run = read_run(bag)  # the attempt that ran (a refused one's bag is removed)
    try:
        assert pub.returncode == 0, (pub.stdout, pub.stderr, err[-3000:])
        assert "final error x" in pub.stdout, pub.stdout
        names = [s for _, s in run.states]
        never_faulted([(n,) for n in names[names.index("armed"):-1]])
    except AssertionError as e:  # a fault: the host's pause, or this test's failure
        paused_by_the_host(run, e)
    assert launch.returncode == 130, (launch.returncode, err[-3000:])
    assert "armed: taking trajectories, setpoints and moves" in err, err[-3000:]
    held = [deserialize_message(data, JointTrajectory) for topic, _, _, data
            in iter_messages(bag) if topic == "/stage/trajectory/accepted"]
    assert len(held) == 1, len(held)
    assert int(run.diagnostics["feedforward"]["trajectories"]) == 1


@pytest.mark.parametrize("rate", ["auto", "fixed"])
def test_a_margin_no_rate_holds_ends_the_launch_in_one_line_never_armed(tmp_path, domain,
                                                                       rate):
    """A real-time launch with a min_margin no host holds (100 x, the highest it
    takes), with an outside publisher (examples/publish_trajectory.py) started at the
    same moment: the driver refuses at start (under `--rate auto` no standard rate
    would have it, so the launcher runs no second set) and the launch ends with one
    line naming the rate refused, the capacity and the runs (exit 1); the stage never
    armed and stayed at the safe voltage. The refusal comes before the set took any
    input, at a rate of the user's as under `--rate auto`: the feedforward takes
    outside inputs once the driver has armed, so no trajectory was accepted and the
    publisher, which waits for the feedforward's subscription, never met it."""
    import re
    d, env = domain
    cfg = realtime_config(tmp_path)
    text = open(cfg).read().replace("min_margin: 0.0", "min_margin: 100.0")
    open(cfg, "w").write(text)
    bag = str(tmp_path / "refused")
    rate_args = ["--rate", "auto"] if rate == "auto" else []
    pub = subprocess.Popen(
        [sys.executable, os.path.join(CONFIG, "..", "examples", "publish_trajectory.py"),
         "--timeout", "60"], env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
        text=True, start_new_session=True)
    try:
        r = subprocess.run(
            [sys.executable, "-m", "piezo_stage.cli", "launch", "--params", cfg, *rate_args,
             "--no-trajectory", "--record", bag, "--duration", "60"],
            env=env, capture_output=True, text=True, timeout=120)
    finally:
        pub.send_signal(signal.SIGINT)
        pub_out, pub_err = pub.communicate(timeout=30)
    assert r.returncode == 1, (r.returncode, r.stderr[-3000:])
    assert "running again" not in r.stderr, r.stderr[-3000:]
    last = r.stderr.strip().splitlines()[-1]
    runs = f"; rate auto ran it once, at {RATE:g} Hz" if rate == "auto" else ""
    assert re.fullmatch(
        rf"piezo-stage launch: stage_driver refused to arm at {RATE:g} Hz: this host holds "
        rf"the loop at [\d,]+ samples/s, \d+\.\d\d x, under min_margin 100{re.escape(runs)}",
        last), last
    assert "died with exit code" not in r.stderr, r.stderr[-3000:]
    assert "taking trajectories, setpoints and moves" not in r.stderr, r.stderr[-3000:]
    run = read_run(bag)
    assert "armed" not in [s for _, s in run.states], run.states
    assert np.all(run.v_V == 0.0)
    # nothing taken: the bag holds no accepted trajectory, the feedforward counted none,
    # and the publisher, stopped by this test, never had its trajectory run
    from piezo_stage.io.bag import iter_messages
    assert not [t for t, _, _, _ in iter_messages(bag) if t.endswith("trajectory/accepted")]
    assert int(run.diagnostics["feedforward"]["trajectories"]) == 0, run.diagnostics
    assert pub.returncode != 0 and "final error" not in pub_out, (pub.returncode, pub_out,
                                                                    pub_err)
