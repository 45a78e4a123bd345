"""Moves without ROS: the on-target judge (core/loop/ontarget.py), the move's profile in
the planner and the feedforward, the motion-time model, the moves closed around the
simulated stage (apps/studies/moves.py), and the adapters of a move and its verdict."""

import math

import numpy as np
import pytest
from hypothesis import example, given, settings
from hypothesis import strategies as st

from piezo_stage.core.errors import DataError
from piezo_stage.core.loop.motion import MotionTimeModel
from piezo_stage.core.loop.ontarget import MOVING, ON_TARGET, OnTargetJudge
from piezo_stage.core.loop.planner import APPROACH, DONE, ReferencePlanner

DT_NS = 1_000_000


def _judge_run(errors_true, noise_um, seed=0, tol=0.3, judge=None):
    """Feed a judge x = target + true error + noise, y at the target: -> (states per
    sample, the changes)."""
    judge = judge or OnTargetJudge(1e-3, tol, 0.005, 0.005)
    rng = np.random.default_rng(seed)
    for k in range(300):  # at rest first: the sensor's noise is learnt
        judge.sample(k * DT_NS, {"x": 10.0 + noise_um * rng.standard_normal(), "y": 0.0})
    t0 = 300 * DT_NS
    judge.begin("m1", {"x": 20.0, "y": 0.0}, t0)
    states, changes = [], []
    for k, e in enumerate(errors_true):
        c = judge.sample(t0 + k * DT_NS, {"x": 20.0 + e + noise_um * rng.standard_normal(),
                                          "y": noise_um * rng.standard_normal()})
        if c is not None:
            changes.append(c)
        states.append(judge.state)
    return states, changes


def test_a_settled_step_is_declared_after_its_window_and_a_departure_is_moving_again():
    e = np.concatenate([10.0 * np.exp(-np.arange(60) / 3.0), np.zeros(60),
                        np.full(40, 1.0), np.zeros(60)])
    states, changes = _judge_run(e, 0.0)
    first_in = int(np.argmax(np.abs(e) <= 0.3))
    on = states.index(ON_TARGET)
    assert first_in + 5 <= on <= first_in + 12  # the average, then the whole window
    assert changes[0].state == ON_TARGET and changes[0].move_id == "m1"
    assert changes[0].settle_s == pytest.approx((on - 5) * 1e-3, abs=2e-3)
    assert changes[0].axes == {"x": ON_TARGET, "y": ON_TARGET}
    assert changes[1].state == MOVING and states[121] == MOVING  # left the window
    assert changes[2].state == ON_TARGET and changes[2].move_id == "m1"  # judged again


def test_a_tolerance_near_the_noise_averages_longer_and_is_still_declared():
    e = np.zeros(400)
    states, _ = _judge_run(e, 0.1, tol=0.1)
    assert ON_TARGET in states
    assert states.index(ON_TARGET) > 30  # (6 sigma / tol)^2 = 36 samples averaged


def test_no_move_is_no_verdict_and_parameters_are_checked():
    j = OnTargetJudge(1e-3)
    assert j.sample(0, {"x": 1.0, "y": 2.0}) is None
    with pytest.raises(Exception, match="tolerance"):
        j.configure(0.0, 0.005, 0.005)


@settings(max_examples=60, deadline=None)
# a ring of about the noise's size, rising through the tolerance's edge as the average
# of its noisy samples reads low: the variance test cannot tell it from the noise
@example(tau_ms=1.0, ring_um=1.0, ring_hz=100.0, zeta=0.02, noise=0.015625, bias=0.28125,
         seed=0)
@example(tau_ms=1.0, ring_um=2.0, ring_hz=181.0, zeta=0.02, noise=0.0625, bias=-0.25,
         seed=377)  # 0.017 um past the tolerance: 0.27 of the noise's sigma
@given(tau_ms=st.floats(0.5, 20.0), ring_um=st.floats(0.0, 3.0),
       ring_hz=st.floats(100.0, 900.0), zeta=st.floats(0.02, 0.3),
       noise=st.floats(0.0, 0.12), bias=st.floats(-0.45, 0.45), seed=st.integers(0, 10**6))
