"""The offline commands, run as a user would (a subprocess of the console script)."""

import os
import shutil
import subprocess
import sys

import numpy as np
import pytest

from conftest import CONFIG, ROOT, sine_v
from piezo_stage.io.csv_table import read_table, write_table

MODEL = os.path.join(CONFIG, "stage_model.yaml")


def run(*args, check=True):
    r = subprocess.run([sys.executable, "-m", "piezo_stage.cli", *map(str, args)],
                       capture_output=True, text=True, cwd=ROOT, timeout=300,
                       env=dict(os.environ, PYTHONPATH=ROOT))
    if check:
        assert r.returncode == 0, r.stderr
    return r


@pytest.fixture
def volts(tmp_path):
    t, v = sine_v(1.0, 2000, 2)
    p = tmp_path / "volts.csv"
    write_table(p, {"t": t, "vx": v, "vy": v[::-1]})
    return p


def test_simulate_writes_displacements(tmp_path, volts):
    out = tmp_path / "out.csv"
    run("simulate", "--in", volts, "--out", out, "--seed", 4)
    c = read_table(out, ["t", "vx", "vy", "wx", "wy"])
    assert 70 < np.ptp(c["wx"]) < 95
    again = tmp_path / "again.csv"
    run("simulate", "--in", volts, "--out", again, "--seed", 4)
    assert open(out).read() == open(again).read()  # deterministic for a seed


def test_invert_then_simulate_model_round_trip(tmp_path):
    t = np.arange(4000) / 4000
    wx = 30 + 20 * np.sin(2 * np.pi * 2 * t)
    wy = 30 + 10 * np.sin(2 * np.pi * 3 * t)
    target = tmp_path / "target.csv"
    write_table(target, {"t": t, "wx": wx, "wy": wy}, fmt="%.17g")
    volts = tmp_path / "v.csv"
    r = run("invert", "--model", MODEL, "--in", target, "--out", volts)
    assert "unreachable" not in r.stderr
    out = tmp_path / "w.csv"
    # round trip through the CSV (written with 10 significant digits)
    run("simulate", "--in", volts, "--out", out, "--model", MODEL)
    c = read_table(out, ["wx", "wy"])
    np.testing.assert_allclose(c["wx"], wx, atol=1e-5)
    np.testing.assert_allclose(c["wy"], wy, atol=1e-5)


