"""`bench accuracy`: the paper's figures of merit, as a user measures them.

Each experiment runs as a whole command (``piezo-stage experiment KIND --model
config/stage_model.yaml --json FILE``, lockstep, the default plant with its own model,
its own ROS_DOMAIN_ID), and the report tabulates its JSON: the tracking error of the
three controllers per frequency, the amplitude cases, the decoupling's coupling
reduction and the noise at rest, against the true position (the paper's figure of
merit, mean absolute error in % of the range) and the measured one. Then the relay
experiment (``tune --relay``) and what its gains earn, beside the default gains. Then
two plants with unmodelled effects (``config/sim_stage_effects.yaml``: creep, an 800 Hz
resonance, a 0.5 ms delay; ``config/sim_stage_600hz.yaml``: a 600 Hz resonance behind
a 0.8 ms delay, whose sampled inverse needs preview): each with the model the gap
recipe writes for it, no value entered by hand (``excite``, ``simulate``, ``gap
--out-model``), tracked with its effects compensated and not. The baseline of each row
is the same controller without what the row adds (the default gains, the effects left
uncompensated), measured in the same invocation. docs/experiments.md links here for
its figures.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import tempfile

NAMESPACE = "/bench_accuracy"  # its own: a set running meanwhile under /stage stays
PAPER_NOISE_UM = 0.104         # the paper's RMS noise at rest
PAPER_DECOUPLING_PCT = 71.0    # the paper's best coupling reduction


def _env() -> dict:
    from benchmarks.procs import own_domain_env
    return own_domain_env()


def _experiment(rep, tmp: str, kind: str, model: str, *more: str) -> dict:
    """One ``experiment KIND`` as a whole command; its JSON document."""
    from benchmarks.procs import command_json
    argv = ["experiment", kind, "--model", model, *more]
    rep.progress(" ".join(["piezo-stage", *(x.replace(tmp + os.sep, "") for x in argv)]))
    return command_json([*argv, "--namespace", NAMESPACE],
                        os.path.join(tmp, f"{kind}_{len(os.listdir(tmp))}"))


def _pct(doc: dict, name: str, ref: str = "true") -> str:
    """'x / y %' of case ``name`` (mean absolute error, % of the range)."""
    by = {c["axis"]: c["mean_abs_err_pct_of_range"] for c in doc["cases"]
          if c["name"] == name and c["reference"] == ref}
    if not by:
        return ""
    return " / ".join(_g(by[a]) for a in ("x", "y") if a in by) + " %"


def _g(x: float) -> str:
    return f"{x:.3f}" if abs(x) < 1 else f"{x:.2f}" if abs(x) < 10 else f"{x:.1f}"


def _mean(doc: dict, name: str, ref: str = "true") -> float:
    v = [c["mean_abs_err_pct_of_range"] for c in doc["cases"]
         if c["name"] == name and c["reference"] == ref]
    return sum(v) / len(v) if v else float("nan")


def bench_accuracy(rep) -> int:
    """The experiments' figures of merit, as whole commands (``rep``: the report)."""
    from piezo_stage.paths import default_config
    model = os.path.relpath(default_config("stage_model.yaml"))
    rep.title(f"the paper's experiments as whole commands, lockstep, the default plant "
              f"(config/sim_stage.yaml) with its own model (--model {model}); mean "
              "absolute error against the true position, % of the range, x / y")
    tmp = tempfile.mkdtemp(prefix="bench_accuracy_")
    try:
        tracking = _experiment(rep, tmp, "tracking", model)
        amplitude = _experiment(rep, tmp, "amplitude", model)
        decoupling = _experiment(rep, tmp, "decoupling", model)
        noise = _experiment(rep, tmp, "noise", model)
        relay, relay_doc = _relay(rep, tmp, model)
        plants = [(cfg, freqs, *_effects_plant(rep, tmp, cfg, freqs))
                  for cfg, freqs in (("sim_stage_effects.yaml", "1,5,10,40"),
                                     ("sim_stage_600hz.yaml", "10,40"))]
    except (RuntimeError, subprocess.TimeoutExpired) as e:
        rep.fail(str(e))
        return 1
    finally:
        shutil.rmtree(tmp, ignore_errors=True)

    freqs = sorted({c["freq_hz"] for c in tracking["cases"]})
    rows = [(f"the paper's trajectory, {f:g} Hz",
             *(_pct(tracking, f"tracking {f:g} Hz {c}") for c in
               ("composite", "feedforward", "feedback"))) for f in freqs]
    rows += [(f"1 Hz, {n.split(' ', 1)[1]}", _pct(amplitude, n), "", "")
             for n in ("amplitude constant 60 um", "amplitude variable 60/40/20 um")]
    rep.table(("case", "composite", "feedforward only", "feedback only"), rows,
              "`experiment tracking` and `experiment amplitude`")

    red = []
    for driven, held in (("x", "y"), ("y", "x")):
        cs = {c["reference"]: c for c in decoupling["cases"] if c["axis"] == held
              and c["name"] == f"decoupling {driven} driven, compensation on"}
        red.append((f"{driven} driven, {held} held",
                    *(f"{cs[r]['coupling_rms_before_um']:.4f} -> "
                      f"{cs[r]['coupling_rms_after_um']:.4f} um, "
                      f"{cs[r]['reduction_pct']:.1f} %" for r in ("true", "measured"))))
    rep.table(("decoupling (feedforward only)", "coupling RMS, true position",
               "measured position (the sensor's noise stays)"), red,
              f"`experiment decoupling`; the paper: 66-{PAPER_DECOUPLING_PCT:g} %")

    rest = {c["axis"]: c for c in noise["cases"] if c["reference"] == "measured"}
    rep.table(("noise at rest, measured", "x", "y", "the paper"),
              [("RMS [um]", f"{rest['x']['rms_err_um']:.3f}", f"{rest['y']['rms_err_um']:.3f}",
                f"{PAPER_NOISE_UM:g}"),
               ("max [um]", f"{rest['x']['max_err_um']:.3f}", f"{rest['y']['max_err_um']:.3f}",
                "")], "`experiment noise`")

    rep.table(("relay experiment (`tune --relay`)", "x", "y"), [
        ("oscillation [Hz]", *(f"{relay['points'][a].freq_hz:.0f}" for a in "xy")),
        ("loop gain at the setpoint [um/V]",
         *(f"{relay['points'][a].gain_um_per_V:.3f}" for a in "xy"))],
        f"both axes held at 30 um, relay +-2 V: kp {relay['tuning'].kp:.3g} V/um, ki "
        f"{relay['tuning'].ki:.0f} V/(um s), crossover {relay['tuning'].crossover_hz:.1f} "
        f"Hz, phase margin {relay['tuning'].phase_margin_deg:.1f} deg, gain margin "
        f"{relay['tuning'].gain_margin_db:.1f} dB")
    rows = []
    for f in (1.0, 10.0):
        for c in ("feedback", "composite"):
            name = f"tracking {f:g} Hz {c}"
            rows.append((f"{c}, {f:g} Hz", _pct(relay_doc, name), _pct(tracking, name),
                         f"{_mean(relay_doc, name) / _mean(tracking, name):.2f}"))
    rep.table(("relay-tuned gains earn", "relay gains", "default gains (kp 0.2, ki 150)",
               "ratio"), rows, "`experiment tracking --params relay.yaml --controllers "
              "feedback,composite --freqs 1,10`")

    worst_ratio = 0.0
    for cfg, fs, found, doc in plants:
        rows = []
        for f in (float(x) for x in fs.split(",")):
            row = [f"{f:g} Hz"]
            for c in ("composite", "feedforward"):
                on, off = f"tracking {f:g} Hz {c}", \
                    f"tracking {f:g} Hz {c} (effects not compensated)"
                row.append(f"{_pct(doc, on)} ({_pct(doc, off)})")
                worst_ratio = max(worst_ratio, _mean(doc, on) / _mean(doc, off))
            rows.append(tuple(row))
        rep.table(("case", "composite (not compensated)", "feedforward only (not "
                   "compensated)"), rows, f"config/{cfg} with the model the gap recipe "
                  f"wrote for it: {found}")

    fb = {f: _mean(tracking, f"tracking {f:g} Hz feedback") for f in freqs}
    comp = {f: _mean(tracking, f"tracking {f:g} Hz composite") for f in freqs}
    ff = {f: _mean(tracking, f"tracking {f:g} Hz feedforward") for f in freqs}
    worst = max(c["reduction_pct"] for c in decoupling["cases"]
                if c["reference"] == "true" and c.get("reduction_pct") is not None)
    least = min(c["reduction_pct"] for c in decoupling["cases"]
                if c["reference"] == "true" and c.get("reduction_pct") is not None)
    rep.target(f"the composite beats the feedback alone at every frequency (at most "
               f"{max(comp[f] / fb[f] for f in freqs):.3f} x)",
               all(comp[f] < fb[f] for f in freqs))
    rep.target(f"the feedforward on its own model within 0.01 % up to 10 Hz (at most "
               f"{max(ff[f] for f in freqs if f <= 10):.4f} %)",
               all(ff[f] <= 0.01 for f in freqs if f <= 10))
    rep.target(f"decoupling beats the paper's {PAPER_DECOUPLING_PCT:g} % against the true "
               f"position ({least:.1f}-{worst:.1f} %)", least > PAPER_DECOUPLING_PCT)
    rep.target("the relay-tuned feedback alone beats the default gains at 1 Hz "
               f"({_mean(relay_doc, 'tracking 1 Hz feedback'):.2f} % against "
               f"{fb[1.0]:.2f} %)", _mean(relay_doc, "tracking 1 Hz feedback") < fb[1.0])
    fx = plants[0][3]
    for f, most in ((1, 0.15), (10, 0.25), (40, 0.5)):
        got = max(c["mean_abs_err_pct_of_range"] for c in fx["cases"]
                  if c["name"] == f"tracking {f} Hz composite" and c["reference"] == "true")
        rep.target(f"the effects plant, composite, {f} Hz <= {most:g} % ({got:.3f} %)",
                   got <= most)
    rep.target(f"compensating the effects the gap recipe found beats leaving them, on "
               f"both plants, every case (at most {worst_ratio:.2f} x)", worst_ratio < 1.0)
    return 0


