"""The gap diagnosis's candidates: each a model (the Duhem base with effects) fitted
on FIT together with the Duhem coefficients (the searches of their parameters in
``searches``, the effects as column operators in ``operators``)."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Protocol

import numpy as np
from numpy.typing import ArrayLike
from scipy import signal

from piezo_stage.core.errors import DataError
from piezo_stage.core.estimation.gap.operators import (  # noqa: F401 (the package's names)
    CREEP_TAUS,
    TRANSFORMS,
    effect_operator,
    transform_ops,
)
from piezo_stage.core.estimation.gap.searches import (
    PLAY_STARTS,
    columns_without,
    delay_rows,
    play_start_columns,
    rate_search,
    search_1d,
    search_transform,
)
from piezo_stage.core.estimation.identify.api import free_response
from piezo_stage.core.estimation.identify.fast import fit_fast
from piezo_stage.core.estimation.identify.prandtl import (
    OPERATORS,
    Around,
    PrandtlIshlinskii,
    fit_pi_class,
    nonneg_family_rms,
)
from piezo_stage.core.estimation.identify.preisach import fit_preisach_class
from piezo_stage.core.estimation.identify.regress import (
    DuhemRegression,
    Fit,
    coupling_term,
)
from piezo_stage.core.estimation.record import Record
from piezo_stage.core.model.duhem import (
    OTHER,
    AxisParts,
    DuhemModel,
    DuhemState,
    voltage_limits_for,
)
from piezo_stage.core.model.effects import Creep, Drift
from piezo_stage.core.model.inverse import invert
from piezo_stage.core.model.play import PlayOperators, play_columns
from piezo_stage.core.types import EffectsBlock, Params

EFFECTS = ("creep", "dynamics", "delay", "drift", "coupling", "structure")


STRUCTURE_DEGREE = (5, 5)  # the richer branch polynomials of the "structure" class


# what changes the hysteresis model itself rather than adding a plant effect: none,
# coupling (a term of the Duhem model), structure (richer branches) and memory (the
# structure candidate with play operators beside the Duhem law: return-point memory
# it lacks; named memory wherever the operators are what paid on HOLDOUT) and rate
# (memory whose play thresholds widen with the input's rate, beta x |dv/dt|: a loop that
# widens with the rate, which neither a resonance nor a delay is; tried where FIT holds
# several rates, named where it pays on HOLDOUT)
SHAPES = ("none", "coupling", "structure", "memory", "rate")


STRUCTURE_PLAYS = 16       # and play operators (memory), thresholds up to half the span






# a form whose exact inverse misses the voltages by more than this fraction of the
# amplifier's range is not kept (0.15 V of 0-150 V: on a 0.3 um/V stage 0.05 um, below
# a capacitive sensor's noise; a branch that turns back misses by volts)
INVERSE_MISS_FRACTION = 1e-3


@dataclass(frozen=True)
class AxisWritten:
    """One axis of a model as ``gap --out-model`` writes it: its hysteresis (the Duhem
    law, the coupling term, play operators: ``parts``) and the plant effects that act
    on it ({name: params}, as ``effects_on`` reads a model file's block per axis).
    What the diagnosis scores on HOLDOUT is this, run as ``simulate --model`` runs the
    file (``gap/written.py``)."""

    parts: AxisParts
    effects: EffectsBlock


class Fitted(Protocol):
    """What the diagnosis asks of a candidate, an effect's (``Candidate``, the Duhem
    law with its effects) or a class's (``ClassCandidate``, memory as the
    Prandtl-Ishlinskii or Preisach class): its name, parameters, the effects it holds,
    its fit on FIT and its prediction of a record (the held-out judge), and the
    effects as a model file writes them."""

    effect: str
    params: Params
    effects: list
    fit_rms_um: float

    def predict(self, rec: Record, axis: str) -> np.ndarray:
        """The candidate's output over ``rec`` [um]."""

    def model_effects(self) -> EffectsBlock:
        """Every kept plant effect as model-file parameters {name: params}."""

    def written(self) -> AxisWritten:
        """The axis as the model file holds it."""


