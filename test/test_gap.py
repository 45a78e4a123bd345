"""Gap diagnosis: blind single-effect records (own and independent effect forms),
no false alarm, inconclusive without the needed excitation, the command's contract,
and closing the loop (the found effect makes the simulator closer to the stage)."""

import json
import os
import subprocess
import sys

import numpy as np
import pytest

from conftest import ROOT
from piezo_stage.apps.studies.gap_blind import make_pair
from piezo_stage.core.errors import ConfigError
from piezo_stage.core.estimation.gap import diagnose
from piezo_stage.io.csv_table import read_table, write_table
from piezo_stage.io.gap_report import axis_figure


@pytest.mark.parametrize("family,kind", [
    ("own", "none"), ("own", "creep"), ("own", "dynamics"), ("own", "delay"),
    ("own", "drift"), ("own", "coupling"), ("independent", "creep"),
    ("independent", "delay"), ("independent", "coupling"),
])
def test_blind_single_effect(family, kind):
    fit, hold = make_pair(kind, family, seed=5)
    res = diagnose(fit, hold, axes=["x"])
    assert res["verdict"] == kind, res["reason"]
    if kind != "none":
        assert res["ranking"][0]["effect"] == kind
        assert res["ranking"][0]["shrink_pct"] >= 50.0
    for r in res["ranking"]:
        for k in ("effect", "rms_before_um", "rms_after_um", "gap_before_um",
                  "gap_after_um", "shrink_pct", "shrink_pm_pct", "params"):
            assert k in r
    # every candidate contains the base (its no-effect limit): never worse on FIT
    base = next(r for r in res["ranking"] if r["effect"] == "none")["fit_rms_um"]
    assert all(r["fit_rms_um"] <= base * (1 + 1e-9) for r in res["ranking"]), res["ranking"]
    if kind != "none":  # the held-out shrink comes with its uncertainty
        assert 0.0 <= res["ranking"][0]["shrink_pm_pct"] < 15.0, res["ranking"][0]


def test_creep_without_holds_is_inconclusive():
    """Creep that shows on a sine (a strong one) fits best, but without holds it
    cannot be told from drift: inconclusive, saying so. A weak one does not show on a
    sine at all: nothing is named."""
    for gamma, verdict, why in ((0.15, "inconclusive", "no holds"),
                                (0.005, "none", "noise floor")):
        fit, hold = _pair_with({"creep": {"gamma": gamma}}, False, seed=1)
        # keep only the sine part of each record (no holds longer than 1 s)
        cut = int(np.flatnonzero(np.diff(fit.v["x"]) == 0)[0]) - 1
        fit, hold = fit.slice(0, cut), hold.slice(0, cut)
        res = diagnose(fit, hold, axes=["x"], effects=("creep", "drift", "delay"))
        assert res["verdict"] == verdict and why in res["reason"], res["reason"]
        assert res["effects"] == []


def _cli(*args):
    return subprocess.run([sys.executable, "-m", "piezo_stage.cli", *map(str, args)],
                          capture_output=True, text=True, cwd=ROOT, timeout=600,
                          env=dict(os.environ, PYTHONPATH=ROOT))


def _csv(path, rec):
    write_table(path, {"t": rec.t, "vx": rec.v["x"], "vy": rec.v["y"],
                       "wx": rec.w["x"], "wy": rec.w["y"]})


def test_gap_command_report_and_closing_the_loop(tmp_path):
    fit, hold = make_pair("delay", "own", seed=2)
    _csv(tmp_path / "fit.csv", fit)
    _csv(tmp_path / "hold.csv", hold)
    r = _cli("gap", tmp_path / "fit.csv", "--holdout", tmp_path / "hold.csv", "--axis", "x",
             "--json", tmp_path / "g.json", "--report", tmp_path / "rep",
             "--out-model", tmp_path / "m.yaml")
    assert r.returncode == 0, r.stderr
    j = json.loads((tmp_path / "g.json").read_text())
    assert j["verdict"] == "delay"
    assert set(j["where"]) >= {"axis", "band_hz", "segment"}
    assert {"noise_floor_um", "seconds", "ranking", "effects", "budget"} <= set(j)
    assert j["axes"]["x"]["effects"][0]["effect"] == "delay"
    assert {"residual_rms_um", "noise_floor_um", "input_locked_um", "not_input_locked_um",
            "explained_um", "unexplained_um"} <= set(j["axes"]["x"]["budget"])
    assert "Gap budget" in (tmp_path / "rep" / "report.md").read_text()
    # the headline says which rule chose the verdict, and so does the report's table
    assert "(chosen by the first-effect rule: it alone closes >= 30 % of the gap)" \
        in j["reason"], j["reason"]
    assert "| chosen by |" in (tmp_path / "rep" / "report.md").read_text()
    assert (tmp_path / "rep" / "report.md").read_text().count("Verdict: delay") == 1
    assert (tmp_path / "rep" / "gap_x.png").stat().st_size > 10_000
    # the simulator with the found effect is closer to the held-out stage
    write_table(tmp_path / "v.csv", {"t": hold.t, "vx": hold.v["x"], "vy": hold.v["y"]})
    r = _cli("simulate", "--in", tmp_path / "v.csv", "--out", tmp_path / "sim.csv",
             "--model", tmp_path / "m.yaml")
    assert r.returncode == 0, r.stderr
    import yaml
    doc = yaml.safe_load((tmp_path / "m.yaml").read_text())
    assert "delay" in doc["effects"]
    found = j["ranking"][0]["params"]["delay_s"]
    assert doc["effects"]["delay"]["delay_s"] == pytest.approx(found)
    sim = read_table(tmp_path / "sim.csv", ["wx"])["wx"]
    doc["effects"] = {}
    with open(tmp_path / "m0.yaml", "w") as fh:
        yaml.safe_dump(doc, fh)
    r0 = _cli("simulate", "--in", tmp_path / "v.csv", "--out", tmp_path / "sim0.csv",
              "--model", tmp_path / "m0.yaml")
    assert r0.returncode == 0, r0.stderr
    sim0 = read_table(tmp_path / "sim0.csv", ["wx"])["wx"]
    e = lambda s: np.sqrt(np.mean((s - hold.w["x"] - np.mean(s - hold.w["x"])) ** 2))  # noqa
    assert e(sim) < 0.7 * e(sim0)


