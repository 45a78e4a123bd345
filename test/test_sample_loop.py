"""The driver's sample loop without ROS (core/loop/sample_loop.py), on the simulated stage."""

import pytest

from piezo_stage.core.errors import DataError
from piezo_stage.core.loop.arming import ArmingParams
from piezo_stage.core.loop.sample_loop import (
    COMMAND_WINDOW_NS,
    LoopOptions,
    SampleLoop,
    check_mode,
)
from piezo_stage.drivers import SimBackend

RATE = 1000.0


def loop(lockstep=True, max_steps=0, **arm):
    changes = []
    s = SampleLoop(SimBackend("", RATE, 0), ArmingParams(**arm), LoopOptions(
        rate_hz=RATE, lockstep=lockstep, max_steps=max_steps, clock_period_s=0.01),
        lambda *a: changes.append(a))
    s.changes = changes
    return s


def close_the_loop(s, v=10.0):
    """Lockstep: commands that hold the applied voltage until arming may go ahead."""
    s.step(0, None, False, 0)
    j = 0
    while s.sup.evidence < s.sup.p.confirm_ticks:
        j += 1
        assert s.command(s.stamp(j), {"x": s.v["x"], "y": s.v["y"]}, 0)
        s.step(j, {"x": s.v["x"], "y": s.v["y"]}, True, s.stamp(j))
    return j


def test_lockstep_takes_the_next_samples_command_only():
    s = loop()
    s.step(0, None, False, 0)
    assert s.command(s.stamp(1), {"x": 1.0, "y": 1.0}, 0)
    assert not s.command(s.stamp(5), {"x": 1.0, "y": 1.0}, 0)
    assert s.stats["unexpected_stamp"] == 1
    out = s.step(1, {"x": 1.0, "y": 1.0}, True, s.stamp(1))
    assert out.ns == s.stamp(1) and s.j == 1 and s.stats["samples"] == 2
    assert out.applied == {"x": 0.0, "y": 0.0}  # disarmed: the safe voltage, not the command


def test_real_time_never_schedules_a_command_stamped_far_from_its_arrival():
    s = loop(lockstep=False)
    recv = 10**12
    assert not s.command(recv + COMMAND_WINDOW_NS + 1, {"x": 1.0, "y": 1.0}, recv)
    assert s.stats["unexpected_stamp"] == 1 and s.sched.received == 0
    assert not s.command(recv + 5_000_000, {"x": 1.0, "y": 1.0}, recv)
    assert s.sched.received == 1 and s.stats["unexpected_stamp"] == 1


def test_arming_names_the_missing_link_when_refused_and_estop_latches():
    s = loop()
    s.step(0, None, False, 0)
    ok, message = s.arm(True, "no command from /stage/controller")
    assert not ok and message.endswith("(no command from /stage/controller)")
    close_the_loop(s)
    ok, message = s.arm(True, "no command from /stage/controller")
    assert ok and "no command" not in message and s.sup.state == "approaching"
    assert "latched" in s.estop() and s.sup.state == "faulted"
    assert not s.arm(True)[0]  # latched until a disarm
    assert s.arm(False)[0] and s.arm(True)[0]


def test_missed_ticks_hold_the_voltage_and_widen_the_slew_step():
    s = loop()
    j = close_the_loop(s)
    s.arm(True)
    # a jump far beyond one sample's slew: held back to the slew over the samples
    s.backend.slew_V_per_s = {"x": 1000.0, "y": 1000.0}
    s.max_step = {"x": 1.0, "y": 1.0}
    before = dict(s.v)
    s.step(j + 3, {"x": 100.0, "y": 100.0}, True, s.stamp(j + 3), missed=2)
    assert s.stats["missed_ticks"] == 2 and s.j == j + 3
    assert s.v["x"] == pytest.approx(before["x"] + 3.0)  # three samples' worth of slew
    assert s.stats["limit_hits"] == 1


def test_a_stop_ramps_to_the_safe_voltage_before_the_loop_may_end():
    s = loop(lockstep=False, safe_V=0.0, ramp_V_per_s=10000.0, max_steps=50)
    s.backend.start()
    j = 0
    s.step(j, None, False, 0)
    s.v = {"x": 30.0, "y": 20.0}  # where the stage was when told to stop
    assert s.past_max_steps(51) and not s.past_max_steps(10)
    budget = s.begin_shutdown()
    assert budget >= 2 * 30.0 / 10000.0 + 6.0 and s.sup.state == "disarmed"
    assert not s.shut_down and not s.past_max_steps(51)
    while not s.shut_down:
        j += 1
        s.step(j, None, False, s.stamp(j))
        assert j < 100
    assert s.v == {"x": 0.0, "y": 0.0}
    assert "disarmed" in s.summary() and "x 0.000 V" in s.summary()


