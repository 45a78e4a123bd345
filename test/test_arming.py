"""Safe start-up and faults in the core: supervisor, approach, planner, command schedule,
state timeline, and the control law's safeguards (no ROS)."""

import math
import os

import numpy as np
import pytest

from piezo_stage.core.errors import ConfigError, PiezoStageError
from piezo_stage.core.loop.arming import (
    APPROACHING,
    ARMED,
    ARMING,
    DISARMED,
    FAULTED,
    ArmingParams,
    ArmingSupervisor,
    StateTimeline,
)
from piezo_stage.core.loop.clock import CommandSchedule
from piezo_stage.core.loop.control import PID, CompositeAxis, PIDGains, clamp_slew
from piezo_stage.core.loop.planner import APPROACH, HOLD, TRACK, Approach, ReferencePlanner
from piezo_stage.core.metrics import LatencyHistogram

MS = 1_000_000


@pytest.mark.parametrize("d", [0.0, 0.5, 30.0, 120.0])
def test_approach_respects_speed_and_acceleration_and_arrives(d):
    ap = Approach({"x": 5.0, "y": 5.0}, {"x": 5.0 + d, "y": 5.0 - d / 2}, 200.0, 20000.0)
    t = np.arange(0.0, ap.duration_s + 0.01, 1e-4)
    x = np.array([ap.at(tau)["x"] for tau in t])
    y = np.array([ap.at(tau)["y"] for tau in t])
    path = np.hypot(x - 5.0, y - 5.0)
    v = np.diff(path) / 1e-4
    a = np.diff(v) / 1e-4
    assert v.max(initial=0) <= 200.0 * (1 + 1e-6)
    assert np.abs(a).max(initial=0) <= 20000.0 * 1.01 + 1e-6 or d == 0.0
    np.testing.assert_allclose([x[-1], y[-1]], [5.0 + d, 5.0 - d / 2], atol=1e-12)
    np.testing.assert_allclose([x[0], y[0]], [5.0, 5.0], atol=1e-12)  # no step at start
    if d >= 30.0:  # long enough to cruise: duration = d_path / v + v / a
        np.testing.assert_allclose(ap.duration_s, math.hypot(d, d / 2) / 200.0 + 0.01,
                                   rtol=1e-9)


def test_planner_holds_then_approaches_then_runs_the_trajectory_clock():
    p = ReferencePlanner(100.0, 10000.0)
    t = np.arange(0, 1.0001, 0.001)
    p.set_trajectory(t, {"x": 20.0 + 0 * t, "y": 10.0 + 10 * t})
    p.hold({"x": 0.0, "y": 0.0})
    assert p.phase == HOLD and p.clock_s(0) is None
    d = [p.sample(k * MS) for k in range(400)]
    assert p.phase == TRACK
    first = p.clock_s(0) * -1e3  # ms at which the trajectory clock started
    assert 200 < first < 260      # the approach over ~22 um at 100 um/s took ~0.23 s
    steps = np.abs(np.diff([[q["x"], q["y"]] for q in d], axis=0)).max()
    assert steps <= 100.0 * 1e-3 + 1e-9  # never faster than the approach speed
    assert d[-1]["y"] == pytest.approx(10.0 + 10 * (399 - first) * 1e-3, abs=1e-6)
    # a fault (hold), then re-enable: the trajectory starts over, through the approach
    p.hold({"x": 3.0, "y": 4.0})
    assert p.sample(1000 * MS) == pytest.approx({"x": 3.0, "y": 4.0})
    assert p.phase == APPROACH
    # a new goal while tracking is approached from the present position, not jumped to
    for k in range(1001, 1400):
        p.sample(k * MS)
    p.set_setpoint({"x": 60.0, "y": 60.0})
    a, b = p.sample(1400 * MS), p.sample(1401 * MS)
    assert max(abs(b["x"] - a["x"]), abs(b["y"] - a["y"])) < 0.2


def sup(**kw):
    changes = []
    s = ArmingSupervisor(ArmingParams(**{"confirm_ticks": 5, **kw}), {"x": 0.0, "y": 0.0},
                         1e-3, 3 * MS, lambda st, why, since: changes.append((st, since)))
    return s, changes


def run_ticks(s, n, k0=0, cmd=None, fresh=True):
    out = []
    for k in range(k0, k0 + n):
        if fresh:
            s.note_command(k * MS)
        v = s.tick(k * MS, k * MS, cmd if cmd is not None else dict(s.v), True)
        s.applied(v)
        out.append(v)
    return out


