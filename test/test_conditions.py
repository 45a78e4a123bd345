"""Models used under other conditions than they were fitted on: past the fitted voltage
range a branch continues straight (never its polynomial's tail), voltage limits belong
to the amplifier, a model run past its range says so, the classical
Prandtl-Ishlinskii peer, and fit-here-use-there cases where every written model loads
and runs. No ROS."""

import os
import subprocess
import sys

import numpy as np
import pytest

from conftest import sine_v
from piezo_stage.core.errors import DataError
from piezo_stage.core.estimation.identify import identify_axis
from piezo_stage.core.estimation.identify.prandtl import fit_prandtl_ishlinskii, held_out_rms
from piezo_stage.core.estimation.record import Record
from piezo_stage.core.model.duhem import (
    POLY_MARGIN,
    DuhemBranch,
    DuhemModel,
    DuhemState,
    StageModel,
    branch_values,
    past_fit_range,
    polynomial_range,
    voltage_limits_for,
)
from piezo_stage.core.model.inverse import invert_stage
from piezo_stage.core.model.model_doc import model_from_dict, model_to_dict
from piezo_stage.core.model.play import PlayOperators

# a degree-5 branch whose tail runs away past 60 V (as a fit on a small stroke gives)
H5 = [0.45, 2e-3, -1e-4, 3e-6, -2e-8, 1e-10]


def _model(fit_range=(0.0, 60.0)):
    b = DuhemBranch.from_h(0.02, H5)
    return DuhemModel(b, DuhemBranch.from_h(0.02, np.array(H5) * 0.9), DuhemState(),
                      fit_range)


def test_a_branch_past_its_fitted_range_continues_straight_from_its_end():
    m = _model()
    lo, hi = polynomial_range(m.fit_range_V)
    assert (lo, hi) == pytest.approx((-POLY_MARGIN * 60.0, 60.0 * (1 + POLY_MARGIN)))
    v = np.linspace(hi, 1000.0, 50)
    y = branch_values(H5, v, m.fit_range_V)
    assert np.allclose(np.diff(y, 2), 0.0, atol=1e-9)  # a straight line past the margin
    assert np.all(np.diff(y) >= 0)                    # never falling
    inside = np.linspace(0.0, 60.0, 7)
    np.testing.assert_allclose(branch_values(H5, inside, m.fit_range_V),
                               np.polynomial.polynomial.polyval(inside, H5))
    # the compiled recursion evaluates the branch exactly as branch_values does
    v = np.concatenate([np.linspace(0, 150, 400), np.linspace(150, 0, 400)])
    w, _ = m.simulate(v)
    ref, wp, vp = [], 0.0, 0.0
    for vk in v:
        b = 0 if vk >= vp else 1
        h = (m.ascending if b == 0 else m.descending).h(b == 0)
        dv = vk - vp
        wp = (wp + dv * float(branch_values(h, vk, m.fit_range_V))) / (1 + 0.02 * abs(dv))
        ref.append(wp)
        vp = vk
    np.testing.assert_allclose(w, ref, rtol=1e-12, atol=1e-12)
    # the polynomial's own tail (no fitted range) is what ran away before
    tail, _ = _model(None).simulate(v)
    assert np.max(np.abs(tail)) > 1.5 * np.max(np.abs(w))


def test_the_model_file_keeps_the_fitted_range_and_checks_slopes_as_the_model_runs():
    m = StageModel({"x": _model(), "y": _model((10.0, 90.0))}, {}, (0.0, 150.0))
    back, _ = model_from_dict(model_to_dict(m), "round trip")
    assert back.axes["x"].fit_range_V == (0.0, 60.0)
    assert back.axes["y"].fit_range_V == (10.0, 90.0)
    # without the range the degree-5 tail is refused over 0-1000 V; with it, taken
    doc = model_to_dict(m.replace(voltage_limits=(0.0, 1000.0)))
    model_from_dict(doc, "with range")
    for a in ("x", "y"):
        del doc["axes"][a]["fitted_range_V"]
    with pytest.raises(Exception, match="um/V within the voltage limits"):
        model_from_dict(doc, "without range")