@dataclass
class Candidate:
    """A fitted model: the Duhem base and ``effects`` [(name, params)] in the order
    they were added (``effect`` is the last one, "none" for the base alone)."""

    effect: str
    params: Params
    alphas: np.ndarray
    theta: np.ndarray
    reg: DuhemRegression
    fit_rms_um: float
    op: Callable[[np.ndarray], np.ndarray] | None = None  # X -> E(X) (columns) or None
    drift_tau_s: float | None = None
    effects: list = field(default_factory=list)
    reg_fs: float = 0.0            # the rate of the record it was fitted on [Hz]
    plays_V: np.ndarray | None = None  # structure: play-operator thresholds [V]
    plays_start: float = 0.0           # and their state at the start (PLAY_STARTS)
    plays_beta: float = 0.0            # rate: their thresholds' widening [s]

    def predict(self, rec: Record, axis: str) -> np.ndarray:
        """Its output over ``rec`` with the initial state, the offset and the play
        operators' start fitted to ``rec`` itself: an in-sample figure on any record
        but FIT (the diagnosis scores HOLDOUT with ``written`` instead)."""
        v = rec.v[axis]
        v_other = rec.v.get(OTHER[axis])
        main, coup = self.reg.models(self.alphas, self.theta)
        # columns: model output from w0 = 0, free response (w0 = 1), constant offset
        st0 = main.initial.__class__(float(v[0]), 0.0)
        base, _ = main.simulate(v, st0)
        a, _ = main.kernel_params()
        parts = [base, free_response(v, a)]
        if coup is not None and v_other is not None:
            # the coupling term from its fitted state (its constant part is tied to its
            # f_0), plus its own free response, re-estimated like the main one
            ac, _ = coup.kernel_params()
            parts[0] = base + coup.simulate(v_other, coup.initial.__class__(
                float(v_other[0]), coup.initial.w))[0]
            parts.append(free_response(v_other, ac))
        cols = np.column_stack(parts)
        # the effects at the record's own rate (HOLDOUT need not share FIT's)
        op = self.op if rec.fs_hz == self.reg_fs else transform_ops(self.effects, rec.fs_hz)
        if op is not None:
            cols = op(cols)
        fixed = cols[:, 0]
        k = len(self.theta)
        if self.drift_tau_s is not None:
            k -= 2
            fixed = fixed + Drift.columns(len(v), rec.fs_hz, self.drift_tau_s) @ self.theta[k:]
        if self.plays_V is not None:  # (their coefficients before the drift's)
            n = len(self.plays_V)
            best: tuple[float, np.ndarray] | None = None
            for start in PLAY_STARTS:  # the start that fits this record best
                P = play_columns(v, self.plays_V, start, self.plays_beta, rec.fs_hz)
                f = fixed + (op(P) if op is not None else P) @ self.theta[k - n:k]
                A = np.column_stack([cols[:, 1:], np.ones(len(v))])
                c, *_ = np.linalg.lstsq(A, rec.w[axis] - f, rcond=None)
                err = float(np.sum((rec.w[axis] - f - A @ c) ** 2))
                if best is None or err < best[0]:
                    best = (err, f)
            assert best is not None  # (PLAY_STARTS is not empty)
            fixed = best[1]
        A = np.column_stack([cols[:, 1:], np.ones(len(v))])
        coef, *_ = np.linalg.lstsq(A, rec.w[axis] - fixed, rcond=None)
        return fixed + A @ coef

    def inverse_miss(self, v: np.ndarray, fs_hz: float,
                       limits_V: tuple | None = None) -> float:
        """How far our exact inverse of the hysteresis it would write (the Duhem law
        and its play operators, from the state they were fitted in: ``v`` [V] starts
        with the fit record's voltages) lands from ``v``: rounding for a law whose
        branches rise with the voltage, volts where one turns back (least-squares play
        weights of any sign beside a Duhem law can bend a branch back near a reversal,
        and the inverse then takes another root). ``limits_V``: the amplifier's; the
        miss is a fraction of their range (INVERSE_MISS_FRACTION)."""
        main, _ = self.reg.models(self.alphas, self.theta)
        v = np.ascontiguousarray(v, dtype=float)
        dt = 1.0 / fs_hz
        out, _ = main.simulate(v, main.initial)
        ops = self.play_operators()
        if ops is not None:
            out = out + ops.run(v, ops.state(), dt)
        lo, hi = voltage_limits_for([v], limits_V)
        back = invert(main, out, (lo, hi), plays=ops, dt_s=dt).v
        miss = float(np.max(np.abs(back - v))) if np.all(np.isfinite(back)) else np.inf
        return miss / (hi - lo)

    def play_operators(self) -> PlayOperators | None:
        """The fitted play operators (thresholds, weights, the state they started the
        fit record in), as a model file holds them; None without memory."""
        if self.plays_V is None:
            return None
        n, k = len(self.plays_V), len(self.theta) - (2 if self.drift_tau_s is not None else 0)
        return PlayOperators.at_rest(self.plays_V, self.theta[k - n:k], float(self.reg.v[0]),
                                     self.plays_start, self.plays_beta)

    def model_effect(self) -> EffectsBlock | None:
        """The effect as model-file / plant parameters (None for none and coupling)."""
        return None if self.effect in SHAPES else dict(self.params)

    def model_effects(self) -> EffectsBlock:
        """Every kept effect as model-file / plant parameters {name: params} (coupling
        is in the Duhem model itself)."""
        return {n: dict(p) for n, p in self.effects if n not in SHAPES}

    def written(self) -> AxisWritten:
        """The axis as the model file holds it: the Duhem law kept rising (a law
        without play operators: ``rising_law``), its coupling, memory's play operators
        from the state they started FIT in, and the kept plant effects."""
        if self.plays_V is None:
            law, coup = rising_law(self)
        else:
            law, coup = self.reg.models(self.alphas, self.theta)
        return AxisWritten(AxisParts(law, coup, self.play_operators()), self.model_effects())