def test_arming_needs_the_loop_closed_and_takes_effect_ahead():
    s, changes = sup()
    ok, why = s.request_arm(0)
    assert not ok and "loop not closed" in why
    for k in range(3):  # commands that do not answer (late): no evidence
        s.tick(k * MS, k * MS, {"x": 0.0, "y": 0.0}, False)
    assert not s.request_arm(3 * MS)[0] and "after the tick" in s.request_arm(3 * MS)[1]
    run_ticks(s, 5, 3)
    ok, why = s.request_arm(8 * MS)
    assert ok and s.state == APPROACHING and s.enable_ns == 11 * MS
    assert changes[-1] == (APPROACHING, 11 * MS)
    v = run_ticks(s, 2, 8, cmd={"x": 50.0, "y": 50.0})  # before enable_ns: still safe
    assert v[-1] == {"x": 0.0, "y": 0.0}
    v = run_ticks(s, 3, 10, cmd={"x": 50.0, "y": 50.0})
    assert v[-1] == {"x": 50.0, "y": 50.0}
    s.set_tracking(True, 13 * MS)
    assert s.state == ARMED and changes[-1] == (ARMED, 13 * MS)


def test_stale_commands_fault_ramp_to_safe_and_auto_re_arm():
    s, changes = sup(auto_arm=True, ramp_V_per_s=1000.0, stale_s=0.01)
    run_ticks(s, 6)
    assert s.state == APPROACHING
    run_ticks(s, 10, 6, cmd={"x": 40.0, "y": 40.0})
    assert s.v == {"x": 40.0, "y": 40.0}
    v = run_ticks(s, 60, 16, cmd={"x": 40.0, "y": 40.0}, fresh=False)  # controller gone
    assert s.state == FAULTED and "stale" in s.reason
    ramp = np.array([q["x"] for q in v])
    assert np.all(np.diff(ramp) >= -1.0 - 1e-9) and ramp[-1] == 0.0  # 1 V per tick
    assert ramp[:10].min() == 40.0  # held until stale (10 ms)
    run_ticks(s, 4, 76)  # back, but not yet enough evidence: still faulted
    assert s.state == FAULTED
    run_ticks(s, 2, 80)
    assert s.state == APPROACHING and s.counts == {"faults": 1, "arms": 2}


def test_e_stop_latches_until_disarm_and_arm():
    s, _ = sup(auto_arm=True)
    run_ticks(s, 6)
    s.trigger_estop(6 * MS)
    v = run_ticks(s, 20, 6)
    assert s.state == FAULTED and v[-1] == {"x": 0.0, "y": 0.0}
    assert not s.request_arm(26 * MS)[0]
    s.request_disarm(26 * MS)
    assert s.state == DISARMED
    run_ticks(s, 6, 26)
    assert s.request_arm(32 * MS)[0]


def test_disarmed_with_a_request_waits_in_arming():
    s, changes = sup(auto_arm=True)
    s.tick(0, 0, None, False, "no controller: nothing publishes /stage/command")
    assert s.state == ARMING and "no controller" in s.reason


def test_command_schedule_applies_at_the_stamped_tick_and_counts_late():
    c = CommandSchedule(1000, MS, 5 * MS)
    c.add(1000 + 7 * MS, {"x": 7.0}, 1000 + 3 * MS, last_tick=2)
    c.add(1000 + 8 * MS, {"x": 8.0}, 1000 + 3 * MS, last_tick=2)
    assert c.due(6) == (None, False)          # nothing for tick 6 yet
    assert c.due(7) == ({"x": 7.0}, True)
    assert c.due(9) == ({"x": 8.0}, False)    # none for 9: the newest earlier one, held
    c.add(1000 + 9 * MS, {"x": 9.0}, 1000 + 10 * MS, last_tick=9)  # after its tick:
    assert c.late == 1 and c.due(10) == ({"x": 8.0}, False)  # counted, dropped
    assert c.arrival_lag.percentile(50) == pytest.approx(1e-3, abs=2e-5)  # lags 1, 0, 6 ms


def test_command_schedule_reports_its_longest_hold_since_it_was_last_asked():
    c = CommandSchedule(1000, MS, 5 * MS)
    for j in (1, 2, 6, 7, 8, 9, 11):  # missing: 3-5 (three in a row), 10
        c.add(1000 + j * MS, {"x": float(j)}, 1000, last_tick=0)
    for j in range(1, 12):
        c.due(j)
    assert c.held_ticks == 4 and c.longest_hold() == 3
    assert c.longest_hold() == 0  # asked again: nothing held since
    c.due(12)
    c.due(13)  # a hold under way when asked is carried into the next report
    assert c.longest_hold() == 2
    c.due(14)
    assert c.longest_hold() == 3
    assert c.due(15, count_held=False) == ({"x": 11.0}, False)  # the run ends
    assert c.longest_hold() == 3 and c.longest_hold() == 0  # reported up to its end


def test_state_timeline_newer_announcements_supersede():
    tl = StateTimeline()
    tl.add(100, APPROACHING)
    assert not tl.enabled(99) and tl.enabled(100)
    tl.add(50, FAULTED)  # a fault announced before the enable took effect cancels it
    assert tl.at(49) == DISARMED and tl.at(200) == FAULTED


