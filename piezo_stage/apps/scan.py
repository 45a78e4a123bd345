"""`piezo-stage experiment scan`: raster scans and the seed trajectory through the node
set, feedforward only, with and without learning feedforward.

Every case is one run of the real node set (experiments.run_case) on a trajectory
written for it, recorded to its own bag, and every figure is computed from the bag,
against the simulated stage's true position (``/stage/sim/true_position``), period by
period from the start of the motion:

* ``raster`` at line rates 5, 20 and 50 Hz (the fast axis x sweeps a 40 um triangle
  with rounded turnarounds, trace and retrace per line period; the slow axis y steps
  inside the lower turnaround; centre 45, 45 um): per period the mean absolute error
  (% of the axis's span), the linearity error over the central 80 % of each sweep
  (RMS and max, % of the scan size) and the trace-retrace offset (the mean error on
  the trace minus on the retrace, over the same central part);
* ``seed`` at 40 and 100 Hz: the paper's y(t) = 21 + 24 sin(2 pi f t - pi/2) um lifted
  by 4 um (centre 25 um: its -3 um bottom is below the stage's 0 V rest) on both axes.

A case's figures are those of its last period; ``periods_to_converge`` is the first
period from which every period's error stays within 10 % (or 0.002 % of the range) of
the mean of the last three. Learning runs with ``learning_period_s`` the trajectory's
period and the controller's feedback off (learning corrects the feedforward).
"""

from __future__ import annotations

import os
import shutil
from dataclasses import dataclass

import numpy as np

from piezo_stage.apps.experiments import RATE_HZ, Case, control_rate, merge_params, run_case
from piezo_stage.core.errors import DataError, RunError
from piezo_stage.core.types import Doc

RASTER_HZ = (5.0, 20.0, 50.0)
SEED_HZ = (40.0, 100.0)
PERIODS = 24            # line periods (raster) or cycles (seed) per run
AFTER_PERIODS = 20      # also reported: the error in this period (the targets' count)
SCAN_SIZE_UM = (40.0, 40.0)
SCAN_CENTER_UM = (45.0, 45.0)
SEED_CENTER_UM = 25.0
DEFAULT_PLANTS = ("sim_stage.yaml", "sim_stage_effects.yaml")
# the motion's last point held this long: in real time arming can eat up to ~3 s of the
# counted steps; lockstep counts none of it (the experiments add a margin too)
HOLD_AFTER_S = {"lockstep": 0.2, "realtime": 1.0}


def _padded(t, w, hold_after_s=1.0, rate_hz=RATE_HZ):
    """``w`` (sampled at ``rate_hz`` from t = 0) held ``hold_after_s`` at its last point
    after (the run's steps are counted from the driver's start, so arming and the
    approach eat into them: in real time up to about 3 s, which the experiments' margin
    and this hold cover); no hold before (the planner approaches the first point
    first): a learner would take a hold for periods of the motion, and its guard would
    then slow every bin the motion's first periods raise."""
    dt = 1.0 / rate_hz
    lead, tail = 0, int(round(hold_after_s / dt))
    out = {a: np.concatenate([np.full(lead, v[0]), v, np.full(tail, v[-1])])
           for a, v in w.items()}
    n = len(next(iter(out.values())))
    return np.arange(n) * dt, out, lead


@dataclass
class ScanCase(Case):
    """A scan case: a Case with what the scan's figures need."""
    kind: str = "raster"          # raster | seed
    learning: bool = False
    periods: int = 0
    n: int = 0                    # samples a period
    rate_hz: float = RATE_HZ