def test_gap_bad_input(tmp_path):
    fit, hold = make_pair("none", "own", seed=3)
    _csv(tmp_path / "fit.csv", fit)
    write_table(tmp_path / "hold.csv", {"t": hold.t, "vx": hold.v["x"], "wx": hold.w["x"]})
    r = _cli("gap", tmp_path / "fit.csv", "--holdout", tmp_path / "hold.csv")
    assert r.returncode == 2 and "axes" in r.stderr
    assert len(r.stderr.strip().splitlines()) == 1
    bad = tmp_path / "nan.csv"
    bad.write_text("t,vx,wx\n0,1,nan\n0.001,2,3\n")
    r = _cli("gap", bad)
    assert r.returncode == 2 and "NaN" in r.stderr
    r = _cli("gap", tmp_path / "nothing.csv")
    assert r.returncode == 2


def test_excite_command(tmp_path):
    r = _cli("excite", "--protocol", "gap", "--out", tmp_path / "e.csv", "--rate", 1000)
    assert r.returncode == 0, r.stderr
    c = read_table(tmp_path / "e.csv", ["t", "vx", "vy"])
    assert 25 < c["t"][-1] < 40
    assert c["vx"].min() >= 0 and c["vx"].max() <= 150
    assert np.all((c["vx"] == 0) | (c["vy"] == 0))  # each axis driven alone
    from piezo_stage.core.estimation.gap import broadband, holds
    assert len(holds(c["vx"], 1000.0)) >= 3           # multi-second holds
    assert broadband(c["vx"], 1000.0)                 # the chirp, by default
    r = _cli("excite", "--chirp", 0, "--out", tmp_path / "e0.csv", "--rate", 1000)
    assert r.returncode == 0, r.stderr
    c0 = read_table(tmp_path / "e0.csv", ["t", "vx", "vy"])
    assert c0["t"][-1] < c["t"][-1] - 4 and not broadband(c0["vx"], 1000.0)
    # --nested: the minor loops that show memory, about 11 s more per axis
    r = _cli("excite", "--nested", "--out", tmp_path / "en.csv", "--rate", 1000)
    assert r.returncode == 0, r.stderr
    cn = read_table(tmp_path / "en.csv", ["t", "vx", "vy"])
    assert 20 < cn["t"][-1] - c["t"][-1] < 24
    assert cn["vx"].min() >= 0 and cn["vx"].max() <= 150


def _pair_with(effects, coupling, seed, fs=1000.0):
    """(FIT, HOLDOUT) from our simulated stage with these effects on (and its
    hysteretic coupling kept or removed)."""
    from piezo_stage.apps.studies.gap_blind import make_multi_pair
    return make_multi_pair(effects, seed, fs, coupling=coupling)


@pytest.mark.parametrize("effects, coupling, want", [
    ({"creep": {"gamma": 0.05}}, True, {"creep", "coupling"}),
    ({"creep": {"gamma": 0.05},
      "dynamics": {"kind": "resonance", "fn_hz": 200.0, "zeta": 0.08}}, False,
     {"creep", "dynamics"}),
])
def test_two_effects_at_once_are_both_named_and_the_budget_adds_up(effects, coupling, want):
    fit, hold = _pair_with(effects, coupling, seed=1)
    res = diagnose(fit, hold)
    for axis, d in res["axes"].items():
        named = {s["effect"] for s in d["effects"]}
        assert named == want, (axis, d["reason"])
        assert d["verdict"] == d["effects"][0]["effect"]  # the dominant one
        # each step names the rule that took it; the headline names the first's
        rules = [s["rule"] for s in d["effects"]]
        assert rules[0].startswith(("the first-effect rule", "the pair rule")), rules
        assert all(r.startswith("the further-effect rule") for r in rules[1:]), rules
        assert f"(chosen by {rules[0]})" in d["reason"], d["reason"]
        gaps = [s["gap_after_um"] for s in d["effects"]]
        assert gaps == sorted(gaps, reverse=True)          # each step shrinks the gap
        b = d["budget"]
        # what the kept effects explain and what is left add up to the gap exactly
        total = sum(v ** 2 for v in b["explained_um"].values()) + b["unexplained_um"] ** 2
        np.testing.assert_allclose(np.sqrt(total), b["gap_um"], rtol=1e-9)
        assert b["unexplained_um"] < 0.25 * b["gap_um"]
        # noise, input-locked and the rest add up to the residual, closely
        assert abs(b["closure_pct"]) < 15.0, b
        assert b["input_locked_um"] > b["not_input_locked_um"]  # these effects repeat
        # one figure per claim: the verdict quotes the table's row for the effect alone,
        # and the joined effects by name with the joined row's figure
        row = next(r for r in d["ranking"] if r["effect"] == d["verdict"])
        assert f"{d['verdict']} shrinks the held-out gap by {row['shrink_pct']:.0f} %" \
            in d["reason"], d["reason"]
        joined = "+".join(s["effect"] for s in d["effects"])
        assert f"({joined}: {d['effects'][-1]['shrink_pct']:.0f} % in all)" in d["reason"]
        # the figure's legend names exactly what was kept; every bar carries its value
        fig = axis_figure(res.per_axis[axis], hold, axis)
        legend = [t.get_text() for t in fig.axes[0].get_legend().get_texts()]
        assert legend == ["before (base model)", f"after ({joined})"]
        bars = fig.axes[3]
        assert len(bars.patches) == len(d["ranking"]) + len(d["effects"])
        values = sorted(float(t.get_text()) for t in bars.texts)
        drawn = sorted(float(f"{p.get_height():.3g}") for p in bars.patches)
        assert values == pytest.approx(drawn)
        import matplotlib.pyplot as plt
        plt.close(fig)