def test_voltage_limits_belong_to_the_amplifier_not_the_record():
    assert voltage_limits_for([np.array([0.0, 10.0])]) == (0.0, 150.0)   # 0-10 V control
    assert voltage_limits_for([np.array([-90.0, 90.0])]) == (-90.0, 150.0)  # bipolar
    assert voltage_limits_for([np.array([-20.0, 120.0])]) == (-20.0, 150.0)
    assert voltage_limits_for([np.array([0.0, 10.0])], (-10.0, 10.0)) == (-10.0, 10.0)
    with pytest.raises(DataError, match="outside the amplifier's limits"):
        voltage_limits_for([np.array([0.0, 120.0])], (0.0, 100.0))
    m = StageModel({"x": _model()}, {}, (0.0, 150.0))
    said = past_fit_range(m, {"x": np.array([5.0, 148.0])})
    assert said == ["vx reaches 148 V, 88 V past the 0..60 V it was fitted on"]
    assert past_fit_range(m, {"x": np.array([5.0, 60.0])}) == []


def test_the_prandtl_ishlinskii_peer_recovers_a_law_of_its_own_class():
    _, v = sine_v(1.0, 1000.0, 4)
    r = np.arange(1, 13) * np.ptp(v) / 26
    true = PlayOperators.at_rest(r, 0.02 * np.exp(-r / 20), float(v[0]))
    w = 0.1 * v + true.run(v, true.state()) + 3.0
    pi = fit_prandtl_ishlinskii(v, w)
    assert held_out_rms(pi.predict(v), w, 1000.0, 0.0) < 1e-6
    nested = 75 + (75 - 60 * np.linspace(0, 1, 4000)) * np.sin(2 * np.pi * np.arange(4000) / 1000)
    want = 0.1 * nested + true.run(nested, np.full(r.size, nested[0])) + 3.0
    assert held_out_rms(pi.predict(nested), want, 1000.0) < 1e-6  # its memory carries over
    with pytest.raises(DataError):
        fit_prandtl_ishlinskii(np.zeros(50), np.zeros(50))


def test_the_pi_class_reaches_the_amplifiers_range_and_carries_a_widening_loop():
    """The class we identify (``fit_pi_class``): non-negative weights, thresholds at the
    record's spacing on to half the amplifier's range. Fitted on the first 40-75 V of a
    Rayleigh law's rising-amplitude triangles (one weight per operator) it predicts the
    triangles up to 150 V far closer than the same class stopped at the record's span
    (the peer's thresholds) and than the peer: the operators past the record move on
    its monotone excursions, and the weights past them follow a smooth density."""
    from piezo_stage.core.estimation.identify.prandtl import SMOOTHNESS, fit_pi_class
    t = np.arange(12000) / 1000.0
    amp = 20.0 + 130.0 * t / t[-1]
    v = amp * (1 - np.abs(((2.0 * t) % 1.0) * 2 - 1))
    r = np.linspace(0.0, 75.0, 16)
    law = PlayOperators.at_rest(r, np.full(16, 0.012), 0.0)
    w = law.run(v, law.state()) + np.random.default_rng(0).normal(0, 0.05, v.size)
    k = 4000  # FIT: up to ~63 V
    cls = fit_pi_class(v[:k], w[:k], reach_V=75.0)
    ops = cls.operators
    step = ops.thresholds_V[1] - ops.thresholds_V[0]
    top = ops.thresholds_V[-1]
    assert ops.thresholds_V.size > 12 and top <= 75.0 < top + step
    assert np.all(ops.weights_um_per_V >= 0) and cls.linear_um_per_V >= 0
    assert cls.smoothness in SMOOTHNESS
    short = fit_pi_class(v[:k], w[:k])  # stopped at the record's span
    assert short.operators.thresholds_V.size == 12
    peer = fit_prandtl_ishlinskii(v[:k], w[:k])

    def held(m):
        return held_out_rms(m.predict(v)[k:], w[k:], 1000.0, 0.0)
    assert held(cls) < 0.3 * held(short) and held(cls) < 0.3 * held(peer), \
        (held(cls), held(short), held(peer))


