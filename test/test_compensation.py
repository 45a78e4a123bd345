"""Effect compensation (core/loop/compensation.py): the inverse of each effect, run through
the plant's own effect operators at the plant's internal rate, gives back the wanted
positions at the control rate."""

import numpy as np
import pytest

from piezo_stage.core.errors import ConfigError
from piezo_stage.core.loop.compensation import (
    DynamicsInverse,
    EffectCompensator,
    PreviewDynamicsInverse,
)
from piezo_stage.core.model.effects import Creep, Delay, Dynamics

FS, R = 1000.0, 10  # control rate, plant substeps per period


def _through_plant(h, makers):
    """Hysteresis targets held over each period, through the plant's effects at its
    internal rate, sampled at the end of each period (as core/model/plant.py does)."""
    y = np.repeat(h, R)
    for make in makers:
        e = make()
        e.reset(h[0])
        y = e.process(y)
    return y[R - 1::R]


def _compensated(effects, w):
    c = EffectCompensator(effects, FS, axes=("x",))
    n = c.lead_ticks["x"]
    c.reset({"x": w[0]})
    ahead = np.concatenate([w, np.full(n, w[-1])])
    return np.array([c.step({"x": ahead[k + n]})["x"] for k in range(len(w))]), c


W40 = 21 + 24 * np.sin(2 * np.pi * 40 * np.arange(2000) / FS - np.pi / 2)


@pytest.mark.parametrize("effects, makers", [
    ({"creep": {"gamma": 0.03}}, [lambda: Creep(FS * R, 0.03)]),
    ({"dynamics": {"kind": "resonance", "fn_hz": 800.0, "zeta": 0.05}},
     [lambda: Dynamics(FS * R, "resonance", 800.0, 0.05)]),
    ({"dynamics": {"kind": "lag", "tau_s": 2e-3}}, [lambda: Dynamics(FS * R, "lag", tau_s=2e-3)]),
    # the delay's fraction moves the instant the resonance is sampled at
    ({"dynamics": {"kind": "resonance", "fn_hz": 600.0, "zeta": 0.08},
      "delay": {"delay_s": 0.0015}},
     [lambda: Dynamics(FS * R, "resonance", 600.0, 0.08), lambda: Delay(FS * R, 0.0015)]),
    ({"delay": {"delay_s": 0.002}}, [lambda: Delay(FS * R, 0.002)]),
])
def test_each_effect_is_inverted_exactly(effects, makers):
    h, c = _compensated(effects, W40)
    y = _through_plant(h, makers)
    assert np.max(np.abs(y - W40)[200:]) < 1e-9  # after the start-up transient
    # and without the compensation the same effects do leave an error
    assert np.max(np.abs(_through_plant(W40, makers) - W40)[50:]) > 0.02
    assert c.compensated == set(effects)


def test_effects_together_within_a_hundredth_of_a_micrometre():
    eff = {"creep": {"gamma": 0.03}, "dynamics": {"kind": "resonance", "fn_hz": 800.0,
                                                  "zeta": 0.05},
           "delay": {"delay_s": 0.0015}}
    h, c = _compensated(eff, W40)
    makers = [lambda: Creep(FS * R, 0.03), lambda: Dynamics(FS * R, "resonance", 800.0, 0.05),
              lambda: Delay(FS * R, 0.0015)]
    # creep acts inside the period too, which the period-level inverse does not see
    assert np.max(np.abs(_through_plant(h, makers) - W40)[100:]) < 0.02
    assert c.lead_ticks["x"] == 1


def test_drift_is_reported_not_compensated():
    c = EffectCompensator({"drift": {"rate_um_per_s": 0.01}}, FS)
    assert not c.compensated and "drift" in c.uncompensated
    assert "not: drift" in c.describe()


@pytest.mark.parametrize("fn_hz, zeta, delay_s", [
    (300.0, 0.05, 0.9e-3),  # sampled soon after the hold starts (whole plant substeps)
    (600.0, 0.08, 0.8e-3),  # the gap issue's stage: a mode above the Nyquist rate
])
def test_non_minimum_phase_dynamics_are_inverted_with_preview(fn_hz, zeta, delay_s):
    """The causal inverse is unstable at these rates; the stable noncausal one makes
    the sampled output follow the wanted positions, previewing them some samples."""
    assert not DynamicsInverse(FS, "resonance", fn_hz, zeta,
                               delta_s=delay_s % (1 / FS)).ok
    eff = {"dynamics": {"kind": "resonance", "fn_hz": fn_hz, "zeta": zeta},
           "delay": {"delay_s": delay_s}}
    h, c = _compensated(eff, W40)
    assert c.compensated == {"dynamics", "delay"} and not c.uncompensated
    assert c.preview_ticks["x"] > 0 and "samples of preview" in c.describe()
    assert c.lead_ticks["x"] == c.preview_ticks["x"] + int(delay_s * FS)
    makers = [lambda: Dynamics(FS * R, "resonance", fn_hz, zeta), lambda: Delay(FS * R, delay_s)]
    y = _through_plant(h, makers)
    # exact at the samples but for the truncated preview (1e-6 of the series' first tap)
    assert np.max(np.abs(y - W40)[400:]) < 1e-3
    assert np.max(np.abs(_through_plant(W40, makers) - W40)[50:]) > 1.0
    # and the command stays bounded: the inverse is stable
    assert np.max(np.abs(h)) < 10 * np.max(np.abs(W40))