@pytest.mark.slow
@pytest.mark.parametrize("pair", [
    ("creep", "coupling"), ("creep", "dynamics"), ("delay", "coupling"),
    ("dynamics", "drift"), ("creep", "delay")])
def test_withheld_two_effect_cases_name_no_third_effect(pair):
    """Two effects on (magnitudes drawn, a seed none of the rules was tuned on): what is
    named is among them, at least one of them is, and each further step stands above
    its own noise (its share of what was left, bootstrapped over HOLDOUT against the
    model before it)."""
    from piezo_stage.apps.studies.gap_blind import make_multi_pair
    fit, hold = make_multi_pair(pair, 6)
    res = diagnose(fit, hold, axes=["x"])
    named = [s["effect"] for s in res["effects"]]
    assert named and set(named) <= set(pair), (named, res["reason"])
    for s in res["effects"][1:]:
        assert s["step_shrink_pct"] >= 2.0 * s["step_pm_pct"], s


def test_the_given_model_s_own_parts_are_not_candidates(tmp_path, stage_model):
    """With --model, only what the sim lacks is tried: a model with coupling and creep
    leaves the dynamics to be found."""
    effects = {"creep": {"gamma": 0.05},
               "dynamics": {"kind": "resonance", "fn_hz": 200.0, "zeta": 0.08}}
    fit, hold = _pair_with(effects, True, seed=2)
    res = diagnose(fit, hold, axes=["x"], base_model=stage_model,
                   base_effects={"creep": {"gamma": 0.05, "axes": ["x", "y"]}})
    tried = {r["effect"] for r in res["ranking"]}
    assert "coupling" not in tried and "creep" not in tried
    # "none" is the given model as it is: a candidate that changes nothing, 0 %
    none = next(r for r in res["ranking"] if r["effect"] == "none")
    assert none["shrink_pct"] == 0.0 and none["rms_after_um"] == none["rms_before_um"]
    assert res["verdict"] == "dynamics", res["reason"]


def test_holds_are_held_voltages_not_slow_turning_points_or_dac_steps():
    from piezo_stage.core.estimation.gap import held, holds
    fs = 5000.0
    t = np.arange(int(10 * fs)) / fs
    sine = 75 - 75 * np.cos(2 * np.pi * 1.0 * t)              # a plain 1 Hz sine
    assert not held(sine, fs).any() and holds(sine, fs) == []
    stairs = np.floor(np.linspace(0, 150, t.size) / 0.01) * 0.01  # a slow DAC ramp
    assert not held(stairs, fs).any()
    step = np.where(t < 3.0, 20.0, 120.0)                     # two long holds
    assert holds(step, fs) == [3.0, 7.0]
    assert held(step, fs).all()


@pytest.mark.parametrize("effects, verdict", [({}, "disturbance"),
                                              ({"creep": {"gamma": 0.05}}, "creep")])
def test_a_floor_vibration_is_a_disturbance_not_an_effect(effects, verdict):
    """A line the input does not cause (113 Hz: away from the excitation's tones and
    their harmonics, where a hysteresis mismatch would put lines): reported with its
    size, band and the feedback bandwidth that rejects it; it neither hides nor fakes
    an effect."""
    fit, hold = _pair_with(effects, False, seed=3)
    rng = np.random.default_rng(1)
    for rec in (fit, hold):
        for a in ("x", "y"):
            rec.w[a] = rec.w[a] + 0.25 * np.sin(2 * np.pi * 113.0 * rec.t + rng.uniform(0, 6))
    res = diagnose(fit, hold)
    for a, d in res["axes"].items():
        assert d["verdict"] == verdict, d["reason"]
        assert [s["effect"] for s in d["effects"]] == ([] if not effects else ["creep"])
        dist = d["budget"]["disturbance"]
        assert dist["band_hz"][0] <= 113.0 <= dist["band_hz"][1]
        assert dist["rms_um"] == pytest.approx(0.25 / np.sqrt(2), rel=0.15)
        assert dist["feedback_bandwidth_hz"] >= 1000.0
        assert "disturbance" in d["reason"]


def test_no_disturbance_is_reported_where_there_is_none():
    fit, hold = _pair_with({"creep": {"gamma": 0.05}}, True, seed=4)
    res = diagnose(fit, hold)
    assert all(d["budget"]["disturbance"] is None for d in res["axes"].values())


