"""The simulated 2-axis stage and the signatures of its unmodelled effects."""

import copy
import os

import numpy as np
import pytest

from conftest import sine_v
from piezo_stage.core.errors import ConfigError
from piezo_stage.core.model.plant import Plant, PlantConfig
from piezo_stage.io.plant_file import load_plant_config


@pytest.fixture
def cfg(plant_config_path):
    return load_plant_config(plant_config_path)


def with_effect(cfg, name, **params):
    c = copy.deepcopy(cfg)
    c.effects = {name: params}
    return c


def test_defaults_effects_off_and_noise(cfg):
    assert cfg.effects == {}
    assert cfg.noise_rms_um == 0.1
    assert cfg.internal_rate_hz == 10_000
    p = Plant(cfg, 1000.0)
    w = p.run(np.full(5000, 50.0), np.zeros(5000))
    noise = w["x"][1000:] - p.last_true["x"][1000:]
    assert 0.09 < np.std(noise) < 0.11
    assert p.substeps == 10


def test_deterministic_for_seed_and_chunking(cfg):
    _, v = sine_v(2.0, 1000, 2)
    a = Plant(cfg, 1000).run(v, v[::-1])
    b = Plant(cfg, 1000).run(v, v[::-1])
    np.testing.assert_array_equal(a["x"], b["x"])
    p = Plant(cfg, 1000)
    steps = np.array([p.step(x, y) for x, y in zip(v, v[::-1])])
    np.testing.assert_array_equal(steps[:, 0], a["x"])
    np.testing.assert_array_equal(steps[:, 1], a["y"])
    # the compiled single step and the batch path share state: any interleaving
    p = Plant(cfg, 1000)
    first = np.array([p.step(x, y) for x, y in zip(v[:700], v[::-1][:700])])
    rest = p.run(v[700:], v[::-1][700:])
    np.testing.assert_array_equal(first[:, 0], a["x"][:700])
    np.testing.assert_array_equal(rest["y"], a["y"][700:])
    c = copy.deepcopy(cfg)
    c.seed = 7
    d = Plant(c, 1000).run(v, v[::-1])
    assert not np.array_equal(d["x"], a["x"])


def test_coupling_moves_the_other_axis_with_hysteresis(cfg):
    _, v = sine_v(1.0, 2000, 3)
    p = Plant(cfg, 2000)
    p.run(np.zeros_like(v), v)
    wx = p.last_true["x"][-2000:]
    vy = v[-2000:]
    assert 0.5 < np.ptp(wx) < 3.0
    up = np.diff(vy, prepend=vy[0]) > 0
    mid = np.abs(vy - 75) < 2
    assert abs(wx[mid & ~up].mean() - wx[mid & up].mean()) > 0.05  # a loop, not a line


def test_amplifier_clamp_and_slew(cfg):
    c = copy.deepcopy(cfg)
    c.slew_V_per_s = 1000.0  # 0.1 V per internal sample
    p = Plant(c, 1000)
    p.run(np.full(10, 200.0), np.full(10, -20.0))
    assert p.limit_hits > 0
    assert p.last_applied["x"][0] == pytest.approx(1.0)  # 10 substeps x 0.1 V
    assert np.all(p.last_applied["y"] == 0.0)
    p.run(np.full(200, 200.0), np.zeros(200))
    assert p.last_applied["x"][-1] == 150.0


def test_creep_keeps_moving_during_a_held_voltage(cfg):
    def held(c):
        c = copy.deepcopy(c)
        c.noise_rms_um = 0.0
        p = Plant(c, 1000)
        p.run(np.full(8000, 100.0), np.zeros(8000))
        w = p.last_true["x"]
        return w[100] , w[1000], w[7999]
    a0, a1, a2 = held(cfg)
    assert abs(a2 - a0) < 1e-9  # without creep a held voltage holds
    b0, b1, b2 = held(with_effect(cfg, "creep", gamma=0.05))
    assert b1 - b0 > 0.2 and b2 - b1 > 0.2  # still creeping, in the step's direction
    # log-like: similar movement per decade of time
    c = with_effect(cfg, "creep", gamma=0.05)
    c.noise_rms_um = 0
    p = Plant(c, 1000)
    p.run(np.full(20000, 100.0), np.zeros(20000))
    w = p.last_true["x"]
    d1, d2 = w[2000] - w[200], w[19999] - w[2000]
    assert 0.4 < d1 / d2 < 2.5