def _cli(rep, tmp: str, *args: str, show: bool = True) -> None:
    """One piezo-stage command in ``tmp``; RuntimeError with its last line if it fails."""
    if show:
        rep.progress("piezo-stage " + " ".join(args))
    r = subprocess.run([sys.executable, "-m", "piezo_stage.cli", *args], cwd=tmp,
                       capture_output=True, text=True, env=_env(), timeout=3600)
    if r.returncode != 0:
        last = (r.stderr.strip().splitlines() or [""])[-1]
        raise RuntimeError(f"{args[0]} exited {r.returncode}: {last}")


def _effects_plant(rep, tmp: str, cfg: str, freqs: str) -> tuple[str, dict]:
    """The gap recipe on plant ``cfg`` (docs/gap.md), then `experiment tracking` with
    the model it wrote: (what it found, the experiment's JSON document)."""
    from piezo_stage.io.model_file import load_model
    from piezo_stage.paths import default_config
    plant = default_config(cfg)
    stem = cfg.split(".")[0]
    for seed, name in ((1, "fit"), (2, "holdout")):
        _cli(rep, tmp, "excite", "--protocol", "gap", "--rate", "5000", "--seed", str(seed),
             "--out", f"e{seed}.csv", show=False)
        _cli(rep, tmp, "simulate", "--in", f"e{seed}.csv", "--out", f"{stem}_{name}.csv",
             "--config", plant, show=False)
    _cli(rep, tmp, "gap", f"{stem}_fit.csv", "--holdout", f"{stem}_holdout.csv",
         "--out-model", f"model_{stem}.yaml")
    model_path = os.path.join(tmp, f"model_{stem}.yaml")
    m, effects = load_model(model_path)
    found = "; ".join(f"{name} " + ", ".join(
        f"{k} {v:.4g}" for k, v in p.items() if isinstance(v, float))
        for name, p in effects.items())
    if m.coupling:
        found = "coupling; " + found
    doc = _experiment(rep, tmp, "tracking", model_path, "--plant", os.path.relpath(plant),
                      "--controllers",
                      "composite,feedforward", "--freqs", freqs)
    return found, doc


def _relay(rep, tmp: str, model: str) -> tuple[dict, dict]:
    """`tune --relay` on the default plant (its points and gains, through the same
    calls as the command), then `experiment tracking` with the gains it writes."""
    from piezo_stage.apps.experiments import run_relay
    from piezo_stage.core.loop.tuning import tune_relay
    from piezo_stage.io.files import atomic_write
    from piezo_stage.paths import default_config
    rep.progress("piezo-stage tune --relay --plant config/sim_stage.yaml --out relay.yaml")
    points = run_relay(os.path.join(tmp, "relay"), default_config("stage.yaml"),
                       default_config("sim_stage.yaml"), namespace=NAMESPACE, env=_env())
    tuning = tune_relay(points, 1000.0, source="relay experiment")
    params = os.path.join(tmp, "relay.yaml")
    with atomic_write(params) as fh:
        fh.write(tuning.params_yaml())
    doc = _experiment(rep, tmp, "tracking", model, "--params", params, "--controllers",
                      "feedback,composite", "--freqs", "1,10")
    return {"points": points, "tuning": tuning}, doc
