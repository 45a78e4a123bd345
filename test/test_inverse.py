"""Exact inverse of the discrete Duhem model, and the paper's eq. 12 for comparison."""

import numpy as np
import pytest

from conftest import sine_v
from piezo_stage.core.model.inverse import invert, invert_seed_eq12, invert_stage


@pytest.mark.parametrize("axis", ["x", "y"])
def test_round_trip_on_reachable_targets(stage_model, axis):
    m = stage_model.axes[axis]
    rng = np.random.default_rng(3)
    # a reachable target: the model's own response to a random smooth voltage
    v = np.clip(75 + np.cumsum(rng.normal(0, 2.0, 5000)), 0, 150)
    target, _ = m.simulate(v)
    r = invert(m, target)
    assert r.n_saturated == 0
    w, _ = m.simulate(r.v)
    np.testing.assert_allclose(w, target, atol=1e-6, rtol=0)
    np.testing.assert_allclose(r.w, w, atol=1e-12)


def test_round_trip_seed_trajectory(stage_model):
    # the paper's desired displacement y(t) = 21 + 24 sin(2 pi 10 t - pi/2) um
    m = stage_model.axes["y"]
    t = np.arange(3000) / 10_000
    target = 21 + 24 * np.sin(2 * np.pi * 10 * t - np.pi / 2)
    # from the virgin state (0 V, 0 um) -3 um is out of reach: it is flagged
    assert invert(m, target).saturated[0]
    # after one full-stroke cycle the stage sits on its lower branch, where it is not
    _, v = sine_v(1.0, 1000, 1)
    _, state = m.simulate(v)
    r = invert(m, target, state=state)
    assert r.n_saturated == 0
    w, _ = m.simulate(r.v, state)
    np.testing.assert_allclose(w, target, atol=1e-6, rtol=0)
    assert 0 <= r.v.min() and r.v.max() <= 150


def test_unreachable_targets_saturate_and_are_reported(stage_model):
    m = stage_model.axes["x"]
    target = np.concatenate([np.linspace(0, 200, 500), np.linspace(200, -50, 500)])
    r = invert(m, target)
    assert r.n_saturated > 0
    assert r.v.max() == 150.0 and r.v.min() == 0.0
    sat = r.saturated
    # where flagged, the voltage sits at a limit and the state is what the model does
    assert np.all((r.v[sat] == 150.0) | (r.v[sat] == 0.0))
    w, _ = m.simulate(r.v)
    np.testing.assert_allclose(r.w, w, atol=1e-12)
    # where not flagged, the target is met
    np.testing.assert_allclose(w[~sat], target[~sat], atol=1e-6)


def test_seed_eq12_is_only_first_order(stage_model):
    m = stage_model.axes["x"]
    # start on the loop: from the virgin state the branch slope at 0 V is ~0 and the
    # explicit form overshoots to the limit (the exact inverse has no such problem)
    _, state = m.simulate(sine_v(1.0, 1000, 1)[1])
    errs = []
    for fs in (1000, 4000, 16000):
        _, v = sine_v(1.0, fs, 2, lo=0, hi=140)
        target, _ = m.simulate(v, state)
        r = invert_seed_eq12(m, target, state=state)
        w, _ = m.simulate(r.v, state)
        errs.append(np.max(np.abs(w - target)))
        exact = invert(m, target, state=state)
        assert np.max(np.abs(m.simulate(exact.v, state)[0] - target)) < 1e-6
    assert errs[0] > 1e-3  # the explicit form is not exact ...
    assert errs[2] < errs[0] / 4  # ... but converges as the steps shrink


def test_joint_inverse_with_coupling(stage_model):
    t = np.arange(4000) / 4000
    wx = 30 + 20 * np.sin(2 * np.pi * 2 * t)
    wy = 25 + 15 * np.cos(2 * np.pi * 3 * t)
    res = invert_stage(stage_model, wx, wy)
    w, _ = stage_model.simulate(res["x"].v, res["y"].v)
    np.testing.assert_allclose(w["x"], wx, atol=1e-6)
    np.testing.assert_allclose(w["y"], wy, atol=1e-6)
    # ignoring the coupling would miss by about the coupling amplitude
    rx = invert(stage_model.axes["x"], wx)
    ry = invert(stage_model.axes["y"], wy)
    w2, _ = stage_model.simulate(rx.v, ry.v)
    assert np.max(np.abs(w2["x"] - wx)) > 0.3