@dataclass
class ClassCandidate:
    """``memory`` as the issue's other model class: the Prandtl-Ishlinskii class or
    the discretized Preisach class (a linear term and play operators, non-negative
    weights: monotone, with return-point memory and an exact inverse;
    core/estimation/identify/prandtl.py, preisach.py) in place of the Duhem law, fitted
    on FIT with the effects kept before it (the transform effects acting on its output
    and the coupling's, a coupling term, a drift), as the Duhem law is. Its branches
    continue past FIT's range along the linear term and the operators' own lines, where
    a polynomial branch continues straight from its end: the candidate for a stroke
    larger than calibrated. Read like a Candidate (``predict``, ``play_operators``,
    ``effects``); ``stage_parts`` gives the model file's terms; ``twin`` is the Duhem
    law's best form with the same effects, on which a further effect's parameters are
    searched (``fit_class_candidate``'s ``base``)."""

    pi: PrandtlIshlinskii
    fit_rms_um: float
    v0: float
    effect: str = "memory"
    params: Params = field(default_factory=dict)
    effects: list = field(default_factory=list)
    reg_fs: float = 0.0
    coupling: DuhemModel | None = None   # from the other axis's voltage (whole law)
    drift_tau_s: float | None = None
    twin: Candidate | None = None

    @property
    def kind(self) -> str:
        """'pi' or 'preisach'."""
        return self.pi.kind

    def predict(self, rec: Record, axis: str) -> np.ndarray:
        """Prediction on another record: the kept effects at the record's own rate, the
        coupling term from rest at the other axis's first voltage, the drift as fitted;
        the constant re-estimated, the operators' start the one of PLAY_STARTS (at rest
        at the record's first voltage, after a fall to it, after a rise) that fits the
        record best, as for the Duhem law's play operators."""
        w = rec.w[axis]
        op = transform_ops(self.effects, rec.fs_hz)
        drift: np.ndarray | float = 0.0
        if self.drift_tau_s is not None:
            drift = Drift.columns(len(w), rec.fs_hz, self.drift_tau_s) @ self.pi.around[-2:]
        best: tuple[float, np.ndarray] | None = None
        for start in PLAY_STARTS:
            h = self.hysteresis(rec, axis, start)
            p = (h[0] + op((h - h[0])[:, None])[:, 0] if op is not None else h) + drift
            p = p + float(np.mean(w - p))
            err = float(np.sum((w - p) ** 2))
            if best is None or err < best[0]:
                best = (err, p)
        assert best is not None  # (PLAY_STARTS is not empty)
        return best[1]

    def hysteresis(self, rec: Record, axis: str, start: float = 0.0) -> np.ndarray:
        """The class's output and the coupling term's over ``rec`` [um], before the
        effects and without the constant: the operators from ``start`` (PLAY_STARTS)
        at the record's first voltage, the coupling from rest at the other axis's."""
        v = np.ascontiguousarray(rec.v[axis], dtype=float)
        ops = self.pi.operators
        h = self.pi.linear_um_per_V * v + ops.run(v, float(v[0]) + start * ops.thresholds_V)
        if self.coupling is not None:
            vo = rec.v.get(OTHER[axis])
            if vo is None:
                raise DataError(f"{rec.source}: the model has coupling but the record "
                                f"has no v{OTHER[axis]}")
            vo = np.ascontiguousarray(vo, dtype=float)
            h = h + self.coupling.simulate(vo, DuhemState(float(vo[0]), 0.0))[0]
        return h

    def play_operators(self) -> PlayOperators:
        """The class's play operators, at rest at FIT's first voltage."""
        return self.stage_parts()[1]

    def stage_parts(self) -> tuple[DuhemModel, PlayOperators, DuhemModel | None]:
        """(Duhem law that is exactly the linear term, play operators, the coupling
        term or None), as ``identify --class`` writes them."""
        return (*self.pi.to_model(self.v0), self.coupling)

    def model_effect(self) -> EffectsBlock | None:
        """The effect as model-file / plant parameters (None for the shapes: memory,
        coupling)."""
        return None if self.effect in SHAPES else dict(self.params)

    def model_effects(self) -> EffectsBlock:
        """Every kept plant effect as model-file parameters {name: params} (coupling is
        a term of the model itself, memory the class)."""
        return {n: dict(p) for n, p in self.effects if n not in SHAPES}

    def written(self) -> AxisWritten:
        """The axis as the model file holds it: the class's linear term as a Duhem law,
        its operators at rest at FIT's first voltage, the coupling term, the kept plant
        effects."""
        law, plays, coup = self.stage_parts()
        return AxisWritten(AxisParts(law, coup, plays), self.model_effects())


