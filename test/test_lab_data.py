"""Lab data as labs record it: measured records of a real stage (a PI P-885 stack), records
off one sample clock (jitter, lost samples, a real-time run's skipped ticks, long holes),
archives of our own `excite` protocol (the axes driven in turn), and models that our
own simulate and invert always take."""

import json
import os
import subprocess
import sys
import warnings

import numpy as np
import pytest

from conftest import ROOT
from piezo_stage.core.estimation.identify.prandtl import fit_prandtl_ishlinskii, held_out_rms
from piezo_stage.core.estimation.record import Record, on_grid
from piezo_stage.io.csv_table import read_table, write_table

P885 = os.path.join(ROOT, "test", "data", "ntu_p885")
FS = 200.0  # the P-885 records' rate (5 ms a sample, no time column)
UNCOMPENSATED = 7400  # the minor-loop record's first run, before the authors' compensation


def cli(*args, timeout=600):
    return subprocess.run([sys.executable, "-m", "piezo_stage.cli", *map(str, args)],
                          capture_output=True, text=True, timeout=timeout, cwd=ROOT)


def p885(name):
    """(v [V], w [um]) of a P-885 record: its columns 1 and 5 (README.md there)."""
    d = np.loadtxt(os.path.join(P885, name))
    return d[:, 0], d[:, 4]


def write_axis(path, v, w=None):
    """A CSV of one axis as a lab exports it: t, vx (and wx)."""
    cols = {"t": np.arange(v.size) / FS, "vx": v}
    if w is not None:
        cols["wx"] = w
    write_table(path, cols)


def simulated_wx(tmp_path, model, v, name):
    """`simulate --model` over the voltages ``v`` (x; y at rest): wx [um]."""
    write_table(tmp_path / f"{name}_v.csv", {"t": np.arange(v.size) / FS, "vx": v,
                                             "vy": np.zeros(v.size)})
    r = cli("simulate", "--model", model, "--in", tmp_path / f"{name}_v.csv", "--out",
            tmp_path / f"{name}_w.csv", "--no-noise")
    assert r.returncode == 0, r.stderr[-2000:]
    return read_table(tmp_path / f"{name}_w.csv", ("t", "wx"))["wx"]


def test_the_measured_records_are_here_with_their_licence():
    """The P-885 records are the tests' own, byte for byte, with the MIT licence and
    the source named."""
    assert "MIT License" in open(os.path.join(P885, "LICENSE")).read()
    readme = open(os.path.join(P885, "README.md")).read()
    assert "github.com/yan9a/DiscreteBacklashOperator" in readme
    v, w = p885("Model_Vi_Do.dat")
    assert v.size == 8027 and 0.0 <= v.min() < 0.01 and 3.59 < v.max() <= 3.6
    v2, w2 = p885("Test_Vi_Do_Di.dat")
    assert v2.size == 14155 and -125 < w2.min() < w2.max() < -70


def test_default_identify_on_the_p885_writes_a_model_simulate_and_invert_take(tmp_path):
    """A 0-3.6 V control input identified with no options: one warning line naming
    --limits (the record spans 2.4 % of the 0-150 V the model gets), a law bounded past
    the record's span and named so in the file (straight, its ascending branch reached
    1.7e4 um/V inside the limits and simulate refused the file), the stack's lag
    found; the model predicts the calibration's held-out second half to <= 0.19 um,
    and `invert --effects` gives the voltages back."""
    v, w = p885("Model_Vi_Do.dat")
    h = v.size // 2
    write_axis(tmp_path / "fit.csv", v[:h], w[:h])
    r = cli("identify", tmp_path / "fit.csv", "--out", tmp_path / "m.yaml")
    assert r.returncode == 0, r.stderr[-2000:]
    warnings = [ln for ln in r.stderr.splitlines() if "warning" in ln]
    assert len(warnings) == 1 and "--limits" in warnings[0], r.stderr
    text = (tmp_path / "m.yaml").read_text()
    assert "voltage_limits_V: [0.0, 150.0]" in text
    assert "lags the voltage by" in r.stdout and "delay:" in text, r.stdout
    sim = simulated_wx(tmp_path, tmp_path / "m.yaml", v[h:], "half")
    assert held_out_rms(sim, w[h:], FS) <= 0.19  # 0.107 um (the peer: 0.356)
    write_table(tmp_path / "target.csv", {"t": np.arange(v.size - h) / FS, "wx": sim})
    r = cli("invert", "--model", tmp_path / "m.yaml", "--in", tmp_path / "target.csv",
            "--out", tmp_path / "back.csv", "--effects")
    assert r.returncode == 0, r.stderr[-2000:]
    back = read_table(tmp_path / "back.csv", ("t", "vx"))["vx"]
    # (the last few targets are held past the end: the delay's preview runs out)
    assert np.max(np.abs(back[:-5] - v[h:-5])) < 1e-6


