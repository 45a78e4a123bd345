"""Learning feedforward on the simulated stage, offline: the feedforward node's own core
pieces (reference planner, effect compensation, exact inverse, learner) closed around
the plant sample by sample, as the lockstep node set runs them, feedforward only.

Per case: the mean absolute error against the true position per period (in % of the
motion's range), before and after learning, and the learned correction's noise.
"""

from __future__ import annotations

import numpy as np

from piezo_stage.core.types import Doc, EffectsBlock, PerAxis

RATE_HZ = 1000.0


def run_case(plant_cfg, model, effects: EffectsBlock | None, t: np.ndarray, w: PerAxis[np.ndarray],
             freq_hz: float, learn: bool = True, gain: float = 1.0, seed: int = 0,
             fast_axis: str | None = None, rate_hz: float = RATE_HZ) -> Doc:
    """One periodic trajectory on the plant, feedforward only (the model's inverse and
    its effects compensated), learning or not.

    Parameters
    ----------
    plant_cfg : PlantConfig
        The simulated stage.
    model : StageModel
        The feedforward's model.
    effects : dict or None
        The model's effects (as the model file has them).
    t : numpy.ndarray
        The trajectory's time [s], at the control rate, whole periods.
    w : dict
        {axis: desired position [um]}.
    freq_hz : float
        The trajectory's frequency (a raster's line rate).
    learn : bool
        Learn from the measured error.
    gain : float
        The learner's first gain.
    seed : int
        The plant's noise seed.
    fast_axis : str, optional
        A raster's fast axis: its linearity error over the central 80 % of each line
        is reported per period (% of the scan size).
    rate_hz : float
        The control rate [Hz] (a whole number of plant substeps; the trajectory's
        samples at it).

    Returns
    -------
    dict
        ``per_period``: {axis: mean absolute error against the true position [% of the
        axis's range] per period}; ``linearity_pct`` (raster: RMS and max per period);
        ``range_um``, ``design`` (one line per axis), ``max_step_V``, ``v_range``,
        ``noise_factor``, ``damped``; ``intersample_um``: {axis: RMS of the true
        position between samples against the straight line through the samples either
        side [um], over the last period} (what a mode above the Nyquist rate does while
        the command is held).
    """
    from dataclasses import replace

    from piezo_stage.core.loop.compensation import EffectCompensator, PreviewedReference
    from piezo_stage.core.loop.learning import PeriodicLearner, design
    from piezo_stage.core.loop.planner import ReferencePlanner
    from piezo_stage.core.model.inverse import StageInverse
    from piezo_stage.core.model.plant import Plant

    dt_ns = int(round(1e9 / rate_hz))
    n = int(round(rate_hz / freq_hz))
    if abs(n * freq_hz - rate_hz) > 1e-6 * rate_hz:
        raise ValueError(f"{freq_hz:g} Hz is not a whole number of samples at {rate_hz:g} Hz")
    periods = int(round(t[-1] * freq_hz))
    plant = Plant(replace(plant_cfg, seed=seed), rate_hz)
    plant.keep_fine = True
    planner = ReferencePlanner(speed_um_s=2000.0, accel_um_s2=2e5)
    ref = PreviewedReference(planner, dt_ns)
    comp = EffectCompensator(effects, rate_hz) if effects else None
    ref.set_compensator(comp)
    inv = StageInverse(model)
    designs = {a: design(n, rate_hz, effects, a, comp, gain) for a in ("x", "y")}
    learner = PeriodicLearner(designs)
    if learn:
        ref.set_learner(learner)
    v0 = model.voltage_limits[0]
    wx, wy = plant.step(v0, v0)
    inv.reset(v={"x": v0, "y": v0}, w={"x": wx, "y": wy})
    planner.hold({"x": wx, "y": wy})
    if comp is not None:
        comp.reset({"x": wx, "y": wy})
    planner.set_trajectory(t, w)
    err: PerAxis[dict[int, float]] = {a: {} for a in ("x", "y")}
    vs: list = []
    # the last period's intersample deviations
    between: dict[str, list] = {a: [] for a in ("x", "y")}
    last = {"x": wx, "y": wy}
    ramp = np.arange(1, plant.substeps + 1) / plant.substeps
    k_end = int(round((t[-1] + 1.0) / (dt_ns * 1e-9)))
    for k in range(1, k_end):
        target = k * dt_ns
        desired, h = ref.sample(target)
        vx, vy, _ = inv.step(h["x"], h["y"])
        mx, my = plant.step(vx, vy)
        vs.append((vx, vy))
        i = ref.sample_index(target)
        if i is None:
            if planner.phase == "done":
                break
            continue
        true = {a: float(plant.last_true[a][-1]) for a in ("x", "y")}
        for a, m in (("x", mx), ("y", my)):
            err[a][i] = desired[a] - true[a]
            if i >= (periods - 1) * n:
                line = last[a] + (true[a] - last[a]) * ramp
                between[a].append(plant.last_true_fine[a] - line)
            last[a] = true[a]
        if learn:
            learner.observe(i, {"x": desired["x"] - mx, "y": desired["y"] - my})
    span = {a: float(np.ptp(w[a])) for a in w}
    per, e_all = {}, {}
    for a in ("x", "y"):
        e_all[a] = np.array([err[a].get(i, np.nan) for i in range(periods * n)]
                            ).reshape(periods, n)
        if span[a] > 0:
            per[a] = (100 * np.nanmean(np.abs(e_all[a]), axis=1) / span[a]).tolist()
    lin = None
    if fast_axis is not None:
        # the central 80 % of each sweep of the fast axis, in % of the scan size
        d = np.asarray(w[fast_axis][:periods * n], float).reshape(periods, n)
        lo, size = float(np.min(w[fast_axis])), span[fast_axis]
        mid = np.abs(d - lo - size / 2) <= 0.4 * size
        e = np.where(mid, e_all[fast_axis], np.nan)
        lin = {"rms": (100 * np.sqrt(np.nanmean(e ** 2, axis=1)) / size).tolist(),
               "max": (100 * np.nanmax(np.abs(e), axis=1) / size).tolist()}
    v = np.array(vs)
    return {"per_period": per, "linearity_pct": lin, "range_um": span, "n": n,
            "design": {a: d.describe() for a, d in designs.items()},
            "max_step_V": float(np.abs(np.diff(v, axis=0)).max()),
            "v_range": (float(v.min()), float(v.max())),
            "noise_factor": {a: learner.noise_factor(a) for a in designs},
            "damped": learner.damped, "noise_um": dict(learner.noise_um),
            "intersample_um": {a: float(np.sqrt(np.mean(np.concatenate(b) ** 2)))
                               if b else 0.0 for a, b in between.items()}}