MEMORY_CLASSES = ("pi", "preisach")  # the memory candidate's class forms


def fit_class_candidate(rec: Record, axis: str, limits_V: tuple | None = None,
                        kind: str = "pi", base: Candidate | None = None,
                        kept: Sequence[tuple[str, Params]] = (),
                        effect: str = "memory") -> ClassCandidate:
    """A class with memory in place of the Duhem law, as the memory candidate's other
    forms, fitted as ``identify --class`` fits it on ``rec``'s axis: ``kind`` 'pi'
    (the Prandtl-Ishlinskii class) or 'preisach' (the discretized Preisach class);
    non-negative weights, thresholds up to half the amplifier's range ``limits_V``,
    else 0-150 V widened to the record's (duhem.voltage_limits_for).

    ``kept`` ([(name, params)], their parameters fixed) are fitted with it: the
    transform effects act on the class's output and the coupling's, a kept coupling is
    a whole-curve Duhem term of the other axis's voltage at ``base``'s coupling alpha
    (its coefficients fitted with the class's weights), a kept drift has ``base``'s
    time constant; the Duhem law's other shapes (structure, memory, rate) are what the
    class replaces. ``base`` (a Candidate with those effects, the Duhem law's) becomes
    the candidate's ``twin``; ``effect`` names the candidate (the last effect added)."""
    if kind not in MEMORY_CLASSES:
        raise ValueError(f"memory class {kind!r}: one of {MEMORY_CLASSES}")
    v = np.ascontiguousarray(rec.v[axis], dtype=float)
    w = rec.w[axis]
    fs = rec.fs_hz
    lo, hi = voltage_limits_for([v], limits_V)
    kept = [(n, dict(p)) for n, p in kept
            if n not in ("structure", "memory", "rate", "none")]
    names = [n for n, _ in kept]
    coupled = coupling_model = None
    if "coupling" in names:
        if base is None:
            raise ValueError("a kept coupling needs the Duhem law's fit with it (base)")
        if base.reg.v_other is not None:
            coupled, coupling_model = coupling_term(rec.v[OTHER[axis]],
                                                    float(base.alphas[-1]))
        else:  # the record has no other axis (a given model's coupling): no term, as
            kept = [x for x in kept if x[0] != "coupling"]  # the Duhem law's fit has
            names = [n for n, _ in kept]
    tau = None
    if "drift" in names:
        tau = base.drift_tau_s if base is not None and base.drift_tau_s else \
            max(rec.t[-1] - rec.t[0], 1.0) / 3.0
    around = Around(transform_ops(kept, fs), coupled,
                    Drift.columns(len(v), fs, tau) if tau is not None else None)
    fit = fit_pi_class if kind == "pi" else fit_preisach_class
    pi = fit(v, w, reach_V=(hi - lo) / 2, around=around)
    coupling = None
    if coupling_model is not None and coupled is not None:
        coupling = coupling_model(pi.around[:coupled.shape[1]])
    params = {"class": "prandtl-ishlinskii", "play_operators": OPERATORS} if kind == "pi" \
        else {"class": "preisach", "cells": int(pi.operators.thresholds_V.size)}
    effects = []
    for n, p in kept:
        if n == "drift":
            p = {"rate_um_per_s": float(pi.around[-2]),
                 "amplitude_um": float(pi.around[-1]), "tau_s": float(tau or 0.0)}
        effects.append((n, p))
    effects.append(("memory", dict(params)))
    if effect != "memory":  # the last effect added: it names the candidate
        effects.append(effects.pop(names.index(effect)))
        params = dict(effects[-1][1])
    cand = ClassCandidate(pi, 0.0, float(v[0]), effect, params, effects, fs, coupling,
                          tau, base)
    cand.fit_rms_um = float(np.sqrt(np.mean((cand.predict(rec, axis) - w) ** 2)))
    return cand