def test_never_declared_while_the_true_position_is_outside(tau_ms, ring_um, ring_hz, zeta,
                                                          noise, bias, seed):
    """Whatever the approach (an exponential, a decaying ring, a bias left that may sit
    just outside or inside the tolerance) and the sensor's noise up to a third of the
    tolerance: the window that declared a move on target had the true position inside
    throughout on a noiseless sensor, and less than the noise's standard deviation past
    it on a noisy one (a ring of the noise's own size hides in it from any variance test
    over the average's samples, and the average's own noise may favour it: the examples
    below; 0.54 sigma was the most past in 7,500 random draws of these parameters); and
    once declared, a stage that leaves the tolerance (a drift through the band to a bias
    outside it) is moving again within the average's length, the lag any judge of a
    noisy sensor has."""
    t = np.arange(400) * 1e-3
    w = 2 * math.pi * ring_hz
    e = 8.0 * np.exp(-t / (tau_ms * 1e-3)) + ring_um * np.exp(-zeta * w * t) * np.sin(
        w * t) + bias
    judge = OnTargetJudge(1e-3, 0.3, 0.005, 0.005)
    states, changes = _judge_run(e, noise, seed, judge=judge)
    on = np.array([s == ON_TARGET for s in states])
    # (past the running sums' rounding; on a noisy sensor, what its noise can hide)
    outside = np.abs(e) > 0.3 + (noise if noise > 0 else 1e-9)
    lag = judge.axes["x"].n_filter
    for c in changes:
        if c.state == ON_TARGET:
            k = int(round(c.settle_s / 1e-3))
            end = k + int(np.argmax(on[k:]))  # the declaring window: [k, end]
            assert not outside[k:end + 1].any(), (k, end, e[k:end + 1])
    run = 0
    for bad in on & outside:
        run = run + 1 if bad else 0
        assert run <= lag, (lag, np.flatnonzero(on & outside)[:10])


def test_a_move_runs_on_its_profile_and_a_one_point_trajectory_is_a_move():
    from piezo_stage.core.loop.feedforward import FeedforwardOptions, InverseFeedforward
    p = ReferencePlanner(200.0, 20000.0)
    p.hold({"x": 0.0, "y": 0.0})
    p.set_move({"x": 10.0, "y": 0.0}, 5000.0, 5e6)
    xs = [p.sample(k * DT_NS)["x"] for k in range(10)]
    assert p.phase == DONE and xs[-1] == 10.0
    assert 0 < xs[1] < 10.0 and np.all(np.diff(xs) >= 0)  # ~3 ms, not the approach's 60
    assert int(np.argmax(np.asarray(xs) >= 10.0)) <= 4
    p.set_move({"x": 0.0, "y": 0.0}, 5000.0, 5e6, start_ns=20 * DT_NS)  # held to its start
    assert p.sample(15 * DT_NS)["x"] == 10.0 and p.phase == APPROACH
    ff = InverseFeedforward(ReferencePlanner(), DT_NS,
                            FeedforwardOptions(wait_for_trajectory=True))
    r = ff.on_sample(0, {"x": 0.0, "y": 0.0}, {"x": 0.0, "y": 0.0}, DT_NS, lambda t: True,
                     realtime=False)
    assert r.wait  # lockstep waits for a trajectory...
    ff.set_trajectory(np.array([0.0]), {"x": np.array([5.0]), "y": np.array([6.0])}, 77,
                      None)
    assert ff.judge.move_id == "trajectory of 1 points stamped 77"
    assert ff.judge.target == {"x": 5.0, "y": 6.0}
    r = ff.on_sample(0, {"x": 0.0, "y": 0.0}, {"x": 0.0, "y": 0.0}, DT_NS, lambda t: False,
                     realtime=False)
    assert not r.wait and r.answers  # ... and a move is one
    ff.on_sample(DT_NS, {"x": 0.0, "y": 0.0}, {"x": 0.0, "y": 0.0}, DT_NS, lambda t: True,
                 realtime=False)
    assert ff.phase() == (APPROACH, "trajectory of 1 points stamped 77")
    y_now = ff.planner.desired["y"]
    first = ff.move("lab-1", {"x": 7.0})
    assert first.state == MOVING and first.move_id == "lab-1"
    assert first.target_um == {"x": 7.0, "y": y_now}  # the axis not named is held
    assert ff.phase()[1] == "move lab-1"
    # asked again (an asker that heard nothing sends it once more): the same move, not a
    # restart; another target under that id, or another id, is a new move
    started = ff.judge.started_ns
    for k in range(2, 6):
        ff.on_sample(k * DT_NS, {"x": 1.0, "y": y_now}, {"x": 0.0, "y": 0.0}, DT_NS,
                     lambda t: True, realtime=False)
    again = ff.move("lab-1", {"x": 7.0})
    assert again.move_id == "lab-1" and again.state == MOVING
    assert ff.judge.started_ns == started and again.stamp_ns == 5 * DT_NS
    assert again.error_um and again.error_um["x"] < -5.0  # its errors so far
    assert ff.move("lab-1", {"x": 8.0}).stamp_ns > 5 * DT_NS  # restarted: a new target
    assert ff.judge.target["x"] == 8.0 and ff.judge.started_ns > started