def test_clock_and_state_announcement():
    s = loop()
    for j in range(11):
        s.step(j, None, False, s.stamp(j))
        assert s.clock_due == (j % 10 == 0)
    a = s.announced()
    assert a["control_rate_hz"] == RATE and a["lookahead_s"] == pytest.approx(1e-3)
    assert a["voltage_limit_lo_V"] < a["voltage_limit_hi_V"]
    assert s.feedforward_phase("tracking", "trajectory of 10 points stamped 0")
    assert not s.feedforward_phase("tracking", "trajectory of 10 points stamped 0")
    a = s.announced()
    assert (a["feedforward_phase"], a["feedforward_follows"]) == (
        "tracking", "trajectory of 10 points stamped 0")


@pytest.mark.parametrize("backend, mode, sim_time", [("daq", "lockstep", False),
                                                     ("pi", "lockstep", False),
                                                     ("sim", "realtime", True)])
def test_modes_a_backend_cannot_run(backend, mode, sim_time):
    with pytest.raises(DataError):
        check_mode(backend, mode, sim_time)
    check_mode("sim", "lockstep", sim_time)


def test_real_time_a_stream_of_late_commands_faults_like_none():
    """A controller that falls behind (its commands arrive 30 ticks after the tick they
    are stamped for, as a restarted one once did for 240 ms) is followed by no one: its
    late commands are dropped (the stage holds the last one on time) and only commands
    on time keep the loop fresh, so it faults within stale_timeout_s of the last one on
    time, and says how far behind the late ones came."""
    s = loop(lockstep=False, stale_s=0.05, confirm_ticks=10)
    ms = 1_000_000

    def run(j0, n, lag, v):
        for j in range(j0, j0 + n):
            k = j - lag if lag > 0 else j + 5  # late: for a tick already run
            if k >= 0:
                s.command(s.stamp(k), dict(v) if v else dict(s.v), s.stamp(j))
            cmd, on_time = s.sched.due(j, count_held=s.sup.state in ("approaching",
                                                                     "armed"))
            s.step(j, cmd, on_time, s.stamp(j))
        return j0 + n

    j = run(0, 20, 0, None)  # holding the applied voltage, on time: the loop closes
    assert s.arm(True)[0]
    j = run(j, 100, 0, {"x": 5.0, "y": 5.0})
    assert s.sup.state == "approaching" and s.v == {"x": 5.0, "y": 5.0}
    last_on_time = s.stamp(j - 1)
    late_before = s.sched.late
    j = run(j, 5, 30, {"x": 9.0, "y": 9.0})  # late, and different: never applied
    assert s.v == {"x": 5.0, "y": 5.0}
    j = run(j, 95, 30, {"x": 5.0, "y": 5.0})
    assert s.sched.late - late_before == 100
    faulted = [ns for state, _, ns in s.changes if state == "faulted"]
    assert len(faulted) == 1 and 0.05 < (faulted[0] - last_on_time) / ms <= 52
    assert s.sup.reason.startswith("late commands: 30 ms behind for 5"), s.sup.reason
    assert "arrived after their tick, dropped" in s.sup.reason
    # the fault's ramp (5 V at 500 V/s) has ended at the safe voltage: what a managed
    # driver's error transition waits for, and reports; never before a fault
    assert s.at_safe and s.faulted_at_safe == "faulted: " + s.sup.reason
    s.v = {"x": 1.0, "y": 0.0}  # (the safe voltage is 0 V)
    assert s.faulted_at_safe is None  # faulted, on the way to safe
    fresh = loop()
    assert fresh.at_safe and fresh.faulted_at_safe is None  # at safe, not faulted


def test_the_lifecycle_transitions_are_the_loops_own():
    """A managed driver's configure (arming left to activate), activate (the explicit
    re-arm of a latched e-stop), deactivate and a hardware fault, on the core alone."""
    changes = []
    s = SampleLoop(SimBackend("", RATE, 0), ArmingParams(auto_arm=True), LoopOptions(
        rate_hz=RATE, lockstep=True, arm_on_start=False), lambda *a: changes.append(a))
    close_the_loop(s)
    assert s.sup.state == "disarmed" and not s.sup.arm_requested  # configure: held
    state, reason = s.activate(arm=False)
    assert (state, reason) == ("disarmed", "activated: arm on the arm service")
    s.estop()
    assert s.sup.estop
    state, reason = s.activate(arm=True)
    assert not s.sup.estop and s.sup.arm_requested  # activate released the latch
    assert reason == "activated: waiting for the loop to close"
    state, reason = s.deactivate()
    assert not s.sup.arm_requested and reason == "deactivated: ramping to the safe voltage"
    s.reject_command()
    assert s.stats["rejected"] == 1
    s.hardware_fault("link lost")
    assert s.sup.state == "faulted" and s.sup.reason == "hardware: link lost"
    s.end_now()
    assert s.shutdown_requested