def test_fit_here_use_there_every_written_model_runs_and_memory_beats_the_peer():
    """On the structure stage (memory and a tanh envelope: not our model class), the
    Rayleigh stage and ours: every model `gap --out-model` writes loads and runs
    through our simulator on the held-out excitation, never worse than the base
    model; fitted on a
    constant-amplitude calibration and used on nested minor loops, that model (with its
    memory) beats the classical Prandtl-Ishlinskii peer by the issue's margin
    (<= 0.8 x); used on a larger stroke than fitted, memory as a class of its own
    carries further than the peer by that margin too (the Duhem law alone: 2.2 x),
    on the structure stage, ours and the Rayleigh stage. Our exact inverse of each
    written model gives the voltages back."""
    from piezo_stage.apps.studies import conditions
    pairs = [p for p in conditions.PAIRS if p[1] != "two-rate->fast"]  # (the next test's)
    rows = {(r["stage"], r["case"]): r for r in conditions.run(pairs)}
    for r in rows.values():
        assert np.isfinite(r["gap_model_um"]) and np.isfinite(r["ours_um"]), r
        assert r["inverse_back_V"] < 1e-6, r  # our invert takes it, past its range too
        assert r["own_fit_um"] < 0.2, r  # the class fits each record itself
    for r in rows.values():  # never worse than the base model (identify's)
        assert r["gap_model_um"] <= 1.02 * r["ours_um"] + 1e-3, r
    # a larger stroke than fitted: memory as a class with memory in place of the Duhem
    # law (its branches continue along its operators' lines, not straight from a
    # polynomial's end; its thresholds reach half the amplifier's range): the Preisach
    # class, whose density varies along the stroke, 0.62 x the peer here and 0.35 x on
    # our own stage (2026-11-27; the Prandtl-Ishlinskii class alone: 0.87 x and not
    # named), the Prandtl-Ishlinskii class 0.08 x on the Rayleigh stage, whose loop
    # keeps widening with the stroke
    for stage in ("structure", "ours"):
        large = rows[(stage, "small->large")]
        assert large["gap_model_um"] <= 0.8 * large["peer_um"] < 0.8 * large["ours_um"], \
            large
    assert rows[("structure", "small->large")]["verdict"] == "memory"
    # our own stage has no memory: the class fits FIT (small strokes) no closer than the
    # Duhem law and is closer on the larger stroke alone, so it is not named
    # (AxisSearch.shows_on_fit), and written as the closest form, said so
    ours = rows[("ours", "small->large")]
    assert ours["verdict"] == "inconclusive" and "fits FIT no closer" in ours["reason"], ours
    rayleigh = rows[("rayleigh", "small->large")]
    assert rayleigh["verdict"] == "memory", rayleigh
    assert rayleigh["gap_model_um"] <= 0.2 * rayleigh["peer_um"], rayleigh
    # nested loops on the Rayleigh stage: the Duhem law with play operators turns a
    # branch back there (its inverse missed by 1.9 V) and is not kept; the class is
    # (the peer, of the stage's own class, is at the noise: as close, not 0.8 x)
    nested = rows[("rayleigh", "periodic->nested")]
    assert nested["verdict"] == "memory", nested
    assert nested["gap_model_um"] <= nested["peer_um"], nested
    nested = rows[("structure", "periodic->nested")]
    assert nested["verdict"] == "memory"  # the class's memory is what carries over
    assert nested["gap_model_um"] <= 0.5 * nested["peer_um"], nested  # 0.32 x
    same = rows[("structure", "periodic->periodic")]
    assert same["gap_model_um"] <= same["peer_um"], same
    # where both are near the sensor's noise (0.1 um) the RMS ratio is near 1 whatever
    # they do: above the noise, 0.71 x and 0.27 x (2026-11-27)
    for key in (("structure", "slow->fast"), ("rayleigh", "periodic->nested")):
        r = rows[key]
        ours = conditions.above_noise(r["gap_model_um"], r["noise_um"])
        assert ours <= 0.8 * conditions.above_noise(r["peer_um"], r["noise_um"]), r
    # our own stage: the same conditions are the noise
    assert rows[("ours", "periodic->periodic")]["ours_um"] < 0.12
    # memory with one of our effects: the class is fitted with the effect (creep on top
    # of it, or the coupling from the other axis), and carries both: 0.33 x and 0.60 x
    # the peer (2026-11-27; test_class_effects.py holds the effects' own share)
    for key in (("structure+creep", "periodic->nested"),
                ("structure+coupling", "small->large")):
        r = rows[key]
        assert r["verdict"] == "memory", r
        assert r["gap_model_um"] <= 0.8 * r["peer_um"], r