def test_resonance_amplifies_near_its_frequency(cfg):
    c = with_effect(cfg, "dynamics", kind="resonance", fn_hz=500.0, zeta=0.05)
    c.noise_rms_um = 0

    def gain(f):
        fs = 10_000
        t = np.arange(int(0.4 * fs)) / fs
        v = 75 + 2 * np.sin(2 * np.pi * f * t)
        base = copy.deepcopy(c)
        base.effects = {}
        ref = Plant(base, fs)  # same stage without the effect
        ref.run(v, np.zeros_like(v))
        p = Plant(c, fs)
        p.run(v, np.zeros_like(v))
        half = t.size // 2
        return np.ptp(p.last_true["x"][half:]) / np.ptp(ref.last_true["x"][half:])

    assert gain(20.0) == pytest.approx(1.0, abs=0.02)
    assert gain(500.0) > 5.0  # Q = 1/(2 zeta) = 10
    assert gain(2000.0) < 0.2


def test_delay_shifts_without_changing_amplitude(cfg):
    fs = 10_000
    c = with_effect(cfg, "delay", delay_s=0.002)
    c.noise_rms_um = 0
    _, v = sine_v(5.0, fs, 2)
    a, b = Plant(cfg, fs), Plant(c, fs)
    a.config.noise_rms_um = 0
    a.run(v, np.zeros_like(v))
    b.run(v, np.zeros_like(v))
    wa, wb = a.last_true["x"], b.last_true["x"]
    np.testing.assert_allclose(wb[20:], wa[:-20], atol=1e-9)
    assert np.ptp(wb[-2000:]) == pytest.approx(np.ptp(wa[-2000:]), rel=1e-3)


def test_drift_moves_without_input(cfg):
    c = with_effect(cfg, "drift", rate_um_per_s=0.05, amplitude_um=0.0, tau_s=10)
    c.noise_rms_um = 0
    p = Plant(c, 100)
    p.run(np.zeros(1000), np.zeros(1000))
    np.testing.assert_allclose(p.last_true["x"][-1] - p.last_true["x"][0], 0.05 * 9.99,
                               rtol=1e-6)


def test_unknown_effect_rejected(cfg):
    with pytest.raises(ConfigError):
        Plant(with_effect(cfg, "magic"), 1000)
    with pytest.raises(ConfigError):
        Plant(with_effect(cfg, "creep", gama=0.1), 1000)


def test_compiled_step_matches_batch_at_limits(cfg):
    """Steps beyond the clamp and the slew limit: the compiled single step counts the
    same limit hits and reports the same true and applied values as the batch path."""
    c = copy.deepcopy(cfg)
    c.slew_V_per_s = 2.0e4  # 2 V per 10 kHz substep: the 0 -> 160 V jumps hit it
    v = np.r_[np.zeros(5), np.full(20, 160.0), np.full(20, -5.0), np.linspace(0, 150, 40)]
    a, b = Plant(c, 1000), Plant(c, 1000)
    batch = a.run(v, v[::-1])
    for k, (x, y) in enumerate(zip(v, v[::-1])):
        assert b.step(x, y) == (batch["x"][k], batch["y"][k])
    assert b.limit_hits == a.limit_hits > 0
    assert b.last_true["x"][0] == a.last_true["x"][-1]
    assert b.last_applied["y"][0] == a.last_applied["y"][-1]


@pytest.mark.parametrize("effect, params", [
    ("creep", {"gamma": 0.05}), ("dynamics", {"kind": "resonance", "fn_hz": 300.0,
                                              "zeta": 0.05}),
    ("dynamics", {"kind": "lag", "tau_s": 2e-3}), ("delay", {"delay_s": 2.3e-3})])
def test_effect_operator_on_columns_equals_the_stateful_effect(effect, params):
    """The compiled column operators (gap diagnosis) and the plant's chunked effect are
    the same linear map, from rest at the first sample (a record starts in a state:
    an offset is no step into the effect)."""
    from piezo_stage.core.model.effects import make_effect
    rng = np.random.default_rng(5)
    X = 50.0 + np.cumsum(rng.normal(size=(3000, 3)), axis=0)
    op = make_effect(effect, 1000.0, params)

    def stateful(x):
        e = make_effect(effect, 1000.0, params)
        e.reset(float(x[0]))
        return e.process(x)
    want = np.column_stack([stateful(X[:, j]) for j in range(3)])
    np.testing.assert_allclose(op.apply(X), want, rtol=1e-9, atol=1e-9)
    # a constant is no input to it: it stays (a delay, a creep, a unit-gain filter)
    np.testing.assert_allclose(op.apply(np.full((50, 2), -120.0)), -120.0, rtol=1e-12)