def fit_class_effect(rec: Record, axis: str, on: ClassCandidate, effect: str,
                     law: Candidate, limits_V: tuple | None = None) -> ClassCandidate | None:
    """``effect`` added to a class kept before it (``on``), the class refitted.

    Every effect is in place in the refit:

    - creep: its fraction searched exactly, every weight refitted at each trial
      (``nonneg_family_rms``: creep is linear in its fraction);
    - a delay, dynamics: their parameters searched with the class's output held in
      its shape (its scale, the constant and a kept drift refitted at each step:
      ``search_transform``), then the class refitted; the two alternate, each from the
      other's last result, while FIT gets closer (CLASS_ALTERNATIONS at most);
    - coupling: at the alpha the Duhem law found for it (``law``, the twin's
      candidate for the same effect);
    - drift: its two shapes.

    None where the effect cannot be added so, or the refit is no closer on FIT (the
    search ended in the wrong place)."""
    kept = [(n, dict(p)) for n, p in on.effects if n != "memory"]
    if effect not in TRANSFORMS:
        if effect == "coupling" and law.reg.v_other is not None:
            kept.append(("coupling", {}))
        elif effect == "drift":
            kept.append(("drift", {}))
        else:
            return None
        k = fit_class_candidate(rec, axis, limits_V, on.kind, law, kept, effect)
        return k if k.fit_rms_um < on.fit_rms_um else None
    if effect == "creep":  # linear in its fraction: searched exactly, the class refitted
        gamma = _class_creep(rec, axis, on, kept)
        k = fit_class_candidate(rec, axis, limits_V, on.kind, law,
                                kept + [("creep", {"gamma": gamma,
                                                   "tau_s": list(CREEP_TAUS)})], effect)
        return k if k.fit_rms_um < on.fit_rms_um else None
    best: ClassCandidate | None = None
    shape = on
    for _ in range(CLASS_ALTERNATIONS):  # the shape held, the effect searched; refitted
        h = shape.hysteresis(rec, axis)
        B = (h - h[0])[:, None]  # from rest (the constant is a column of its own)
        extra = [np.ones((len(h), 1))]
        if on.drift_tau_s is not None:
            extra.append(Drift.columns(len(h), rec.fs_hz, on.drift_tau_s))

        def design_without(names: Sequence[str],
                           kept: Sequence[tuple[str, Params]] = kept) -> np.ndarray:
            op = transform_ops([x for x in kept if x[0] not in names], rec.fs_hz)
            return op(B) if op is not None else B
        params, now = search_transform(effect, design_without, extra, rec.w[axis],
                                       rec.fs_hz, kept, delay_rows(kept, rec.fs_hz))
        k = fit_class_candidate(rec, axis, limits_V, on.kind, law, now + [(effect, params)],
                                effect)
        if best is not None and k.fit_rms_um >= best.fit_rms_um * (1 - 1e-3):
            if k.fit_rms_um < best.fit_rms_um:
                best = k
            break
        best = shape = k
    return best if best is not None and best.fit_rms_um < on.fit_rms_um else None