def test_a_calibration_at_two_rates_names_rate_and_carries_to_a_faster_line_rate(tmp_path):
    """On the rate stage (its loop widens with |dv/dt|) calibrated at 2 and 5 Hz and
    used at 10 Hz: the diagnosis names rate, the model it writes (play operators whose
    thresholds widen with the rate, beta in the file) loads, runs through our simulator
    within 1.3 x the model fitted at 10 Hz itself and under 0.8 x the Prandtl-Ishlinskii
    peer, and our exact inverse gives its voltages back; with the rate candidate's
    widening set to 0 (memory alone) the same fit misses by far more."""
    from piezo_stage.apps.studies import conditions
    from piezo_stage.core.estimation.gap import diagnose
    from piezo_stage.core.model.plant import Plant, PlantConfig
    from piezo_stage.io.model_file import load_model, save_model
    [row] = conditions.run([("rate", "two-rate->fast")])
    assert row["verdict"] == "rate", row
    assert row["gap_model_um"] <= 1.3 * row["own_fit_um"], row
    assert row["gap_model_um"] <= 0.8 * row["peer_um"], row
    assert row["inverse_back_V"] < 1e-6, row
    fit, hold, _ = conditions.case_records("rate", "two-rate->fast")
    model, _ = diagnose(fit, hold, axes=["x"]).model()
    beta = model.plays["x"].rate_widening_s
    assert 0.5e-3 < beta < 1.9e-3  # the stage's own: 1 ms
    save_model(tmp_path / "m.yaml", model)
    back, _ = load_model(str(tmp_path / "m.yaml"))
    assert back.plays["x"].rate_widening_s == beta
    flat = back.replace(plays={"x": type(back.plays["x"])(
        back.plays["x"].thresholds_V, back.plays["x"].weights_um_per_V,
        back.plays["x"].initial_V, 0.0)})
    v = hold.v["x"]

    def miss(m):
        p = Plant(PlantConfig.exact(m, conditions.FS_HZ), conditions.FS_HZ).run(
            v, np.zeros_like(v))["x"]
        from piezo_stage.core.estimation.identify.prandtl import held_out_rms
        return held_out_rms(p, hold.w["x"], conditions.FS_HZ)
    assert miss(back) == pytest.approx(row["gap_model_um"], rel=1e-6)
    assert miss(flat) > 2 * miss(back)


hypothesis = pytest.importorskip("hypothesis")
from hypothesis import HealthCheck, given, settings  # noqa: E402
from hypothesis import strategies as st  # noqa: E402