def test_the_motion_time_model_recovers_its_terms_and_refuses_too_few_steps():
    truth = MotionTimeModel(0.004, 0.0005, 0.002, 0.3)
    s = np.exp(np.linspace(np.log(0.2), np.log(40.0), 30))
    t = np.array([truth.predict(x) for x in s])
    fit = MotionTimeModel.fit(s, t, 0.3)
    assert fit.a_s == pytest.approx(0.004, rel=1e-6)
    assert fit.b_s_per_um == pytest.approx(0.0005, rel=1e-6)
    assert fit.ring_s == pytest.approx(0.002, rel=1e-6)
    assert MotionTimeModel.from_dict(fit.to_dict()) == fit
    with pytest.raises(DataError, match="three steps"):
        MotionTimeModel.fit([1.0, 1.0, 1.0], [0.01, 0.01, 0.01], 0.3)
    with pytest.raises(DataError, match="motion time model"):
        MotionTimeModel.from_dict({"a_s": 1})


def test_moves_on_the_simulated_stage_settle_faster_with_the_inverse_and_are_judged_true():
    """The default stage, 10 random 10 um steps: the composite law settles in under a
    third of the PID alone's time (true position), and the judge declares none falsely
    and misses none, with either law."""
    from dataclasses import replace

    from benchmarks.settle import STAGES, _stage, _walk
    from piezo_stage.apps.studies.moves import MoveSetup, run_moves
    name, plant, model = STAGES[0]
    res = {}
    for comp in (True, False):
        start, targets = _walk(np.random.default_rng(3), 10, lambda r: 10.0)
        res[comp] = run_moves(*_stage(plant, model, 0), targets,
                              replace(MoveSetup(), composite=comp), start=start)
    for rs in res.values():
        assert all(r.declared_s is not None for r in rs)
        assert sum(r.false_samples for r in rs) == 0 and not any(r.missed for r in rs)
        assert all(abs(r.step_um - 10.0) < 1e-6 for r in rs)
    c = np.median([r.true_settle_s for r in res[True]])
    p = np.median([r.true_settle_s for r in res[False]])
    assert c < p / 3, (c, p)


def test_a_move_and_its_verdict_through_the_adapters():
    pytest.importorskip("rclpy")
    import piezo_stage_msgs_adapters as A
    from piezo_stage.core.loop.ontarget import TargetState
    m = A.move_msg("scan-7", {"x": 12.5, "y": 40.0}, 5)
    assert A.move_from_msg(m, (-10.0, 90.0)) == ("scan-7", pytest.approx(
        {"x": 12.5, "y": 40.0}))
    with pytest.raises(DataError, match="outside the stage range"):
        A.move_from_msg(A.move_msg("a", {"x": 120.0, "y": 0.0}), (-10.0, 90.0))
    with pytest.raises(DataError, match="id of over"):
        A.move_from_msg(A.move_msg("a" * 201, {"x": 1.0, "y": 0.0}))
    s = TargetState("scan-7", ON_TARGET, {"x": ON_TARGET, "y": ON_TARGET}, 0.0123,
                    {"x": 0.01, "y": -0.02}, {"x": 12.5, "y": 40.0}, 123_000_000, 100_000_000)
    back = A.on_target_from_msg(A.on_target_msg(s))
    assert back == s
    moving = TargetState("m", MOVING, {"x": MOVING}, None, {}, {"x": 1.0}, 5, 5)
    assert A.on_target_from_msg(A.on_target_msg(moving)).settle_s is None
    from diagnostic_msgs.msg import DiagnosticArray
    with pytest.raises(DataError, match="on_target"):
        A.on_target_from_msg(DiagnosticArray())


def test_a_move_never_asks_faster_than_the_amplifier_slews():
    """The move's speed is capped at half the driver's slew limit at the model's
    steepest mean gain: a 1,000 V/s amplifier gets a slow move, a fast one the
    profile's own speed."""
    from piezo_stage.core.loop.feedforward import MOVE_SLEW_SHARE, InverseFeedforward
    from piezo_stage.io.model_file import load_model
    from piezo_stage.paths import default_config
    model, effects = load_model(default_config("stage_model.yaml"))
    ff = InverseFeedforward(ReferencePlanner(), DT_NS)
    ff.set_model(model, effects, "model")
    assert ff.profile() == (5000.0, 5.0e6)  # no driver announced yet
    assert ff.profile(1.0e5) == (5000.0, 5.0e6)
    speed, _ = ff.profile(1000.0)
    assert speed == pytest.approx(MOVE_SLEW_SHARE * 1000.0 * ff.model_gain)
    assert 0.3 < ff.model_gain < 1.0  # um/V: the default stage's ~75 um over 150 V