def _class_creep(rec: Record, axis: str, on: ClassCandidate,
                 kept: Sequence[tuple[str, Params]]) -> float:
    """Creep's fraction gamma for a class (``on``: its operators as regressors, the
    coupling's output as one column), every weight refitted at each gamma
    (``nonneg_family_rms``), the kept transform effects in place."""
    v = np.ascontiguousarray(rec.v[axis], dtype=float)
    H = np.column_stack([v, on.pi.operators.columns(v)])
    n_pos = H.shape[1]
    if on.coupling is not None:
        H = np.column_stack([H, on.hysteresis(rec, axis) - H @ np.concatenate(
            [[on.pi.linear_um_per_V], on.pi.operators.weights_um_per_V])])
    H = H - H[0]  # from rest (the constant is a column of its own)
    op = transform_ops(kept, rec.fs_hz)
    if op is not None:
        H = op(H)
    F = Creep(rec.fs_hz, tau_s=CREEP_TAUS).fast_part(H)
    extra = [np.ones((len(v), 1))]
    if on.drift_tau_s is not None:
        extra.append(Drift.columns(len(v), rec.fs_hz, on.drift_tau_s))
    E = np.column_stack(extra)
    cost = nonneg_family_rms(np.column_stack([H, E]),
                             np.column_stack([F, np.zeros_like(E)]), rec.w[axis], n_pos)
    return float(search_1d(cost, 0.0, 0.3)[0])


CLASS_ALTERNATIONS = 4  # an effect added to a class: its search and the refit, alternated