def test_a_law_whose_straight_continuation_is_no_stage_is_written_level(tmp_path):
    """The law identify wrote for the P-885 before: fitted on 0-3.6 V, its ascending
    branch carried straight on reaches 1.67e4 um/V inside 0-150 V, which the loader
    refuses. A writer continues it level past its span instead, says so in a note and
    in the file, and the loader takes it; a law that is no stage even so is refused
    before anything is written."""
    from piezo_stage.core.errors import ModelError
    from piezo_stage.core.model.duhem import DuhemBranch, DuhemModel, DuhemState, StageModel
    from piezo_stage.io.model_file import load_model, save_model
    law = DuhemModel(DuhemBranch.from_h(5.47, [-650.7, 57.83, 0.2886, 1.0946]),
                     DuhemBranch.from_h(1e-5, [22.09, -12.76, 5.758, -1.009]),
                     DuhemState(1.8, -124.5), (0.0, 3.6))
    notes = save_model(tmp_path / "m.yaml", StageModel({"x": law}))
    assert len(notes) == 1 and "1.67e+04" in notes[0] and "level" in notes[0], notes
    assert "continued_past_fit: level" in (tmp_path / "m.yaml").read_text()
    back, _ = load_model(tmp_path / "m.yaml")
    assert back.axes["x"].continuation == "level"
    w, _ = back.simulate(np.linspace(0, 150, 300), np.zeros(300))
    assert np.all(np.isfinite(w["x"]))
    bad = DuhemModel(DuhemBranch.from_h(1.0, [1e5]), DuhemBranch.from_h(1.0, [1e5]))
    with pytest.raises(ModelError, match="no stage"):
        save_model(tmp_path / "bad.yaml", StageModel({"x": bad}))
    assert not (tmp_path / "bad.yaml").exists()


def test_class_auto_from_the_p885_calibration_predicts_its_nested_loops(tmp_path):
    """From the constant-amplitude calibration alone (major loops), `identify --class
    auto` cannot choose on memory and says so (the excitation that would tell:
    `excite --nested`); its model predicts the measured nested minor loops at <= 0.8 x
    the textbook Prandtl-Ishlinskii peer's RMS (offset removed, after 1 s)."""
    v, w = p885("Model_Vi_Do.dat")
    vt, wt = p885("Test_Vi_Do_Di.dat")
    vt, wt = vt[:UNCOMPENSATED], wt[:UNCOMPENSATED]
    peer = held_out_rms(fit_prandtl_ishlinskii(v, w).predict(vt), wt, FS)
    assert 0.55 < peer < 0.65  # 0.595 um
    write_axis(tmp_path / "calib.csv", v, w)
    r = cli("identify", tmp_path / "calib.csv", "--class", "auto", "--out",
            tmp_path / "auto.yaml")
    assert r.returncode == 0, r.stderr[-2000:]
    assert "class x: pi" in r.stdout and "excite --nested" in r.stdout, r.stdout
    got = held_out_rms(simulated_wx(tmp_path, tmp_path / "auto.yaml", vt, "minor"), wt, FS)
    assert got <= 0.8 * peer, (got, peer)  # 0.258 um: 0.43 x the peer


