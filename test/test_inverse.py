"""Exact inverse of the discrete Duhem model, and the seed's eq. 12 for comparison."""

import numpy as np
import pytest

from conftest import sine_v
from piezo_stage.core.inverse import invert, invert_seed_eq12, invert_stage


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
    # the seed's desired displacement y(t) = 21 + 24 sin(2 pi 10 t - pi/2) um
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
    from piezo_stage.core.inverse import StageInverse
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