def plan(periods: int = PERIODS, raster_hz=RASTER_HZ, seed_hz=SEED_HZ,
         mode: str = "lockstep", rate_hz: float = RATE_HZ,
         learning=(False, True)) -> list[ScanCase]:
    """The cases: each trajectory without and with learning (``learning``: which),
    sampled at the control rate ``rate_hz`` (a period must be a whole number of its
    samples: learning needs that)."""
    from piezo_stage.core.loop.trajectory import generate, raster
    cases = []
    trajs = []
    for f in raster_hz:
        t, w = raster(f, periods, SCAN_SIZE_UM, SCAN_CENTER_UM, dt_s=1.0 / rate_hz)
        trajs.append(("raster", f, t, w))
    for f in seed_hz:
        t, w = generate("sine", periods / f, 1.0 / rate_hz, f, SEED_CENTER_UM, 24.0)
        trajs.append(("seed", f, t, w))
    for kind, f, t, w in trajs:
        n = int(round(rate_hz / f))
        if abs(n * f - rate_hz) > 1e-6 * rate_hz:
            raise DataError(f"{kind} at {f:g} Hz is not a whole number of samples at "
                            f"{rate_hz:g} Hz")
        t, w, _ = _padded(t, {a: np.asarray(v, float)[:periods * n + 1]
                              for a, v in w.items()}, HOLD_AFTER_S[mode], rate_hz)
        for learn in learning:
            name = f"{kind} {f:g} Hz{' learning' if learn else ''}"
            c = ScanCase(name, f, t, w, "feedforward", moving="x",
                         eval_s=periods / f,
                         params={"feedforward": {"inverse_feedforward": True,
                                                 "learning": learn,
                                                 "learning_period_s": 1.0 / f},
                                 "controller": {"feedback": False}},
                         kind=kind, learning=learn, periods=periods, n=n, rate_hz=rate_hz)
            cases.append(c)
    return cases


def _span(ks, moved, states, accepted=()) -> str:
    """Where the desired position moved, the largest gap between stamps, the driver's
    states, in ms from the first stamp, and the trajectories the stage ran (by name):
    what a short motion is judged from."""
    ms = lambda k: f"{(int(k) - int(ks[0])) * 1e-6:.1f}"  # noqa: E731
    gap = int(np.diff(ks).max()) if ks.size > 1 else 0
    said = ", ".join(f"{st} {ms(since)}" for since, st in states)
    return (f"{ks.size} stamps to {ms(ks[-1])} ms, moving from {ms(ks[moved[0]])} to "
            f"{ms(ks[moved[-1] + 1])} ms, largest gap {gap * 1e-6:.1f} ms; states: {said}; "
            f"trajectories run: {len(accepted)} ({', '.join(accepted) or 'unnamed'})")


def _motion(case, run):
    """(period index (m,), desired (m, 2), true (m, 2), applied (m, 2) V) over the
    motion's periods x n samples' time, found from its end (the last stamp the desired
    position changes on), by stamp (in real time a missed tick leaves a gap, not a
    shift), checked against the trajectory written for the case (to within one
    sample's motion: the planner's clock need not fall on its points)."""
    # up to the end of the last armed spell: once disarmed (a real-time run's end) the
    # feedforward holds where the stage is, which moves with the noise
    after = [since for since, st in run.states if st != "armed" and
             any(st2 == "armed" and s2 < since for s2, st2 in run.states)]
    stop = after[-1] if after else np.iinfo(np.int64).max
    ks = np.array([k for k in sorted(run.desired_um) if k in run.true_um and k < stop],
                  dtype=np.int64)
    d = np.array([run.desired_um[k] for k in ks]).reshape(-1, 2)
    moved = np.flatnonzero(np.any(np.abs(np.diff(d, axis=0)) > 1e-9, axis=1))
    if moved.size == 0:
        raise DataError(f"{case.name}: the stage was never asked to move")
    period_ns = 1e9 / case.freq_hz
    half = 0.5e9 / case.rate_hz  # half a sample
    t_end = int(ks[int(moved[-1]) + 1])  # the motion's last point
    t0 = t_end - case.periods * period_ns
    sel = (ks >= t0 - half) & (ks < t_end - half)
    where = _span(ks, moved, run.states, run.accepted)
    if ks[0] > t0 + period_ns or sel.sum() < 0.9 * case.periods * case.n:
        raise RunError(f"{case.name}: the bag holds {int(sel.sum())} of the motion's "
                        f"{case.periods * case.n} samples ({where})")
    ks, d = ks[sel], d[sel]
    tau = (ks - t0) * 1e-9
    want = np.column_stack([np.interp(tau, case.t, case.w[a]) for a in "xy"])
    step = np.max(np.abs(np.diff(want, axis=0)), axis=0) if len(want) > 1 else 0.0
    if np.any(np.max(np.abs(d - want), axis=0) > step + 1e-6):
        raise RunError(f"{case.name}: the recorded desired positions are not the "
                        f"trajectory's (did the run end before the trajectory did? {where})")
    period = np.clip(np.floor((ks - t0 + half) / period_ns).astype(int), 0,
                     case.periods - 1)
    vmap = dict(zip(run.t_ns.tolist(), run.v_V))
    v = np.array([vmap[k] for k in ks.tolist() if k in vmap]).reshape(-1, 2)
    return period, d, np.array([run.true_um[k] for k in ks.tolist()]), v