def test_gap_on_the_p885_halves_writes_a_model_that_runs_and_names_what_would_tell(
        tmp_path):
    """gap --out-model on the calibration's halves: the model simulate and invert take,
    and, since neither half holds a minor loop, the reason says that the forms with
    memory were not judged where they differ and which excitation would tell."""
    v, w = p885("Model_Vi_Do.dat")
    h = v.size // 2
    write_axis(tmp_path / "fit.csv", v[:h], w[:h])
    write_axis(tmp_path / "hold.csv", v[h:], w[h:])
    r = cli("gap", tmp_path / "fit.csv", "--holdout", tmp_path / "hold.csv", "--out-model",
            tmp_path / "g.yaml", "--json", tmp_path / "g.json")
    assert r.returncode == 0, r.stderr[-2000:]
    doc = json.loads((tmp_path / "g.json").read_text())
    assert "excite --nested" in doc["reason"], doc["reason"]
    sim = simulated_wx(tmp_path, tmp_path / "g.yaml", v[h:], "gap")
    assert held_out_rms(sim, w[h:], FS) < 0.19
    write_table(tmp_path / "target.csv", {"t": np.arange(v.size - h) / FS, "wx": sim})
    r = cli("invert", "--model", tmp_path / "g.yaml", "--in", tmp_path / "target.csv",
            "--out", tmp_path / "back.csv")
    assert r.returncode == 0, r.stderr[-2000:]


@pytest.mark.parametrize("split", ["periodic: first 20 s -> the rest",
                                   "periodic -> nested minor loops"])
def test_the_model_gap_writes_scores_what_its_table_says_and_no_worse_than_identify(
        tmp_path, split):
    """One model, one figure, on the measured P-885: `gap --out-model` with default
    options, the file run by our own `simulate` over HOLDOUT scores what the table's
    `written` row says (within 5 %; it is the same computation) and no worse than the
    `identify` model of the same FIT. (Before: the table said 0.117 um for memory+creep,
    the file scored 0.683, `identify` 0.107; on the nested loops 0.593 against 0.390.)"""
    v, w = p885("Model_Vi_Do.dat")
    if split.startswith("periodic:"):
        n = int(20 * FS)
        fit, hold = (v[:n], w[:n]), (v[n:], w[n:])
    else:
        vt, wt = p885("Test_Vi_Do_Di.dat")
        fit, hold = (v, w), (vt[:UNCOMPENSATED], wt[:UNCOMPENSATED])
    write_axis(tmp_path / "fit.csv", *fit)
    write_axis(tmp_path / "hold.csv", *hold)
    r = cli("gap", tmp_path / "fit.csv", "--holdout", tmp_path / "hold.csv", "--axis", "x",
            "--out-model", tmp_path / "gap.yaml", "--json", tmp_path / "g.json")
    assert r.returncode == 0, r.stderr[-2000:]
    written = json.loads((tmp_path / "g.json").read_text())["axes"]["x"]["written"]
    row = next(ln for ln in r.stdout.splitlines() if ln.split()[1:2] == ["written"])
    assert f"{written['rms_after_um']:9.4f}" in row, (row, written)
    r = cli("identify", tmp_path / "fit.csv", "--out", tmp_path / "identify.yaml")
    assert r.returncode == 0, r.stderr[-2000:]
    got = held_out_rms(simulated_wx(tmp_path, tmp_path / "gap.yaml", hold[0], "gap"),
                       hold[1], FS)
    ident = held_out_rms(simulated_wx(tmp_path, tmp_path / "identify.yaml", hold[0],
                                      "identify"), hold[1], FS)
    assert got == pytest.approx(written["rms_after_um"], rel=0.05), (got, written)
    assert got <= ident * (1 + 1e-9), (got, ident, written)