def test_preview_inverse_of_minimum_phase_dynamics_is_the_causal_inverse():
    inv = DynamicsInverse(FS, "resonance", 800.0, 0.05)
    assert inv.ok
    p = PreviewDynamicsInverse(inv)
    assert p.preview == 0
    inv.reset(W40[0])
    p.reset(W40[0])
    a = np.array([inv.step(w) for w in W40[:300]])
    b = np.array([p.step(w) for w in W40[:300]])
    assert np.max(np.abs(a - b)) < 1e-8


def test_a_preview_longer_than_allowed_is_refused():
    inv = DynamicsInverse(FS, "resonance", 600.0, 0.08, delta_s=0.8e-3)
    assert PreviewDynamicsInverse(inv).preview > 5
    with pytest.raises(ConfigError, match="samples of preview"):
        PreviewDynamicsInverse(inv, max_taps=5)


def test_axes_list_and_disabled_effects_are_honoured():
    c = EffectCompensator({"creep": {"gamma": 0.05, "axes": ["y"]},
                           "delay": {"delay_s": 0.003, "enabled": False}}, FS)
    assert set(c.creep) == {"y"} and c.lead_ticks == {"x": 0, "y": 0}
    c.reset({"x": 5.0, "y": 5.0})
    out = c.step({"x": 10.0, "y": 10.0})
    assert out["x"] == 10.0 and out["y"] > 10.0  # creep asks for more at first


def test_a_streamed_setpoint_gets_no_dynamics_inversion():
    c = EffectCompensator({"dynamics": {"kind": "resonance", "fn_hz": 800.0, "zeta": 0.05}},
                          FS)
    c.reset({"x": 0.0, "y": 0.0})
    assert c.step({"x": 10.0, "y": 0.0}, preview=False)["x"] == 10.0
    c.reset({"x": 0.0, "y": 0.0})
    assert abs(c.step({"x": 10.0, "y": 0.0}, preview=True)["x"]) > 10.0


def test_previewed_reference_runs_the_planner_ahead_by_the_delay():
    """With a 2-period delay the planner is sampled 2 periods ahead: the hysteresis
    target commanded at a tick is what the stage should be 2 ticks later, and the
    desired position reported for a tick is the planner's value for that tick (its
    clock started when it was first asked, 2 ticks earlier than without the lead)."""
    from piezo_stage.core.loop.compensation import PreviewedReference
    from piezo_stage.core.loop.planner import ReferencePlanner
    dt = 1_000_000
    t = np.arange(200) * 1e-3
    traj = {"x": 10 + 5 * np.sin(2 * np.pi * 5 * t), "y": np.full_like(t, 3.0)}

    def run(effects, on=True):
        p = ReferencePlanner(1e6, 1e12)  # an immediate approach
        ref = PreviewedReference(p, dt)
        ref.set_compensator(EffectCompensator(effects, FS) if effects else None)
        ref.on = on
        ref.hold({"x": 10.0, "y": 3.0}, {"x": 10.0, "y": 3.0})
        p.set_trajectory(t, traj)
        return [ref.sample(k * dt) for k in range(100)]

    plain = run(None)
    lead = run({"delay": {"delay_s": 0.002}})
    off = run({"delay": {"delay_s": 0.002}}, on=False)
    for k in range(10, 98):
        assert lead[k][1]["x"] == pytest.approx(lead[k + 2][0]["x"])  # asked 2 ahead
        assert lead[k][0] == pytest.approx(plain[k - 2][0])           # same path
        assert off[k] == plain[k]                                      # switched off


def test_a_resonance_above_the_limit_is_taken_as_its_group_delay():
    dyn = {"kind": "resonance", "fn_hz": 800.0, "zeta": 0.05}
    inverted = EffectCompensator({"dynamics": dyn, "delay": {"delay_s": 0.5e-3}}, FS)
    assert "dynamics" in inverted.compensated and "x" in inverted.dynamics
    limited = EffectCompensator({"dynamics": dyn, "delay": {"delay_s": 0.99e-3}}, FS,
                                max_resonance_hz=500.0)
    # not inverted; its group delay 2 zeta / wn = 19.9 us pushes 0.99 ms over a period
    assert limited.dynamics == {} and "dynamics" not in limited.compensated
    assert "group delay of 20 us" in limited.uncompensated["dynamics"]
    assert limited.lead_ticks == {"x": 1, "y": 1}