# the paper's y(t) = 21 + 24 sin(2 pi f t - pi/2) um reaches -3 um, below this stage's
# 0 V rest (-0.4 um): lifted by 4 um, so its bottom is reachable and what is left is
# what the feedforward does, not the amplifier's lower limit
LIFTED_CENTER_UM = 25.0


def cases(periods: int = 20) -> list[dict]:
    """The study's cases: (name, plant config, model file, trajectory kind, frequency)."""
    return [{"name": f"{kind} {f:g} Hz, {plant}", "plant": plant, "kind": kind,
             "freq_hz": f, "periods": periods}
            for plant in ("sim_stage.yaml", "sim_stage_effects.yaml", "sim_stage_600hz.yaml")
            for kind, f in (("sine", 40.0), ("sine", 100.0), ("raster", 20.0))]


def trajectory(kind: str, freq_hz: float, periods: int, rate_hz: float = RATE_HZ) -> tuple:
    """(t, w, fast axis or None) of a case, sampled at ``rate_hz``."""
    from piezo_stage.core.loop.trajectory import generate, raster
    if kind == "raster":
        t, w = raster(freq_hz, periods, (40.0, 40.0), (45.0, 45.0), dt_s=1.0 / rate_hz)
        return t, w, "x"
    t, w = generate("sine", periods / freq_hz, 1.0 / rate_hz, freq_hz,
                    LIFTED_CENTER_UM, 24.0)
    return t, w, None


def run(periods: int = 20, model_error: float = 0.0, progress=None,
        rate_hz: float = RATE_HZ) -> list[dict]:
    """Every case without and with learning at the control rate ``rate_hz``; with
    ``model_error`` the model's effect parameters are all off by that factor
    (1 + model_error) for the learning runs."""
    import copy

    from piezo_stage.io.plant_file import load_plant_config
    from piezo_stage.paths import default_config
    out = []
    for case in cases(periods):
        cfg = load_plant_config(default_config(case["plant"]))
        model = cfg.model
        effects = {k: dict(v or {}) for k, v in cfg.effects.items()} or None
        if model_error and effects:
            effects = copy.deepcopy(effects)
            for p in effects.values():
                for k in ("delay_s", "fn_hz", "zeta", "gamma"):
                    if k in p:
                        p[k] *= 1 + model_error
        t, w, fast = trajectory(case["kind"], case["freq_hz"], periods, rate_hz)
        res = {}
        for learn in (False, True):
            res[learn] = run_case(cfg, model, effects, t, w, case["freq_hz"], learn,
                                  fast_axis=fast, rate_hz=rate_hz)
            if progress:
                progress()
        out.append({**case, "model_error": model_error, "rate_hz": rate_hz,
                    "without": res[False],
                    "with": res[True]})
    return out


def print_report(rows: list[dict]) -> None:
    """The table: per case and axis, the first and the last period without learning
    and with it (mean absolute error, % of the range), a raster's linearity, the true
    position's RMS between samples over the last period [um]."""
    print(f"{'case':<44} {'axis':>4} {'no_learning':>12} {'learning_1st':>14} "
          f"{'last':>8} {'linearity_rms/max_%':>20} {'damped':>7} {'between_um':>10}")
    for r in rows:
        for a in r["with"]["per_period"]:
            wo, wi = r["without"]["per_period"][a], r["with"]["per_period"][a]
            lin = r["with"]["linearity_pct"]
            lin_txt = (f"{lin['rms'][-1]:.3f}/{lin['max'][-1]:.3f}"  # one column, as labelled
                       if lin and a == "x" else "")
            print(f"{r['name']:<44} {a:>4} {wo[-1]:11.3f}% {wi[0]:13.3f}% {wi[-1]:7.3f}% "
                  f"{lin_txt:>20} {r['with']['damped']:>7} "
                  f"{r['with']['intersample_um'][a]:10.4f}")
