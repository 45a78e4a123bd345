"""One axis's diagnosis: every candidate fitted on FIT and scored on HOLDOUT, forward
selection of the effects that shrink the held-out gap, and the verdict."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from piezo_stage.core.errors import DataError, ModelError
from piezo_stage.core.estimation.gap.budget import gap_above_floor, gap_budget, shrink_uncertainty
from piezo_stage.core.estimation.gap.candidates import (
    EFFECTS,
    INVERSE_MISS_FRACTION,
    MEMORY_CLASSES,
    TRANSFORMS,
    AxisWritten,
    Candidate,
    ClassCandidate,
    Fitted,
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
from piezo_stage.core.estimation.gap.written import held_out, predicted, start_up_samples
from piezo_stage.core.estimation.identify.api import check_identifiable
from piezo_stage.core.estimation.identify.fast import fit_fast
from piezo_stage.core.estimation.identify.segmentation import inner_reversals
from piezo_stage.core.estimation.record import Record
from piezo_stage.core.metrics import noise_floor, rms
from piezo_stage.core.model.duhem import OTHER, AxisParts, StageModel, voltage_limits_for
from piezo_stage.core.model.effects import effects_on
from piezo_stage.core.types import Doc, EffectsBlock, Params


class GivenModel:
    """A model from a file as the base ("the sim"): its axis and the effects its file
    gives that axis, run as ``simulate --model`` runs the file, like every candidate."""

    effect = "given"
    params: Params = {}

    def __init__(self, stage_model: StageModel, effects: EffectsBlock | None, axis: str) -> None:
        self.model, self.effects, self.axis = stage_model, effects, axis

    def written(self) -> AxisWritten:
        """The given model's axis as its file holds it."""
        a, m = self.axis, self.model
        return AxisWritten(AxisParts(m.axes[a], m.coupling.get(a), m.plays.get(a)),
                           effects_on(self.effects, a))


class IdentifiedModel:
    """What ``identify`` writes for FIT's axis (its Duhem law, coupling and lag, the lag as
    its delay effect): the model a lab has before any diagnosis, which the diagnosis
    never writes a worse one than on HOLDOUT (``AxisSearch.written_choice``)."""

    effect = "identify"
    params: Params = {}

    def __init__(self, res: Any) -> None:
        self.res = res

    def written(self) -> AxisWritten:
        """The model identify writes for the axis, as its file holds it."""
        effects = {"delay": {"delay_s": float(self.res.delay_s)}} if self.res.delay_s > 0 \
            else {}
        return AxisWritten(self.res.parts(), effects)


@dataclass
class AxisDiagnosis:
    """One axis's diagnosis: verdict, ranking, kept effects, budget, models."""
    axis: str
    verdict: str
    reason: str
    ranking: list
    where: Doc
    noise_floor_um: float
    candidates: Doc = field(default_factory=dict)
    effects: list = field(default_factory=list)    # forward selection: kept, in order
    budget: Doc = field(default_factory=dict)
    model: Fitted | None = None  # the model with every kept effect
    skip: int = 0  # HOLDOUT's samples run but not scored (written.start_up_samples)
    # what --out-model writes for the axis (AxisSearch.written_choice): the model, what
    # it is, and its held-out figures [um]
    written: Any = None
    written_as: str = ""
    written_rms_um: float = float("nan")
    written_gap_um: float = float("nan")


FIRST_SHRINK_PCT = 30.0  # the dominant effect must close this much of the held-out gap


STEP_SHRINK_PCT = 15.0   # each further effect this much of what is left


STEP_NOISE_SIGMAS = 2.0  # and that share must stand this many of its own standard
                         # deviations (shrink_uncertainty between the model before the
                         # step and after it) above nothing: no effect named for what
                         # another stretch of the same stage would not repeat


PAIR_POOL = 3           # no single effect closes the first 30 %: pairs among these best


POLISH_BUDGET = 24       # and for a kept one, polished


NOISE_STOP = 0.5         # a gap under this share of the noise floor is at the floor
                         # (the residual within 12 % of the noise RMS, which is itself
                         # estimated from the data: below it, a free term takes the
                         # last of what is left "by 100 %"); between it and the floor a further
                         # effect must close what the first must (FIRST_SHRINK_PCT):
                         # what is left there is near the noise, where a free term can
                         # shave a share off it (a coupling took 16 % of what a creep
                         # and a drift left at 0.8 x the noise), and an effect another
                         # one has mostly taken in (a drift after a coupling, when the
                         # axes are driven in turn: a step stands for 75 % of a ramp)
                         # closes nearly all of it


def further_need(g_left: float, floor: float) -> float:
    """The share [%] of what is left (``g_left``, the gap above the ``floor``) a
    further effect must close: STEP_SHRINK_PCT, or FIRST_SHRINK_PCT where what is left
    is below the floor (see NOISE_STOP)."""
    return FIRST_SHRINK_PCT if g_left < floor else STEP_SHRINK_PCT


LAG_ZETA = 0.5           # a resonance damped this much or more has a peak of at most
                         # 15 % (none from 1/sqrt(2)): a lag, not a mode that rings


def delay_shape(steps: list[dict[str, Any]]) -> str:
    """Marks a kept dynamics that is a lag beside a kept delay as the delay's shape at
    the samples (``shape_of``: it stays in the model, and is not named as an effect of
    its own). A delay seen through a command held over each period and the amplifier's
    slew is no pure shift at the samples: a delay found short plus a resonance damped
    at zeta 0.56-0.80 near 0.35 fs stood for it on 6 of 213 generated stages with a
    delay and no resonance, where the stages' own resonances are damped at 0.03-0.2.
    -> a note for the verdict's reason, or ""."""
    names = [st["effect"] for st in steps]
    if "delay" not in names or "dynamics" not in names:
        return ""
    st = steps[names.index("dynamics")]
    p = st["params"]
    zeta = float(p.get("zeta", 0.0)) if p.get("kind") == "resonance" else 0.0
    if zeta < LAG_ZETA:
        return ""
    st["shape_of"] = "delay"
    return (f"the dynamics kept beside the delay is a lag (a resonance at "
            f"{float(p['fn_hz']):.0f} Hz damped at zeta {zeta:.2f}: no mode that rings), "
            "the delay's shape at the samples (a held command and the amplifier's slew "
            "make a delay no pure shift there): named as the delay")


