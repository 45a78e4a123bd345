"""Fit here, use there: models scored on an excitation other than the one they were
fitted on, beside the classical Prandtl-Ishlinskii peer (core/estimation/identify/prandtl.py).

A lab identifies its stage once, on one excitation, and drives it with another. Each
case fits on FIT and scores on HOLDOUT, one axis, 1 kHz, on two simulated stages: the
structure stage (config/structure_stage.yaml: play operators with return-point memory
and a tanh envelope, not our model class) and our own (config/sim_stage.yaml):

* ``periodic->nested``: FIT a constant-amplitude 1 Hz full-stroke sine (a calibration);
  HOLDOUT a 1 Hz sine whose amplitude decays to a tenth and grows again about the
  middle of the stroke, every loop a minor loop nested in the calibration's;
* ``small->large``: rising-amplitude 2 Hz triangles from 0 V; FIT their first third
  (up to about 60 V), HOLDOUT the rest (up to 150 V): a larger stroke than fitted;
* ``periodic->periodic``: FIT and HOLDOUT two different sines of the calibration's
  kind (the same conditions: the reference);
* ``slow->fast``: FIT a 2 Hz full-stroke sine, HOLDOUT the same at 10 Hz (a faster
  line rate than calibrated), on the rate stage (config/rate_stage.yaml: the structure
  stage's law with thresholds that widen with |dv/dt|, its loop 7.1 um wide at mid
  stroke at 2 Hz, 9.1 um at 10 Hz) and on ours (rate independent: the control);
* ``two-rate->fast``: FIT a calibration at two rates (2 Hz for 3 s, then 5 Hz for 3 s),
  HOLDOUT the same sine at 10 Hz, on the rate stage: what a rate model needs;
* ``periodic->nested`` and ``small->large`` also on the Rayleigh stage
  (config/rayleigh_stage.yaml: play operators of one weight up to half the stroke, no
  envelope: a uniform Preisach density along the diagonal, the Rayleigh law of
  piezoceramics below their coercive field, whose loop widens with the stroke as a
  stack's does: 5.2 um of stroke on FIT's 20-63 V triangles, 19 um on HOLDOUT's);
* ``periodic->nested`` on the structure stage with creep (``structure+creep``: 12 %
  of each step over 0.05-50 s), and ``small->large`` on it with its cross-axis
  coupling and the other axis driven apart (``structure+coupling``): memory with one
  of our effects, which the class with memory is fitted with as the Duhem law is.

Scored (``prandtl.held_out_rms``: after the first second, each model's mean offset
removed) against the measured displacement: ours (``identify``'s fast fit, cubic
segmented branches), the model ``gap --out-model`` writes (saved, loaded back and run
through our own simulator, noise free; its hysteresis's output also inverted back to
the voltages by our exact inverse), the peer (a linear term and 12 play operators,
least squares on the same samples), and ours fitted on HOLDOUT itself (what the model
class can reach there).
"""

from __future__ import annotations

import os
import tempfile

import numpy as np

from piezo_stage.core.estimation.record import Record

FS_HZ = 1000.0
STAGES = {"structure": "structure_stage.yaml", "ours": "sim_stage.yaml",
          "rate": "rate_stage.yaml", "rayleigh": "rayleigh_stage.yaml"}
CASES = ("periodic->periodic", "periodic->nested", "small->large", "slow->fast")
# the (stage, case) pairs the study runs: every case on the structure stage and ours,
# the rate stage where rate is what changes (and its calibration at two rates), the
# Rayleigh stage where memory and stroke do
PAIRS = tuple((s, c) for s in ("structure", "ours") for c in CASES) + \
    (("rate", "periodic->periodic"), ("rate", "slow->fast"), ("rate", "two-rate->fast"),
     ("rayleigh", "periodic->nested"), ("rayleigh", "small->large"),
     ("structure+creep", "periodic->nested"), ("structure+coupling", "small->large"))
# a stage with one of our effects besides its memory: (the stage, its effects, whether
# the other axis moves and couples in)
WITH_EFFECTS = {
    "structure+creep": ("structure", {"creep": {"gamma": 0.12,
                                                "tau_s": [0.05, 0.5, 5.0, 50.0]}}, False),
    "structure+coupling": ("structure", {}, True),
}


def _sine(t, phase=0.0, lo=0.0, hi=150.0):
    return lo + (hi - lo) * 0.5 * (1 - np.cos(2 * np.pi * t + phase))


