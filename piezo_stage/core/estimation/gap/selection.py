"""One axis's diagnosis: every candidate fitted on FIT and scored on HOLDOUT, forward
selection of the effects that shrink the held-out gap, and the verdict."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from piezo_stage.core.errors import DataError
from piezo_stage.core.estimation.gap.budget import gap_above_floor, gap_budget, shrink_uncertainty
from piezo_stage.core.estimation.gap.candidates import (
    EFFECTS,
    INVERSE_MISS_FRACTION,
    MEMORY_CLASSES,
    TRANSFORMS,
    Candidate,
    ClassCandidate,
    broadband,
    fit_candidate,
    fit_class_candidate,
    fit_class_effect,
    with_drift,
)
from piezo_stage.core.estimation.gap.disturbance import disturbance
from piezo_stage.core.estimation.gap.where import (
    MIN_HOLD_S,
    holds,
    one_rate_note,
    several_rates,
    where,
)
from piezo_stage.core.estimation.identify.api import check_identifiable
from piezo_stage.core.estimation.identify.fast import fit_fast
from piezo_stage.core.estimation.identify.segmentation import inner_reversals
from piezo_stage.core.estimation.record import Record
from piezo_stage.core.metrics import noise_floor, rms
from piezo_stage.core.model.duhem import OTHER, StageModel


class GivenModel:
    """A model from a file as the base ("the sim"): prediction with the initial state
    and a constant offset re-estimated on the record, like every candidate."""

    effect = "given"
    params: dict = {}

    def __init__(self, stage_model: StageModel):
        self.model = stage_model

    def predict(self, rec: Record, axis: str) -> np.ndarray:
        """The given model's prediction on a record (no fit)."""
        from piezo_stage.core.estimation.identify.api import simulate_axis
        m = self.model.axes[axis]
        c = self.model.coupling.get(axis)
        vo = rec.v.get(OTHER[axis])
        if c is not None and vo is None:
            c = None
        w = simulate_axis(m, c, rec.v[axis], vo, w_meas=rec.w[axis])
        r = rec.w[axis] - w
        return w + r.mean()


@dataclass
class AxisDiagnosis:
    """One axis's diagnosis: verdict, ranking, kept effects, budget, models."""
    axis: str
    verdict: str
    reason: str
    ranking: list
    where: dict
    noise_floor_um: float
    candidates: dict = field(default_factory=dict)
    effects: list = field(default_factory=list)    # forward selection: kept, in order
    budget: dict = field(default_factory=dict)
    model: Candidate | ClassCandidate | None = None  # the model with every kept effect


FIRST_SHRINK_PCT = 30.0  # the dominant effect must close this much of the held-out gap


STEP_SHRINK_PCT = 15.0   # each further effect this much of what is left


STEP_NOISE_SIGMAS = 2.0  # and that share must stand this many of its own standard
                         # deviations (shrink_uncertainty between the model before the
                         # step and after it) above nothing: no effect named for what
                         # another stretch of the same stage would not repeat


PAIR_POOL = 3           # no single effect closes the first 30 %: pairs among these best


POLISH_BUDGET = 24       # and for a kept one, polished


NOISE_STOP = 0.6         # a gap under this share of the noise floor is at the floor


                         # (the residual within 17 % of the noise RMS, which is itself
                         # estimated from the data)


def _significant(rms_a, rms_b, nf, n):
    """A held-out improvement counts when it is well above what chance gives on this
    many samples (the MSE of white noise fluctuates by nf^2 sqrt(2/N))."""
    return rms_a ** 2 - rms_b ** 2 > max(0.05 * nf ** 2, 10 * nf ** 2 * np.sqrt(2.0 / n))


def _given_effects(base_model, base_effects, axis):
    """What the user's model already has on this axis: never a candidate, and part of
    every candidate's fit. -> [(name, params)]."""
    out: list[tuple[str, dict]] = []
    if base_model is None or axis not in base_model.axes:
        return out
    if axis in base_model.coupling:
        out.append(("coupling", {}))
    for name, p in (base_effects or {}).items():
        p = dict(p or {})
        if axis in p.pop("axes", ["x", "y"]) and name in TRANSFORMS + ("drift",):
            out.append((name, p))
    return out


def _quiet(what: str) -> None:
    """No progress to show."""


# the classes with memory are fitted again with the effects kept later only where, the
# first time (with the effects the sim already has), the closer of them was within this
# factor of the Duhem law's best structure form on HOLDOUT
CLASS_WITH_EFFECTS = 1.5