def _significant(rms_a: float, rms_b: float, nf: float, n: int) -> bool:
    """A held-out improvement counts when it is well above what chance gives on this
    many samples (the MSE of white noise fluctuates by nf^2 sqrt(2/N))."""
    return rms_a ** 2 - rms_b ** 2 > max(0.05 * nf ** 2, 10 * nf ** 2 * np.sqrt(2.0 / n))


def _given_effects(base_model: StageModel | None, base_effects: EffectsBlock | None,
                   axis: str) -> list[tuple[str, Doc]]:
    """What the user's model already has on this axis: never a candidate, and part of
    every candidate's fit. -> [(name, params)]."""
    out: list[tuple[str, Doc]] = []
    if base_model is None or axis not in base_model.axes:
        return out
    if axis in base_model.coupling:
        out.append(("coupling", {}))
    for name, p in (base_effects or {}).items():
        # (one block for both axes, or a list of blocks with their axes: a written
        # model's effects with each axis's own parameters)
        for q in (p if isinstance(p, list) else [p]):
            q = dict(q or {})
            if axis in q.pop("axes", ["x", "y"]) and name in TRANSFORMS + ("drift",):
                out.append((name, q))
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

@dataclass(frozen=True)
class SearchOptions:
    """What one axis's search tries and against what (``AxisSearch``, by keyword): the
    ``effects`` it may add, the sim to compare with (``base_model`` with the
    ``base_effects`` of its file; None: the Duhem model identified on FIT), the written
    models' voltage ``limits_V`` (None: from the records) and HOLDOUT's first
    ``history`` samples run but not scored; ``live``: the live watch's reading (``diagnose``;
    with a history, the sensor's zero is the history's)."""
    effects: tuple[str, ...] = tuple(EFFECTS)
    base_model: StageModel | None = None
    base_effects: EffectsBlock | None = None
    limits_V: tuple | None = None
    history: int = 0
    live: bool = False


def diagnose_axis(fit: Record, holdout: Record, axis: str, effects: Sequence[str] = EFFECTS,
                  base_model: StageModel | None = None,
                  progress: Callable[[str], None] | None = None,
                  base_effects: EffectsBlock | None = None,
                  limits_V: tuple | None = None, history: int = 0,
                  live: bool = False) -> AxisDiagnosis:
    """Fit every candidate on FIT, score on HOLDOUT, then add effects one at a time
    (forward selection, each refitted jointly with the Duhem model and the effects
    kept before it) while the held-out gap keeps shrinking clearly. ``base_model`` (a
    StageModel, with ``base_effects`` from its file) replaces the FIT-identified Duhem
    model as the sim to compare with; what it already has is not a candidate.
    ``progress(what)`` is called after each candidate is fitted; ``limits_V``, the
    amplifier's, are the written models' (the memory classes' thresholds reach half the
    span of FIT's and HOLDOUT's voltages: ``AxisSearch.reach_V``). HOLDOUT's
    first ``history`` samples are its history: every model runs over them (the stage's
    state at the scored part's start follows from them: a creep in progress is no
    drift), and only the rest is scored. The stages are AxisSearch's."""
    search = AxisSearch(fit, holdout, axis, SearchOptions(
        effects=tuple(effects), base_model=base_model, base_effects=base_effects,
        limits_V=limits_V, history=history, live=live), progress)
    cands = search.fit_candidates()
    ranking = search.rank(cands)
    steps, model = search.select(cands)
    return search.decide(ranking, steps, model, cands)