def excitations(case: str, seed: int = 0) -> tuple[np.ndarray, np.ndarray, int]:
    """(t [s], v [V], the first HOLDOUT sample): one continuous voltage record, FIT
    before the split and HOLDOUT after it (run through the stage as one, so HOLDOUT
    starts where FIT left the stage, as a lab's next run would)."""
    rng = np.random.default_rng(seed)
    if case == "small->large":
        t = np.arange(int(12 * FS_HZ)) / FS_HZ
        amp = 20.0 + 130.0 * t / t[-1]                      # 20 -> 150 V
        tri = 1 - np.abs(((2.0 * t) % 1.0) * 2 - 1)          # 0..1..0 at 2 Hz
        return t, amp * tri, int(4 * FS_HZ)
    fit_s, hold_s = 6.0, 12.0
    t = np.arange(int((fit_s + hold_s) * FS_HZ)) / FS_HZ
    v = _sine(t, phase=float(rng.uniform(-0.2, 0.2)))
    k = int(fit_s * FS_HZ)
    if case == "slow->fast":  # 2 Hz, then 10 Hz, both from the bottom of a cycle
        v[:k] = _sine(2.0 * t[:k])
        v[k:] = _sine(10.0 * (t[k:] - t[k]))
    if case == "rising->fast":  # 2 Hz triangles rising 30 -> 150 V, then a 10 Hz sine
        amp = 30.0 + 120.0 * t[:k] / t[k]
        v[:k] = amp * (1 - np.abs(((2.0 * t[:k]) % 1.0) * 2 - 1))
        v[k:] = _sine(10.0 * (t[k:] - t[k]))
    if case == "two-rate->fast":  # 2 Hz for 3 s, 5 Hz for 3 s, then 10 Hz
        h = k // 2
        v[:h] = _sine(2.0 * t[:h])
        v[h:k] = _sine(5.0 * (t[h:k] - t[h]))
        v[k:] = _sine(10.0 * (t[k:] - t[k]))
    if case == "periodic->nested":
        th = t[k:] - t[k]
        # 1 Hz about the middle, the amplitude 75 -> 7.5 -> 75 V over HOLDOUT's 12 s
        env = 75.0 * (0.1 + 0.9 * np.abs(np.cos(np.pi * th / th[-1])))
        v[k:] = 75.0 - env * np.cos(2 * np.pi * th)
        # (continuous at the split: both start at the bottom of a cycle)
        v[k:] += v[k - 1] - v[k]
        v[k:] = np.clip(v[k:], 0.0, 150.0)
    return t, v, k


def case_records(stage: str, case: str, seed: int = 0) -> tuple[Record, Record, np.ndarray]:
    """(FIT, HOLDOUT, HOLDOUT's true displacement [um]) of axis x: y held at 0 V, or,
    on a stage of ``WITH_EFFECTS`` whose other axis couples in, driven by a 0.37 Hz
    sine over 15-135 V (apart from x, so that the coupling is identifiable)."""
    from piezo_stage.core.model.plant import Plant
    from piezo_stage.io.plant_file import load_plant_config
    from piezo_stage.paths import default_config
    base, effects, coupled = WITH_EFFECTS.get(stage, (stage, {}, False))
    cfg = load_plant_config(default_config(STAGES[base]))
    if not coupled:
        cfg.model.coupling.clear()
    if effects:
        cfg.effects = {n: dict(p) for n, p in effects.items()}
    cfg.seed = seed
    t, v, k = excitations(case, seed)
    vy = 75.0 + 60.0 * np.sin(2 * np.pi * 0.37 * t) if coupled else np.zeros_like(v)
    plant = Plant(cfg, FS_HZ)
    w = plant.run(v, vy)["x"]
    true = plant.last_true["x"]
    both = {"x": v, "y": vy} if coupled else {"x": v}
    fit = Record(t[:k], {a: x[:k] for a, x in both.items()}, {"x": w[:k]},
                 source=f"{stage} {case} FIT")
    hold = Record(t[k:] - t[k], {a: x[k:] for a, x in both.items()}, {"x": w[k:]},
                  source=f"{stage} {case} HOLDOUT")
    return fit, hold, true[k:]


