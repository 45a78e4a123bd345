"""`piezo-stage bench settle`: point-to-point moves on the simulated default stage and on
one with a 600 Hz resonance and a 0.8 ms delay, the composite law (the inverse
feedforward and the PID) against the PID alone, the true position from the simulator
(apps/studies/moves.py): settle times of 10 um steps, false and missed on-target over
random moves, a z-stack of small steps with dwells, and the motion-time model fitted on
one set of random steps and judged on another."""

from __future__ import annotations

import json
import os
from dataclasses import replace

import numpy as np

from piezo_stage.core.model.duhem import StageModel
from piezo_stage.core.model.plant import Plant

STAGES = (("default stage", "sim_stage.yaml", "stage_model.yaml"),
          ("600 Hz resonance, 0.8 ms delay", "sim_stage_600hz.yaml", None))
LO_UM, HI_UM = 5.0, 70.0  # where the random moves go (inside the stroke)


def _stage(plant_file: str, model_file: str | None, seed: int) -> tuple[Plant, StageModel,
                                                                       dict]:
    """(a fresh plant, the feedforward's model, its effects): the shipped model, or
    the plant's own (its effects too) where the stage has effects our model lacks."""
    from piezo_stage.io.model_file import load_model
    from piezo_stage.io.plant_file import load_plant_config
    from piezo_stage.paths import default_config
    cfg = replace(load_plant_config(default_config(plant_file)), seed=seed)
    if model_file is None:
        model, effects = cfg.model, {k: dict(v) for k, v in cfg.effects.items()}
    else:
        model, effects = load_model(default_config(model_file))
    return Plant(cfg, 1000.0), model, effects


def _walk(rng, n: int, size) -> tuple[dict, list[dict]]:
    """A start and ``n`` targets, each ``size(rng)`` um from the last in a random
    direction, kept inside [LO_UM, HI_UM]."""
    here = {"x": 40.0, "y": 40.0}
    start, out = dict(here), []
    for _ in range(n):
        d, phi = size(rng), rng.uniform(0, 2 * np.pi)
        for _ in range(100):  # a direction that stays inside
            nxt = {"x": here["x"] + d * np.cos(phi), "y": here["y"] + d * np.sin(phi)}
            if all(LO_UM <= v <= HI_UM for v in nxt.values()):
                break
            phi = rng.uniform(0, 2 * np.pi)
        here = nxt
        out.append(dict(here))
    return start, out


def _median(xs) -> float:
    xs = [x for x in xs if x is not None]
    return float(np.median(xs)) if xs else float("nan")