def _structure_cfg():
    import os

    from conftest import ROOT
    c = load_plant_config(os.path.join(ROOT, "config", "structure_stage.yaml"))
    c.noise_rms_um = c.quantization_um = 0.0
    return c


def test_the_structure_plant_has_return_point_memory_and_chunks_alike():
    """config/structure_stage.yaml's play-operator law: a minor loop inside the major
    one closes where it began (return-point memory, which our Duhem law lacks); a run
    in one batch, in chunks or a command at a time gives the same output."""
    fs = 1000.0
    up = np.linspace(0.0, 120.0, 600)
    minor = 90.0 + 30.0 * np.cos(np.linspace(0.0, 2 * np.pi, 400))  # 120 -> 60 -> 120
    v = np.concatenate([up, minor, np.linspace(120.0, 0.0, 600)])
    w = Plant(_structure_cfg(), fs).run(v, np.zeros_like(v))["x"]
    at_start, at_end = w[599], w[999]          # 120 V before and after the minor loop
    assert abs(at_end - at_start) < 1e-9       # closed where it began
    assert abs(w[799] - w[599]) > 1.0          # and it was a loop, not a rest
    # the Duhem stage does not close it
    d = Plant(load_plant_config(_default_path()), fs)
    d.config.noise_rms_um = 0.0
    wd = Plant(copy.deepcopy(d.config), fs).run(v, np.zeros_like(v))["x"]
    assert abs(wd[999] - wd[599]) > 0.05
    # chunking and stepping
    one = Plant(_structure_cfg(), fs)
    stepped = np.array([one.step(a, 0.3 * a)[0] for a in v])
    chunks = Plant(_structure_cfg(), fs)
    chunked = np.concatenate([chunks.run(v[i:i + 37], 0.3 * v[i:i + 37])["x"]
                              for i in range(0, v.size, 37)])
    batch = Plant(_structure_cfg(), fs).run(v, 0.3 * v)["x"]
    assert np.array_equal(stepped, batch) and np.array_equal(chunked, batch)


def _default_path():
    from piezo_stage.io.plant_file import default_plant_config_path
    return default_plant_config_path()


@pytest.mark.parametrize("block, says", [
    ({"kind": "preisach"}, "only 'prandtl-ishlinskii'"),
    ({"operators": 0}, "operators = 0"),
    ({"envelope": {"scale_um": -9.0, "width_um": 8.0}}, "monotone"),
    ({"decay": 3}, "unknown key"),
])
def test_a_bad_hysteresis_block_is_refused_by_name(tmp_path, block, says):
    import os

    import yaml

    from conftest import ROOT
    doc = yaml.safe_load(open(os.path.join(ROOT, "config", "structure_stage.yaml")))
    doc["model"] = os.path.join(ROOT, "config", "stage_model.yaml")
    doc["hysteresis"] = {"kind": "prandtl-ishlinskii", **block}
    p = tmp_path / "p.yaml"
    p.write_text(yaml.safe_dump(doc))
    with pytest.raises(ConfigError, match=says):
        load_plant_config(p)


def test_a_model_with_play_operators_is_the_plant_exactly():
    """``simulate --model`` with a model that has play operators (as ``gap --out-model``
    writes structure with memory): the exact plant (no noise, no slew limit reached)
    gives the model's own output, in one batch or a command at a time, and the
    operators are really in it."""
    from piezo_stage.core.model.play import PlayOperators
    model = load_plant_config(_default_path()).model
    r = np.linspace(0.0, 50.0, 8)
    plays = {"x": PlayOperators.at_rest(r, 0.05 * np.exp(-r / 20.0), 0.0)}
    m = model.replace(plays=plays)
    fs = 1000.0
    t = np.arange(2000) / fs
    vx = 75 - 60 * np.cos(2 * np.pi * 1.5 * t) * np.exp(-t)
    vy = 60 + 20 * np.sin(2 * np.pi * 2 * t)
    want, _ = m.simulate(vx, vy)
    plant = Plant(PlantConfig.exact(m, fs), fs)
    plant.run(vx, vy)
    np.testing.assert_allclose(plant.last_true["x"], want["x"], atol=1e-9)
    np.testing.assert_allclose(plant.last_true["y"], want["y"], atol=1e-9)
    one = Plant(PlantConfig.exact(m, fs), fs)
    stepped = np.array([one.step(a, b)[0] for a, b in zip(vx, vy)])
    batch = Plant(PlantConfig.exact(m, fs), fs).run(vx, vy)["x"]
    assert np.array_equal(stepped, batch)
    without = Plant(PlantConfig.exact(model, fs), fs)
    without.run(vx, vy)
    assert np.max(np.abs(without.last_true["x"] - want["x"])) > 1.0