def fit_candidate(rec: Record, axis: str, effect: str, base: Candidate | None = None,
                  kept: Sequence[tuple[str, Params]] = (), memory: bool = False,
                  rate: bool = False) -> Candidate:
    """Fit the Duhem model, the effects already ``kept`` ([(name, params)], their
    parameters fixed) and ``effect`` (its parameters searched) together on rec. The
    transform effects are linear and time invariant, so they commute: the new one is
    searched on the kept ones' output. ``memory`` (structure with play operators) and
    ``rate`` (their thresholds widened with the rate, beta searched) are the structure
    candidate's other forms. Returns a Candidate."""
    v, w = rec.v[axis], rec.w[axis]
    fs = rec.fs_hz
    names = [n for n, _ in kept] + [effect]
    v_other = rec.v.get(OTHER[axis]) if "coupling" in names else None
    # structure: the hysteresis itself needs a richer branch shape (more polynomial
    # terms); the extra freedom is kept only if it pays on HOLDOUT, like any effect
    if (memory or rate) and effect == "structure":
        effect = "rate" if rate else "memory"
        names[-1] = effect
    deg = STRUCTURE_DEGREE if {"structure", "memory", "rate"} & set(names) else (3, 2)
    reg = DuhemRegression(v, w, "segmented", n=deg[0], m=deg[1], v_other=v_other)
    reg.fit_from = delay_rows(kept, fs)  # (run, not fitted: searches.delay_rows)
    tau: float | None = None
    plays: np.ndarray | None = None
    start, extra = 0.0, []
    memory = bool({"memory", "rate"} & set(names))
    beta = float(dict(kept).get("rate", {}).get("rate_widening_s", 0.0))
    if memory:  # return-point memory: play operators, linear in their weights
        plays = np.ptp(v) * np.arange(1, STRUCTURE_PLAYS + 1) / (2 * STRUCTURE_PLAYS)
        if effect == "rate" and base is not None:
            beta = rate_search(reg, base.alphas, kept, plays, v, w, fs, tau)
        # the operators' sum is part of the hysteresis: the kept effects act on it as
        # on the law's output (reg.beside), as the model file and the plant apply them
        P, start = play_start_columns(v, w, plays, reg.B, beta, fs)
        reg.beside = P
    if "drift" in names:  # (last: its coefficients come last in theta)
        tau = max(rec.t[-1] - rec.t[0], 1.0) / 3.0
        extra.append(Drift.columns(len(v), fs, tau))
    if extra:
        reg.extra = np.column_stack(extra)
    fixed_op = transform_ops(kept, fs)
    reg.transform = fixed_op
    if effect == "none" or base is None:
        alphas, fit, _ = fit_fast(reg, budget=BASE_BUDGET)
        return Candidate(effect, {}, alphas, fit.theta, reg, fit.rms, fixed_op, tau,
                         with_drift(list(kept), reg, fit.theta, tau), fs, plays, start, beta)
    alphas = np.asarray(base.alphas, float)
    params: Params = {}
    if effect == "coupling" and base.reg.v_other is None:
        alphas = np.append(alphas, alphas.mean())
    elif effect in ("structure", "memory", "rate"):
        params = {"degree": STRUCTURE_DEGREE[0]}
        if memory:
            params["play_operators"] = STRUCTURE_PLAYS
        if effect == "rate":
            params["rate_widening_s"] = beta
    elif effect in TRANSFORMS:
        extra = [] if reg.extra is None else [reg.extra]
        held = list(kept)

        def design_without(names: Sequence[str]) -> np.ndarray:
            return columns_without(reg, alphas, held, names, fs)
        params, kept = search_transform(effect, design_without, extra, w, fs, held,
                                        reg.fit_from)
        reg.transform = transform_ops(list(kept) + [(effect, params)], fs)
        reg.fit_from = delay_rows(list(kept) + [(effect, params)], fs)
    # the alphas again, with the effect in place (base and effects fitted together)
    alphas, fit, _ = fit_fast(reg, budget=TRIAL_BUDGET, x0=alphas, step=0.2)
    if effect == "delay":
        params, alphas, fit = _whole_sample_delay(reg, kept, params, alphas, fit, fs)
    if fit.rms > base.fit_rms_um * (1.0 + FIT_TOLERANCE):
        # every candidate contains its base (no delay, no resonance, no creep, a zero
        # coupling or higher-degree term): worse on FIT means the search ended in the
        # wrong place, and the no-effect limit is the better answer
        return no_effect_limit(base, effect)
    effects = with_drift(list(kept) + [(effect, params)], reg, fit.theta, tau)
    params = dict(effects[-1][1])
    return Candidate(effect, params, alphas, fit.theta, reg, fit.rms, reg.transform, tau,
                     effects, fs, plays, start, beta)