def test_stage_inverse_per_sample_matches_the_model(stage_model):
    from piezo_stage.core.model.inverse import StageInverse
    t = np.arange(2000) / 2000
    wx = 30 + 20 * np.sin(2 * np.pi * 2 * t)
    wy = 25 + 15 * np.cos(2 * np.pi * 3 * t)
    inv = StageInverse(stage_model)
    v = np.array([inv.step(a, b)[:2] for a, b in zip(wx, wy)])
    w, _ = stage_model.simulate(v[:, 0], v[:, 1])
    np.testing.assert_allclose(w["x"], wx, atol=1e-6)
    np.testing.assert_allclose(w["y"], wy, atol=1e-6)
    # sync with other voltages: the next step starts from the state they produced
    inv2 = StageInverse(stage_model)
    applied = v + 0.5
    for k in range(len(t)):
        inv2.sync(*applied[k])
    w2, st = stage_model.simulate(applied[:, 0], applied[:, 1])
    vx, vy, _ = inv2.step(40.0, 30.0, commit=False)
    nxt, _ = stage_model.simulate([*applied[:, 0], vx], [*applied[:, 1], vy])
    assert nxt["x"][-1] == pytest.approx(40.0, abs=1e-6)
    assert nxt["y"][-1] == pytest.approx(30.0, abs=1e-6)


def _with_plays(stage_model, start=0.0):
    """The stage model with 12 play operators per axis (return-point memory; weights
    of both signs, as a least-squares fit gives them)."""
    from piezo_stage.core.model.play import PlayOperators
    r = np.linspace(0.0, 60.0, 12)
    p = 0.04 * np.exp(-r / 15.0) * np.where(np.arange(12) % 5 == 4, -0.5, 1.0)
    plays = {a: PlayOperators.at_rest(r, p * (1.0 + 0.3 * (a == "y")), 10.0, start)
             for a in stage_model.axes}
    return stage_model.replace(plays=plays)


def test_play_operators_give_memory_and_are_inverted_exactly(stage_model):
    """A model with play operators: a minor loop closes where it began (return-point
    memory, which the Duhem law alone lacks), the batch inverse (coupling included) and
    the per-sample inverse both make the model reach a target with nested loops to
    rounding, and a reset from a measured position starts the operators at rest."""
    from piezo_stage.core.model.inverse import StageInverse
    m = _with_plays(stage_model, start=1.0)
    # memory: 20 -> 120 -> 60 -> 90 -> 60 V: the minor loop 60-90-60 closes on itself
    v = np.concatenate([np.linspace(20, 120, 400), np.linspace(120, 60, 200),
                        np.linspace(60, 90, 100), np.linspace(90, 60, 100)])
    z = m.plays["x"].state()
    w = m.plays["x"].run(v, z)
    assert w[-1] == pytest.approx(w[599], abs=1e-12)   # the operators' sum closes
    duhem_only, _ = stage_model.axes["x"].simulate(v)
    assert abs(duhem_only[-1] - duhem_only[599]) > 1e-3  # the Duhem law does not
    t = np.arange(3000) / 1000
    wx = 20 + 8 * np.sin(2 * np.pi * 2 * t) + 3 * np.sin(2 * np.pi * 9 * t)
    wy = 18 + 6 * np.cos(2 * np.pi * 3 * t) * np.exp(-t)
    res = invert_stage(m, wx, wy)
    w, _ = m.simulate(res["x"].v, res["y"].v)
    assert res["x"].n_saturated == res["y"].n_saturated == 0
    np.testing.assert_allclose(w["x"], wx, atol=1e-6)
    np.testing.assert_allclose(w["y"], wy, atol=1e-6)
    without, _ = m.replace(plays={}).simulate(res["x"].v, res["y"].v)
    assert np.max(np.abs(without["x"] - wx)) > 1.0     # the operators matter here
    inv = StageInverse(m)
    v = np.array([inv.step(a, b)[:2] for a, b in zip(wx[:1000], wy[:1000])])
    np.testing.assert_allclose(v[:, 0], res["x"].v[:1000], atol=1e-6)
    assert inv.w["x"] == pytest.approx(wx[999], abs=1e-6)
    snap = inv.snapshot()
    ahead = inv.step_ahead([{"x": 25.0, "y": 20.0}], 26.0, 20.0)
    inv.restore(snap)
    assert inv.w["x"] == pytest.approx(wx[999], abs=1e-6) and ahead["x"] > v[-1, 0]
    inv.reset(v={"x": 50.0, "y": 50.0}, w={"x": 12.0, "y": 11.0})
    np.testing.assert_array_equal(inv.pz[0, :12], 50.0)
    assert inv.w["x"] == pytest.approx(12.0 + inv.cwp[0], abs=1e-9)