def test_a_whole_lockstep_run_from_the_loops_outcomes_alone():
    """Arm, track, fault, end: one call per message (on_start, on_command), each
    answered by an Outcome the driver only has to follow."""
    from piezo_stage.core.loop.planner import TRACK
    from piezo_stage.core.loop.sample_loop import Next
    s = SampleLoop(SimBackend("", RATE, 0), ArmingParams(auto_arm=True), LoopOptions(
        rate_hz=RATE, lockstep=True, max_steps=600), lambda *a: None)
    out = s.on_start()
    assert out.sample is not None and out.next is Next.NONE and out.sample.ns == s.stamp(0)
    assert not s.on_command(s.stamp(7), {"x": 0.0, "y": 0.0}, 0).sample  # not the next one
    states, nexts, armed_at = [], [], None
    while True:
        j = s.j + 1
        if s.sup.state == "approaching" and j == 100:  # the feedforward's phase message
            assert s.feedforward_phase(TRACK, "trajectory of 2 points stamped 0")
        if armed_at is None and s.sup.state == "armed":
            armed_at = j
        # hold where the stage is until armed, then ramp x up 10 V over 100 samples
        cmd = dict(s.v) if armed_at is None else \
            {"x": 10.0 * min(1.0, (j - armed_at) / 100), "y": 0.0}
        if j == 400:
            s.estop()  # the fault: latched, ramping to the safe voltage
        out = s.on_command(s.stamp(j), cmd, 0)
        nexts.append(out.next)
        if out.next is Next.DONE:
            assert out.sample is None
            break
        assert out.sample is not None and out.sample.ns == s.stamp(j)
        states.append(s.sup.state)
        if armed_at is not None and j == armed_at + 200:  # tracking: the command applied
            assert abs(out.sample.applied["x"] - 10.0) < 1e-9
    assert armed_at is not None and "approaching" in states and states[-1] == "faulted"
    assert Next.FAULTED_AT_SAFE in nexts  # once the fault's ramp reached safe
    assert nexts.index(Next.FAULTED_AT_SAFE) > 400 - 2 and s.j == 600


def test_a_real_time_stop_and_a_hardware_fault_are_outcomes():
    """Real time: max_steps begins the stop (its bound said once), the ramp ends in
    SHUT_DOWN; a backend fault is a FAULT outcome carrying the error, no sample."""
    from piezo_stage.core.errors import BackendFault
    from piezo_stage.core.loop.sample_loop import Next
    s = SampleLoop(SimBackend("", RATE, 0), ArmingParams(), LoopOptions(
        rate_hz=RATE, lockstep=False, max_steps=50), lambda *a: None)
    t, outs = 100.0, []
    while not outs or outs[-1].next is Next.NONE:
        t += 1 / RATE
        outs.append(s.on_tick(t, lambda: int(t * 1e9)))
        assert len(outs) < 5000
    began = [o.stop_began_s for o in outs if o.stop_began_s is not None]
    assert len(began) == 1 and began[0] > 0 and outs[-1].next is Next.SHUT_DOWN
    assert all(o.deadline is not None and o.sample is not None for o in outs)

    class Failing(SimBackend):  # the simulated stage losing its link at sample 20
        def step(self, vx, vy):
            if self.plant.samples >= 20:
                raise BackendFault("link lost")
            return super().step(vx, vy)
    f = SampleLoop(Failing("", RATE, 0), ArmingParams(), LoopOptions(
        rate_hz=RATE, lockstep=True), lambda *a: None)
    out = f.on_start()
    while out.next is Next.NONE:
        out = f.on_command(f.stamp(f.j + 1), dict(f.v), 0)
    assert out.next is Next.FAULT and out.sample is None and "link lost" in str(out.error)
    assert f.sup.state == "faulted"


def test_the_loop_says_its_state_and_why_without_the_supervisor_read_through_it():
    """The driver node reads the loop's state and reason from the loop itself (the
    supervisor stays the loop's own): they follow every change."""
    s = SampleLoop(SimBackend("", RATE, 0), ArmingParams(auto_arm=True), LoopOptions(
        rate_hz=RATE, lockstep=True, arm_on_start=False), lambda *a: None)
    assert (s.state, s.reason) == ("disarmed", "started disarmed")
    close_the_loop(s)
    s.activate(arm=True)
    assert s.reason == "activated: waiting for the loop to close" == s.sup.reason
    s.hardware_fault("link lost")
    assert (s.state, s.reason) == ("faulted", "hardware: link lost")