def _whole_sample_delay(reg: DuhemRegression, kept: Sequence[tuple[str, Params]],
                       params: Params, alphas: np.ndarray, fit: Fit, fs: float) -> tuple:
    """A delay found between two whole samples, tried at each of them, its alphas
    polished as the fraction's were (a command held over each period makes a plant's
    delay a shift of whole samples at the samples: a stage's 2.8 ms delay was found as
    1.8 ms at 1.9 x the noise, the 2-sample shift fits to the noise; no more alpha
    search than any other candidate gets, which would pay for its own sake). Each judged
    on the rows the fraction's fit took (``reg.fit_from``). -> (params, alphas, fit) of
    the closest on FIT; ``reg.transform`` set to its operator."""
    d = float(params["delay_s"]) * fs
    best = (fit.rms, params, alphas, fit, reg.transform)
    for k in sorted({int(np.floor(d + 1e-9)), int(np.ceil(d - 1e-9))}):
        if k < 0 or abs(k - d) < 1e-9:
            continue
        p = {"delay_s": k / fs}
        reg.transform = transform_ops(list(kept) + [("delay", p)], fs)
        a, f, _ = fit_fast(reg, budget=TRIAL_BUDGET, x0=alphas, step=0.2)
        if f.rms < best[0]:
            best = (f.rms, p, a, f, reg.transform)
    reg.transform = best[4]
    return best[1], best[2], best[3]


FIT_TOLERANCE = 1e-9  # relative: a candidate's FIT RMS above its base's by more is a miss


def no_effect_limit(base: Candidate, effect: str) -> Candidate:
    """``effect`` at its no-effect limit: the base model itself under the effect's
    name (params say so), so its FIT RMS is the base's and it can never be kept."""
    return Candidate(effect, {"no_effect_limit": True}, base.alphas, base.theta, base.reg,
                     base.fit_rms_um, base.op, base.drift_tau_s, list(base.effects),
                     base.reg_fs, base.plays_V, base.plays_start, base.plays_beta)


def with_drift(effects: list, reg: DuhemRegression, theta: np.ndarray,
               tau: float | None) -> list:
    """The drift's fitted rate and amplitude (its coefficients come last in theta)."""
    out = []
    for n, p in effects:
        if n == "drift":
            k = len(theta) - 2
            p = {"rate_um_per_s": float(theta[k]), "amplitude_um": float(theta[k + 1]),
                 "tau_s": float(tau or 0.0)}
        out.append((n, p))
    return out


def broadband(v: ArrayLike, fs: float, lo_hz: float = 100.0, rel: float = 1e-6) -> bool:
    """Whether the voltage excites a band, not just tones: the median of its Welch
    spectrum between ``lo_hz`` and 0.4 fs is at least ``rel`` of the spectrum's peak.
    The protocol's chirp gives 3e-5 to 1e-4 at 1 and 5 kHz; its sines and steps alone
    7e-8 and 2e-11."""
    v = np.asarray(v, float)
    if len(v) < 64 or 0.4 * fs <= lo_hz:
        return False
    nper = int(min(len(v), 2 ** round(np.log2(max(fs / 10.0, 64)))))
    f, p = signal.welch(v - v.mean(), fs=fs, nperseg=nper)
    band = (f >= lo_hz) & (f <= 0.4 * fs)
    return bool(band.any() and p.max() > 0 and np.median(p[band]) >= rel * p.max())


RISING_NEAR = True
BASE_BUDGET = 100  # alpha evaluations of the base fit
TRIAL_BUDGET = 8         # alpha evaluations per candidate fit


def rising_law(c: Candidate) -> tuple:
    """The Duhem law (and coupling) of a candidate without play operators as written:
    where a branch of its law turns back (a descending branch whose shape goes
    negative where its memory's pull does not make up for it, found on a
    rate-dependent stage's rising triangles: the exact inverse then missed by 9 V),
    refitted with every branch kept rising (identify's rule, ``fast.keep_rising``:
    within 10 % of the fit's RMS, else as fitted). A law with play operators beside it
    keeps its own guard (``Candidate.inverse_miss``)."""
    from piezo_stage.core.estimation.identify.fast import keep_rising
    from piezo_stage.core.estimation.identify.prandtl import min_slope
    from piezo_stage.core.estimation.identify.regress import Fit
    reg, alphas, theta = c.reg, c.alphas, c.theta
    reg.monotone_floor = min_slope(reg.v, reg.w)
    try:
        alphas, kept = keep_rising(reg, alphas, Fit(theta, c.fit_rms_um),
                                   near=RISING_NEAR)
        theta = kept.theta
    finally:
        reg.monotone_floor = None
    return reg.models(alphas, theta)