def test_a_richer_hysteresis_shape_is_the_structure_class():
    """The stage's branches bend more than the cubic Duhem branches can follow (a
    quintic term): the structure candidate (degree-5 branches), chosen on HOLDOUT,
    closes the gap, and no effect is named for it."""
    import copy

    from piezo_stage.core.estimation.excitation import gap_protocol
    from piezo_stage.core.estimation.record import Record
    from piezo_stage.core.model.duhem import DuhemBranch, DuhemModel
    from piezo_stage.core.model.plant import Plant
    from piezo_stage.io.plant_file import default_plant_config_path, load_plant_config
    cfg = copy.deepcopy(load_plant_config(default_plant_config_path()))
    cfg.model.coupling.clear()
    m = cfg.model.axes["x"]

    def richer(b, asc):
        h = np.append(b.h(asc), [0.0, 0.0, 0.0])
        h[5] = (-1 if asc else 1) * 0.3 / 150 ** 4  # um/V per V^5: a 0.3 um/V bend
        return DuhemBranch.from_h(b.alpha, h)
    cfg.model.axes["x"] = DuhemModel(richer(m.ascending, True),
                                     richer(m.descending, False), m.initial)
    recs = []
    for k in range(2):
        cfg.seed = 40 + k
        t, vx, vy = gap_protocol(1000.0, seed=cfg.seed)
        recs.append(Record(t, {"x": vx, "y": vy}, Plant(cfg, 1000.0).run(vx, vy),
                           source=f"record {k}"))
    res = diagnose(*recs, axes=["x"])
    assert res["verdict"] == "structure", res["reason"]
    assert [s["effect"] for s in res["effects"]] == ["structure"]
    assert res["effects"][0]["params"] == {"degree": 5}  # no memory: none was needed
    # the best first-round candidate; kept, its alphas polished, it closes the gap
    assert res["ranking"][0]["effect"] == "structure"
    assert res["effects"][0]["shrink_pct"] > 80


def test_dynamics_read_before_the_hold_ends_is_the_plants_sampled_form():
    """effects.Dynamics(delay_frac_s): an input held over each sample, the output read
    that long before the sample's end, against a fine simulation of the same."""
    from scipy import signal

    from piezo_stage.core.model.effects import Dynamics
    fs, fine, delta = 5000.0, 100, 0.1e-3
    wn = 2 * np.pi * 800.0
    u = np.random.default_rng(0).standard_normal(300)
    u[0] = 0.0  # apply() starts at rest at the first row: here rest at 0, as lfilter's
    bf, af, _ = signal.cont2discrete(([wn ** 2], [1, 2 * 0.05 * wn, wn ** 2]),
                                     1 / (fs * fine), method="zoh")
    yf = signal.lfilter(np.ravel(bf), af, np.repeat(u, fine))  # yf[i]: at i fine steps
    want = yf[(np.arange(300) + 1) * fine - int(round(delta * fs * fine))]
    got = Dynamics(fs, "resonance", 800.0, 0.05, delay_frac_s=delta).apply(u[:, None])[:, 0]
    assert np.max(np.abs(got - want)) < 1e-9
    # 0 is the plain ZOH form, and the fraction must stay within a sample
    assert np.array_equal(Dynamics(fs, delay_frac_s=0.0).apply(u[:, None]),
                          Dynamics(fs).apply(u[:, None]))
    with pytest.raises(ConfigError):
        Dynamics(fs, delay_frac_s=1.0 / fs)


def test_a_resonance_and_a_delay_are_both_found_with_the_chirp():
    """The protocol's chirp (``excite``'s default) passes through the resonance: the
    diagnosis names the resonance and the delay (not a delay standing in for both) with
    their values. Without it they are told apart only by what they do to slow motion:
    not at all for a resonance far above the excitation."""
    from piezo_stage.apps.studies.gap_blind import make_multi_pair
    eff = {"delay": {"delay_s": 0.0015},
           "dynamics": {"kind": "resonance", "fn_hz": 300.0, "zeta": 0.06}}
    res = diagnose(*make_multi_pair(eff, 3, 1000.0, coupling=False), axes=["x"])
    got = {s["effect"]: s["params"] for s in res["effects"]}
    assert set(got) == {"delay", "dynamics"}, res["reason"]
    assert got["dynamics"]["fn_hz"] == pytest.approx(300.0, rel=0.03)
    assert got["dynamics"]["zeta"] == pytest.approx(0.06, rel=0.25)
    assert got["delay"]["delay_s"] == pytest.approx(0.0015, abs=0.1e-3)
    assert res["budget"]["unexplained_um"] < 0.2 * res["budget"]["gap_um"]
    assert "chirp" not in res["reason"]  # it had the excitation


def test_a_delay_on_a_record_without_a_chirp_says_what_would_separate_it():
    from piezo_stage.core.estimation.excitation import gap_protocol
    from piezo_stage.core.estimation.gap import broadband
    fit, hold = make_pair("delay", "own", 0, chirp_s=0.0)  # excite --chirp 0
    res = diagnose(fit, hold, axes=["x"])
    assert res["verdict"] == "delay"
    assert "without `--chirp 0`" in res["reason"]
    t, vx, _ = gap_protocol(1000.0, seed=1)  # the default has it
    assert broadband(vx, 1000.0) and not broadband(fit.v["x"], 1000.0)