def test_rate_dependent_play_operators_widen_with_rate_and_are_inverted_exactly(
        stage_model, tmp_path):
    """Play operators whose thresholds widen by beta x |dv/dt| (the gap diagnosis's
    `rate`): the loop is wider at 10 Hz than at 2 Hz over the same stroke, the model
    file keeps beta, the batch and the per-sample inverse make the model reach a
    target to rounding at the target's own rate, and a model without the sample rate,
    or with beta at the rate filter's time constant (where the operators' sum would
    fall while the voltage rises), is refused."""
    from piezo_stage.core.errors import ModelError
    from piezo_stage.core.model.inverse import StageInverse
    from piezo_stage.core.model.play import PlayOperators
    from piezo_stage.io.model_file import load_model, save_model
    r = np.linspace(0.0, 60.0, 12)
    p = 0.04 * np.exp(-r / 15.0)
    beta = 1.5e-3
    m = stage_model.replace(plays={a: PlayOperators.at_rest(r, p, 10.0, 0.0, beta)
                                   for a in stage_model.axes})
    fs = 1000.0

    def width(f):  # the operators' loop at mid-stroke, one period after the first
        t = np.arange(int(2 * fs / f)) / fs
        v = 75 - 60 * np.cos(2 * np.pi * f * t)
        w = m.plays["x"].run(v, m.plays["x"].state(), 1 / fs)
        half = t >= 1 / f
        up = half & (np.gradient(v) > 0)
        down = half & (np.gradient(v) < 0)
        return float(np.interp(75, v[down][::-1], w[down][::-1]) -
                     np.interp(75, v[up], w[up]))
    assert width(10.0) > 1.3 * width(2.0) > 0
    save_model(tmp_path / "m.yaml", m)
    back, _ = load_model(str(tmp_path / "m.yaml"))
    assert back.plays["x"].rate_widening_s == beta and back.plays == m.plays
    t = np.arange(3000) / fs
    wx = 20 + 8 * np.sin(2 * np.pi * 5 * t) + 3 * np.sin(2 * np.pi * 19 * t)
    wy = 18 + 6 * np.cos(2 * np.pi * 3 * t) * np.exp(-t)
    res = invert_stage(m, wx, wy, dt_s=1 / fs)
    w, _ = m.simulate(res["x"].v, res["y"].v, dt_s=1 / fs)
    assert res["x"].n_saturated == res["y"].n_saturated == 0
    np.testing.assert_allclose(w["x"], wx, atol=1e-6)
    np.testing.assert_allclose(w["y"], wy, atol=1e-6)
    slow, _ = m.simulate(res["x"].v, res["y"].v, dt_s=1.0)  # no widening to speak of
    assert np.max(np.abs(slow["x"] - wx)) > 0.05   # the widening matters here
    inv = StageInverse(m, dt_s=1 / fs)
    v = np.array([inv.step(a, b)[:2] for a, b in zip(wx[:1000], wy[:1000])])
    np.testing.assert_allclose(v[:, 0], res["x"].v[:1000], atol=1e-6)
    assert inv.w["x"] == pytest.approx(wx[999], abs=1e-6)
    with pytest.raises(ModelError, match="sample rate"):
        m.simulate(res["x"].v, res["y"].v)
    with pytest.raises(ModelError, match="rate_widening_s"):
        PlayOperators.at_rest(r, p, 10.0, 0.0, 2e-3)