class AxisSearch:
    """One axis's diagnosis in its named stages (``diagnose_axis`` runs them in order):
    what can be tested (built), every candidate alone (``fit_candidates``; the forms of
    structure and the memory classes in ``structure_candidate``), each against the sim
    (``rank``), forward selection (``select``: the pair rule, ``pair_first``; a kept
    effect polished, ``polish``) and the verdict with its notes and budget
    (``decide``). A candidate is a Fitted: an effect's (Candidate) or a class's
    (ClassCandidate), judged alike by its held-out residual."""

    def __init__(self, fit: Record, holdout: Record, axis: str, options: SearchOptions,
                 progress: Callable[[str], None] | None = None) -> None:
        effects, base_model, base_effects = options.effects, options.base_model, \
            options.base_effects
        limits_V, history = options.limits_V, options.history
        self.live = options.live
        self.progress = progress or _quiet
        for rec in (fit, holdout):
            if axis not in rec.v or axis not in rec.w:
                raise DataError(f"{rec.source}: no v{axis}/w{axis} for axis {axis}")
        # every held-out figure is the written model's, run from its file's initial
        # state over all of HOLDOUT; scored after its start-up (gap/written.py)
        self.skip = start_up_samples(len(holdout), holdout.fs_hz, history)
        self.scored = holdout.slice(self.skip, len(holdout)) if self.skip else holdout
        for rec in (fit, self.scored):
            check_identifiable(rec.v[axis], rec.source)
        self.fit, self.holdout, self.axis, self.history = fit, holdout, axis, history
        self.nf_fit = noise_floor(fit.w[axis])  # FIT's own noise (shows_on_fit)
        self.base_model, self.base_effects = base_model, base_effects
        # the limits of the models written (diagnose gives those of every axis)
        self.limits_V = voltage_limits_for([fit.v[axis], holdout.v[axis]], limits_V)
        # how far the memory classes' operators reach: half the span of the voltages
        # the models are fitted and scored on (a threshold past every excursion there
        # never moves: it is no term of the fit), not an amplifier's range far beyond
        # them (0-150 V for a 0-3.6 V input made every operator a constant there, and
        # the verdict turned on --limits)
        both = np.concatenate([fit.v[axis], holdout.v[axis]])
        self.reach_V = (float(both.min()), float(both.max()))
        self._resid: dict[int, tuple[Any, np.ndarray]] = {}  # id -> (model, residual)
        self.notes: list[str] = []
        if holdout is fit:
            self.notes.append("no HOLDOUT: scored on FIT itself, where extra freedom is "
                              "not penalised (record the excitation twice)")
        self.given = self._given(base_effects)
        self.testable = self._testable(effects)
        self.no_band = "dynamics" in self.testable and "delay" in self.testable and \
            not broadband(fit.v[axis], fit.fs_hz)
        self.rates = several_rates(fit.v[axis], fit.fs_hz)
        # the classes' held-out RMS over the Duhem law's best structure form, the first
        # time both were fitted: far behind (a stage of the Duhem law's own class), they
        # are not fitted again with the effects kept later (they cost more than any
        # other candidate)
        self.class_tried: list[float] = []
        # the first effect, closer on HOLDOUT alone (it fits FIT no closer: shows_on_fit)
        self.refused: Fitted | None = None

    def _given(self, base_effects: EffectsBlock | None) -> list[tuple[str, Doc]]:
        given = _given_effects(self.base_model, base_effects, self.axis)
        vo_fit = self.fit.v.get(OTHER[self.axis])
        if any(n == "coupling" for n, _ in given) and (vo_fit is None or np.ptp(vo_fit) < 1.0):
            # the model's coupling term has nothing to be fitted on where the other axis
            # rests (a protocol that drives the axes in turn): it adds a constant there
            given = [(n, p) for n, p in given if n != "coupling"]
            self.notes.append("the model's coupling is left out: the other axis's voltage "
                              "does not move in FIT")
        return given

    def _testable(self, effects: Sequence[str]) -> list[str]:
        testable = []
        for e in effects:
            if e in [n for n, _ in self.given]:
                continue  # the sim has it already
            if e == "coupling":
                other = OTHER[self.axis]
                vo_f, vo_h = self.fit.v.get(other), self.holdout.v.get(other)
                if vo_f is None or vo_h is None or np.ptp(vo_f) < 1.0:
                    self.notes.append("coupling not tested: the other axis's voltage does "
                                      "not move")
                    continue
            testable.append(e)
        return testable

    def resid_of(self, c: Fitted | GivenModel | None) -> np.ndarray:
        """A model's held-out residual over the scored part: the model as written, run
        over HOLDOUT as ``simulate --model`` runs the file, its mean offset removed
        (gap/written.py)."""
        assert c is not None
        hit = self._resid.get(id(c))
        if hit is not None and hit[0] is c:
            return hit[1]
        try:
            pred = predicted(c.written(), self.axis, self.holdout, self.limits_V)
            if self.live and self.history:
                # the live watch: the sensor's zero is the one over the history (FIT,
                # where the model was fitted), so a level that moves since is a gap (a
                # drift), not an offset of the held-out part
                full = np.asarray(pred, float) - np.asarray(self.holdout.w[self.axis], float)
                r = full[self.skip:] - full[:self.skip].mean()
            else:
                r = held_out(pred, self.holdout.w[self.axis], self.skip)
        except ModelError as e:  # no model file would hold it (no stage): no candidate
            c.params = {**getattr(c, "params", {}), "not_writable": str(e)}
            r = np.full(len(self.scored.t), np.inf)
        if not np.all(np.isfinite(r)):  # a model that diverges there: no candidate
            r = np.full(r.shape, np.inf)
        self._resid[id(c)] = (c, r)  # (the model kept: its id is not reused meanwhile)
        return r

    def forget(self, c: Fitted) -> None:
        """``c`` changed (polished): its held-out residual is computed again."""
        self._resid.pop(id(c), None)

    # -- the candidates -------------------------------------------------------------------
    def candidate(self, e: str, on: Fitted, kept: list) -> Fitted:
        """A candidate: fit_candidate; structure in its forms (``structure_candidate``). On a class
        (``on`` a ClassCandidate) the effect is added to the class (fit_class_effect)
        and to its twin, the Duhem law's best form with the same effects; the closer of
        the two on HOLDOUT is the candidate (the class's twin the law's)."""
        fit, axis = self.fit, self.axis
        if isinstance(on, ClassCandidate):
            assert on.twin is not None  # a class is kept with its twin (below)
            law = self.candidate(e, on.twin, on.twin.effects)
            k = fit_class_effect(fit, axis, on, e, law, self.reach_V) \
                if isinstance(law, Candidate) else None
            if k is None or not isinstance(law, Candidate):
                return law
            k.twin = law
            r_law = rms(self.resid_of(law))
            return k if rms(self.resid_of(k)) <= r_law else law
        assert isinstance(on, Candidate)
        law = fit_candidate(fit, axis, e, on, kept)  # the best form of the Duhem law
        return self.structure_candidate(law, on, kept) if e == "structure" else law

    def structure_candidate(self, law: Candidate, on: Candidate, kept: list) -> Fitted:
        """Structure: the richer branches (``law``), with play operators (memory), where
        FIT holds several rates with their thresholds widened by the rate (rate), and
        memory as the Prandtl-Ishlinskii or the discretized Preisach class in place of
        the Duhem law, with the effects kept before it: the one closest on HOLDOUT, so
        memory and rate are named only where they pay. A form whose exact inverse does
        not give the records' voltages back (a branch turning back) must be closer by
        10 % than the best before it (NOT_INVERTIBLE_PAYS)."""
        fit, axis, limits_V, e = self.fit, self.axis, self.limits_V, "structure"
        both = np.concatenate([fit.v[axis], self.holdout.v[axis]])
        best = rms(self.resid_of(law))
        tried = not self.class_tried or self.class_tried[0] <= CLASS_WITH_EFFECTS
        classes = [(k, rms(self.resid_of(k)))
                   for k in (fit_class_candidate(fit, axis, self.reach_V, kind, on, kept)
                             for kind in (MEMORY_CLASSES if tried else ()))]
        for form in (("memory", "rate") if self.rates else ("memory",)):
            m = fit_candidate(fit, axis, e, on, kept, memory=True, rate=form == "rate")
            if m.effect == "rate" and not m.params.get("rate_widening_s"):
                continue  # no widening fits FIT better: memory already
            r = rms(self.resid_of(m))
            if r < best:
                if r > NOT_INVERTIBLE_PAYS * min([best] + [x[1] for x in classes]) \
                        and m.inverse_miss(both, fit.fs_hz, limits_V) > \
                        INVERSE_MISS_FRACTION:
                    continue  # a branch turns back, for little: the exact inverse wins
                law, best = m, r
        if not self.class_tried and classes:  # the first try: how close the classes came
            self.class_tried.append(min(r for _, r in classes) / best if best > 0 else 0.0)
        c: Fitted = law
        for k, r in classes:
            if r < best:
                c, best = k, r
        if isinstance(c, ClassCandidate):  # a class came closer than the law
            c.twin = law
        return c

    def fit_candidates(self) -> dict[str, Fitted]:
        """The sim's own fit ("none") and every testable effect alone on top of it."""
        base = fit_candidate(self.fit, self.axis, "none", kept=self.given)
        self.progress(f"{self.axis} none")
        cands: dict[str, Fitted] = {"none": base}
        for e in self.testable:
            cands[e] = self.candidate(e, base, base.effects)
            self.progress(f"{self.axis} {e}")
        self.base = base
        return cands

    # -- the ranking -----------------------------------------------------------------------
    def rank(self, cands: dict[str, Fitted]) -> list[dict[str, Any]]:
        """Each candidate against the sim on HOLDOUT: the gap above the noise floor (and
        a line the input does not cause) before and after it, best first."""
        scored, axis = self.scored, self.axis
        self.nf = nf = noise_floor(scored.w[axis])
        self.n = len(scored.w[axis])
        sim: Fitted | GivenModel = GivenModel(self.base_model, self.base_effects, axis) \
            if self.base_model is not None and axis in self.base_model.axes else self.base
        self.resid = resid = self.resid_of(sim)
        self.r_before = r_before = rms(resid)
        if not np.isfinite(r_before):
            raise DataError(f"axis {axis}: the sim's model cannot be run over HOLDOUT "
                            f"({sim.params.get('not_writable', 'it diverges')}): nothing "
                            "to compare the candidates with")
        # a line the input does not cause (a floor vibration) is no model's to close: for
        # choosing effects it counts with the noise (the gap is what a model could close)
        dist0 = disturbance(scored, axis, resid, nf)
        self.floor = floor = float(np.hypot(nf, dist0["rms_um"])) if dist0 else nf
        self.g_before = g_before = gap_above_floor(r_before, floor)
        resids = {e: self.resid_of(c) for e, c in cands.items()}
        if sim is not self.base:  # "none" is the sim as given: a candidate that changes nothing
            resids["none"] = resid
        self.scores: dict[str, float] = {e: rms(r) for e, r in resids.items()}
        ranking: list[dict[str, Any]] = []
        for e, c in cands.items():
            g_after = gap_above_floor(self.scores[e], floor)
            ranking.append({"effect": c.effect, "rms_before_um": r_before,
                            "rms_after_um": self.scores[e],
                            "gap_before_um": g_before, "gap_after_um": g_after,
                            "shrink_pct": 100.0 * (1 - g_after / g_before)
                            if g_before > 0 else 0.0,
                            "shrink_pm_pct": shrink_uncertainty(resid, resids[e], floor,
                                                                scored.fs_hz),
                            "fit_rms_um": c.fit_rms_um, "params": c.params,
                            "shows_on_fit": e == "none" or self.shows_on_fit(c, None)})
        ranking.sort(key=lambda r: r["gap_after_um"])
        return ranking

    # -- forward selection -------------------------------------------------------------------
    def select(self, cands: dict[str, Fitted]) -> tuple[list[dict[str, Any]], Fitted | None]:
        """Forward selection: the best candidate joins when it shrinks the held-out gap
        clearly; the rest are refitted with it in place and tried again. -> (the steps
        kept, the model with every kept effect or None)."""
        floor, g_before, scores = self.floor, self.g_before, self.scores
        steps: list[dict[str, Any]] = []
        model: Fitted | None = None
        r_cur = self.r_before
        # (all stay in: creep that explains nothing alone shows once a coupling is in)
        pool = {e: cands[e] for e in self.testable}
        # (a, b): b fitted on top of a, and its held-out RMS (the pairs)
        tried: dict[tuple[str, str], tuple[Fitted, float]] = {}
        partner: str | None = None  # the second of a pair its first joined for: next
        while pool:
            if (nxt := self.next_try(pool, model, bool(steps), partner)) is None:
                break
            e, c = nxt
            g_cur, g_new = gap_above_floor(r_cur, floor), gap_above_floor(scores[e], floor)
            need = (50.0 if g_before <= 0.5 * floor else FIRST_SHRINK_PCT) if not steps \
                else further_need(g_cur, floor)
            step = 100.0 * (1 - g_new / g_cur) if g_cur > 0 else 0.0
            rule = (f"the first-effect rule: it alone closes >= {need:.0f} % of the gap"
                    if not steps else f"the further-effect rule: it closes >= {need:.0f} % "
                    "of what was left")
            if not steps and step < need and len(pool) > 1 and g_before > 0.5 * floor:
                paired = self.pair_first(pool, r_cur, g_cur, need, tried)
                if paired is not None:
                    e, c, g_new, step, rule, partner = paired
                    need = 0.0  # the first of a pair that closes the gap together
            elif e == partner:
                rule = (f"the pair rule: the second of the pair {steps[0]['effect']} joined "
                        f"for; it closes >= {need:.0f} % of what was left")
            if not (_significant(r_cur, scores[e], floor, self.n) and step >= need):
                break
            if need > 0.0 and self.unshown(c, model, step, first=not steps):
                break
            # a further effect's step, bootstrapped over HOLDOUT against the model before it
            step_pm = shrink_uncertainty(self.resid_of(model), self.resid_of(c), floor,
                                         self.scored.fs_hz) if steps else float("nan")
            # (a pair's second was judged with its first: admitting the first alone, for
            # a shrink it does not make alone, would keep half of what the data showed)
            pair_second = bool(steps) and e == partner
            if steps:
                partner = None  # tried once, right after its first
            if steps and not pair_second and np.isfinite(step_pm) \
                    and step < STEP_NOISE_SIGMAS * step_pm:
                break  # within the noise of the step itself
            # what fits as well at this step (the excitation cannot tell them apart)
            alike = [e2 for e2 in pool if e2 != e and gap_above_floor(scores[e2], floor) <=
                     1.02 * g_new + 0.02 * (g_cur - g_new)]
            if steps and not pair_second and len(alike) >= 2 and len(alike) == len(pool) - 1:
                break  # every candidate helps alike: the refit helps, not any one effect
            steps.append({"effect": c.effect, "params": c.params, "rms_after_um": scores[e],
                          "gap_after_um": g_new, "step_shrink_pct": step,
                          "shrink_pct": 100.0 * (1 - g_new / g_before) if g_before else 0.0,
                          "equally_well": alike, "rule": rule, "step_pm_pct": step_pm})
            self.polish(c, e, steps[-1])
            g_new = steps[-1]["gap_after_um"]
            steps[-1]["shrink_pm_pct"] = shrink_uncertainty(
                self.resid, self.resid_of(c), floor, self.scored.fs_hz)
            model, r_cur = c, scores[e]
            del pool[e]
            if g_new <= NOISE_STOP * floor:
                break  # at the noise floor (itself estimated): nothing left to explain
            for e2 in list(pool):
                if len(steps) == 1 and (e, e2) in tried:
                    # fitted already as a pair on top of the effect just kept
                    pool[e2], scores[e2] = tried[(e, e2)]
                else:
                    pool[e2] = self.candidate(e2, model, model.effects)
                    scores[e2] = rms(self.resid_of(pool[e2]))
                self.progress(f"{self.axis} {'+'.join(x['effect'] for x in steps)}+{e2}")
        if len(steps) >= 2 and model is not None:
            steps, model = self.prune(steps, model, cands)
        if model is not None:  # each effect's parameters as finally refitted (drift's)
            final = dict(model.effects)
            for st in steps:
                st["params"] = final.get(st["effect"], st["params"])
        self.notes.extend(filter(None, [delay_shape(steps)]))  # a delay's lag, said
        return steps, model

    def next_try(self, pool: dict[str, Fitted], model: Fitted | None, kept: bool,
                 partner: str | None) -> tuple[str, Fitted] | None:
        """The candidate forward selection tries next: the partner a pair's first
        joined for, else the closest on HOLDOUT of those that fit FIT closer than
        ``model`` (``shows_on_fit``); with none kept yet and none such, the closest of
        all (a pair may take it). None: nothing to try."""
        shown = {e: c for e, c in pool.items() if self.shows_on_fit(c, model)}
        if partner is not None and partner in pool:
            # (the pair's second must add something on FIT to its first)
            return (partner, pool[partner]) if partner in shown else None
        if shown:
            return min(shown.items(), key=lambda kv: self.scores[kv[0]])
        return None if kept else min(pool.items(), key=lambda kv: self.scores[kv[0]])

    def shows_on_fit(self, c: Fitted, before: Fitted | None) -> bool:
        """Whether ``c`` fits FIT clearly closer than ``before`` (None: the sim fitted
        on FIT), by what ``_significant`` asks of a held-out step, judged with FIT's own
        noise: an effect shows on the record its parameters were fitted on. A candidate
        that fits FIT no closer and yet is closer on HOLDOUT is the same fit at another
        point of a flat valley (a coupling term and the law trading their constants on
        a record that drives the axes in turn), extrapolated differently there: chance,
        not an effect (a coupling named after a creep, a memory on a stage with no
        effect, on 3 of 134 generated stages). Where HOLDOUT continues FIT (a history:
        the live watch, a record's later part held out) it does not apply: an effect
        that grows with time (a creep switching on in the window) shows mostly after
        FIT, where a law refitted on FIT's few seconds of it fits FIT as closely."""
        if self.history:
            return True
        b = (before or self.base).fit_rms_um
        return bool(np.isfinite(c.fit_rms_um)) and _significant(
            b, c.fit_rms_um, self.nf_fit, len(self.fit.t))

    def unshown(self, c: Fitted, before: Fitted | None, step: float, first: bool) -> bool:
        """Whether ``c``, which passed the held-out rules with ``step`` %, fits FIT no
        closer than ``before`` (``shows_on_fit``): then it is not kept, the reason says
        why, and as the first effect it is the form ``written_choice`` weighs."""
        if self.shows_on_fit(c, before):
            return False
        self.notes.append(self.fit_note(c, before, step))
        if first:
            self.refused = c
        return True

    def fit_note(self, c: Fitted, before: Fitted | None, step: float) -> str:
        """Why ``c``, closer on HOLDOUT, was not kept (``shows_on_fit``)."""
        b = (before or self.base).fit_rms_um
        return (f"{c.effect} closes {step:.0f} % of the held-out gap but fits FIT no "
                f"closer ({c.fit_rms_um:.4g} against {b:.4g} um, FIT's noise "
                f"{self.nf_fit:.3g} um): another point of the same fit, not an effect")

    def chain(self, names: Sequence[str], cache: dict[tuple[str, ...], Fitted]) -> list[Fitted]:
        """The models of the effects ``names`` added to the sim in this order, each
        fitted on the one before it (as forward selection fits them): [after the
        first, after the second, ...]; ``cache`` keeps each prefix's."""
        out: list[Fitted] = []
        m: Fitted = self.base
        # (memory and rate are forms of the structure candidate: fitted as it is)
        names = ["structure" if e in ("memory", "rate") else e for e in names]
        for i, e in enumerate(names):
            key = tuple(names[:i + 1])
            if key not in cache:
                cache[key] = self.candidate(e, m, m.effects)
            m = cache[key]
            out.append(m)
        return out

    def prune(self, steps: list[dict[str, Any]], model: Fitted,
              cands: dict[str, Fitted]) -> tuple[list[dict[str, Any]], Fitted]:
        """Backward elimination, stepwise selection's second half: each kept effect is
        left out in turn (the others refitted in their order); one whose return on top
        of the others closes less than the further-effect rule asks of a step, or less
        than twice its own bootstrap spread, was another effect's stand-in when it
        joined (a resonance standing in for a delay found later, a coupling for what a
        drift left): it is dropped, and the rest judged again. The steps' figures are
        then those of the chain that is left. One the others reach the floor without
        (NOISE_STOP) is dropped too: forward selection would have stopped there."""
        floor, fs = self.floor, self.scored.fs_hz
        cache: dict[tuple[str, ...], Fitted] = {(e,): c for e, c in cands.items() if e != "none"}
        dropped = False
        while len(steps) >= 2:
            r_all = self.resid_of(model)
            g_all = gap_above_floor(rms(r_all), floor)
            worst = None
            for i in range(len(steps)):
                rest = [s["effect"] for j, s in enumerate(steps) if j != i]
                m = self.chain(rest, cache)[-1]
                r = self.resid_of(m)
                g = gap_above_floor(rms(r), floor)
                step = 100.0 * (1 - g_all / g) if g > 0 else 0.0
                pm = shrink_uncertainty(r, r_all, floor, fs)
                if g <= NOISE_STOP * floor or step < further_need(g, floor) or (
                        np.isfinite(pm) and step < STEP_NOISE_SIGMAS * pm):
                    if worst is None or step < worst[0]:
                        worst = (step, i)
            if worst is None:
                break
            gone, dropped = steps.pop(worst[1]), True
            self.notes.append(f"{gone['effect']} left out: on top of the others it closed "
                              f"{worst[0]:.0f} % of what they leave (a stand-in for one "
                              "found later)")
        if not dropped:
            return steps, model
        # what is left, the best alone first (the verdict's effect), each on the last
        key = {"memory": "structure", "rate": "structure"}
        steps.sort(key=lambda st: self.scores.get(key.get(st["effect"], st["effect"]),
                                                  np.inf))
        names = [s["effect"] for s in steps]
        models = self.chain(names, cache)
        for i, st in enumerate(steps):
            st["rule"] = ("backward elimination: the effects left, the best alone first"
                          if i == 0 else "backward elimination: it closes >= "
                          f"{STEP_SHRINK_PCT:.0f} % of what the others leave")
        before = self.resid
        for st, m in zip(steps, models):  # the chain's own figures, step by step
            r = self.resid_of(m)
            r_now = rms(r)
            g_prev = gap_above_floor(rms(before), floor)
            g_now = gap_above_floor(r_now, floor)
            st.update(effect=m.effect, rms_after_um=r_now, gap_after_um=g_now,
                      step_shrink_pct=100.0 * (1 - g_now / g_prev) if g_prev > 0 else 0.0,
                      shrink_pct=100.0 * (1 - g_now / self.g_before) if self.g_before else 0.0,
                      shrink_pm_pct=shrink_uncertainty(self.resid, r, floor, fs),
                      step_pm_pct=shrink_uncertainty(before, r, floor, fs)
                      if st is not steps[0] else float("nan"))
            before = r
        return steps, models[-1]

    def pair_first(self, pool: dict[str, Fitted], r_cur: float, g_cur: float, need: float,
                   tried: dict[tuple[str, str], tuple[Fitted, float]]
                   ) -> tuple[str, Fitted, float, float, str, str] | None:
        """The pair rule: effects of similar size, none alone closes 30 %; two of the
        three best together may (the better one of the best such pair joins first; the
        other is tried next, on top of it, and joins when it still closes its share of
        what was left: the pair was judged against the noise as a pair). -> (effect,
        candidate, gap after it, its step %, the rule, the other) or None."""
        floor, scores = self.floor, self.scores
        top = sorted(pool, key=scores.__getitem__)[:PAIR_POOL]
        pairs = [(a, b) for i, a in enumerate(top) for b in top[i + 1:]]
        if "delay" in pool and "dynamics" in pool and not {"delay", "dynamics"} <= set(top):
            # a resonance seen through a delay: neither alone may fit at all
            d0, d1 = sorted(("delay", "dynamics"), key=scores.__getitem__)
            pairs.append((d0, d1))
        best_pair = None
        for a0, b0 in pairs:
            # in both orders: the one fitted first can take the other's part (a lag-like
            # resonance fitted before a delay, and the delay on top then closes little)
            for a, b in ((a0, b0), (b0, a0)):
                first = pool[a]
                pair = self.candidate(b, first, first.effects)
                self.progress(f"{self.axis} {a}+{b}")
                r_pair = rms(self.resid_of(pair))
                tried[(a, b)] = (pair, r_pair)
                g_pair = gap_above_floor(r_pair, floor)
                g_a = gap_above_floor(scores[a], floor)
                if 100.0 * (1 - g_pair / g_cur) >= need \
                        and _significant(r_cur, r_pair, floor, self.n) \
                        and self.shows_on_fit(pair, None) \
                        and 100.0 * (1 - g_pair / g_a) >= STEP_SHRINK_PCT \
                        and (best_pair is None or g_pair < best_pair[0]):
                    best_pair = (g_pair, a, b)
        if best_pair is None:
            return None
        e = best_pair[1]
        g_new = gap_above_floor(scores[e], floor)
        step = 100.0 * (1 - g_new / g_cur) if g_cur > 0 else 0.0
        rule = (f"the pair rule: {e} and {best_pair[2]} together close "
                f"{100.0 * (1 - best_pair[0] / g_cur):.0f} % of the gap (>= "
                f"{need:.0f} %), which no effect does alone")
        return e, pool[e], g_new, step, rule, best_pair[2]

    def polish(self, c: Fitted, e: str, step: dict[str, Any]) -> None:
        """A kept effect's alphas polished fully, so that what the next candidates earn
        is theirs and not a better alpha search riding along (the other class has
        none); kept where HOLDOUT agrees (``step`` and the score updated)."""
        if not isinstance(c, Candidate):
            return
        alphas, fitted, _ = fit_fast(c.reg, budget=POLISH_BUDGET, x0=c.alphas, step=0.1)
        if not fitted.rms < c.fit_rms_um:
            return
        was = (c.alphas, c.theta, c.fit_rms_um, c.effects)
        c.alphas, c.theta, c.fit_rms_um = alphas, fitted.theta, fitted.rms
        c.effects = with_drift(c.effects, c.reg, c.theta, c.drift_tau_s)
        self.forget(c)
        polished = rms(self.resid_of(c))
        if polished <= self.scores[e]:
            self.scores[e] = polished
            g_new = gap_above_floor(polished, self.floor)
            step.update(rms_after_um=polished, gap_after_um=g_new,
                        shrink_pct=100.0 * (1 - g_new / self.g_before)
                        if self.g_before else 0.0)
        else:  # closer on FIT, further on HOLDOUT: the extra freedom overfits
            c.alphas, c.theta, c.fit_rms_um, c.effects = was
            self.forget(c)

    # -- the verdict ---------------------------------------------------------------------------
    def decide(self, ranking: list[dict[str, Any]], steps: list[dict[str, Any]],
               model: Fitted | None, cands: dict[str, Fitted]) -> AxisDiagnosis:
        """The verdict and its reason (``_decide``), the notes on what the records can
        and cannot tell, where the gap lies, its budget and a line the input does not
        cause."""
        fit, scored, axis, nf = self.fit, self.scored, self.axis, self.nf
        notes = self.notes
        loc = where(scored, axis, self.resid, nf)
        verdict, reason = _decide(ranking, steps, self.g_before, self.floor, fit, scored,
                                  axis, self.told_apart(ranking, steps, model, cands),
                                  self.live)
        if verdict in ("none", "inconclusive"):
            steps, model = [], None
        if self.no_band and ({"delay", "dynamics"} & {st["effect"] for st in steps}
                             or "delay and dynamics" in reason
                             or "dynamics and delay" in reason):
            notes.append("no broadband excitation (no chirp): a resonance above the "
                         "excitation's tones cannot be told from a delay (record the "
                         "protocol with its chirp: `excite` without `--chirp 0`)")
        rate_note = one_rate_note(fit, scored, axis) if fit is not self.holdout else None
        if rate_note:
            notes.append(rate_note)
        if not any(inner_reversals(r.v[axis]) for r in (fit, scored)):
            notes.append("FIT and HOLDOUT hold no minor loops (their reversals lie at their "
                          "ends): the forms with memory were judged on major loops alone, "
                          "not on the minor loops where they differ, and a written model's "
                          "minor loops are untested; record nested loops to tell (`excite "
                          "--nested`; `identify --class auto` chooses the "
                          "Prandtl-Ishlinskii class for such a record)")
        if notes:
            reason = (reason + "; " if reason else "") + "; ".join(notes)
        left = self.resid_of(model) if model is not None else self.resid
        dist = disturbance(scored, axis, left, nf)
        budget = gap_budget(scored, axis, self.resid, nf, self.g_before, steps)
        budget["disturbance"] = dist
        g_left = budget["unexplained_um"]
        if dist is not None and (not steps or dist["rms_um"] >= g_left):
            # what is left is mostly a line no model of the input removes
            said = (f"disturbance: {dist['rms_um']:.3g} um at {dist['freq_hz']:.1f} Hz, "
                    f"not caused by the input (reject it with >= "
                    f"{dist['feedback_bandwidth_hz']:.0f} Hz of feedback bandwidth)")
            if verdict == "none":
                verdict, reason = "disturbance", said
            else:
                reason += "; what is left is a " + said
        written, written_as, r_written = self.written_choice(model)
        if not (written is model or (model is None and written is self.base)):
            reason += (f"; the model written is {written_as} (held-out RMS "
                       f"{r_written:.4g} um), closer on HOLDOUT than "
                       f"{'the kept effects' if model is not None else 'the sim'}' "
                       f"({rms(self.resid_of(model or self.base)):.4g} um)")
        return AxisDiagnosis(axis, verdict, reason, ranking, loc, nf, cands, steps, budget,
                             model, self.skip, written, written_as, r_written,
                             gap_above_floor(r_written, self.floor))

    def told_apart(self, ranking: list[dict[str, Any]], steps: list[dict[str, Any]],
                   model: Fitted | None, cands: dict[str, Fitted]) -> bool:
        """Whether the two effects that explain the gap alike on their own (the
        ranking's best two; one kept, the other not) are told apart by the others kept:
        the kept model with the other in place of the kept one is further on HOLDOUT
        by more than the 2 % ``_decide`` calls alike (a delay and a resonance alike
        alone, told apart once the coupling beside them is modelled)."""
        eff = [r["effect"] for r in ranking if r["effect"] != "none"]
        names = [st["effect"] for st in steps]
        if model is None or len(names) < 2 or len(eff) < 2:
            return False
        key = {"memory": "structure", "rate": "structure"}
        kept = [key.get(n, n) for n in names]
        a, b = (key.get(e, e) for e in eff[:2])
        if (a in kept) == (b in kept):
            return False
        old, new = (a, b) if a in kept else (b, a)
        other = self.chain([new if n == old else n for n in kept], {})[-1]
        return rms(self.resid_of(other)) > 1.02 * rms(self.resid_of(model)) + 1e-3

    def written_choice(self, model: Fitted | None) -> tuple[Any, str, float]:
        """What ``--out-model`` writes for the axis: the model with the kept effects (the
        sim's own fit where none was kept), unless the model a lab already has does
        better on HOLDOUT: the given model (``--model``), else what ``identify`` writes
        for FIT. -> (the model, what it is, its held-out RMS [um])."""
        own = model if model is not None else self.base
        r_own = rms(self.resid_of(own))
        name = "the model with the kept effects" if model is not None else "the sim's fit"
        rival: Any = None
        if self.base_model is not None and self.axis in self.base_model.axes:
            rival, rival_name = GivenModel(self.base_model, self.base_effects,
                                           self.axis), "the given model (--model)"
        else:
            from piezo_stage.core.errors import SolverError
            from piezo_stage.core.estimation.identify.api import identify_axis
            try:
                rival = IdentifiedModel(identify_axis(self.fit, self.axis))
                rival_name = "identify's model of FIT"
            except (DataError, SolverError):
                rival = None
        best = (own, name, r_own)
        if rival is not None:
            r = rms(self.resid_of(rival))
            if r < r_own:
                best = (rival, rival_name, r)
        if model is None and self.refused is not None:
            # a form that carries further past FIT (a larger stroke held out) but fits
            # FIT no closer: not named, and written where it is the closest on HOLDOUT,
            # said so (the figure is the file's, chosen on HOLDOUT as the rival is)
            r = rms(self.resid_of(self.refused))
            if r < best[2]:
                best = (self.refused, f"{self.refused.effect}'s form (not named: it fits "
                        "FIT no closer, an extrapolation, not an effect FIT shows)", r)
        return best