def test_a_fit_at_one_rate_used_at_another_says_what_would_separate_a_rate_effect():
    """FIT at one rate (2 Hz), HOLDOUT at 10 Hz, on the stage whose loop widens with
    rate: nothing fitted at one rate shows how the loop grows, and the diagnosis says so
    and names the calibration that would (two rates). A FIT at 2 and 5 Hz, or the same
    rate on both sides (a larger stroke), gets no such note."""
    from piezo_stage.apps.studies.conditions import _sine, case_records, excitations
    from piezo_stage.core.estimation.gap.where import main_tones, one_rate_note
    from piezo_stage.core.estimation.record import Record
    fit, hold, _ = case_records("rate", "slow->fast")
    assert main_tones(fit.v["x"], fit.fs_hz) == pytest.approx([2.0] * 4, abs=0.05)
    res = diagnose(fit, hold, axes=["x"])
    assert "FIT runs at one rate (2 Hz) and HOLDOUT at another (10 Hz)" in res["reason"]
    assert "calibrate at two rates at least" in res["reason"]
    t = fit.t
    two = np.where(t < 3.0, _sine(2.0 * t), _sine(5.0 * (t - 3.0)))
    assert main_tones(two, 1000.0) == pytest.approx([2.0, 2.0, 5.0, 5.0], abs=0.05)
    assert one_rate_note(Record(t, {"x": two}, {"x": 0.3 * two}), hold, "x") is None
    t, v, k = excitations("small->large")
    big = Record(t[k:] - t[k], {"x": v[k:]}, {"x": v[k:] * 0.3}, source="larger")
    small = Record(t[:k], {"x": v[:k]}, {"x": v[:k] * 0.3}, source="smaller")
    assert one_rate_note(small, big, "x") is None
    # which FIT the rate candidate is tried on: several rates (two tones, a growing
    # slope), not one sine nor the gap protocol (whose holds have no rate)
    from piezo_stage.core.estimation.excitation import gap_protocol
    from piezo_stage.core.estimation.gap.where import several_rates
    assert several_rates(two, 1000.0) and several_rates(small.v["x"], 1000.0)
    assert not several_rates(fit.v["x"], 1000.0)
    assert not any(several_rates(v, 1000.0) for v in gap_protocol(1000.0, seed=1)[1:])
    assert res["verdict"] != "rate"


STOP_AT_FORK = r"""
import os, signal, sys
def stop(signum, frame):  # as the command's own handler does
    raise KeyboardInterrupt
signal.signal(signal.SIGINT, stop)
# a Ctrl-C that reaches an axis's process the moment it is forked, before it has
# handlers of its own (the whole process group gets a terminal's Ctrl-C)
os.register_at_fork(after_in_child=lambda: os.kill(os.getpid(), signal.SIGINT))
from piezo_stage.apps.studies.gap_blind import make_pair
from piezo_stage.core.estimation.gap import diagnose
fit, hold = make_pair("creep", "own", 0)
res = diagnose(fit, hold)
print(sorted(res["axes"]))
"""


def test_a_stop_at_the_moment_an_axis_process_is_forked_leaves_it_quiet():
    """The axes' processes are forked with the stop signals blocked until they ignore
    them (the parent decides about stops): a SIGINT that reaches a child in between is
    not raised there, so no child prints a traceback and both axes finish."""
    r = subprocess.run([sys.executable, "-c", STOP_AT_FORK], capture_output=True,
                       text=True, timeout=300, cwd=ROOT)
    assert r.returncode == 0, r.stderr[-2000:]
    assert r.stdout.strip() == "['x', 'y']"
    assert "KeyboardInterrupt" not in r.stderr and "Traceback" not in r.stderr, r.stderr


WORKER_STOPPED_EARLY = r"""
import os, signal, sys
def stop(signum, frame):
    raise KeyboardInterrupt
signal.signal(signal.SIGINT, stop)
from piezo_stage.core.workers import forking, quiet_worker
with forking():
    pid = os.fork()
    if pid == 0:  # a worker (it never leaves): a Ctrl-C before its first line, and after
        os.kill(os.getpid(), signal.SIGINT)
        quiet_worker()
        os.kill(os.getpid(), signal.SIGINT)
        os._exit(0)
_, status = os.waitpid(pid, 0)
print(os.waitstatus_to_exitcode(status))
"""


def test_a_worker_forked_with_the_stops_held_never_raises_them():
    """core/workers.py, as refit's and gap's workers use it: a SIGINT before the
    worker's first line and one after it are both ignored; the worker exits 0."""
    r = subprocess.run([sys.executable, "-c", WORKER_STOPPED_EARLY], capture_output=True,
                       text=True, timeout=60, cwd=ROOT)
    assert (r.returncode, r.stdout.strip(), r.stderr) == (0, "0", "")


def test_two_axes_run_apart_with_progress_results_and_errors_relayed():
    """Two axes run in two forked processes: the parent receives each axis's progress
    and its full diagnosis (the kept model too: ``model`` works from it), the same as
    diagnosing that axis here; a record error in one axis's process is raised here as
    the same DataError."""
    from threadpoolctl import threadpool_limits

    from piezo_stage.core.errors import DataError
    from piezo_stage.core.estimation.gap import diagnose_axis
    fit, hold = make_pair("creep", "own", 0)
    seen = []
    res = diagnose(fit, hold, progress=seen.append)
    assert {w.split()[0] for w in seen} == {"x", "y"} and len(seen) >= 14
    with threadpool_limits(1):
        alone = diagnose_axis(fit, hold, "y")
    assert [s["effect"] for s in res["axes"]["y"]["effects"]] == \
        [s["effect"] for s in alone.effects]
    assert res["axes"]["y"]["budget"]["gap_um"] == pytest.approx(alone.budget["gap_um"])
    model, effects = res.model()
    assert set(model.axes) == {"x", "y"} and "creep" in effects
    bad = fit.__class__(hold.t, {"x": hold.v["x"], "y": np.zeros_like(hold.v["y"])},
                        hold.w, source="flat y")
    with pytest.raises(DataError, match="constant"):
        diagnose(fit, bad)


@pytest.mark.parametrize("kind", ["delay", "dynamics"])
def test_one_column_search_finds_what_the_exact_search_finds(kind, monkeypatch):
    """The effect's parameters searched on the held fit's one-column prediction,
    alternating with the exact refit, end where the search on every column ends."""
    from piezo_stage.core.estimation.gap import candidates, searches
    fit, _ = make_pair(kind, "own", 5)
    base = candidates.fit_candidate(fit, "x", "none")
    fast = candidates.fit_candidate(fit, "x", kind, base, base.effects)
    monkeypatch.setattr(searches, "ONE_COLUMN_SEARCH", False)
    exact = candidates.fit_candidate(fit, "x", kind, base, base.effects)
    assert fast.fit_rms_um <= exact.fit_rms_um * 1.01
    for k, v in exact.params.items():
        if isinstance(v, float):
            assert fast.params[k] == pytest.approx(v, rel=0.05), k
        else:
            assert fast.params[k] == v