def converged_at(per: list[float], floor: float = 0.002) -> int:
    """The first period from which every period's error is within 10 % (or ``floor``)
    of the mean of the last three."""
    final = float(np.mean(per[-3:]))
    ok = np.asarray(per) <= max(1.1 * final, final + floor)
    bad = np.flatnonzero(~ok)
    return int(bad[-1] + 1) if bad.size else 0


def evaluate(case, bag) -> Doc:
    """Per axis, per period and for the last period: the figures of the module doc."""
    from piezo_stage.io.run_bag import read_run
    period, d, true, v = _motion(case, read_run(bag))
    P = case.periods
    out = {"desired": d, "true": true, "period": period, "axes": {},
           "samples": int(len(period)),
           "v_range": (float(np.min(v)), float(np.max(v))) if v.size else (np.nan, np.nan),
           "max_step_V": float(np.abs(np.diff(v, axis=0)).max()) if len(v) > 1 else 0.0}
    groups = [period == p for p in range(P)]
    for i, a in enumerate("xy"):
        span = float(np.ptp(d[:, i]))
        if span <= 0:
            continue
        e = true[:, i] - d[:, i]
        per = [float(100 * np.mean(np.abs(e[g])) / span) if g.any() else float("nan")
               for g in groups]
        last = groups[-1]
        fig = {"per_period_pct": per, "mean_abs_err_pct_of_range": per[-1],
               "rms_err_um": float(np.sqrt(np.mean(e[last] ** 2))),
               "max_err_um": float(np.max(np.abs(e[last]))),
               "periods_to_converge": converged_at(per)}
        if P >= AFTER_PERIODS:
            fig["pct_after_20_periods"] = per[AFTER_PERIODS - 1]
        if case.kind == "raster" and a == "x":
            lo = float(np.min(d[:, i]))
            mid = np.abs(d[:, i] - lo - span / 2) <= 0.4 * span
            vel = np.gradient(d[:, i])
            rms = [float(100 * np.sqrt(np.mean(e[g & mid] ** 2)) / span) for g in groups]
            mx = [float(100 * np.max(np.abs(e[g & mid])) / span) for g in groups]
            off = [float(np.mean(e[g & mid & (vel > 0)]) - np.mean(e[g & mid & (vel < 0)]))
                   for g in groups]
            fig.update({"linearity_rms_pct_of_scan": rms[-1],
                        "linearity_max_pct_of_scan": mx[-1],
                        "linearity_rms_per_period_pct": rms,
                        "trace_retrace_offset_um": off[-1],
                        "trace_retrace_offset_pct_of_scan": 100 * abs(off[-1]) / span})
        out["axes"][a] = fig
    return out


def own_model(plant_path: str, out_dir: str) -> str:
    """The plant's own model and effects as a model file (no --model: the feedforward
    knows the stage it drives, as `study learning` does)."""
    from piezo_stage.io.model_file import save_model
    from piezo_stage.io.plant_file import load_plant_config
    cfg = load_plant_config(plant_path)
    path = os.path.join(out_dir, "model_" + os.path.basename(plant_path))
    save_model(path, cfg.model, {k: dict(v) for k, v in cfg.effects.items()} or None)
    return path


def _with_rate(config, extra, rate_hz):
    """(parameters with ``rate_hz`` for the driver, feedforward and controller when
    given, the control rate they run at)."""
    if rate_hz is not None:
        extra = merge_params(extra or {}, {n: {"control_rate_hz": float(rate_hz)} for n in
                                           ("stage_driver", "feedforward", "controller")})
    return extra, control_rate(config, extra)