# a structure form whose exact inverse misses the records' voltages (its branch turns
# back: candidates.INVERSE_MISS_FRACTION) replaces an exactly invertible one only when
# its held-out RMS is below this fraction of that one's
NOT_INVERTIBLE_PAYS = 0.9

def diagnose_axis(fit: Record, holdout: Record, axis: str, effects: Sequence[str] = EFFECTS,
                  base_model: StageModel | None = None,
                  progress: Callable[[str], None] | None = None,
                  base_effects: dict | None = None,
                  limits_V: tuple | None = None, history: int = 0) -> AxisDiagnosis:
    """Fit every candidate on FIT, score on HOLDOUT, then add effects one at a time
    (forward selection, each refitted jointly with the Duhem model and the effects
    kept before it) while the held-out gap keeps shrinking clearly. ``base_model`` (a
    StageModel, with ``base_effects`` from its file) replaces the FIT-identified Duhem
    model as the sim to compare with; what it already has is not a candidate.
    ``progress(what)`` is called after each candidate is fitted; ``limits_V``, the
    amplifier's, bound the memory class's thresholds (fit_class_candidate). HOLDOUT's
    first ``history`` samples are its history: every model runs over them (the stage's
    state at the scored part's start follows from them: a creep in progress is no
    drift), and only the rest is scored."""
    if progress is None:
        progress = _quiet
    for rec in (fit, holdout):
        if axis not in rec.v or axis not in rec.w:
            raise DataError(f"{rec.source}: no v{axis}/w{axis} for axis {axis}")
    scored = holdout.slice(history, len(holdout)) if history else holdout
    for rec in (fit, scored):
        check_identifiable(rec.v[axis], rec.source)

    def resid_of(c) -> np.ndarray:  # a model's held-out residual, over the scored part
        return (c.predict(holdout, axis) - holdout.w[axis])[history:]
    notes = []
    if holdout is fit:
        notes.append("no HOLDOUT: scored on FIT itself, where extra freedom is not "
                     "penalised (record the excitation twice)")
    given = _given_effects(base_model, base_effects, axis)
    vo_fit = fit.v.get(OTHER[axis])
    if any(n == "coupling" for n, _ in given) and (vo_fit is None or np.ptp(vo_fit) < 1.0):
        # the model's coupling term has nothing to be fitted on where the other axis
        # rests (a protocol that drives the axes in turn): it adds a constant there
        given = [(n, p) for n, p in given if n != "coupling"]
        notes.append("the model's coupling is left out: the other axis's voltage does "
                     "not move in FIT")
    testable = []
    for e in effects:
        if e in [n for n, _ in given]:
            continue  # the sim has it already
        if e == "coupling":
            vo_f, vo_h = fit.v.get(OTHER[axis]), holdout.v.get(OTHER[axis])
            if vo_f is None or vo_h is None or np.ptp(vo_f) < 1.0:
                notes.append("coupling not tested: the other axis's voltage does not move")
                continue
        testable.append(e)
    no_band = "dynamics" in testable and "delay" in testable and not broadband(
        fit.v[axis], fit.fs_hz)
    rates = several_rates(fit.v[axis], fit.fs_hz)

    def candidate(e, on, kept):
        """fit_candidate; structure in its forms (richer branches; with play
        operators: memory; where FIT holds several rates, with their thresholds
        widened by the rate: rate; memory as the Prandtl-Ishlinskii or the discretized
        Preisach class in place of the Duhem law, with the effects kept before it), the
        one closest on HOLDOUT kept (as every candidate is judged), so memory and rate
        are named only where they pay. A form whose exact inverse does not give the
        records' voltages back (a branch turning back) must be closer by 10 % than the
        best before it (NOT_INVERTIBLE_PAYS). On a class (``on`` a ClassCandidate) the
        effect is added to the class (fit_class_effect) and to its twin, the Duhem
        law's best form with the same effects; the closer of the two on HOLDOUT is the
        candidate (the class's twin the law's)."""
        if isinstance(on, ClassCandidate):
            assert on.twin is not None  # a class is kept with its twin (below)
            law = candidate(e, on.twin, on.twin.effects)
            k = fit_class_effect(fit, axis, on, e, law, limits_V) \
                if isinstance(law, Candidate) else None
            if k is None:
                return law
            k.twin = law
            r_law = rms(resid_of(law))
            return k if rms(resid_of(k)) <= r_law else law
        law = fit_candidate(fit, axis, e, on, kept)  # the best form of the Duhem law
        c: Candidate | ClassCandidate = law
        if e == "structure":
            both = np.concatenate([fit.v[axis], holdout.v[axis]])
            best = rms(resid_of(law))
            tried = not class_tried or class_tried[0] <= CLASS_WITH_EFFECTS
            classes = [(k, rms(resid_of(k)))
                       for k in (fit_class_candidate(fit, axis, limits_V, kind, on, kept)
                                 for kind in (MEMORY_CLASSES if tried else ()))]
            for form in (("memory", "rate") if rates else ("memory",)):
                m = fit_candidate(fit, axis, e, on, kept, memory=True,
                                  rate=form == "rate")
                if m.effect == "rate" and not m.params.get("rate_widening_s"):
                    continue  # no widening fits FIT better: memory already
                r = rms(resid_of(m))
                if r < best:
                    if r > NOT_INVERTIBLE_PAYS * min([best] + [x[1] for x in classes]) \
                            and m.inverse_miss(both, fit.fs_hz, limits_V) > \
                            INVERSE_MISS_FRACTION:
                        continue  # a branch turns back, for little: the exact inverse wins
                    law, best = m, r
            if not class_tried and classes:  # the first try: how close the classes came
                class_tried.append(min(r for _, r in classes) / best if best > 0 else 0.0)
            c = law
            for k, r in classes:
                if r < best:
                    c, best = k, r
            if isinstance(c, ClassCandidate):  # a class came closer than the law
                c.twin = law
        return c
    # the classes' held-out RMS over the Duhem law's best structure form, the first time
    # both were fitted: far behind (a stage of the Duhem law's own class), they are not
    # fitted again with the effects kept later (they cost more than any other candidate)
    class_tried: list[float] = []
    base = fit_candidate(fit, axis, "none", kept=given)
    progress(f"{axis} none")
    cands = {"none": base}
    for e in testable:
        cands[e] = candidate(e, base, base.effects)
        progress(f"{axis} {e}")
    nf = noise_floor(scored.w[axis])
    w_h = scored.w[axis]
    n = len(w_h)
    sim = GivenModel(base_model) if base_model is not None and axis in base_model.axes \
        else base
    resid = resid_of(sim)
    r_before = rms(resid)
    # a line the input does not cause (a floor vibration) is no model's to close: for
    # choosing effects it counts with the noise (the gap is what a model could close)
    dist0 = disturbance(scored, axis, resid, nf)
    floor = float(np.hypot(nf, dist0["rms_um"])) if dist0 else nf
    g_before = gap_above_floor(r_before, floor)
    resids = {e: resid_of(c) for e, c in cands.items()}
    if sim is not base:  # "none" is the sim as given: a candidate that changes nothing
        resids["none"] = resid
    scores: dict[str, float] = {e: rms(r) for e, r in resids.items()}
    ranking: list[dict[str, Any]] = []
    for e, c in cands.items():
        g_after = gap_above_floor(scores[e], floor)
        ranking.append({"effect": c.effect, "rms_before_um": r_before, "rms_after_um": scores[e],
                        "gap_before_um": g_before, "gap_after_um": g_after,
                        "shrink_pct": 100.0 * (1 - g_after / g_before) if g_before > 0 else 0.0,
                        "shrink_pm_pct": shrink_uncertainty(resid, resids[e], floor,
                                                            scored.fs_hz),
                        "fit_rms_um": c.fit_rms_um, "params": c.params})
    ranking.sort(key=lambda r: r["gap_after_um"])
    # forward selection: the best candidate joins when it shrinks the held-out gap
    # clearly; the rest are refitted with it in place and tried again
    steps: list[dict[str, Any]] = []
    model, r_cur = None, r_before
    # (every candidate stays in: one that explains nothing on its own, as creep
    # beside a larger coupling, can show once the larger one is modelled)
    pool = {e: cands[e] for e in testable}
    tried = {}  # (a, b): b fitted on top of a, and its held-out RMS (the pairs)
    while pool:
        e, c = min(pool.items(), key=lambda kv: scores[kv[0]])
        g_cur, g_new = gap_above_floor(r_cur, floor), gap_above_floor(scores[e], floor)
        need = (50.0 if g_before <= 0.5 * floor else FIRST_SHRINK_PCT) if not steps \
            else STEP_SHRINK_PCT
        step = 100.0 * (1 - g_new / g_cur) if g_cur > 0 else 0.0
        rule = (f"the first-effect rule: it alone closes >= {need:.0f} % of the gap"
                if not steps else f"the further-effect rule: it closes >= {need:.0f} % "
                "of what was left")
        if not steps and step < need and len(pool) > 1 and g_before > 0.5 * floor:
            # effects of similar size: none alone closes 30 %, two of the three best
            # together may (the better one of the best such pair joins first; the other
            # must then still earn its place as a later step)
            top = sorted(pool, key=scores.__getitem__)[:PAIR_POOL]
            pairs = [(a, b) for i, a in enumerate(top) for b in top[i + 1:]]
            if "delay" in pool and "dynamics" in pool and not {"delay", "dynamics"} <= set(top):
                # a resonance seen through a delay: neither alone may fit at all
                d0, d1 = sorted(("delay", "dynamics"), key=scores.__getitem__)
                pairs.append((d0, d1))
            best_pair = None
            for a, b in pairs:
                first = pool[a]
                pair = candidate(b, first, first.effects)
                progress(f"{axis} {a}+{b}")
                r_pair = rms(resid_of(pair))
                tried[(a, b)] = (pair, r_pair)
                g_pair, g_a = gap_above_floor(r_pair, floor), gap_above_floor(scores[a], floor)
                if 100.0 * (1 - g_pair / g_cur) >= need \
                        and _significant(r_cur, r_pair, floor, n) \
                        and 100.0 * (1 - g_pair / g_a) >= STEP_SHRINK_PCT \
                        and (best_pair is None or g_pair < best_pair[0]):
                    best_pair = (g_pair, a, b)
            if best_pair is not None:
                e = best_pair[1]
                c, g_new = pool[e], gap_above_floor(scores[e], floor)
                step = 100.0 * (1 - g_new / g_cur) if g_cur > 0 else 0.0
                rule = (f"the pair rule: {e} and {best_pair[2]} together close "
                        f"{100.0 * (1 - best_pair[0] / g_cur):.0f} % of the gap (>= "
                        f"{need:.0f} %), which no effect does alone")
                need = 0.0  # the first of a pair that closes the gap together
        if not (_significant(r_cur, scores[e], floor, n) and step >= need):
            break
        # a further effect's step, bootstrapped over HOLDOUT against the model before it
        step_pm = shrink_uncertainty(resid_of(model), resid_of(c), floor, scored.fs_hz) \
            if steps else float("nan")
        if steps and np.isfinite(step_pm) and step < STEP_NOISE_SIGMAS * step_pm:
            break  # within the noise of the step itself
        # what fits as well at this step (the excitation cannot tell them apart)
        alike = [e2 for e2 in pool if e2 != e and gap_above_floor(scores[e2], floor) <=
                 1.02 * g_new + 0.02 * (g_cur - g_new)]
        if steps and len(alike) >= 2 and len(alike) == len(pool) - 1:
            break  # every candidate helps alike: the refit helps, not any one effect
        steps.append({"effect": c.effect, "params": c.params, "rms_after_um": scores[e],
                      "gap_after_um": g_new, "step_shrink_pct": step,
                      "shrink_pct": 100.0 * (1 - g_new / g_before) if g_before else 0.0,
                      "equally_well": alike, "rule": rule, "step_pm_pct": step_pm})
        # polish the kept model's alphas fully, so that what the next candidates earn
        # is theirs and not a better alpha search riding along (the other class has none)
        if isinstance(c, Candidate):
            alphas, fitted, _ = fit_fast(c.reg, budget=POLISH_BUDGET, x0=c.alphas, step=0.1)
            if fitted.rms < c.fit_rms_um:
                was = (c.alphas, c.theta, c.fit_rms_um, c.effects)
                c.alphas, c.theta, c.fit_rms_um = alphas, fitted.theta, fitted.rms
                c.effects = with_drift(c.effects, c.reg, c.theta, c.drift_tau_s)
                polished = rms(resid_of(c))
                if polished <= scores[e]:
                    scores[e] = polished
                    g_new = gap_above_floor(scores[e], floor)
                    steps[-1].update(rms_after_um=scores[e], gap_after_um=g_new,
                                     shrink_pct=100.0 * (1 - g_new / g_before)
                                     if g_before else 0.0)
                else:  # closer on FIT, further on HOLDOUT: the extra freedom overfits
                    c.alphas, c.theta, c.fit_rms_um, c.effects = was
        steps[-1]["shrink_pm_pct"] = shrink_uncertainty(
            resid, resid_of(c), floor, scored.fs_hz)
        model, r_cur = c, scores[e]
        del pool[e]
        if g_new <= NOISE_STOP * floor:
            break  # at the noise floor (itself estimated): nothing left to explain
        for e2 in list(pool):
            if len(steps) == 1 and (e, e2) in tried:
                # fitted already as a pair on top of the effect just kept
                pool[e2], scores[e2] = tried[(e, e2)]
            else:
                pool[e2] = candidate(e2, model, model.effects)
                scores[e2] = rms(resid_of(pool[e2]))
            progress(f"{axis} {'+'.join(x['effect'] for x in steps)}+{e2}")
    if model is not None:  # each effect's parameters as finally refitted (drift's)
        final = dict(model.effects)
        for st in steps:
            st["params"] = final.get(st["effect"], st["params"])
    loc = where(scored, axis, resid, nf)
    verdict, reason = _decide(ranking, steps, g_before, floor, fit, scored, axis)
    if verdict in ("none", "inconclusive"):
        steps, model = [], None
    if no_band and ({"delay", "dynamics"} & {st["effect"] for st in steps}
                    or "delay and dynamics" in reason or "dynamics and delay" in reason):
        notes.append("no broadband excitation (no chirp): a resonance above the "
                     "excitation's tones cannot be told from a delay (record the "
                     "protocol with its chirp: `excite` without `--chirp 0`)")
    rate_note = one_rate_note(fit, scored, axis) if fit is not holdout else None
    if rate_note:
        notes.append(rate_note)
    if not any(inner_reversals(r.v[axis]) for r in (fit, scored)):
        notes.append("FIT and HOLDOUT hold no minor loops (their reversals lie at their "
                     "ends): the forms with memory were judged on major loops alone, not "
                     "on the minor loops where they differ, and a written model's minor "
                     "loops are untested; record nested loops to tell (`excite --nested`; "
                     "`identify --class auto` chooses the Prandtl-Ishlinskii class for "
                     "such a record)")
    if notes:
        reason = (reason + "; " if reason else "") + "; ".join(notes)
    left = resid_of(model) if model is not None else resid
    dist = disturbance(scored, axis, left, nf)
    budget = gap_budget(scored, axis, resid, nf, g_before, steps)
    budget["disturbance"] = dist
    g_left = budget["unexplained_um"]
    if dist is not None and (not steps or dist["rms_um"] >= g_left):
        # what is left is mostly a line no model of the input removes
        said = (f"disturbance: {dist['rms_um']:.3g} um at {dist['freq_hz']:.1f} Hz, not "
                f"caused by the input (reject it with >= {dist['feedback_bandwidth_hz']:.0f}"
                " Hz of feedback bandwidth)")
        if verdict == "none":
            verdict, reason = "disturbance", said
        else:
            reason += "; what is left is a " + said
    return AxisDiagnosis(axis, verdict, reason, ranking, loc, nf, cands, steps, budget,
                         model)