def structure_path():
    import os

    from piezo_stage.io.plant_file import default_config_dir
    return os.path.join(default_config_dir(), "structure_stage.yaml")


def test_a_stage_with_memory_is_named_memory_and_its_locked_part_is_the_truth():
    """A stage whose hysteresis is not our model class (play operators: memory our
    Duhem law lacks, branches no cubic follows): memory (the structure candidate with
    play-operator columns beside richer branches) is named, the held-out gap shrinks by
    far more than 60 % with the stage's coupling, and the budget's input-locked part is
    within 15 % of the truth the plant knows. (Before: the structure class was degree-5
    branches only: 1 % shrink, verdict inconclusive; the locked part was 0.41 of 0.47
    um.)"""
    from piezo_stage.apps.studies.gap_blind import locked_truth, structure_pair
    fit, hold, true = structure_pair()
    res = diagnose(fit, hold, axes=["x"])
    named = [s["effect"] for s in res["effects"]]
    # both are the stage's, and close in size: which comes first is the pair rule's
    # (since the Preisach class, an exact inverse as close as the memory form alone on
    # this record, coupling by 0.3 %); both must be named. Memory is a class with
    # memory fitted with the coupling kept before it (the discretized Preisach class:
    # 0.114 um held out, 2026-11-27), or the Duhem law's play operators (16)
    assert sorted(named) == ["coupling", "memory"], res["reason"]
    assert res["verdict"] == named[0]
    memory = res["effects"][named.index("memory")]
    assert memory["params"].get("play_operators") == 16 or \
        memory["params"].get("class") in ("preisach", "prandtl-ishlinskii"), memory
    assert res["effects"][-1]["shrink_pct"] >= 60.0, res["effects"]
    locked_true = locked_truth(fit, hold, true["x"], "x")
    b = res["budget"]
    assert abs(b["input_locked_um"] - locked_true) <= 0.15 * locked_true, (b, locked_true)
    # --out-model writes the play operators and the coupling, and the inverse of that
    # model tracks the stage with memory (noise-free, a 2 + 7 Hz target) far better
    # than the Duhem law identified alone: 0.136 against 0.568 um RMS (2026-11-27: the
    # Preisach class with the coupling; the Duhem law's memory form, written before
    # the class was fitted with effects, tracked at 0.064, but its exact inverse turns
    # a branch back, so the exact class wins for being within 10 % on HOLDOUT)
    from piezo_stage.core.estimation.gap import fit_candidate
    from piezo_stage.core.model.inverse import invert
    from piezo_stage.core.model.plant import Plant
    from piezo_stage.io.model_file import model_from_dict, model_to_dict
    from piezo_stage.io.plant_file import load_plant_config
    model, _ = model_from_dict(model_to_dict(*res.model()))
    assert model.plays["x"].thresholds_V.size >= 16 and "x" in model.coupling
    base = fit_candidate(fit, "x", "none")
    duhem = base.reg.models(base.alphas, base.theta)[0]
    cfg = load_plant_config(structure_path())
    cfg.noise_rms_um = cfg.quantization_um = 0.0
    t = np.arange(3000) / 1000.0
    target = 20 - 12 * np.cos(2 * np.pi * 2 * t) - 3 * np.sin(2 * np.pi * 7 * t)
    err = {}
    for name, m, plays in (("plays", model.axes["x"], model.plays["x"]),
                           ("duhem", duhem, None)):
        r = invert(m, target, model.voltage_limits, plays=plays)
        plant = Plant(cfg, 1000.0)
        plant.run(r.v, np.zeros_like(r.v))
        e = (plant.last_true["x"] - target)[1000:]
        err[name] = float(np.std(e))
    assert err["plays"] < 0.15 and err["plays"] < err["duhem"] / 4, err


def test_a_repeating_input_gets_a_model_free_locked_part():
    """When the held-out input repeats (a 1 Hz sine over 8 s), the budget's locked part
    is the synchronous average over its periods less the average's noise bias: a known
    locked residual (0.2 um RMS, bumps at the turning points) under 0.1 um of white
    noise comes back within 5 %, and the JSON names the estimator. An input that does
    not repeat (the gap protocol) gets the regression estimate, named as such."""
    from piezo_stage.core.estimation.gap import gap_budget, input_period
    from piezo_stage.core.estimation.record import Record
    fs = 1000.0
    t = np.arange(int(8 * fs)) / fs
    v = 75 - 75 * np.cos(2 * np.pi * t)
    phase = 2 * np.pi * t
    locked = np.sin(2 * phase) + 0.6 * np.sin(5 * phase + 1.0)
    locked *= 0.2 / np.sqrt(np.mean(locked ** 2))
    resid = locked + np.random.default_rng(3).normal(0, 0.1, t.size)
    rec = Record(t, {"x": v}, {"x": v * 0.3})
    assert input_period(v, None, fs) == 1000
    b = gap_budget(rec, "x", resid, 0.1, 0.2, [])
    assert b["locked_estimator"]["kind"] == "synchronous average"
    assert b["locked_estimator"]["periods"] == 7
    assert abs(b["input_locked_um"] - 0.2) < 0.01, b
    assert b["not_input_locked_um"] < 0.02, b  # the rest is the noise itself
    # an input that does not repeat: the regression estimate, said so
    fit, hold = make_pair("none", "own", seed=3)
    assert input_period(hold.v["x"], hold.v["y"], hold.fs_hz) is None
    b = gap_budget(hold, "x", hold.w["x"] * 0.0 + np.random.default_rng(1).normal(
        0, 0.1, hold.t.size), 0.1, 0.0, [])
    assert b["locked_estimator"]["kind"] == "regression"