def test_feedback_switches_bumplessly_and_does_not_wind_up():
    g = PIDGains(kp=0.5, ki=200.0)
    ax = CompositeAxis(PID(g, 1e-3), (0.0, 150.0))
    for _ in range(200):  # a steady error: the integral builds
        v, _ = ax.update(50.0, 0.1, True)
    v0 = v
    ax.set_feedback(False)
    off = [ax.update(50.0, 0.1, True)[0] for _ in range(500)]  # 10 fade time constants
    assert abs(off[0] - v0) < 0.1          # no drop when switched off: it fades
    assert off[-1] == pytest.approx(50.0, abs=0.01)
    ax.set_feedback(True)
    on = [ax.update(50.0, 0.4, True)[0] for _ in range(2)]
    assert abs(on[0] - off[-1]) < 0.1      # no jump when switched on
    # clamped at the top: the integral holds instead of winding up
    ax.reset()
    for _ in range(1000):
        ax.update(149.0, 5.0, True)
    assert ax.pid.integral < 2.0
    # loop not closed (hold): the integral holds; inactive: feedforward only
    ax.reset()
    ax.update(50.0, 1.0, True, hold=True)
    assert ax.pid.integral == 0.0
    assert ax.update(70.0, 3.0, False) == (70.0, False)


def test_clamp_slew_per_axis_limits():
    v, hit = clamp_slew({"x": 200.0, "y": -5.0}, {"x": 140.0, "y": 1.0},
                        {"x": (0.0, 150.0), "y": (-10.0, 10.0)}, {"x": 5.0, "y": 100.0})
    assert v == {"x": 145.0, "y": -5.0} and hit


def test_latency_histogram_percentiles():
    h = LatencyHistogram()
    for x in np.linspace(0, 0.01, 1001):
        h.add(x)
    assert h.percentile(50) == pytest.approx(0.005, abs=2e-5)
    assert h.percentile(99) == pytest.approx(0.0099, abs=2e-5)
    assert h.max_s == pytest.approx(0.01)


def test_bad_arming_parameters_are_refused():
    with pytest.raises(ConfigError):
        ArmingParams(ramp_V_per_s=0.0)
    with pytest.raises(ConfigError):
        Approach({"x": 0.0}, {"x": 1.0}, 0.0, 1.0)


def test_the_safe_ramp_keeps_its_rate_over_missed_ticks():
    s, _ = sup(ramp_V_per_s=1000.0)
    s.v = {"x": 10.0, "y": 10.0}
    assert s.tick(0, 0, None, False, periods=4) == {"x": 6.0, "y": 6.0}  # 4 ms: 4 V


def test_host_pauses_are_where_every_cpu_sentinel_stopped_at_once():
    import os
    import signal
    import time

    from benchmarks.host_pauses import HostPauseMonitor, inside, overlap
    # the overlap logic: only what every CPU shares, longer than the floor
    assert overlap([[(0, 10), (20, 30)], [(5, 25)]]) == [(5, 10), (20, 25)]
    assert overlap([[(0, 10)], [(12, 20)]]) == []
    assert overlap([[(0, 10)], [(0, 10)]], min_ns=10) == []
    assert inside(35, [(20, 30)], after_ns=5) and not inside(36, [(20, 30)], after_ns=5)
    # the real sentinels: stopping them all for 60 ms is a pause of about that length;
    # stopping one of them is not
    with HostPauseMonitor() as mon:
        time.sleep(0.3)
        s0 = time.time_ns()
        os.kill(mon.procs[0].pid, signal.SIGSTOP)
        time.sleep(0.06)
        os.kill(mon.procs[0].pid, signal.SIGCONT)
        s1 = time.time_ns()
        time.sleep(0.2)
        t0 = time.time_ns()
        for p in mon.procs:
            os.kill(p.pid, signal.SIGSTOP)
        time.sleep(0.06)
        for p in mon.procs:
            os.kill(p.pid, signal.SIGCONT)
        t1 = time.time_ns()
        time.sleep(0.2)
    # (a busy host adds real pauses of a few ms anywhere: only long ones are ours)
    long = [(a, b) for a, b in mon.pauses if b - a > 40_000_000]
    if len(mon.procs) > 1:  # one sentinel stopped alone is no pause
        assert not [p for p in long if p[0] < s1 and p[1] > s0], mon.pauses
    assert len(long) == 1, mon.pauses
    a, b = long[0]
    assert a >= t0 - 2_000_000 and b <= t1 + 2_000_000