def _written_model_prediction(fit: Record, hold: Record
                              ) -> tuple[np.ndarray, str, float, str]:
    """What `gap --out-model` writes for FIT, saved, loaded and run through our own
    simulator (noise free) over HOLDOUT's voltages: (its output [um], the verdict, how
    far [V] our exact inverse of its hysteresis's output lands from HOLDOUT's voltages,
    and the diagnosis's reason)."""
    from piezo_stage.core.estimation.gap import diagnose
    from piezo_stage.core.model.inverse import invert, invert_stage
    from piezo_stage.core.model.plant import Plant
    from piezo_stage.io.model_file import load_model, save_model
    res = diagnose(fit, hold, axes=["x"])
    model, effects = res.model()
    with tempfile.TemporaryDirectory() as d:
        path = os.path.join(d, "model.yaml")
        save_model(path, model, effects=effects or None)
        model, effects = load_model(path)  # loads: our loader accepts it
    v = hold.v["x"]
    vy = hold.v.get("y", np.zeros_like(v))
    pred = Plant.of_model(model, effects, FS_HZ).run(v, vy)["x"]
    # the exact inverse takes the hysteresis (the feedforward compensates the effects
    # apart): the output of the hysteresis alone must invert back to the voltages (a
    # coupling from y, whose voltages the model of x alone does not solve for, taken
    # out at y's known voltages)
    hyst = Plant.of_model(model, None, FS_HZ).run(v, vy)
    if "x" in model.coupling and "y" not in model.axes:
        wc = model.coupling["x"].simulate(vy)[0]
        inv = invert(model.axes["x"], hyst["x"] - wc, model.voltage_limits,
                     plays=model.plays.get("x"), dt_s=1.0 / FS_HZ).v
    else:
        inv = invert_stage(model, hyst["x"], hyst["y"], dt_s=1.0 / FS_HZ)["x"].v
    back = float(np.max(np.abs(inv - v))) if np.all(np.isfinite(inv)) else float("nan")
    return pred, str(res["verdict"]), back, str(res["reason"])


def run(pairs=PAIRS, seed: int = 0, progress=None) -> list[dict]:
    """Each (stage, case) of ``pairs``: the held-out RMS of each model [um]."""
    from piezo_stage.core.estimation.identify import identify_axis
    from piezo_stage.core.estimation.identify.api import predict_axis
    from piezo_stage.core.estimation.identify.prandtl import fit_prandtl_ishlinskii, held_out_rms
    rows = []
    for stage, case in pairs:
        fit, hold, true = case_records(stage, case, seed)
        w = hold.w["x"]
        score = lambda p: held_out_rms(p, w, FS_HZ)  # noqa: E731
        ours = predict_axis(identify_axis(fit, "x"), hold)[2]
        own = predict_axis(identify_axis(hold, "x"), hold)[2]
        peer = fit_prandtl_ishlinskii(fit.v["x"], fit.w["x"]).predict(hold.v["x"])
        written, verdict, back, reason = _written_model_prediction(fit, hold)
        rows.append({"stage": stage, "case": case, "ours_um": score(ours),
                     "gap_model_um": score(written), "verdict": verdict, "reason": reason,
                     "inverse_back_V": back,
                     "peer_um": score(peer), "own_fit_um": score(own),
                     "noise_um": score(true)})
        if progress:
            progress(f"{stage} {case}")
    return rows


def above_noise(rms_um: float, noise_um: float) -> float:
    """The part of a held-out RMS [um] the sensor's noise does not explain:
    sqrt(max(rms^2 - noise^2, 0)) (the records' noise is known here: the stage's true
    displacement is kept)."""
    return float(np.sqrt(max(rms_um ** 2 - noise_um ** 2, 0.0)))


COLUMNS = ("stage", "case", "identify", "gap model", "PI peer", "own fit", "noise",
           "identify/PI", "gap/PI", "above noise", "verdict")


def table_rows(rows: list[dict]) -> list[tuple[str, ...]]:
    """The rows' cells (``COLUMNS``), ours against the peer as ratios: of the held-out
    RMS, and of the part of it above the sensor's noise (where both models are near the
    noise the first ratio is near 1 whatever they do)."""
    out: list[tuple[str, ...]] = []
    for r in rows:
        n = r["noise_um"]
        peer = above_noise(r["peer_um"], n)
        ratio = above_noise(r["gap_model_um"], n) / peer if peer > 0 else float("nan")
        out.append((r["stage"], r["case"], f"{r['ours_um']:.3f}", f"{r['gap_model_um']:.3f}",
                    f"{r['peer_um']:.3f}", f"{r['own_fit_um']:.3f}", f"{n:.3f}",
                    f"{r['ours_um'] / r['peer_um']:.2f}",
                    f"{r['gap_model_um'] / r['peer_um']:.2f}", f"{ratio:.2f}", r["verdict"]))
    return out