def test_a_scan_cut_from_a_run_of_a_stage_with_memory():
    """The issue's kind of record, on the stage with memory: one axis, a 1 Hz sine of
    the full stroke at 5 kHz for 10 s, fit on 3 s and held out on the next 4 s (cut
    from the run: the operators did not start at rest). Structure is named and closes
    >= 40 % of the held-out gap; the budget's locked part is the synchronous average
    (the held-out input repeats) and within 10 % of the truth; no candidate is worse on
    FIT than the base. (Before: structure was degree-5 branches, 1 % at best.) Named
    memory: the play operators are what paid."""
    from piezo_stage.apps.studies.gap_blind import locked_truth, scan_cut
    fit, hold, true = scan_cut()
    res = diagnose(fit, hold)
    assert res["verdict"] == "memory", res["reason"]
    assert res["effects"][0]["shrink_pct"] >= 40.0
    base = next(r for r in res["ranking"] if r["effect"] == "none")["fit_rms_um"]
    assert all(r["fit_rms_um"] <= base * (1 + 1e-9) for r in res["ranking"])
    budget = res["budget"]
    # (HOLDOUT's 4 periods, its first second run, not scored: 3, the 2 after the first)
    assert budget["locked_estimator"] == {"kind": "synchronous average", "periods": 2,
                                          "period_s": 1.0}
    truth = locked_truth(fit, hold, true, "x")
    assert abs(budget["input_locked_um"] - truth) <= 0.10 * truth, (budget, truth)
    # the model --out-model writes (play operators in their fitted start state), run
    # on through HOLDOUT's later cycles: within 0.03 um of the true displacement (the
    # Duhem law identified alone: 0.107 um; 0.012 when written)
    model, _ = res.model()
    v = np.concatenate([fit.v["x"], hold.v["x"]])
    w = model.simulate(v, np.zeros_like(v))[0]["x"][fit.t.size:]
    assert np.sqrt(np.mean((w - true) ** 2)) < 0.03