def _decide(ranking: list[Doc], steps: list[Doc], g_before: float, nf: float, fit: Record,
            holdout: Record, axis: str, told_apart: bool = False, live: bool = False
            ) -> tuple[str, str]:
    """The verdict: the first (dominant) effect forward selection kept, unless the
    excitation cannot tell it from another (``told_apart``: the effects kept beside it
    do: AxisSearch.told_apart), or it is creep or drift and the records hold still
    nowhere; ``live`` (the watch's reading, ``diagnose``): neither makes it
    inconclusive, an effect alike is said beside the one kept."""
    eff = [r for r in ranking if r["effect"] != "none"]
    if not eff:
        return "inconclusive", "no candidate effect could be tested"
    if not steps:
        if g_before <= 0.5 * nf:
            return "none", f"the residual is at the noise floor (gap {g_before:.3g} um, " \
                           f"noise {nf:.3g} um)"
        best = eff[0]
        if not best.get("shows_on_fit", True):
            return "inconclusive", (
                f"no candidate both closes the gap ({g_before:.3g} um) and fits FIT "
                f"closer: {best['effect']} shrinks it by {best['shrink_pct']:.0f} % on "
                "HOLDOUT alone")
        return "inconclusive", (f"no candidate closes the gap ({g_before:.3g} um): best "
                                f"{best['effect']} shrinks it by {best['shrink_pct']:.0f} %")
    lead = steps[0]  # (a lag kept first as a delay's shape: the verdict is the delay)
    first = lead.get("shape_of") or lead["effect"]
    if first in ("creep", "drift") and not live:
        if not holds(fit.v[axis], fit.fs_hz) or not holds(holdout.v[axis], holdout.fs_hz):
            return "inconclusive", (f"no holds longer than {MIN_HOLD_S:g} s: creep cannot be "
                                    "separated from drift")
    kept = [s["effect"] for s in steps]
    alike = [e["effect"] for e in eff[:2] if e["effect"] not in kept]
    if len(eff) > 1 and eff[1]["gap_after_um"] <= eff[0]["gap_after_um"] * 1.02 + 1e-3 and \
            eff[1]["shrink_pct"] >= FIRST_SHRINK_PCT and eff[1]["effect"] not in kept \
            and not told_apart:
        if not live:
            return "inconclusive", (f"{eff[0]['effect']} and {eff[1]['effect']} explain "
                                    "the gap equally well on this excitation")
    else:
        alike = []
    said = ", then ".join(f"{s['effect']} to {s['gap_after_um']:.3g} um" + (
        f" ({' or '.join(s['equally_well'])} as well: not separable on this excitation)"
        if s["equally_well"] and i else "") for i, s in enumerate(steps))
    # one figure per claim: the effect alone as the table's row has it; the effects
    # joined as the table's joined row (gap.py's command prints it, named)
    row = next((r for r in ranking if r["effect"] == first), None)
    alone = row["shrink_pct"] if row is not None else lead["shrink_pct"]
    joined = "+".join(s["effect"] for s in steps)
    return first, (f"{first} shrinks the held-out gap by {alone:.0f} % "
                   f"(chosen by {lead['rule']})"
                   + (f"; with {said} ({joined}: {steps[-1]['shrink_pct']:.0f} % in all)"
                      if len(steps) > 1 else "")
                   + (f"; {' and '.join(alike)} explains it as well on this excitation "
                      f"(alike: {first} is the one kept)" if alike else ""))