def test_gap_s_verdict_does_not_turn_on_the_amplifier_limits_the_data_lie_inside(
        tmp_path):
    """On the measured P-885 (0-3.6 V; the calibration held out on its nested minor
    loops, where memory is the verdict), `gap` with the default limits (0-150 V) and
    with `--limits=0,3.6` (the record's own span) names the same effects with the same
    figures, every candidate's: the memory classes' operators reach half the span of
    the records' voltages, not of an amplifier's range beyond them (before: memory
    without, and inconclusive with the limits)."""
    v, w = p885("Model_Vi_Do.dat")
    vt, wt = p885("Test_Vi_Do_Di.dat")
    write_axis(tmp_path / "fit.csv", v, w)  # the calibration -> its nested minor loops
    write_axis(tmp_path / "hold.csv", vt[:UNCOMPENSATED], wt[:UNCOMPENSATED])
    got = []
    for extra in ([], ["--limits=0,3.6"]):
        r = cli("gap", tmp_path / "fit.csv", "--holdout", tmp_path / "hold.csv", "--axis",
                "x", "--json", tmp_path / "g.json", *extra)
        assert r.returncode == 0, r.stderr[-2000:]
        d = json.loads((tmp_path / "g.json").read_text())
        got.append((d["verdict"], [(s["effect"], round(s["rms_after_um"], 4))
                                   for s in d["effects"]],
                    [(c["effect"], round(c["rms_after_um"], 4)) for c in d["ranking"]],
                    round(d["axes"]["x"]["written"]["rms_after_um"], 4)))
    assert got[0] == got[1], got


def _sim_record(seconds=12.0, fs=1000.0, seed=0, freqs=(1.0, 2.7)):
    """Axis x of the simulated stage driven by two sines (minor loops in it)."""
    from piezo_stage.core.model.plant import Plant
    from piezo_stage.io.plant_file import default_plant_config_path, load_plant_config
    cfg = load_plant_config(default_plant_config_path())
    cfg.seed = seed
    t = np.arange(int(seconds * fs)) / fs
    v = 75 + 45 * np.sin(2 * np.pi * freqs[0] * t) + 25 * np.sin(2 * np.pi * freqs[1] * t)
    w = Plant(cfg, fs).run(v, np.zeros_like(v))["x"]
    return Record(t, {"x": v}, {"x": w}, source=f"sim {seed}")


def _validate(rec, held):
    from piezo_stage.core.estimation.identify.api import identify_axis, predict_axis
    res = identify_axis(rec, "x")
    return held_out_rms(predict_axis(res, held)[2], held.w["x"], held.fs_hz), res