def test_a_record_sampled_too_slowly_for_fast_dynamics_is_diagnosed_not_refused(tmp_path):
    """The gap protocol at 40 Hz (a host-paced loop's rate: the NV200's link) played on
    the simulated stage: `gap` gives a verdict (no resonance candidate or budget feature
    above the record's Nyquist rate; it once failed with a traceback from its worker)."""
    exe = [sys.executable, "-m", "piezo_stage"]
    wave, rec = str(tmp_path / "e40.csv"), str(tmp_path / "r40.csv")
    for args in (["excite", "--rate", "40", "--out", wave], ["play", wave, "--out", rec]):
        subprocess.run(exe + args, check=True, capture_output=True, timeout=120)
    r = subprocess.run(exe + ["gap", rec, "--axis", "x", "--model",
                              os.path.join(ROOT, "config", "stage_model.yaml")],
                       capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr[-2000:]
    assert r.stdout.startswith("verdict: ") and "Traceback" not in r.stderr, r.stderr[-2000:]


def test_the_live_residual_takes_the_sensors_zero_out_and_measures_the_gap():
    """The gap node's core (ResidualMonitor): against its own twin a stage read with a
    constant sensor offset leaves no residual; one with creep the model lacks does."""
    from piezo_stage.core.estimation.gap.monitor import ResidualMonitor
    from piezo_stage.core.model.plant import Plant
    from piezo_stage.io.model_file import load_model
    from piezo_stage.paths import default_config
    model, effects = load_model(default_config("stage_model.yaml"))
    fs = 1000.0
    t = np.arange(3000) / fs
    v = 75 - 60 * np.cos(2 * np.pi * t)
    same = Plant.of_model(model, effects, fs)
    crept = Plant.of_model(model, {"creep": {"gamma": 0.03, "tau_s": 0.5}}, fs)
    mon, mon_c = (ResidualMonitor(model, effects, fs, 500) for _ in range(2))
    for x in v:
        w = same.step(x, x)
        r = mon.sample({"x": w[0] + 2.0, "y": w[1] - 1.0}, {"x": x, "y": x})
        wc = crept.step(x, x)
        mon_c.sample({"x": wc[0], "y": wc[1]}, {"x": x, "y": x})
    assert max(abs(r["x"]), abs(r["y"])) < 1e-9  # the offset is the sensor's zero
    assert max(mon.rms_um().values()) < 1e-9 and mon.n == len(v)
    assert min(mon_c.rms_um().values()) > 0.05


@pytest.mark.slow
def test_stages_generated_with_fresh_seeds_meet_the_rules_error_rates():
    """Six stages generated with seeds drawn now (not the ones any threshold was tuned
    on: gap_blind.generated_case, one or two effects of the candidates or none, their
    sizes, noise, rate and protocol drawn). At the rates `bench gap` measures
    (spurious <= 2 %, missed <= 5 % of stages) two spurious stages of six come by chance
    once in 170 runs and three missed once in 500: more says the rule names what is not
    there, or leaves out what is (the seeds are in the message, to run it again)."""
    from piezo_stage.apps.studies.gap_blind import run_generated
    base = int(np.random.SeedSequence().entropy % (2 ** 31 - 10))
    rows = run_generated(range(base, base + 6))
    spurious = [r for r in rows if r["spurious"]]
    missed = [r for r in rows if r["missed"]]
    said = [(r["seed"], r["truth"], r["named"], r["spurious"], r["missed"]) for r in rows]
    assert len(spurious) <= 1 and len(missed) <= 2, said


@pytest.mark.slow
def test_an_effect_closer_on_holdout_alone_is_not_named():
    """A generated stage with no effect (seed 2077697533, drawn after the thresholds):
    on its x axis a coupling and the memory form fit FIT no closer than the Duhem law
    alone (to 1e-5 um) and yet are 20 % closer on HOLDOUT, the same fit at another
    point of a flat valley extrapolated differently there. Neither is named: an effect
    must show on the record it was fitted on too (``AxisSearch.shows_on_fit``), and the
    reason says so. Before the rule the axis named memory."""
    from piezo_stage.apps.studies.gap_blind import generated_case, named_effects
    from piezo_stage.core.estimation.gap.selection import diagnose_axis
    case = generated_case(2077697533)
    assert case["truth"] == set()
    d = diagnose_axis(case["fit"], case["hold"], "x")
    assert named_effects({"effects": d.effects, "verdict": d.verdict}) == set(), d.reason
    rank = {r["effect"]: r for r in d.ranking}
    for e in ("coupling", "memory"):
        assert rank[e]["shrink_pct"] > 30.0 and not rank[e]["shows_on_fit"]
    assert rank["none"]["shows_on_fit"]
    assert "fits FIT no closer" in d.reason and "HOLDOUT alone" in d.reason, d.reason


def test_misses_are_counted_by_the_footprint_of_the_effect_left_out():
    """Each effect on an axis falls in one footprint band (its HOLDOUT footprint over
    the noise); a miss counts in its band and only where that axis left it out."""
    from piezo_stage.apps.studies.gap_blind import missed_by_footprint, wilson
    rows = [{"params": {"noise_um": 0.1}, "named": {"x": ["creep"], "y": []},
             "visible_um": {"x": {"creep": 0.5, "drift": 0.12}, "y": {"creep": 0.45,
                                                                    "drift": 0.05}}}]
    bands = {b: (on, missed) for b, on, missed in missed_by_footprint(rows)}
    assert bands == {"1-1.5 x": (1, 1), "1.5-2 x": (0, 0), "2-4 x": (0, 0),
                     ">= 4 x": (2, 1)}
    lo, hi = wilson(0, 200)
    assert lo == 0.0 and 0.01 < hi < 0.03


def test_a_lag_kept_beside_a_delay_is_named_as_the_delays_shape():
    """A delay seen through a held command and the amplifier's slew is no pure shift at
    the samples: a resonance damped past LAG_ZETA kept beside a delay stays in the model
    but is named as the delay (the verdict too, where it joined first); a ringing one,
    or a lag with no delay kept, is named dynamics."""
    from piezo_stage.apps.studies.gap_blind import named_effects
    from piezo_stage.core.estimation.gap.selection import LAG_ZETA, _decide, delay_shape

    def step(effect, params, rule="r", shrink=50.0):
        return {"effect": effect, "params": params, "gap_after_um": 0.1, "rule": rule,
                "shrink_pct": shrink, "equally_well": []}
    lag = {"kind": "resonance", "fn_hz": 740.0, "zeta": 0.76}
    ring = {"kind": "resonance", "fn_hz": 300.0, "zeta": 0.06}
    steps = [step("dynamics", lag, "the first-effect rule"), step("coupling", {}),
             step("delay", {"delay_s": 1.2e-3})]
    note = delay_shape(steps)
    assert steps[0]["shape_of"] == "delay" and "zeta 0.76" in note
    assert named_effects({"effects": steps, "verdict": "delay"}) == {"coupling", "delay"}
    ranking = [{"effect": "dynamics", "gap_after_um": 0.2, "shrink_pct": 51.0},
               {"effect": "delay", "gap_after_um": 0.21, "shrink_pct": 47.0}]
    rec = make_pair("none", "own", 1)[0]
    verdict, reason = _decide(ranking, steps, 0.45, 0.07, rec, rec, "x")
    assert verdict == "delay" and reason.startswith("delay shrinks the held-out gap by 47 %")
    for kept in ([step("dynamics", ring), step("delay", {"delay_s": 1e-3})],
                 [step("dynamics", {**lag, "zeta": LAG_ZETA - 0.01}), step("delay", {})],
                 [step("dynamics", lag), step("coupling", {})]):
        assert delay_shape(kept) == "" and not any("shape_of" in s for s in kept)


def test_a_written_models_effects_per_axis_are_the_given_ones_of_each_axis(stage_model):
    """A model `gap --out-model` wrote lists an effect per axis (a list of blocks with
    their axes): given as `--model`, each axis has its own (the live watch diagnoses
    against such a model); one block for both axes is each axis's too."""
    from piezo_stage.core.estimation.gap.selection import _given_effects
    per_axis = {"creep": [{"axes": ["x"], "gamma": 0.06, "tau_s": [0.05, 5.0]},
                          {"axes": ["y"], "gamma": 0.03, "tau_s": [0.05, 5.0]}]}
    assert _given_effects(stage_model, per_axis, "x") == [
        ("coupling", {}), ("creep", {"gamma": 0.06, "tau_s": [0.05, 5.0]})]
    assert ("creep", {"gamma": 0.03, "tau_s": [0.05, 5.0]}) in \
        _given_effects(stage_model, per_axis, "y")
    both = {"drift": {"rate_um_per_s": 0.01, "amplitude_um": 0.2, "tau_s": 60.0}}
    assert ("drift", both["drift"]) in _given_effects(stage_model, both, "y")