def check_rate(config, extra=None, rate_hz=None) -> float:
    """The scan's control rate, checked: every trajectory's period a whole number of
    its samples (DataError otherwise)."""
    _, rate = _with_rate(config, extra, rate_hz)
    for f in RASTER_HZ + SEED_HZ:
        if abs(round(rate / f) * f - rate) > 1e-6 * rate:
            raise DataError(f"experiment scan: {f:g} Hz is not a whole number of samples "
                            f"at {rate:g} Hz: use a control rate that is a multiple of 200 Hz "
                            "(1000, 2000, 5000)")
    return rate


def run_scan(out_dir, config, plants, model=None, mode="lockstep", extra=None,
             namespace="/stage", env=None, log=print, periods=PERIODS,
             raster_hz=RASTER_HZ, seed_hz=SEED_HZ, rate_hz=None, learning=(False, True)):
    """Every case on every plant; bags under ``out_dir``. ``rate_hz``: the control rate
    of the driver, the feedforward and the controller (default: the parameters' own,
    ``config`` and ``extra``); the trajectories are sampled at it. Returns the JSON
    document and [(plant, case, evaluation)] for the figure."""
    from piezo_stage.paths import default_config
    from piezo_stage.progress import bar
    plants = [os.path.abspath(p) for p in plants] if plants else \
        [default_config(p) for p in DEFAULT_PLANTS]
    extra, rate = _with_rate(config, extra, rate_hz)
    cases = plan(periods, raster_hz, seed_hz, mode, rate, learning)
    doc = {"experiment": "scan", "mode": mode, "model": os.path.abspath(model) if model
           else "each plant's own", "plants": plants, "control_rate_hz": rate,
           "cases": []}
    evals: list[tuple] = []
    with bar(total=len(cases) * len(plants), desc="experiment scan", unit="run") as pb:
        for plant in plants:
            pname = os.path.splitext(os.path.basename(plant))[0]
            m = model or own_model(plant, out_dir)
            for k, case in enumerate(cases):
                bag = os.path.join(out_dir, f"{pname}_{k:02d}_" + "".join(
                    c if c.isalnum() else "_" for c in case.name))
                if os.path.exists(bag):
                    shutil.rmtree(bag)
                run_case(case, bag, config, plant, m, mode, merge_params(extra or {}),
                         namespace, env, exclusive=not evals)
                ev = evaluate(case, bag)
                evals.append((pname, case, ev))
                for a, fig in ev["axes"].items():
                    doc["cases"].append({
                        "plant": pname, "name": case.name, "kind": case.kind,
                        "freq_hz": case.freq_hz, "axis": a, "learning": case.learning,
                        "reference": "true", "periods": periods,
                        "control_rate_hz": rate, **fig,
                        "v_range_V": list(ev["v_range"]), "max_step_V": ev["max_step_V"],
                        "bag": os.path.abspath(bag)})
                pb.update(1)
                x = ev["axes"]["x"]
                log(f"  {pname}, {case.name}: x {x['mean_abs_err_pct_of_range']:.3f} % "
                    + (f"(linearity {x['linearity_rms_pct_of_scan']:.3f} %) "
                       if "linearity_rms_pct_of_scan" in x else "")
                    + f"after {periods} periods")
    return doc, evals


def table(doc) -> str:
    """One row per plant, case and axis: the last period's figures."""
    rows = [f"{'plant':<18} {'case':<22} {'axis':>4} {'mean_pct':>9} {'at_20':>7} "
            f"{'lin_rms%':>9} {'lin_max%':>9} {'tr-re um':>9} {'converged':>9}"]
    for c in doc["cases"]:
        lin = c.get("linearity_rms_pct_of_scan")
        at20 = c.get("pct_after_20_periods")
        rows.append(
            f"{c['plant']:<18} {c['name']:<22} {c['axis']:>4} "
            f"{c['mean_abs_err_pct_of_range']:9.3f} "
            + (f"{at20:7.3f} " if at20 is not None else " " * 8)
            + (f"{lin:9.3f} {c['linearity_max_pct_of_scan']:9.3f} "
               f"{c['trace_retrace_offset_um']:9.4f} " if lin is not None else " " * 30)
            + f"{c['periods_to_converge']:9d}")
    return "\n".join(rows)