def test_a_record_that_jitters_and_loses_samples_identifies_like_the_clean_one(tmp_path):
    """Time stamps that jitter by +-30 % of a step and 1 % of the samples lost: put on
    the 1 ms grid (one note line saying how and how many were interpolated), the
    model is within 10 % RMS of the clean record's on the same held-out record; the
    CLI reads such a CSV as it is."""
    clean, held = _sim_record(seed=1), _sim_record(seed=2, freqs=(1.3, 3.1))
    rng = np.random.default_rng(3)
    n = len(clean)
    keep = np.sort(rng.permutation(n)[: n - n // 100])
    t = clean.t + rng.uniform(-0.3, 0.3, n) * 1e-3
    # the signals as a logger samples them at its jittered instants
    v = np.interp(t, clean.t, clean.v["x"])
    w = np.interp(t, clean.t, clean.w["x"])
    raw = Record(t[keep], {"x": v[keep]}, {"x": w[keep]}, source="jittered.csv")
    assert not raw.uniform
    grid = on_grid(raw)
    assert grid.uniform and abs(grid.dt - 1e-3) < 1e-7
    # the lost samples' ticks alone are unmeasured (left out of the fits); a jittered
    # stamp is its tick's measurement
    assert 0 < grid.unmeasured() <= n // 100, grid.unmeasured()
    note = grid.notes[-1]
    assert "1 ms grid" in note and "interpolated" in note and "hole" not in note, note
    e_clean, _ = _validate(clean, held)
    e_jit, _ = _validate(grid, held)
    assert e_jit <= 1.1 * e_clean, (e_jit, e_clean)
    write_table(tmp_path / "j.csv", {"t": raw.t, "vx": raw.v["x"], "wx": raw.w["x"]})
    r = cli("identify", tmp_path / "j.csv", "--axis", "x")
    assert r.returncode == 0, r.stderr[-2000:]
    assert "note: j.csv" in r.stdout.replace(str(tmp_path) + "/", "") or \
        "not uniformly sampled" in r.stdout, r.stdout


def test_a_long_hole_splits_the_record_into_segments_fitted_together():
    """A real-time run's host stall: 40 ticks skipped at once. On the grid the voltage
    is held over them (as the driver held it), the hole's displacement is marked
    unmeasured and left out of the fit, the note names the segments; the model is
    the unbroken record's within 10 % on the held-out record."""
    from piezo_stage.core.estimation.record import fitted_together
    clean, held = _sim_record(seed=4), _sim_record(seed=5, freqs=(1.3, 3.1))
    cut = np.r_[np.arange(0, 5000), np.arange(5040, len(clean))]
    raw = Record(clean.t[cut], {"x": clean.v["x"][cut]}, {"x": clean.w["x"][cut]},
                 source="stall", voltage_exact=True)
    grid = on_grid(raw)
    assert grid.unmeasured() == 40 and "2 segments" in grid.notes[-1], grid.notes
    assert np.all(grid.v["x"][5000:5040] == clean.v["x"][4999])  # held, as the driver does
    e_clean, _ = _validate(clean, held)
    e_hole, res = _validate(grid, held)
    assert e_hole <= 1.1 * e_clean, (e_hole, e_clean)
    # left out: the fit does not follow what the hole's interpolation made up
    seen = []
    fitted_together(grid, lambda r: seen.append(r.w["x"][5000:5040].copy()) or len(seen),
                    lambda fitted, r: {"x": np.full(len(r), -1.0)})
    assert len(seen) == 2 and np.all(seen[1] == -1.0)  # the second fit: the prediction's


def test_a_real_time_bag_with_skipped_ticks_goes_through_identify_gap_and_refit(tmp_path):
    """A bag whose stamps skip ticks (a real-time run) is identified, diagnosed and
    refitted, each saying how it was put on the grid."""
    from piezo_stage.io.bag import write_record_bag
    rec = _sim_record(seconds=16.0, seed=6)
    rng = np.random.default_rng(6)
    gone = np.zeros(len(rec), bool)
    for start in rng.choice(len(rec) - 20, 25, replace=False):
        gone[start:start + rng.integers(1, 7)] = True  # a few ticks, 25 times
    gone[:10] = False
    keep = ~gone
    bag = tmp_path / "rt"
    write_record_bag(bag, Record(rec.t[keep], {"x": rec.v["x"][keep]},
                                 {"x": rec.w["x"][keep]}, source="rt"))
    r = cli("identify", bag, "--axis", "x", "--out", tmp_path / "m.yaml")
    assert r.returncode == 0, r.stderr[-2000:]
    assert "not uniformly sampled" in r.stdout and "held over skipped ticks" in r.stdout
    r = cli("gap", bag, "--axis", "x")
    assert r.returncode == 0 and "verdict" in r.stdout, r.stderr[-2000:]
    r = cli("refit", bag, "--out", tmp_path / "refit", "--jobs", 1)
    assert r.returncode == 0, r.stderr[-2000:]
    assert "skipped:" not in r.stdout and "not uniformly sampled" in r.stdout, r.stdout


def _excite_archive(tmp_path, gammas, rate=1000.0):
    """Bags of `play` of `excite`'s protocol (x first, then y; its defaults, at 1 kHz)
    on the simulated stage, one a day, its creep's gamma per bag."""
    from piezo_stage.core.estimation.excitation import gap_protocol
    from piezo_stage.drivers.playback import play_record
    from piezo_stage.io.bag import write_record_bag
    from piezo_stage.io.plant_file import default_plant_config_path, load_plant_config
    t, vx, vy = gap_protocol(rate, seed=0)
    wave = Record(t, {"x": vx, "y": vy}, source="excite.csv")
    paths = []
    for day, g in enumerate(gammas):
        cfg = load_plant_config(default_plant_config_path())
        cfg.effects = {"creep": {"gamma": g}}
        cfg.seed = 10 + day
        played = play_record("sim", wave, plant_config=cfg)
        path = tmp_path / "archive" / f"2026110{day + 1}-090000" / "run"
        write_record_bag(path, played, metadata={"piezo_stage_run": {
            "started_utc": f"2026-11-0{day + 1}T09:00:00+00:00"}})
        paths.append(path)
    return paths


@pytest.mark.slow
def test_refit_of_our_own_excite_protocol_names_the_growing_creep_alone(tmp_path):
    """Six bags of `excite`'s protocol played on the simulated stage (each axis rests
    while the other moves), creep's gamma growing 0.01 -> 0.08: every axis is fitted
    and held out where its voltage moves, and the growth named is creep's, on both
    axes, and no other effect."""
    from piezo_stage.io.model_file import save_model
    from piezo_stage.io.plant_file import default_plant_config_path, load_plant_config
    _excite_archive(tmp_path, np.linspace(0.01, 0.08, 6))
    save_model(tmp_path / "reference.yaml", load_plant_config(default_plant_config_path())
               .model)
    r = cli("refit", tmp_path / "archive", "--out", tmp_path / "out", "--against",
            tmp_path / "reference.yaml", "--jobs", 2, timeout=1200)
    assert r.returncode == 0, r.stderr[-3000:]
    doc = json.loads((tmp_path / "out" / "refit.json").read_text())
    assert not doc["skipped"] and len(doc["bags"]) == 6
    growth = {(g["axis"], g["effect"]): g for g in doc["growth"]}
    assert set(growth) == {("x", "creep"), ("y", "creep")}, growth
    for a in ("x", "y"):
        g = growth[(a, "creep")]
        assert g["change_pct"] > 200 and 0.06 < g["last"] < 0.1, g
    assert "x: creep +" in r.stdout and "y: creep +" in r.stdout


def test_when_no_bag_can_be_refitted_every_bag_is_named_with_its_reason(tmp_path):
    from piezo_stage.io.bag import write_record_bag
    for k in range(4):  # four runs of a stage at rest
        t = np.arange(500) / 1000.0
        write_record_bag(tmp_path / "a" / f"run{k}", Record(
            t, {"x": np.full(500, 10.0)}, {"x": np.full(500, 5.0)}, source="rest"))
    r = cli("refit", tmp_path / "a", "--out", tmp_path / "o", "--jobs", 1)
    assert r.returncode == 2 and len(r.stderr.strip().splitlines()) == 1, r.stderr
    for k in range(4):
        assert f"a_run{k}" in r.stderr, r.stderr
    assert "at rest" in r.stderr


def largest_step_V(rec) -> float:
    """The largest change of the applied voltage from one sample to the next [V], over
    both axes."""
    return max(float(np.abs(np.diff(x)).max()) for x in rec.v.values())


# A real-time run is the lockstep run's twin while the commands kept pace: where the host
# paused the loop's processes, the driver held the last command for those ticks and then
# stepped to where the path had got to (a stall of 48 ms put a 92 V step into one sample
# on this 2-core VM, 2026-12-02, where the lockstep run's largest is 12 V). The paper's
# Duhem law takes each sample's increment in one implicit-Euler step, so such steps are
# another excitation: on 18 real-time runs of this test (250 Hz), the 3 whose largest
# step stayed within TWIN_STEPS x the lockstep run's identified within 0.91 x of it, the
# others 0.94-2.5 x. The record is not the cause: re-simulating the stage on a bag's
# applied voltage gives its measured samples exactly, and the bag's model came within
# 0.99-1.03 x of the model of that simulation (every sample measured) on all 18, and
# 1.055 x in a fresh clone's CI (a voltage one sample off its displacement: 1.25-1.81 x)
TWIN_STEPS = 2.0


@pytest.mark.slow
@pytest.mark.realtime
def test_a_real_time_run_identifies_like_its_lockstep_twin(tmp_path, ros_env, ros_domains):
    """The same run recorded in real time (at the rate this host holds with margin:
    its stamps skip the ticks the host stalled) and in lockstep: identify, gap and
    refit take the real-time bag; its model predicts a held-out record within 10 % RMS
    of the model of the same applied voltage with every sample measured (the stage
    simulated on it: what the skipped ticks and the stamps' jitter cost), and within
    10 % RMS of the lockstep bag's model whenever the real-time run applied the same
    excitation (its largest step within TWIN_STEPS x the lockstep run's: see above;
    recorded once more when not, and said in a warning with the figures when neither
    run was a twin). A pair that fails, once more at the rate the host holds then
    (conftest.realtime_twice)."""
    from conftest import realtime_twice
    realtime_twice(lambda e, rate, which: _twins(tmp_path / which, e, rate), ros_env,
                   ros_domains, name="the real-time twin")


def _twins(tmp_path, ros_env, rate):
    from conftest import CONFIG
    from piezo_stage.core.estimation.identify.api import identify_stage, predict_axis
    from piezo_stage.core.model.plant import Plant
    from piezo_stage.io.plant_file import default_plant_config_path, load_plant_config
    from piezo_stage.io.records import load_record
    from piezo_stage.launcher.launcher import Launch, LaunchOptions
    tmp_path.mkdir()
    traj = {"kind": "seed", "duration_s": 6.0, "excite_s": 8.0}

    def record(mode, bag):
        o = {"stage_driver": {"mode": mode, "min_margin": 0.0},
             "feedforward": {"model_file": os.path.join(CONFIG, "stage_model.yaml")},
             "trajectory": traj}
        launch = Launch(os.path.join(CONFIG, "stage.yaml"), LaunchOptions(record=bag, overrides=o,
            exclusive=False, armed_s=15.0, rate=rate,
            nodes=["stage_driver", "feedforward", "controller", "trajectory"]), env=ros_env)
        assert launch.run(launch.wall_bound()) == 0, launch.failed
        return bag
    bags = {mode: record(mode, str(tmp_path / mode)) for mode in ("realtime", "lockstep")}
    cfg = load_plant_config(default_plant_config_path())
    t = np.arange(10_000) / 1000.0
    vx = 75 + 45 * np.sin(2 * np.pi * 0.9 * t) + 20 * np.sin(2 * np.pi * 2.3 * t)
    vy = 70 + 50 * np.sin(2 * np.pi * 1.3 * t)
    w = Plant(cfg, 1000.0).run(vx, vy)
    held = Record(t, {"x": vx, "y": vy}, {"x": w["x"], "y": w["y"]}, source="held out")

    def held_out(rec):
        fit = identify_stage(rec, ["x", "y"])
        return held_out_rms(predict_axis(fit.results["x"], held)[2], held.w["x"],
                            held.fs_hz)
    recs = {mode: load_record(bag) for mode, bag in bags.items()}
    steps = largest_step_V(recs["realtime"]) / largest_step_V(recs["lockstep"])
    if steps > TWIN_STEPS:  # the host paused the commands: once more
        bags["realtime"] = record("realtime", str(tmp_path / "realtime_again"))
        recs["realtime"] = load_record(bags["realtime"])
        steps = largest_step_V(recs["realtime"]) / largest_step_V(recs["lockstep"])
    rt = recs["realtime"]
    # the same applied voltage with every sample measured: the stage simulated on it
    ws = Plant(cfg, rt.fs_hz).run(rt.v["x"], rt.v["y"])
    full = Record(rt.t, dict(rt.v), {"x": ws["x"], "y": ws["y"]}, "every sample",
                  voltage_exact=True)
    rms = {"realtime": held_out(rt), "every sample": held_out(full),
           "lockstep": held_out(recs["lockstep"])}
    assert rms["realtime"] <= 1.1 * rms["every sample"], rms
    if steps <= TWIN_STEPS:
        assert rms["realtime"] <= 1.1 * rms["lockstep"], (rms, steps)
    else:
        warnings.warn(f"neither real-time run was the lockstep run's twin: the host "
                      f"paused the commands, the largest voltage step {steps:.1f} x the "
                      f"lockstep run's; held-out RMS {rms}", stacklevel=1)
    for cmd in (["identify", bags["realtime"], "--out", tmp_path / "rt.yaml"],
                ["gap", bags["realtime"]],
                ["refit", bags["realtime"], "--out", tmp_path / "refit", "--jobs", 1]):
        r = cli(*cmd)
        assert r.returncode == 0, (cmd, r.stderr[-2000:])