@settings(max_examples=12, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(lo=st.floats(0.0, 60.0), span=st.floats(15.0, 90.0), cycles=st.integers(2, 4),
       seed=st.integers(0, 1000))
def test_every_identified_model_loads_simulates_and_inverts_over_the_amplifier_range(
        lo, span, cycles, seed):
    """A record on any part of the stroke: the model identify writes (limits 0-150 V,
    the amplifier's) is accepted by our loader and runs finite through simulate and the
    exact inverse over the whole 0-150 V, past its fitted range."""
    from piezo_stage.core.model.plant import Plant, PlantConfig
    from piezo_stage.io.plant_file import default_plant_config_path, load_plant_config
    hi = min(lo + span, 150.0)
    _, v = sine_v(1.0, 1000.0, cycles, lo, hi)
    cfg = load_plant_config(default_plant_config_path())
    cfg.model.coupling.clear()
    cfg.seed = seed
    w = Plant(cfg, 1000.0).run(v, np.zeros_like(v))["x"]
    res = identify_axis(Record(np.arange(v.size) / 1000.0, {"x": v}, {"x": w}), "x")
    model = StageModel({"x": res.model, "y": res.model}, {}, voltage_limits_for([v]))
    model, _ = model_from_dict(model_to_dict(model), "written")
    full = np.concatenate([np.linspace(0, 150, 500), np.linspace(150, 0, 500)])
    out = Plant(PlantConfig.exact(model, 1000.0), 1000.0).run(full, full)
    assert all(np.all(np.isfinite(x)) for x in out.values())
    inv = invert_stage(model, out["x"], out["y"])
    assert all(np.all(np.isfinite(r.v)) for r in inv.values())


def test_identify_writes_the_amplifiers_limits_and_simulate_warns_past_the_fit(tmp_path):
    from piezo_stage.io.csv_table import write_table
    from piezo_stage.io.model_file import load_model

    def cli(*a):
        return subprocess.run([sys.executable, "-m", "piezo_stage.cli", *map(str, a)],
                              capture_output=True, text=True, timeout=120)
    small = tmp_path / "small.csv"
    _, v = sine_v(1.0, 1000.0, 4, -20.0, 60.0)  # a -20..60 V record
    write_table(small, {"t": np.arange(v.size) / 1e3, "vx": v, "vy": v * 0 + 10.0})
    r = cli("simulate", "--in", small, "--out", tmp_path / "small_w.csv",
            "--config", os.path.join(os.path.dirname(__file__), "..", "config",
                                     "sim_stage.yaml"))
    # the default plant's amplifier takes 0-150 V: that record is refused by it
    assert r.returncode == 2 and "outside the voltage limits" in r.stderr
    _, v = sine_v(1.0, 1000.0, 4, 0.0, 60.0)
    write_table(small, {"t": np.arange(v.size) / 1e3, "vx": v, "vy": v * 0.5 + 5})
    assert cli("simulate", "--in", small, "--out", tmp_path / "small_w.csv").returncode == 0
    r = cli("identify", tmp_path / "small_w.csv", "--out", tmp_path / "m.yaml")
    assert r.returncode == 0, r.stderr
    model, _ = load_model(tmp_path / "m.yaml")
    assert model.voltage_limits == (0.0, 150.0)  # the amplifier's, not the record's
    assert model.axes["x"].fit_range_V[1] == pytest.approx(60.0, abs=0.5)
    big = tmp_path / "big.csv"
    _, v = sine_v(1.0, 1000.0, 2, 0.0, 150.0)
    write_table(big, {"t": np.arange(v.size) / 1e3, "vx": v, "vy": v})
    r = cli("simulate", "--in", big, "--model", tmp_path / "m.yaml", "--out",
            tmp_path / "big_w.csv")
    assert r.returncode == 0, r.stderr
    lines = [ln for ln in r.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1 and "past its fitted range" in lines[0] and "vx reaches 150 V" \
        in lines[0], r.stderr
    r = cli("identify", tmp_path / "small_w.csv", "--out", tmp_path / "m2.yaml",
            "--limits=-10,10")  # (a negative first value: the = form)
    assert r.returncode == 2 and "outside the amplifier's limits" in r.stderr
    assert not (tmp_path / "m2.yaml").exists()
    r = cli("identify", tmp_path / "small_w.csv", "--out", tmp_path / "m3.yaml",
            "--limits=-90,90")
    assert r.returncode == 0 and load_model(tmp_path / "m3.yaml")[0].voltage_limits == \
        (-90.0, 90.0)


def test_gap_names_each_axis_and_warns_when_holdout_leaves_fits_range(tmp_path):
    """FIT on a small stroke, HOLDOUT on the full one: one warning line says so, each
    axis's verdict is printed, and the model --out-model writes loads and runs over
    HOLDOUT's voltages through our simulate (saying, in one line, where it is past its
    fitted range)."""
    def cli(*a):
        return subprocess.run([sys.executable, "-m", "piezo_stage.cli", *map(str, a)],
                              capture_output=True, text=True, timeout=300)
    for name, extra in (("fit", ["--v-max", "80"]), ("hold", ["--seed", "3"])):
        assert cli("excite", "--rate", "1000", "--out", tmp_path / f"{name}_v.csv",
                   *extra).returncode == 0
        assert cli("simulate", "--in", tmp_path / f"{name}_v.csv", "--out",
                   tmp_path / f"{name}.csv").returncode == 0
    r = cli("gap", tmp_path / "fit.csv", "--holdout", tmp_path / "hold.csv", "--out-model",
            tmp_path / "g.yaml")
    assert r.returncode == 0, r.stderr[-2000:]
    warned = [ln for ln in r.stderr.splitlines() if "warning" in ln]
    assert len(warned) == 1 and "HOLDOUT goes past FIT's voltage range" in warned[0], r.stderr
    assert "verdict x: " in r.stdout and "verdict y: " in r.stdout, r.stdout
    r = cli("simulate", "--in", tmp_path / "hold_v.csv", "--model", tmp_path / "g.yaml",
            "--out", tmp_path / "pred.csv")
    assert r.returncode == 0, r.stderr
    assert [ln for ln in r.stderr.splitlines() if ln.strip()][-1].count("past its fitted") == 1


def test_gap_warns_when_the_records_differ_in_units_not_by_an_effect(tmp_path):
    """FIT written in a 0-10 V control voltage (its amplifier's gain 15 unknown to us),
    HOLDOUT in the amplifier's volts: the sim misses HOLDOUT by more than FIT's whole
    stroke, which no unmodelled effect does; one warning line says so (besides the one
    about HOLDOUT leaving FIT's voltage range)."""
    from piezo_stage.io.csv_table import read_table, write_table

    def cli(*a):
        return subprocess.run([sys.executable, "-m", "piezo_stage.cli", *map(str, a)],
                              capture_output=True, text=True, timeout=300)
    for name, seed in (("fit", "1"), ("hold", "3")):
        assert cli("excite", "--rate", "1000", "--out", tmp_path / f"{name}_v.csv",
                   "--seed", seed).returncode == 0
        assert cli("simulate", "--in", tmp_path / f"{name}_v.csv", "--out",
                   tmp_path / f"{name}.csv").returncode == 0
    c = read_table(tmp_path / "fit.csv", ("t", "vx", "vy", "wx", "wy"))
    write_table(tmp_path / "fit.csv", {"t": c["t"], "vx": c["vx"] / 15.0,
                                       "vy": c["vy"] / 15.0, "wx": c["wx"], "wy": c["wy"]})
    r = cli("gap", tmp_path / "fit.csv", "--holdout", tmp_path / "hold.csv", "--axis", "x")
    assert r.returncode == 0, r.stderr[-2000:]
    warned = [ln for ln in r.stderr.splitlines() if "warning" in ln]
    assert any("more than FIT's whole stroke" in ln and "units and gain" in ln
               for ln in warned), r.stderr


def test_the_rate_stages_loop_widens_with_the_input_rate_and_the_structure_stages_does_not():
    """config/rate_stage.yaml: the structure stage's play operators with thresholds
    r_j + 1 ms x |dv/dt| (filtered): over the full stroke its loop at mid stroke is
    wider at 10 Hz than at 2 Hz; the structure stage's (rate independent) is not; a
    batch run and a run one command at a time agree."""
    from piezo_stage.core.model.plant import Plant
    from piezo_stage.io.plant_file import load_plant_config
    from piezo_stage.paths import default_config

    def width(name, f):
        cfg = load_plant_config(default_config(name))
        cfg.model.coupling.clear()
        cfg.noise_rms_um = 0.0
        t = np.arange(3000) / 1000.0
        v = 75.0 - 75.0 * np.cos(2 * np.pi * f * t)
        w = Plant(cfg, 1000.0).run(v, np.zeros_like(v))["x"]
        k = t > 2.0
        vv, ww, dv = v[k], w[k], np.gradient(v[k])
        mid = np.abs(vv - 75.0) < 3.0
        return ww[mid & (dv < 0)].mean() - ww[mid & (dv > 0)].mean(), (v, w)
    slow, (v, w) = width("rate_stage.yaml", 2.0)
    fast, _ = width("rate_stage.yaml", 10.0)
    assert fast > 1.2 * slow > 0, (slow, fast)
    s_slow, _ = width("structure_stage.yaml", 2.0)
    s_fast, _ = width("structure_stage.yaml", 10.0)
    assert abs(s_fast - s_slow) < 0.02 * s_slow, (s_slow, s_fast)
    from piezo_stage.core.model.plant import Plant as P
    cfg = load_plant_config(default_config("rate_stage.yaml"))
    cfg.model.coupling.clear()
    cfg.noise_rms_um = 0.0
    one = P(cfg, 1000.0)
    stepped = np.array([one.step(x, 0.0)[0] for x in v[:500]])
    cfg2 = load_plant_config(default_config("rate_stage.yaml"))
    cfg2.model.coupling.clear()
    cfg2.noise_rms_um = 0.0
    batch = P(cfg2, 1000.0).run(v[:500], np.zeros(500))["x"]
    assert np.allclose(stepped, batch, atol=1e-9)


@pytest.mark.parametrize("units, volts, um, limits", [
    ("a bipolar stack, -75..+75 V", lambda v: v - 75.0, lambda w: w, "-90,90"),
    ("a 0-10 V control voltage (amplifier gain 15)", lambda v: v / 15.0, lambda w: w,
     "0,10"),
    ("a sensor offset of -120 um", lambda v: v, lambda w: w - 120.0, None),
])
def test_any_input_units_identify_and_run_through_the_written_model(tmp_path, units, volts,
                                                                     um, limits):
    """The same stage recorded in other units (a bipolar drive, a control voltage before
    an amplifier of unknown gain, a sensor with an offset): `identify` fits it, writes
    the amplifier's limits, and the written model run through `simulate` over a held-out
    record in the same units is within the sensor's noise plus a little."""
    from piezo_stage.core.model.plant import Plant
    from piezo_stage.io.csv_table import read_table, write_table
    from piezo_stage.io.plant_file import default_plant_config_path, load_plant_config

    def cli(*a):
        return subprocess.run([sys.executable, "-m", "piezo_stage.cli", *map(str, a)],
                              capture_output=True, text=True, timeout=120)
    cfg = load_plant_config(default_plant_config_path())
    cfg.model.coupling.clear()
    recs = {}
    for name, seed, phase in (("fit", 1, 0.0), ("hold", 2, 0.7)):
        cfg.seed = seed
        t, v = sine_v(1.0, 1000.0, 4, 0.0, 150.0)
        v = 75.0 - 75.0 * np.cos(2 * np.pi * t + phase) * np.exp(-0.1 * t)
        w = Plant(cfg, 1000.0).run(v, np.zeros_like(v))["x"]
        recs[name] = (t, volts(v), um(w))
        write_table(tmp_path / f"{name}.csv", {"t": t, "vx": volts(v), "wx": um(w)})
    args = ["identify", tmp_path / "fit.csv", "--out", tmp_path / "m.yaml", "--axis", "x"]
    if limits:
        args.append(f"--limits={limits}")
    r = cli(*args)
    assert r.returncode == 0, (units, r.stderr[-1500:])
    t, vh, wh = recs["hold"]
    write_table(tmp_path / "hold_v.csv", {"t": t, "vx": vh, "vy": np.zeros_like(vh)
                                          + (float(limits.split(",")[0]) if limits else 0)})
    r = cli("simulate", "--in", tmp_path / "hold_v.csv", "--model", tmp_path / "m.yaml",
            "--out", tmp_path / "pred.csv")
    assert r.returncode == 0, (units, r.stderr[-1500:])
    pred = read_table(tmp_path / "pred.csv", ("t", "wx"))["wx"]
    assert held_out_rms(pred, wh, 1000.0) < 0.25, units  # the noise is 0.1 um


def test_identify_class_pi_carries_memory_to_nested_loops_and_inverts_exactly(tmp_path):
    """`identify --class pi` and `--class preisach` on the structure stage's
    constant-amplitude calibration: a Prandtl-Ishlinskii model and a discretized
    Preisach model (non-negative weights) written as model files our simulate and
    invert take; on nested minor loops they predict far better than the Duhem law
    fitted on the same record (Preisach better still), and their exact inverses give
    the voltages back. `--class auto` says per axis which class it chose and why."""
    from piezo_stage.apps.studies import conditions
    from piezo_stage.io.csv_table import read_table, write_table

    def cli(*a):
        return subprocess.run([sys.executable, "-m", "piezo_stage.cli", *map(str, a)],
                              capture_output=True, text=True, timeout=300)
    fit, hold, _ = conditions.case_records("structure", "periodic->nested")
    for name, rec in (("fit", fit), ("hold", hold)):  # the same axis twice: x and y
        write_table(tmp_path / f"{name}.csv", {"t": rec.t, "vx": rec.v["x"],
                                               "vy": rec.v["x"], "wx": rec.w["x"],
                                               "wy": rec.w["x"]})
    write_table(tmp_path / "hold_v.csv", {"t": hold.t, "vx": hold.v["x"],
                                          "vy": hold.v["x"]})
    held = {}
    for cls in ("duhem", "pi", "preisach"):
        r = cli("identify", tmp_path / "fit.csv", "--class", cls, "--coupling", "off",
                "--out", tmp_path / f"{cls}.yaml")
        assert r.returncode == 0, r.stderr[-1500:]
        r = cli("simulate", "--in", tmp_path / "hold_v.csv", "--model",
                tmp_path / f"{cls}.yaml", "--out", tmp_path / f"{cls}_w.csv")
        assert r.returncode == 0, r.stderr[-1500:]
        w = read_table(tmp_path / f"{cls}_w.csv", ("t", "wx"))["wx"]
        held[cls] = held_out_rms(w, hold.w["x"], 1000.0)
    assert held["pi"] <= 0.5 * held["duhem"], held  # 0.58 against 2.2 um when written
    # the Preisach class's density varies along the stroke as the tanh envelope does
    assert held["preisach"] <= 0.6 * held["pi"], held
    for cls in ("pi", "preisach"):
        out = read_table(tmp_path / f"{cls}_w.csv", ("t", "wx", "wy"))
        write_table(tmp_path / "target.csv", {"t": out["t"], "wx": out["wx"],
                                              "wy": out["wy"]})
        r = cli("invert", "--model", tmp_path / f"{cls}.yaml", "--in",
                tmp_path / "target.csv", "--out", tmp_path / "v.csv")
        assert r.returncode == 0, r.stderr[-1500:]
        v = read_table(tmp_path / "v.csv", ("t", "vx"))["vx"]
        assert np.max(np.abs(v - hold.v["x"])) < 1e-6, cls
    r = cli("identify", tmp_path / "fit.csv", "--class", "auto", "--coupling", "off")
    assert r.returncode == 0, r.stderr[-1500:]
    assert "class x: " in r.stdout and "class y: " in r.stdout
    assert "pi " in r.stdout and "preisach " in r.stdout


def test_a_law_whose_branch_would_turn_back_is_kept_rising_and_inverts_exactly():
    """On the rate stage, rising-amplitude triangles (FIT) fitted by the free least
    squares give a Duhem law whose descending branch turns back right after the top
    reversal (its shape h goes negative where alpha w does not make up for it): our
    exact inverse then took another root, 3.7 V off on FIT's voltages and 9.3 V on a
    10 Hz sine over 0-150 V. identify keeps every branch rising (the coefficients
    refitted under that constraint over the record and a probe path of every reversal
    size: 0.1742 -> 0.1783 um on FIT, 2026-11-27), and so does the model `gap
    --out-model` writes: both invert back to rounding."""
    from piezo_stage.apps.studies import conditions
    from piezo_stage.core.estimation.gap import diagnose
    from piezo_stage.core.estimation.identify import IdentifyOptions
    from piezo_stage.core.estimation.identify.fast import fit_fast
    from piezo_stage.core.estimation.identify.regress import DuhemRegression
    from piezo_stage.core.model.inverse import invert
    fit, hold, _ = conditions.case_records("rate", "rising->fast")
    v, w = fit.v["x"], fit.w["x"]
    free_reg = DuhemRegression(v, w, "segmented", 3, 2)
    alphas, free, _ = fit_fast(free_reg)
    loose, _ = free_reg.models(alphas, free.theta)
    res = identify_axis(fit, "x", IdentifyOptions())
    assert res.fit["rms_um"] <= 1.1 * free.rms, (res.fit, free.rms)
    written, _ = diagnose(fit, hold, axes=["x"]).model()
    for vv in (v, hold.v["x"]):
        out, _ = loose.simulate(vv)
        assert np.max(np.abs(invert(loose, out, (0.0, 150.0)).v - vv)) > 1.0  # turned back
        for m in (res.model, written.axes["x"]):
            out, _ = m.simulate(vv)
            assert np.max(np.abs(invert(m, out, (0.0, 150.0)).v - vv)) < 1e-6
            step = np.diff(out) * np.sign(np.diff(vv))
            assert step.min() >= -1e-12  # every branch rises with the voltage