def test_invert_with_effects_makes_the_600_hz_stage_follow_at_a_controllers_rate(tmp_path):
    """``invert --effects``: the model's delay, resonance (above the Nyquist rate at 1 kHz,
    inverted with preview) and creep compensated at the target's own rate; played on
    the stage they belong to (``simulate``), the record follows the target to the
    sensor's noise, where the hysteresis inverse alone misses by micrometres."""
    from piezo_stage.io.model_file import load_model, save_model
    model, _ = load_model(MODEL)
    mfile = tmp_path / "m600.yaml"
    save_model(mfile, model, {"creep": {"gamma": 0.039}, "delay": {"delay_s": 0.000813},
                              "dynamics": {"kind": "resonance", "fn_hz": 602.0,
                                           "zeta": 0.084}})
    for fs in (1000, 5000):
        t = np.arange(int(0.5 * fs) + 1) / fs
        w = 25 + 24 * np.sin(2 * np.pi * 40 * t - np.pi / 2)
        target = tmp_path / f"t{fs}.csv"
        write_table(target, {"t": t, "wx": w, "wy": w}, fmt="%.17g")
        rms = {}
        for flag in ((), ("--effects",)):
            volts, out = tmp_path / "v.csv", tmp_path / "w.csv"
            r = run("invert", "--model", mfile, "--in", target, "--out", volts, *flag)
            run("simulate", "--in", volts, "--out", out, "--config",
                os.path.join(CONFIG, "sim_stage_600hz.yaml"))
            c = read_table(out, ["wx", "wy"])
            rms[flag] = max(np.sqrt(np.mean((c[k] - w)[len(w) // 5:] ** 2))
                            for k in ("wx", "wy"))
        assert "samples of preview" in r.stderr or fs == 5000
        assert rms[("--effects",)] < 0.2 and rms[()] > 1.5, rms
    r = run("invert", "--model", MODEL, "--in", target, "--out", volts, "--effects",
            check=False)
    assert r.returncode == 2 and "no effects" in r.stderr


def test_invert_reports_unreachable(tmp_path):
    t = np.arange(100) / 100
    target = tmp_path / "target.csv"
    write_table(target, {"t": t, "wx": np.linspace(0, 300, 100), "wy": np.zeros(100)})
    r = run("invert", "--model", MODEL, "--in", target, "--out", tmp_path / "v.csv")
    assert "axis x" in r.stderr and "unreachable" in r.stderr
    v = read_table(tmp_path / "v.csv", ["vx"])["vx"]
    assert v.max() == 150.0


def _bad(tmp_path, text, *extra):
    p = tmp_path / "bad.csv"
    p.write_text(text)
    out = tmp_path / "out.csv"
    r = run("simulate", "--in", p, "--out", out, *extra, check=False)
    assert r.returncode == 2, r.stderr
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and "Traceback" not in r.stderr, r.stderr
    assert not out.exists()
    assert not [f for f in os.listdir(tmp_path) if f.endswith(".tmp")]
    return lines[0]


@pytest.mark.parametrize("text,needle", [
    ("t,vx,vz\n0,1,2\n0.1,1,2\n", "the axes are x and y"),
    ("t,wx\n0,1\n0.1,1\n", "missing columns: need t and, for at least one axis, v"),
    ("t,vx,vy\n0,1,nan\n0.1,1,2\n", "NaN"),
    ("t,vx,vy\n0,1,inf\n0.1,1,2\n", "NaN or inf"),
    ("t,vx,vy\n0,1,2\n0,1,2\n", "not increasing"),
    ("t,vx,vy\n0,1,2\n0.1,1,2\n0.3,1,2\n", "not uniformly"),
    ("t,vx,vy\n0,1,2\n0.1,1,200\n", "outside the voltage limits"),
    ("t,vx,vy\n0,1,2\n0.1,x,2\n", "non-numeric"),
    ("t,vx,vy\n0,1,2\n0.1,1\n", "fields"),
    ("", "empty"),
])
def test_simulate_bad_input(tmp_path, text, needle):
    assert needle in _bad(tmp_path, text)


def test_one_axis_records_are_taken_wherever_two_axis_ones_are(tmp_path):
    """A lab's record of one axis (t,vx; t,wx) where a two-axis one is taken: simulate
    (the other axis at rest; the record's own displacement scored), invert (a model of
    both axes, the other held at rest, its coupling taken in), play (the other at the
    safe voltage), and what they write runs on (before: "missing column(s) vy")."""
    t = np.arange(2000) / 1000.0
    v = 75 - 60 * np.cos(2 * np.pi * t)
    write_table(tmp_path / "v.csv", {"t": t, "vx": v})
    model = os.path.join(ROOT, "config", "stage_model.yaml")
    run("simulate", "--in", tmp_path / "v.csv", "--out", tmp_path / "w.csv", "--model",
        model)
    w = read_table(tmp_path / "w.csv", ["t", "vx", "wx"])
    assert "vy" not in w and np.ptp(w["wx"]) > 50
    r = run("simulate", "--in", tmp_path / "w.csv", "--out", tmp_path / "w2.csv",
            "--model", model)
    assert "x: 0.0000 um RMS from" in r.stdout, r.stdout  # the same stage: no error
    write_table(tmp_path / "target.csv", {"t": t, "wx": w["wx"]})
    run("invert", "--model", model, "--in", tmp_path / "target.csv", "--out",
        tmp_path / "back.csv")
    back = read_table(tmp_path / "back.csv", ["t", "vx", "vy"])
    assert np.all(back["vy"] == 0.0)
    np.testing.assert_allclose(back["vx"], v, atol=1e-6)  # the coupling of vy at rest
    run("play", tmp_path / "v.csv", "--out", tmp_path / "played.csv")
    played = read_table(tmp_path / "played.csv", ["t", "vx", "vy", "wx", "wy"])
    np.testing.assert_allclose(played["vx"], v, atol=1e-6)  # (the CSV's 10 digits)
    assert np.all(played["vy"] == 0.0)


def test_malformed_yaml_config(tmp_path, volts):
    cfg = tmp_path / "c.yaml"
    cfg.write_text("piezo_stage_plant: 1\nmodel: [unclosed\n")
    r = run("simulate", "--in", volts, "--out", tmp_path / "o.csv", "--config", cfg,
            check=False)
    assert r.returncode == 2 and "malformed YAML" in r.stderr
    assert len(r.stderr.strip().splitlines()) == 1
    model = tmp_path / "m.yaml"
    model.write_text("piezo_stage_model: 1\naxes:\n  x: {structure: whole, alpha: -1, "
                     "f: [0], g: [1]}\n")
    r = run("simulate", "--in", volts, "--out", tmp_path / "o.csv", "--model", model,
            check=False)
    assert r.returncode == 2 and "alpha" in r.stderr


def test_existing_output_untouched_on_error(tmp_path):
    out = tmp_path / "out.csv"
    out.write_text("precious\n")
    bad = tmp_path / "bad.csv"
    bad.write_text("t,vx,vy\n0,1,nan\n0.1,1,1\n")
    r = run("simulate", "--in", bad, "--out", out, check=False)
    assert r.returncode == 2
    assert out.read_text() == "precious\n"


def test_usage_error_is_one_line():
    r = run("simulate", "--bogus", check=False)
    assert r.returncode == 2
    assert len(r.stderr.strip().splitlines()) == 1


def test_loop_prints_figures():
    r = run("loop", "--cycles", 2, "--rate", 2000)
    assert "width_um" in r.stdout
    rows = [line.split() for line in r.stdout.splitlines() if line.split()[:1] in (["x"], ["y"])]
    assert len(rows) == 2
    for row in rows:
        assert 60 < float(row[2]) < 100   # stroke [um]
        assert 5 < float(row[4]) < 25     # loop width [% of stroke]


def test_the_demo_picture_shows_the_whole_run(tmp_path, monkeypatch):
    """The demo's tracking.png: its first column spans the whole recorded run
    (excitation, approach, tracking), the second and third the tracking window. (Before:
    only the last second, where desired and measured lie on top of each other.)"""
    from piezo_stage.io import plots
    from piezo_stage.io.run_bag import Run
    figs = []
    monkeypatch.setattr(plots, "_save", lambda fig, path: figs.append(fig) or path)
    t_ns = np.arange(0, 4000) * 1_000_000                   # 4 s at 1 kHz
    w = np.c_[np.sin(t_ns * 1e-9), np.cos(t_ns * 1e-9)]
    run = Run(t_ns, w, w, t_ns, desired_um={int(k): w[i] for i, k in enumerate(t_ns)
                                             if k >= 3_000_000_000})
    plots.tracking_png(tmp_path / "p.png", run, 3.1, excite_s=2.5)
    ax = figs[0].axes
    lo, hi = ax[0].get_xlim()
    assert lo <= 0.0 and hi >= 3.999                           # the whole run
    lo, hi = ax[1].get_xlim()
    assert lo >= 3.0 and hi <= 4.2                             # the tracking window
    assert "the whole run" in ax[0].get_title()


def test_a_figure_drawn_apart_is_the_figure_drawn_here_and_a_lost_worker_loses_none(
        tmp_path):
    """identify's figure comes from a worker process that imported matplotlib while the
    fit ran (io/plots.FigureWorker): the same PNG as drawn in the command's own process;
    a worker that died, or was asked for no figure, still leaves the figure drawn (here)
    and no process behind."""
    from piezo_stage.io import plots
    t = np.arange(400) / 100.0
    v = 75 - 75 * np.cos(2 * np.pi * 0.5 * t)
    curves = {"x": (v, 0.5 * v + 0.01 * np.sin(7 * t), 0.5 * v, 0)}
    here = plots.identification_png(str(tmp_path / "here.png"), t, curves)
    with plots.FigureWorker() as w:
        proc = w.proc
        apart = w.draw("identification_png", str(tmp_path / "apart.png"), t, curves)
    assert apart == str(tmp_path / "apart.png") and proc.wait(10) == 0
    assert open(apart, "rb").read() == open(here, "rb").read()
    with plots.FigureWorker() as w:  # its process gone: drawn here
        w.proc.kill()
        w.proc.wait()
        lost = w.draw("identification_png", str(tmp_path / "lost.png"), t, curves)
    assert open(lost, "rb").read() == open(here, "rb").read()
    with plots.FigureWorker() as w:  # never asked (the command failed first): ended
        proc = w.proc
    assert proc.poll() is not None
    r = subprocess.run([sys.executable, "-m", "piezo_stage.io.plots"], input=b"",
                       capture_output=True, timeout=60)
    assert r.returncode == 0 and r.stdout == b""  # no request: nothing drawn, exit 0


def test_experiment_rate_is_checked_before_anything_runs(tmp_path):
    """`experiment scan --rate`: a rate that does not hold every scan trajectory's period
    in whole samples is a one-line data error (exit 2) before any bag folder is made;
    the other experiments refuse --rate (their trajectories are written at 1 kHz)."""
    pytest.importorskip("rclpy")
    bags = tmp_path / "bags"
    r = run("experiment", "scan", "--rate", "1300", "--record", bags, check=False)
    assert r.returncode == 2 and len(r.stderr.strip().splitlines()) == 1, r.stderr
    assert "1300 Hz" in r.stderr and not bags.exists()
    r = run("experiment", "tracking", "--rate", "5000", "--record", bags, check=False)
    assert r.returncode == 2 and "--params" in r.stderr and not bags.exists(), r.stderr


def _records(tmp_path):
    """A fit and a held-out record of the simulated stage (excite, simulate)."""
    run = lambda *a: subprocess.run([sys.executable, "-m", "piezo_stage.cli", *map(str, a)],  # noqa: E731
                                    capture_output=True, text=True, timeout=120, check=True)
    run("excite", "--out", tmp_path / "exc.csv")
    for name, seed in (("fit", 2), ("hold", 3)):
        run("simulate", "--in", tmp_path / "exc.csv", "--out", tmp_path / f"{name}.csv",
            "--seed", seed)
    return tmp_path / "fit.csv", tmp_path / "hold.csv"


STOPPED = {  # command -> (its arguments, the moments to stop it at [s], its last line)
    # (play: about 3.0 s in all here; identify --structure auto: about 5.3 s, one BLAS
    # thread; the plain fit ends by 4.4 s, before the later moments)
    "identify": (lambda d, f, h, b: [f, "--out", d / "m.yaml", "--structure", "auto"],
                 (1.0, 3.5), "piezo-stage: stopped by SIGINT"),
    "gap": (lambda d, f, h, b: [f, "--holdout", h, "--out-model", d / "g.yaml"], (1.5, 7.0),
            "piezo-stage: stopped by SIGINT"),
    "play": (lambda d, f, h, b: [f.parent / "exc.csv", "--out", d / "played"], (0.8, 2.2),
             "piezo-stage: stopped by SIGINT"),
    "experiment": (lambda d, f, h, b: ["noise", "--model", os.path.join(CONFIG,
                                       "stage_model.yaml"), "--record", d / "bags"],
                   (2.0, 5.0), "piezo-stage: stopped by SIGINT"),
    "demo": (lambda d, f, h, b: ["--out", d / "demo"], (3.0, 8.0),
             "piezo-stage: stopped by SIGINT"),
    "launch": (lambda d, f, h, b: ["--duration", "60"], (3.0, 6.0),
               "piezo-stage launch: stopped by SIGINT"),
    # (before the bag is read and its publishers matched, the command's own line)
    "replay": (lambda d, f, h, b: [b, "--rate", "0.5"], (2.0, 6.0),
               ("replayed ", "piezo-stage: stopped by SIGINT")),
}


@pytest.fixture(scope="module")
def stop_inputs(tmp_path_factory):
    """What the stopped commands read, made once for all of them: the excitation, a fit
    and a held-out record, and a bag of the excitation played on the simulated stage."""
    d = tmp_path_factory.mktemp("stop_inputs")
    fit, hold = _records(d)
    subprocess.run([sys.executable, "-m", "piezo_stage.cli", "play", d / "exc.csv",
                    "--out", d / "bag"], capture_output=True, timeout=120, check=True)
    return fit, hold, d / "bag"


@pytest.mark.slow
@pytest.mark.parametrize("command", sorted(STOPPED))
def test_ctrl_c_at_a_random_moment_ends_a_command_with_130_and_its_line(tmp_path, ros_env,
                                                                      command, stop_inputs):
    """Ctrl-C (SIGINT to the command's whole process group, as a terminal sends it) at a
    random moment of the command's run: exit 130, the command's own stop line last, no
    traceback from it or its worker processes, no half-written output."""
    import random
    import signal
    import time
    fit, hold, bag = stop_inputs
    args, (lo, hi), last = STOPPED[command]
    for _ in range(3):
        # (a faster host can end the command before the moment drawn: that run says
        # nothing about Ctrl-C, so the moment is drawn again within the run it took)
        at = random.uniform(lo, hi)
        began = time.monotonic()
        p = subprocess.Popen([sys.executable, "-m", "piezo_stage", command,
                              *map(str, args(tmp_path, fit, hold, bag))], env=ros_env,
                             stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                             start_new_session=True, cwd=tmp_path)
        time.sleep(at)
        if p.poll() is None:
            os.killpg(p.pid, signal.SIGINT)
            break
        p.communicate(timeout=120)
        assert p.returncode == 0, (command, p.returncode)
        took = time.monotonic() - began
        lo, hi = 0.4 * min(lo, took), 0.8 * min(hi, took)
        for out in tmp_path.glob("*"):  # (what the ended run wrote)
            shutil.rmtree(out) if out.is_dir() else out.unlink()
    else:
        pytest.fail(f"{command} ended before each moment drawn (last {at:.2f} s)")
    out, err = p.communicate(timeout=120)
    said = [ln for ln in (out + err).splitlines() if ln.startswith(last)]
    if command == "replay" and said and said[-1].startswith("replayed "):
        assert "stopped by SIGINT" in said[-1], said  # how far it got, and why it ended
    assert p.returncode == 130, (at, p.returncode, err[-2000:])
    assert said, (at, out[-1000:], err[-2000:])
    assert "Traceback" not in err, (at, err[-3000:])
    assert not list(tmp_path.glob("**/.*.tmp")), "a temporary output left behind"


def test_a_misnamed_or_half_given_column_is_named_not_passed_over(tmp_path):
    """A CSV with `wX` for `wx` (or an axis's voltage without its displacement) was
    fitted on the other axis with a note; now it is refused with the column named."""
    t, v = sine_v(1.0, 2000, 2)
    bad = tmp_path / "bad.csv"
    write_table(bad, {"t": t, "vx": v, "vy": v, "wX": v, "wy": v})
    r = run("identify", bad, "--out", tmp_path / "m.yaml", check=False)
    assert r.returncode == 2 and len(r.stderr.strip().splitlines()) == 1, r.stderr
    assert "column 'wX' is not one of t, vx, vy, wx, wy (did you mean 'wx'?)" in r.stderr
    half = tmp_path / "half.csv"
    write_table(half, {"t": t, "vx": v, "vy": v, "wy": v})
    r = run("identify", half, "--out", tmp_path / "m.yaml", check=False)
    assert r.returncode == 2 and "column wx is missing (vx is there)" in r.stderr, r.stderr
    assert not (tmp_path / "m.yaml").exists()


def test_identify_plots_the_record_it_validated_on(tmp_path, monkeypatch):
    """--plot with --validate: the validation record's loop and error are drawn beside
    the fit's, and its RMS is in the title (before: only the fit record)."""
    from piezo_stage.cli import main
    from piezo_stage.io import plots
    fit, hold = _records(tmp_path)
    figs = []
    monkeypatch.setattr(plots, "_save", lambda fig, path: figs.append(fig) or path)
    # drawn in this process (the worker's figure is the same PNG: the test above)
    monkeypatch.setattr(plots.FigureWorker, "__init__", lambda w: setattr(w, "proc", None))
    assert main(["identify", str(fit), "--out", str(tmp_path / "m.yaml"), "--validate",
                 str(hold), "--plot", str(tmp_path / "id.png")]) == 0
    (fig,) = figs
    for row in range(2):
        loop, err = fig.axes[2 * row], fig.axes[2 * row + 1]
        labels = [t.get_text() for t in loop.get_legend().get_texts()]
        assert labels == ["measured (fit)", "identified model", "measured (validation)",
                          "model (validation)"]
        assert "validation rms" in err.get_title()
        assert len(err.get_lines()) == 2


def test_refit_dates_runs_to_the_second_and_an_empty_panel_says_so(monkeypatch):
    from piezo_stage.apps.refit import _when
    from piezo_stage.io import plots
    assert _when("2026-11-28T09:20:45.123456+00:00") == "2026-11-28 09:20:45"
    figs = []
    monkeypatch.setattr(plots, "_save", lambda fig, path: figs.append(fig) or path)
    rows = [{"started_utc": f"2026-11-28T09:{m:02d}:00+00:00",
             "axes": {"x": {"gain_um_per_V": 0.5, "held_out_rms_um": 0.1, "change_um": 0.0,
                            "against": {"effects": {}}}}} for m in (0, 20, 40)]
    plots.refit_png("r.png", rows)
    ax = figs[0].axes
    assert [t.get_text() for t in ax[2].texts] == ["none found"]
    for a in ax:  # runs of one day: times to the second, the day in the label
        assert a.get_xlabel() == "run started (UTC, 2026-11-28)"
    figs[0].canvas.draw()
    ticks = [t.get_text() for t in ax[0].get_xticklabels() if t.get_text()]
    assert ticks and all(len(t) == 8 and t.count(":") == 2 for t in ticks), ticks