def test_a_trajectory_starts_at_its_stamp_and_ends_done():
    """A future start time holds the first point after the approach until then; past
    the last point the phase is done and the last point is held."""
    from piezo_stage.core.loop.planner import DONE, TRACK, ReferencePlanner
    p = ReferencePlanner()
    p.hold({"x": 10.0, "y": 10.0})
    t = np.array([0.0, 0.1])
    p.set_trajectory(t, {"x": np.array([10.0, 20.0]), "y": np.array([10.0, 10.0])},
                     start_ns=500_000_000)
    assert p.sample(1_000_000)["x"] == 10.0            # at the goal already: approach ends
    assert p.sample(400_000_000)["x"] == 10.0 and p.phase == TRACK  # waits for 0.5 s
    assert abs(p.sample(550_000_000)["x"] - 15.0) < 1e-9           # half way at 0.55 s
    assert p.sample(600_000_000)["x"] == 20.0 and p.phase == TRACK
    assert p.sample(601_000_000)["x"] == 20.0 and p.phase == DONE  # the last point held
    p.set_trajectory(t, {"x": np.array([20.0, 20.0]), "y": np.array([10.0, 10.0])})
    assert p.phase != DONE                                          # a new one restarts


def test_a_lockstep_experiment_runs_long_enough_for_its_approach():
    """An experiment's lockstep case runs its trajectory, the planner's approach to the
    first point from rest (at the feedforward's approach speed, the case's own over the
    defaults) and a slack: farther first points and slower approaches get more steps."""
    import numpy as np

    from piezo_stage.apps.experiments import LOCKSTEP_SLACK_S, Case, lockstep_margin_s
    from piezo_stage.core.loop.planner import Approach

    config = os.path.join(os.path.dirname(os.path.dirname(__file__)), "config", "stage.yaml")
    t = np.arange(11) * 1e-3

    def case(x0, **ff):
        return Case("c", 1.0, t, {"x": np.full(11, x0), "y": np.zeros(11)}, "feedforward",
                    params={"feedforward": ff})

    near, far = lockstep_margin_s(case(1.0), config), lockstep_margin_s(case(80.0), config)
    assert LOCKSTEP_SLACK_S < near < far
    assert far == pytest.approx(LOCKSTEP_SLACK_S + Approach(
        {"x": 0.0, "y": 0.0}, {"x": 80.0, "y": 0.0}, 200.0, 20000.0).duration_s)
    assert far - LOCKSTEP_SLACK_S > 80.0 / 200.0  # the cruise alone
    slow = lockstep_margin_s(case(80.0, approach_speed_um_per_s=20.0), config)
    assert slow - LOCKSTEP_SLACK_S > 80.0 / 20.0


def test_the_controllers_law_is_one_call_per_reference():
    """core.control.CompositeController: v = ff + PID(asked(t_k) - measured(t_k)) while
    enabled; the feedforward alone (and a restart) while not; the integral holds while
    the loop is not closed; a gap in the references restarts it; never a non-finite
    command."""
    from piezo_stage.core.loop.control import PARAMETERS, CompositeController
    from piezo_stage.core.params import defaults
    p = defaults(PARAMETERS)
    p.update(kp=0.5, ki=100.0, kd=0.0, control_rate_hz=1000.0, relay_amplitude_V=0.0)
    c = CompositeController(p)
    dt = c.dt_ns
    w, ff = {"x": 10.0, "y": 10.0}, {"x": 20.0, "y": 20.0}
    v = c.on_sample(2 * dt, dt, {"x": 12.0, "y": 10.0}, ff, w, {"x": 0.0, "y": 0.0}, False)
    assert v == ff  # not enabled: the feedforward alone
    # enabled, t_k = 2 dt answered: asked 12 um there, measured 10: a 2 um error on x
    v = c.on_sample(3 * dt, 2 * dt, {"x": 12.0, "y": 10.0}, ff, w, dict(v), True)
    assert v["x"] > ff["x"] + 0.5 * 2.0 and v["y"] == pytest.approx(ff["y"])
    held = c.on_sample(4 * dt, 3 * dt, {"x": 12.0, "y": 10.0}, ff, w,
                       {"x": 0.0, "y": 0.0}, True)  # its command did not come back
    assert c.stats["not_closed"] == 1 and held["x"] == pytest.approx(v["x"])
    c.on_sample(40 * dt, 39 * dt, {"x": 12.0, "y": 10.0}, ff, w, {"x": 0.0, "y": 0.0},
                True)
    assert c.stats["restarts"] == 1  # a stall of 36 ticks
    nan = c.on_sample(41 * dt, 40 * dt, {"x": 12.0, "y": 10.0}, {"x": math.nan, "y": 0.0},
                      w, {"x": 0.0, "y": 0.0}, True)
    assert nan is None and c.stats["non_finite"] == 1
    with pytest.raises(PiezoStageError):
        c.set_gains(kp=-1.0)
    assert c.gains.kp == 0.5