def _decide(ranking, steps, g_before, nf, fit, holdout, axis):
    """The verdict: the first (dominant) effect forward selection kept, unless the
    excitation cannot tell it from another."""
    eff = [r for r in ranking if r["effect"] != "none"]
    if not eff:
        return "inconclusive", "no candidate effect could be tested"
    if not steps:
        if g_before <= 0.5 * nf:
            return "none", f"the residual is at the noise floor (gap {g_before:.3g} um, " \
                           f"noise {nf:.3g} um)"
        best = eff[0]
        return "inconclusive", (f"no candidate closes the gap ({g_before:.3g} um): best "
                                f"{best['effect']} shrinks it by {best['shrink_pct']:.0f} %")
    first = steps[0]["effect"]
    if first in ("creep", "drift"):
        if not holds(fit.v[axis], fit.fs_hz) or not holds(holdout.v[axis], holdout.fs_hz):
            return "inconclusive", (f"no holds longer than {MIN_HOLD_S:g} s: creep cannot be "
                                    "separated from drift")
    kept = [s["effect"] for s in steps]
    if len(eff) > 1 and eff[1]["gap_after_um"] <= eff[0]["gap_after_um"] * 1.02 + 1e-3 and \
            eff[1]["shrink_pct"] >= FIRST_SHRINK_PCT and eff[1]["effect"] not in kept:
        return "inconclusive", (f"{eff[0]['effect']} and {eff[1]['effect']} explain the gap "
                                "equally well on this excitation")
    said = ", then ".join(f"{s['effect']} to {s['gap_after_um']:.3g} um" + (
        f" ({' or '.join(s['equally_well'])} as well: not separable on this excitation)"
        if s["equally_well"] and i else "") for i, s in enumerate(steps))
    # one figure per claim: the effect alone as the table's row has it; the effects
    # joined as the table's joined row (gap.py's command prints it, named)
    row = next((r for r in ranking if r["effect"] == first), None)
    alone = row["shrink_pct"] if row is not None else steps[0]["shrink_pct"]
    joined = "+".join(s["effect"] for s in steps)
    return first, (f"{first} shrinks the held-out gap by {alone:.0f} % "
                   f"(chosen by {steps[0]['rule']})"
                   + (f"; with {said} ({joined}: {steps[-1]['shrink_pct']:.0f} % in all)"
                      if len(steps) > 1 else ""))