def bench_settle(rep, steps: int = 50, moves: int = 200, out: str | None = None) -> int:
    """The moves' benchmark (``rep``: the report); ``out``: the default stage's
    motion-time model written there (JSON)."""
    from piezo_stage.apps.studies.moves import MoveSetup, run_moves
    rep.title(f"point-to-point moves at 1 kHz on the simulated stages, the composite law "
              f"against the PID alone (the same gains), judged on target to 0.3 um by the "
              f"feedforward's judge; {steps} random 10 um steps, {moves} random moves, a "
              "50-step z-stack, the motion-time model; true positions from the simulator")
    setup = MoveSetup()
    rows, checks, models = [], [], {}
    for k, (name, plant, model) in enumerate(STAGES):
        res = {}
        for comp in (True, False):
            start, targets = _walk(np.random.default_rng(10 + k), steps, lambda r: 10.0)
            res[comp] = run_moves(*_stage(plant, model, k), targets,
                                  replace(setup, composite=comp), start=start)
        c, p = res[True], res[False]
        ratio = _median(r.true_settle_s for r in c) / _median(r.true_settle_s for r in p)
        after = max(r.after_declared_um for r in c)
        rows.append((name, "10 um steps, median settle (true)",
                     f"{_median(r.true_settle_s for r in c) * 1e3:.1f} ms",
                     f"{_median(r.true_settle_s for r in p) * 1e3:.1f} ms", f"{ratio:.2f}"))
        rows.append(("", "10 um steps, median settle (declared)",
                     f"{_median(r.declared_s for r in c) * 1e3:.1f} ms",
                     f"{_median(r.declared_s for r in p) * 1e3:.1f} ms",
                     f"{_median(r.declared_s for r in c) / _median(r.declared_s for r in p):.2f}"))
        rows.append(("", "largest true error once declared", f"{after:.3f} um",
                     f"{max(r.after_declared_um for r in p):.3f} um", ""))
        checks.append((f"{name}: composite settles in <= 0.3 x the PID alone's time",
                       ratio <= 0.3))
        checks.append((f"{name}: no overshoot past the tolerance once declared",
                       after <= setup.tol_um))
        # random moves: every size, false and missed on-target
        fm = {}
        for comp in (True, False):
            start, targets = _walk(np.random.default_rng(20 + k), moves,
                                   lambda r: float(np.exp(r.uniform(np.log(0.2),
                                                                    np.log(40.0)))))
            rs = run_moves(*_stage(plant, model, 100 + k), targets,
                           replace(setup, composite=comp), start=start)
            fm[comp] = (sum(r.false_samples > 0 for r in rs), sum(r.missed for r in rs),
                        sum(r.declared_s is None for r in rs))
            if comp:
                models[name] = _fit_and_judge(rs, setup.tol_um)
        rows.append(("", f"{moves} random moves 0.2-40 um: false / missed / timed out",
                     "{} / {} / {}".format(*fm[True]), "{} / {} / {}".format(*fm[False]), ""))
        checks.append((f"{name}: 0 false and 0 missed on-target in {moves} moves (both laws)",
                       fm[True][:2] == (0, 0) and fm[False][:2] == (0, 0)))
        # a z-stack: 50 steps of 0.5 um, a 20 ms dwell on target each
        zs, ideal = {}, {}
        for comp in (True, False):
            targets = [{"x": 30.0 + 0.5 * j, "y": 40.0} for j in range(1, 51)]
            rs = run_moves(*_stage(plant, model, 200 + k), targets,
                           replace(setup, composite=comp, dwell_s=0.02),
                           start={"x": 30.0, "y": 40.0})
            zs[comp] = sum(r.elapsed_s for r in rs)
            # what a judge without latency would give: the true settle, then the dwell
            ideal[comp] = sum((r.true_settle_s or 0.0) + 0.02 for r in rs)
        rows.append(("", "z-stack, 50 x 0.5 um, 20 ms dwells: total", f"{zs[True]:.2f} s",
                     f"{zs[False]:.2f} s", f"{zs[True] / zs[False]:.2f}"))
        rows.append(("", "z-stack as a judge without latency would time it (true settle "
                     "+ dwell)", f"{ideal[True]:.2f} s", f"{ideal[False]:.2f} s",
                     f"{ideal[True] / ideal[False]:.2f}"))
        checks.append((f"{name}: the z-stack in <= 0.5 x the PID alone's time",
                       zs[True] / zs[False] <= 0.5))
        fit, err = models[name]
        rows.append(("", "motion-time model (composite): a + b |s| + r ln(|s| / tol)",
                     f"a {fit.a_s * 1e3:.1f} ms, b {fit.b_s_per_um * 1e3:.2f} ms/um, "
                     f"r {fit.ring_s * 1e3:.1f} ms", "",
                     f"median error {100 * err:.0f} %"))
        checks.append((f"{name}: the motion-time model within 20 % (median)", err <= 0.2))
    rep.table(("stage", "figure", "composite", "PID alone", "ratio"), rows)
    for what, ok in checks:
        rep.target(what, ok)
    if out:
        from piezo_stage.io.files import atomic_write
        with atomic_write(out) as fh:
            json.dump(models[STAGES[0][0]][0].to_dict(), fh, indent=1)
        rep.progress(f"the default stage's motion-time model: {os.path.abspath(out)}")
    return 0


def _fit_and_judge(results, tol_um: float):
    """The motion-time model fitted on the first half of the moves' declared settle
    times, and its median relative error on the second half."""
    from piezo_stage.core.loop.motion import MotionTimeModel
    pts = [(r.step_um, r.declared_s) for r in results if r.declared_s]
    half = len(pts) // 2
    fit = MotionTimeModel.fit([s for s, _ in pts[:half]], [t for _, t in pts[:half]], tol_um)
    err = [abs(fit.predict(s) - t) / t for s, t in pts[half:]]
    return fit, float(np.median(err))