def test_a_scheduled_change_switches_an_effect_on_mid_run(cfg, tmp_path):
    """``changes`` (a plant file's block): creep switched on at 1.5 s of the run. Before
    it the stage is the one without changes, sample for sample; from it the held
    stage creeps after the next step of the voltage (before, a held voltage held),
    its creep starting at rest (no jump at the change); stepping one command at a
    time gives the batch's samples; a reset runs the schedule again from the start."""
    changed = load_plant_config(_with_block(tmp_path, {"changes": [
        {"at_s": 1.5, "effects": {"creep": {"enabled": True, "gamma": 0.08}}}]}))
    assert len(changed.changes) == 1
    v = np.concatenate([np.linspace(0, 100, 500), np.full(1500, 100.0), np.full(1500, 60.0)])
    a, b = Plant(changed, 1000.0), Plant(cfg, 1000.0)
    wa, wb = a.run(v, 0 * v), b.run(v, 0 * v)
    np.testing.assert_array_equal(wa["x"][:1500], wb["x"][:1500])
    ta, tb = a.last_true["x"], b.last_true["x"]
    assert abs(ta[1500] - tb[1500]) < 0.05  # at rest at the change: no jump
    assert np.ptp(tb[2100:]) < 0.05 and abs(ta[-1] - ta[2100]) > 0.3  # creeping after
    s = Plant(changed, 1000.0)
    stepped = np.array([s.step(x, 0.0)[0] for x in v])
    np.testing.assert_allclose(stepped, wa["x"], atol=1e-9)
    a.reset()
    np.testing.assert_array_equal(a.run(v, 0 * v)["x"], wa["x"])


@pytest.mark.parametrize("block, says", [
    ("changes: {at_s: 1}", "changes must be a list"),
    ("changes: [{at_s: 1, effects: {creep: {enabled: true}}, when: 2}]", "nothing else"),
    ("changes: [{at_s: -1, effects: {}}]", "at_s"),
    ("changes: [{at_s: 1, effects: {creap: {enabled: true}}}]", "creap"),
])
def test_a_bad_changes_block_is_refused_by_name(tmp_path, block, says):
    import yaml
    with pytest.raises(ConfigError, match=says):
        load_plant_config(_with_block(tmp_path, yaml.safe_load(block)))


def _with_block(tmp_path, block: dict) -> str:
    """config/sim_stage.yaml with ``block`` added, written under ``tmp_path``."""
    import yaml

    from conftest import CONFIG
    with open(os.path.join(CONFIG, "sim_stage.yaml")) as f:
        doc = yaml.safe_load(f)
    doc["model"] = os.path.join(CONFIG, doc["model"])
    doc.update(block)
    path = tmp_path / "plant.yaml"
    path.write_text(yaml.safe_dump(doc))
    return str(path)


WARM_PROBE = r"""
import json, sys
from piezo_stage.core.model import _kernels
from piezo_stage.drivers import SimBackend
backend = SimBackend(sys.argv[1], 1000.0)  # warms its plant (Plant.warm)
def compiled():
    return {n: len(k.signatures) for n, k in vars(_kernels).items()
            if hasattr(k, "signatures")}
before, modules = compiled(), set(sys.modules)
for _ in range(600):  # past the change at 0.5 s
    backend.step(10.0, 0.0)
print(json.dumps({"compiled": {n: c for n, c in compiled().items() if c != before[n]},
                  "imported": sorted(set(sys.modules) - modules)}))
"""


def test_a_simulated_stage_warms_its_scheduled_changes_before_the_first_sample(tmp_path):
    """The stage driver's simulated stage compiles and imports what its scheduled
    changes run before its first sample: a real-time run stalled 0.5 s at a change
    (scipy.signal's import and the creep's kernels: the driver faulted on stale
    commands). Stepping past the change compiles and imports nothing."""
    import json
    import subprocess
    import sys
    path = _with_block(tmp_path, {"changes": [
        {"at_s": 0.5, "effects": {"creep": {"enabled": True, "gamma": 0.06}}}]})
    r = subprocess.run([sys.executable, "-c", WARM_PROBE, path], capture_output=True,
                       text=True, timeout=300)
    assert r.returncode == 0, r.stderr[-2000:]
    out = json.loads(r.stdout.strip().splitlines()[-1])
    assert out == {"compiled": {}, "imported": []}, out
