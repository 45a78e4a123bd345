"""Sim-to-real gap diagnosis: where the simulator and the stage disagree, which
unmodelled effects cause it, and how far the gap shrinks once they are added.

Base model ("the sim"): the segmented Duhem model per axis, identified on FIT (or
given: then what it has is not a candidate). Candidates, each a small physical
operator from core/effects.py added to the sim and fitted on FIT *together with* the
Duhem coefficients (the effect operator is linear, so E(X theta) = E(X) theta: for
fixed alphas and effect parameters it is one least-squares problem; the effect's own
parameters are searched):

    creep      w = E_creep(H(v)), log-like relaxation bank, gamma searched
    dynamics   w = G(s) H(v), resonance (fn, zeta) or lag (tau), the better of the two
    delay      w(t) = H(v)(t - d), d searched
    drift      w = H(v) + a t + b (1 - exp(-t / tau)), input independent
    coupling   w = H(v) + H_c(v_other), a Duhem term driven by the other axis
    structure  H with richer branch polynomials (the hysteresis's own shape)
    none       the base model alone

Every candidate is scored on HOLDOUT (a different record): the initial Duhem state
and a constant sensor offset are re-estimated there, the same for all. The gap is the
part of the residual above the floor (the noise, and a disturbance line if any),
sqrt(max(rms^2 - floor^2, 0)); shrink = 100 (1 - gap_after / gap_before). Effects join
one at a time (forward selection, each refitted with those before it) while the
held-out gap keeps shrinking clearly. The budget splits the held-out residual into
noise, input-locked and not input-locked parts, and the gap into what each kept
effect explains and what is left; a disturbance (a line the input does not cause) is
reported with the feedback bandwidth that rejects it.
"""

from __future__ import annotations

import contextlib
import math
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike
from scipy import signal
from scipy.optimize import minimize, minimize_scalar

from piezo_stage.core._jit import play_run
from piezo_stage.core.duhem import OTHER, StageModel
from piezo_stage.core.effects import Creep, Delay, Drift, Dynamics
from piezo_stage.core.errors import DataError
from piezo_stage.core.identify.api import check_identifiable, free_response
from piezo_stage.core.identify.fast import fit_fast
from piezo_stage.core.identify.regress import DuhemRegression, gram, gram_blocks, solve_gram
from piezo_stage.core.identify.segmentation import segment
from piezo_stage.core.metrics import noise_floor, rms
from piezo_stage.core.record import Record

EFFECTS = ("creep", "dynamics", "delay", "drift", "coupling", "structure")
STRUCTURE_DEGREE = (5, 5)  # the richer branch polynomials of the "structure" class
STRUCTURE_PLAYS = 16       # and play operators (memory), thresholds up to half the span
CREEP_TAUS = (0.05, 0.5, 5.0, 50.0)
MIN_HOLD_S = 1.0


TRANSFORMS = ("creep", "dynamics", "delay")  # linear time-invariant: they commute


@dataclass
class Candidate:
    """A fitted model: the Duhem base and ``effects`` [(name, params)] in the order
    they were added (``effect`` is the last one, "none" for the base alone)."""

    effect: str
    params: dict
    alphas: np.ndarray
    theta: np.ndarray
    reg: DuhemRegression
    fit_rms_um: float
    op: object = None              # callable X -> E(X) (columns) or None
    drift_tau_s: float | None = None
    effects: list = field(default_factory=list)
    reg_fs: float = 0.0            # the rate of the record it was fitted on [Hz]
    plays_V: np.ndarray | None = None  # structure: play-operator thresholds [V]

    def predict(self, rec: Record, axis: str) -> np.ndarray:
        """Prediction on another record; initial state and offset re-estimated."""
        v = rec.v[axis]
        v_other = rec.v.get(OTHER[axis])
        main, coup = self.reg.models(self.alphas, self.theta)
        # columns: model output from w0 = 0, free response (w0 = 1), constant offset
        st0 = main.initial.__class__(float(v[0]), 0.0)
        base, _ = main.simulate(v, st0)
        a, _ = main.kernel_params()
        cols = [base, free_response(v, a)]
        if coup is not None:
            # the coupling term from its fitted state (its constant part is tied to its
            # f_0), plus its own free response, re-estimated like the main one
            ac, _ = coup.kernel_params()
            cols[0] = base + coup.simulate(v_other, coup.initial.__class__(
                float(v_other[0]), coup.initial.w))[0]
            cols.append(free_response(v_other, ac))
        cols = np.column_stack(cols)
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
            best = None
            for start in PLAY_STARTS:  # the start that fits this record best
                f = fixed + play_columns(v, self.plays_V, start) @ self.theta[k - n:k]
                A = np.column_stack([cols[:, 1:], np.ones(len(v))])
                c, *_ = np.linalg.lstsq(A, rec.w[axis] - f, rcond=None)
                err = float(np.sum((rec.w[axis] - f - A @ c) ** 2))
                if best is None or err < best[0]:
                    best = (err, f)
            fixed = best[1]
        A = np.column_stack([cols[:, 1:], np.ones(len(v))])
        coef, *_ = np.linalg.lstsq(A, rec.w[axis] - fixed, rcond=None)
        return fixed + A @ coef

    def model_effect(self) -> tuple[str, dict] | None:
        """The effect as model-file / plant parameters (None for none and coupling)."""
        return None if self.effect in ("none", "coupling", "structure") \
            else dict(self.params)

    def model_effects(self) -> dict:
        """Every kept effect as model-file / plant parameters {name: params} (coupling
        is in the Duhem model itself)."""
        return {n: dict(p) for n, p in self.effects
                if n not in ("none", "coupling", "structure")}


def _search_1d(f, lo, hi, n_grid=12, log=False):
    g = np.geomspace(lo, hi, n_grid) if log else np.linspace(lo, hi, n_grid)
    vals = [f(x) for x in g]
    i = int(np.argmin(vals))
    a, b = g[max(i - 1, 0)], g[min(i + 1, n_grid - 1)]
    r = minimize_scalar(f, bounds=(a, b), method="bounded", options={"xatol": (b - a) * 1e-3})
    return (r.x, r.fun) if r.fun <= vals[i] else (g[i], vals[i])


def effect_operator(name: str, fs: float, params: dict) -> Callable[[np.ndarray], np.ndarray]:
    """The column operator (X -> E(X)) of a transform effect with these parameters."""
    if name == "creep":
        return Creep(fs, gamma=params["gamma"], tau_s=params.get("tau_s", CREEP_TAUS)).apply
    if name == "delay":
        return Delay(fs, delay_s=params["delay_s"]).apply
    if name == "dynamics":
        return Dynamics(fs, **params).apply
    raise ValueError(f"{name} is not a transform effect")


def transform_ops(effects: Sequence[tuple[str, dict]],
                  fs: float) -> Callable[[np.ndarray], np.ndarray] | None:
    """The column operator of the transform effects among ``effects`` [(name, params)]
    (None: none). With both dynamics and a delay, the delay shifts by its whole samples
    and its fraction goes into the dynamics' sampling (Dynamics ``delay_frac_s``): the
    exact sampled form of dynamics then a delay for an input held over each sample,
    which linear interpolation of the fraction only approximates (it biased the
    resonance and the delay found: 824 Hz and 0.62 ms for 800 Hz and 0.5 ms)."""
    eff = [(n, dict(p)) for n, p in effects if n in TRANSFORMS]
    names = [n for n, _ in eff]
    if "delay" in names and "dynamics" in names:
        d = float(dict(eff)["delay"]["delay_s"])
        whole = math.floor(d * fs + 1e-9)
        frac = max(0.0, d - whole / fs)
        frac = frac if frac < 1.0 / fs * (1 - 1e-9) else 0.0
        eff = [(n, {"delay_s": whole / fs} if n == "delay" else
                ({**p, "delay_frac_s": frac} if n == "dynamics" else p)) for n, p in eff]
    return _compose([effect_operator(n, fs, p) for n, p in eff])


class _Chain:
    """Operators applied in turn (a class, not a closure: a diagnosis crosses a process
    boundary, see ``diagnose``)."""

    def __init__(self, ops):
        self.ops = ops

    def __call__(self, X):
        for o in self.ops:
            X = o(X)
        return X


def _compose(ops):
    ops = [o for o in ops if o is not None]
    if not ops:
        return None
    return ops[0] if len(ops) == 1 else _Chain(ops)


def fit_candidate(rec: Record, axis: str, effect: str, base: Candidate | None = None,
                  kept: Sequence[tuple[str, dict]] = (), memory: bool = False) -> Candidate:
    """Fit the Duhem model, the effects already ``kept`` ([(name, params)], their
    parameters fixed) and ``effect`` (its parameters searched) together on rec. The
    transform effects are linear and time invariant, so they commute: the new one is
    searched on the kept ones' output. Returns a Candidate."""
    v, w = rec.v[axis], rec.w[axis]
    fs = rec.fs_hz
    names = [n for n, _ in kept] + [effect]
    v_other = rec.v.get(OTHER[axis]) if "coupling" in names else None
    # structure: the hysteresis itself needs a richer branch shape (more polynomial
    # terms); the extra freedom is kept only if it pays on HOLDOUT, like any effect
    deg = STRUCTURE_DEGREE if "structure" in names else (3, 2)
    reg = DuhemRegression(v, w, "segmented", n=deg[0], m=deg[1], v_other=v_other)
    tau, plays, extra = None, None, []
    kept_structure = dict(kept).get("structure", {})
    memory = (memory and effect == "structure") or "play_operators" in kept_structure
    if memory:  # return-point memory: play operators, linear in their weights
        plays = np.ptp(v) * np.arange(1, STRUCTURE_PLAYS + 1) / (2 * STRUCTURE_PLAYS)
        extra.append(play_start_columns(v, w, plays, reg.B))
    if "drift" in names:  # (last: its coefficients come last in theta)
        tau = max(rec.t[-1] - rec.t[0], 1.0) / 3.0
        extra.append(Drift.columns(len(v), fs, tau))
    if extra:
        reg.extra = np.column_stack(extra)
    fixed_op = transform_ops(kept, fs)
    reg.transform = fixed_op
    if effect == "none" or base is None:
        alphas, fit, _ = fit_fast(reg, budget=100, grid=11)
        return Candidate(effect, {}, alphas, fit.theta, reg, fit.rms, fixed_op, tau,
                         _with_drift(list(kept), reg, fit.theta, tau), fs, plays)
    alphas = np.asarray(base.alphas, float)
    params = {}
    if effect == "coupling" and base.reg.v_other is None:
        alphas = np.append(alphas, alphas.mean())
    elif effect == "structure":
        params = {"degree": STRUCTURE_DEGREE[0]}
        if memory:
            params["play_operators"] = STRUCTURE_PLAYS
    elif effect in TRANSFORMS:
        # the kept operators applied once for these alphas; the new effect's parameter
        # search then filters only what it must (creep: once in all)
        KX = reg.design(alphas)
        KX = fixed_op(KX) if fixed_op is not None else KX.copy()
        extra = [] if reg.extra is None else [reg.extra]

        def solve(cols):
            return solve_gram(*gram_blocks([cols] + extra, w), len(w)).rms

        if effect == "creep":
            F = Creep(fs, tau_s=CREEP_TAUS).fast_part(KX)
            g, _ = _search_1d(lambda g: solve(KX - g * F), 0.0, 0.3)
            params = {"gamma": float(g), "tau_s": list(CREEP_TAUS)}
        elif effect == "delay":
            dmax = min(0.02, 50 / fs)

            def search(cost, p0):
                return {"delay_s": float(_search_1d(lambda d: cost({"delay_s": d}), 0.0,
                                                    dmax, n_grid=15)[0])}
            if "dynamics" in dict(kept):  # the pair's exact sampled form
                dyn = dict(kept)["dynamics"]
                KB = _without(reg, alphas, kept, ("delay", "dynamics"), fs)
                params = _alternate(KB, extra, w, search, {"delay_s": 0.0},
                                    lambda p: transform_ops([("dynamics", dyn),
                                                             ("delay", p)], fs))
            else:
                params = _alternate(KX, extra, w, search, {"delay_s": 0.0},
                                    lambda p: Delay(fs, delay_s=p["delay_s"]).apply)
        else:
            seeds = _resonance_seeds(KX, w, fs, extra)

            def search(cost, p0):  # from the data's peak and the last alternation's end
                last = [(p0["fn_hz"], p0["zeta"])] if p0 and p0["kind"] == "resonance" \
                    else []
                return _search_dynamics(fs, cost, seeds + last if seeds else seeds)
            if "delay" in dict(kept):
                d0 = dict(kept)["delay"]
                KB = _without(reg, alphas, kept, ("delay",), fs)

                def dyn_op(p):
                    return transform_ops([("dynamics", p), ("delay", d0)], fs)
                params = _alternate(KB, extra, w, search, None, dyn_op,
                                    start=Delay(fs, **d0).apply)
            else:
                params = _alternate(KX, extra, w, search, None,
                                    lambda p: Dynamics(fs, **p).apply, start=_identity)
            if seeds and "delay" in dict(kept) and params["kind"] == "resonance":
                # a delay fitted before the resonance took the resonance's phase as
                # well (on a record whose chirp excites it): the resonance and the
                # delay polished together
                def pair_op(p):
                    dyn_p = {k: v for k, v in p.items() if k != "delay_s"}
                    return transform_ops([("dynamics", dyn_p),
                                          ("delay", {"delay_s": p["delay_s"]})], fs)
                both = _alternate(KB, extra, w, lambda cost, p0: _polish_pair(p0, fs, cost),
                                  {**params, "delay_s": float(d0["delay_s"])}, pair_op)
                d = both.pop("delay_s")
                params = both
                kept = [(n, {**p, "delay_s": d} if n == "delay" else p) for n, p in kept]
        reg.transform = transform_ops(list(kept) + [(effect, params)], fs)
    # the alphas again, with the effect in place (base and effects fitted together)
    alphas, fit, _ = fit_fast(reg, budget=TRIAL_BUDGET, x0=alphas, step=0.2)
    if fit.rms > base.fit_rms_um * (1.0 + FIT_TOLERANCE):
        # every candidate contains its base (no delay, no resonance, no creep, a zero
        # coupling or higher-degree term): worse on FIT means the search ended in the
        # wrong place, and the no-effect limit is the better answer
        return no_effect_limit(base, effect)
    effects = _with_drift(list(kept) + [(effect, params)], reg, fit.theta, tau)
    params = dict(effects[-1][1])
    return Candidate(effect, params, alphas, fit.theta, reg, fit.rms, reg.transform, tau,
                     effects, fs, plays)


PLAY_STARTS = (0.0, 1.0, -1.0)  # operators at rest at v[0], after a fall, after a rise


def play_columns(v: np.ndarray, thresholds_V: np.ndarray, start: float = 0.0) -> np.ndarray:
    """One column per play operator (threshold r [V]): the memory a Duhem law lacks, as
    regressors (core/play.py's law, unit weights). Each starts at v[0] + start * r: at
    rest (0), or as left by a fall (+1) or a rise (-1) to v[0] before the record."""
    v = np.ascontiguousarray(v, dtype=float)
    out = np.empty((v.size, len(thresholds_V)))
    one, col = np.ones(1), np.empty(v.size)
    for j, r in enumerate(thresholds_V):
        play_run(v, np.array([float(r)]), one, np.array([v[0] + start * float(r)]), col)
        out[:, j] = col
    return out


def play_start_columns(v: np.ndarray, w: np.ndarray, thresholds_V: np.ndarray,
                       others: np.ndarray | None = None) -> np.ndarray:
    """The play columns of the start (PLAY_STARTS) that, with ``others`` (columns)
    and a constant, explains ``w`` best: the operators' state before a record is
    not known, and a record cut from a run (a scan's later cycles) did not start at
    rest. Chosen like the free response and the offset, from the record itself."""
    best = (np.inf, None)
    for start in PLAY_STARTS:
        P = play_columns(v, thresholds_V, start)
        A = np.column_stack([P] + ([others] if others is not None else [])
                            + [np.ones(len(v))])
        coef, *_ = np.linalg.lstsq(A, w, rcond=None)
        err = float(np.sum((w - A @ coef) ** 2))
        if err < best[0]:
            best = (err, P)
    return best[1]


FIT_TOLERANCE = 1e-9  # relative: a candidate's FIT RMS above its base's by more is a miss


def no_effect_limit(base: Candidate, effect: str) -> Candidate:
    """``effect`` at its no-effect limit: the base model itself under the effect's
    name (params say so), so its FIT RMS is the base's and it can never be kept."""
    return Candidate(effect, {"no_effect_limit": True}, base.alphas, base.theta, base.reg,
                     base.fit_rms_um, base.op, base.drift_tau_s, list(base.effects),
                     base.reg_fs, base.plays_V)


def _without(reg, alphas, kept, names, fs):
    """The design for these alphas with the kept transform effects applied, except
    ``names``."""
    op = transform_ops([(n, p) for n, p in kept if n not in names], fs)
    KX = reg.design(alphas)
    return op(KX) if op is not None else KX


def _polish_pair(p0, fs, cost, maxfev=40):
    """A resonance and a delay searched together (Nelder-Mead over log fn, log zeta and
    the delay, from ``p0`` {kind, fn_hz, zeta, delay_s}, where the separate searches
    ended): separately, each takes part of the other's phase (found 824 Hz and 0.62 ms
    for 800 Hz and 0.5 ms). Returns the better of p0 and the search's end."""
    def params(x):
        return {"kind": "resonance", "fn_hz": float(np.exp(x[0])),
                "zeta": float(np.exp(x[1])), "delay_s": float(x[2])}

    def f(x):
        p = params(x)
        return cost(p) if p["fn_hz"] < fs / 2.02 and 0 <= p["delay_s"] <= 0.02 else 1e300
    x0 = np.array([np.log(p0["fn_hz"]), np.log(p0["zeta"]), p0["delay_s"]])
    simplex = [x0, x0 + [0.03, 0, 0], x0 + [0, 0.2, 0], x0 + [0, 0, 0.5 / fs]]
    r = minimize(f, x0, method="Nelder-Mead",
                 options={"maxfev": maxfev, "xatol": 1e-4, "initial_simplex": simplex})
    return params(r.x if r.fun <= f(x0) else x0)


def _identity(X):
    return X


ALTERNATIONS = 4  # profile searches per effect fit, at most
# The two speed-ups of the diagnosis, switchable so that ``bench gap`` measures the path
# without them in the same run: the one-column searches (False: every search step
# filters every column, the exact cost) and the axes in processes (False: threads)
ONE_COLUMN_SEARCH = True
AXES_IN_PROCESSES = True


def _alternate(B, extra, w, search, p0, make_op, start=None):
    """An effect's parameters searched with the Duhem coefficients held, alternating
    with their exact refit (block coordinate descent; each step lowers the exact cost,
    and its fixed point is where neither block can improve, the joint optimum's).

    ``B``: the design the effect's operator acts on (alphas fixed); ``extra``: columns
    appended after it; ``make_op(params)``: that operator; ``search(cost, params)``
    -> params minimising cost(params) (from ``params``, or None); ``start``: the
    operator of the fit to begin from (default ``make_op(p0)``). Held coefficients make
    the cost one column through the operator, scaled by least squares (the scale keeps
    it an exact-model value: c theta is a coefficient vector too): ~15x cheaper than
    filtering every column of B, and the refit after each search keeps it exact."""
    k = B.shape[1]
    E = np.column_stack(extra) if extra else None

    def refit(op):
        fit = solve_gram(*gram_blocks([op(B)] + list(extra), w), len(w))
        p = B @ fit.theta[:k]
        r = w - E @ fit.theta[k:] if E is not None else w
        return fit.rms, p, r

    if not ONE_COLUMN_SEARCH:
        return search(lambda q: refit(make_op(q))[0], p0)
    best, p, r = refit(start if start is not None else make_op(p0))
    params = p0
    for _ in range(ALTERNATIONS):
        rr = float(r @ r)

        def cost(q, p=p, r=r, rr=rr):
            y = make_op(q)(p)
            yy = float(y @ y)
            c = float(y @ r) / yy if yy > 0 else 0.0
            return float(np.sqrt(max(rr - c * c * yy, 0.0) / len(r)))
        new = search(cost, params)
        rms_new, p_new, r_new = refit(make_op(new))
        if params is not None and rms_new >= best * (1 - 1e-4):
            if rms_new < best:
                params, best = new, rms_new
            break
        params, best, p, r = new, rms_new, p_new, r_new
    return params


def _with_drift(effects, reg, theta, tau):
    """The drift's fitted rate and amplitude (its coefficients come last in theta)."""
    out = []
    for n, p in effects:
        if n == "drift":
            k = len(theta) - 2
            p = {"rate_um_per_s": float(theta[k]), "amplitude_um": float(theta[k + 1]),
                 "tau_s": float(tau)}
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


def _resonance_seeds(KX, w, fs, extra=(), min_coherence=0.9, min_peak=1.3, min_bins=20):
    """Where a resonance shows in the data, as starting points for its search: the
    frequency response from the model's prediction without dynamics (KX theta) to the
    measured position (Welch's H1 estimate), where the excitation has broadband content
    (a chirp: coherence >= ``min_coherence`` above 50 Hz in at least ``min_bins`` of
    its ~10 Hz bins, which a few tones and their harmonics never give), peaks at the
    resonance with height about 1 / (2 zeta). [] when the record has no such content
    or no peak of at least ``min_peak``: the coarse grid alone then searches (a
    resonance far above the excitation cannot be told from a delay anyway)."""
    theta = solve_gram(*gram_blocks([KX] + list(extra), w), len(w)).theta
    p = KX @ theta[:KX.shape[1]]
    nper = int(min(len(w), 2 ** round(np.log2(fs / 10.0))))  # ~10 Hz resolution
    if nper < 64:
        return []
    f, pxy = signal.csd(p, w, fs=fs, nperseg=nper)
    _, pxx = signal.welch(p, fs=fs, nperseg=nper)
    _, pyy = signal.welch(w, fs=fs, nperseg=nper)
    with np.errstate(divide="ignore", invalid="ignore"):
        coh = np.abs(pxy) ** 2 / (pxx * pyy)
        H = np.abs(pxy / pxx)
    ok = (f > 50.0) & (f < 0.45 * fs) & np.isfinite(coh) & (coh >= min_coherence)
    if ok.sum() < min_bins:  # a few tones and their harmonics are not broadband
        return []
    i = np.argmax(np.where(ok, H, 0.0))
    peak = float(H[i])
    if peak < min_peak:
        return []
    zeta = float(np.clip(1.0 / (2.0 * peak), 0.01, 0.5))
    return [(float(f[i]) * k, zeta) for k in (0.97, 1.0, 1.03)]


def _search_dynamics(fs, cost, seeds=()):
    """A resonance (fn, zeta) or a first-order lag (tau), whichever fits better; the
    coarse grid plus ``seeds`` [(fn, zeta)] found in the data start the search."""
    nyq = fs / 2

    def res_f(x):
        try:
            return cost({"kind": "resonance", "fn_hz": float(np.exp(x[0])),
                         "zeta": float(np.exp(x[1]))})
        except ValueError:  # above Nyquist
            return 1e300
    best = (np.inf, None)
    seeds = [s for s in seeds if s[0] < nyq / 1.01]
    # a peak in the data says where the resonance is: the coarse grid only without one
    grid = [] if seeds else [(fn, z) for fn in np.geomspace(5.0, nyq / 1.25, 8)
                             for z in (0.03, 0.15, 0.6)]
    for fn, z in grid + seeds:
        val = res_f((np.log(fn), np.log(z)))
        if val < best[0]:
            best = (val, (np.log(fn), np.log(z)))
    r = minimize(res_f, best[1], method="Nelder-Mead",
                 options={"maxfev": 60, "xatol": 1e-3})
    x = r.x if r.fun < best[0] else best[1]
    fn, z = float(np.exp(x[0])), float(np.exp(x[1]))
    if not fn < nyq / 1.01:
        fn = nyq / 1.05
    if seeds:  # a resonance peak: not a lag
        return {"kind": "resonance", "fn_hz": fn, "zeta": z}
    tau_l, lag_val = _search_1d(lambda tau: cost({"kind": "lag", "tau_s": tau}), 0.2 / fs,
                                0.1, n_grid=9, log=True)
    if lag_val < min(r.fun, best[0]):
        return {"kind": "lag", "tau_s": float(tau_l)}
    return {"kind": "resonance", "fn_hz": fn, "zeta": z}


def _gap(r, nf):
    return float(np.sqrt(max(r * r - nf * nf, 0.0)))


SHRINK_BLOCK_S = 0.5     # block bootstrap of the held-out shrink: blocks this long
SHRINK_RESAMPLES = 400


def shrink_uncertainty(before: np.ndarray, after: np.ndarray, floor: float,
                       fs: float, seed: int = 0) -> float:
    """One standard deviation [percentage points] of the held-out shrink
    1 - gap(after)/gap(before), by a block bootstrap over the held-out record (blocks of
    SHRINK_BLOCK_S, so the residuals' correlation in time is kept): how much the figure
    would move on another stretch of the same stage."""
    n = min(len(before), len(after))
    size = max(int(SHRINK_BLOCK_S * fs), 1)
    k = n // size
    if k < 4:
        return float("nan")
    sb = (np.asarray(before[:k * size]) ** 2).reshape(k, size).sum(axis=1)
    sa = (np.asarray(after[:k * size]) ** 2).reshape(k, size).sum(axis=1)
    pick = np.random.default_rng(seed).integers(0, k, size=(SHRINK_RESAMPLES, k))
    rb = np.sqrt(sb[pick].sum(axis=1) / (k * size))
    ra = np.sqrt(sa[pick].sum(axis=1) / (k * size))
    gb = np.sqrt(np.maximum(rb ** 2 - floor ** 2, 0.0))
    ga = np.sqrt(np.maximum(ra ** 2 - floor ** 2, 0.0))
    ok = gb > 0
    if ok.sum() < SHRINK_RESAMPLES // 2:
        return float("nan")
    return float(np.std(100.0 * (1.0 - ga[ok] / gb[ok])))


def hold_runs(v: ArrayLike, fs: float, min_s: float = 0.2,
              tol_frac: float = 1e-3) -> list[tuple[int, int]]:
    """The holds of ``v``: [(start, stop)] sample ranges of at least ``min_s`` seconds
    over which the voltage stays within ``tol_frac`` of its span (the whole stretch,
    not sample to sample: a slow sine's turning points and a staircase DAC output move
    on, and are not holds)."""
    from piezo_stage.core._jit import hold_runs_kernel
    v = np.ascontiguousarray(v, dtype=float)
    if v.size == 0:
        return []
    tol = tol_frac * max(float(np.ptp(v)), 1e-12)
    need = max(int(round(min_s * fs)), 1)
    out = np.empty((v.size // need + 1, 2), np.int64)
    n = hold_runs_kernel(v, tol, need, out)
    return [(int(a), int(b)) for a, b in out[:n]]


def held(v: ArrayLike, fs: float, min_s: float = 0.2, tol_frac: float = 1e-3) -> np.ndarray:
    """Mask of the samples inside holds (see ``hold_runs``)."""
    mask = np.zeros(len(v), bool)
    for a, b in hold_runs(v, fs, min_s, tol_frac):
        mask[a:b] = True
    return mask


def holds(v: ArrayLike, fs: float, min_s: float = MIN_HOLD_S) -> list[float]:
    """Lengths [s] of the holds of at least ``min_s`` seconds (see ``hold_runs``)."""
    return [(b - a) / fs for a, b in hold_runs(v, fs, min_s)]


def where(rec: Record, axis: str, resid: np.ndarray, nf: float) -> dict:
    """Localise the residual: band, segment, amplitude, correlation with the other axis."""
    v = rec.v[axis]
    fs = rec.fs_hz
    out = {"axis": axis, "rms_um": rms(resid), "noise_floor_um": nf}
    f, P = signal.welch(resid - resid.mean(), fs=fs, nperseg=min(len(resid), 4096))
    white = nf ** 2 / (fs / 2)  # one-sided PSD of white noise of variance nf^2
    edges = [0.0, 0.3, 3.0, 30.0, 300.0, fs / 2]
    bands = []
    for lo, hi in zip(edges[:-1], edges[1:]):
        m = (f >= lo) & (f < hi) if hi < fs / 2 else (f >= lo)
        if m.sum() == 0 or lo >= fs / 2:
            continue
        excess = float(np.sum(np.clip(P[m] - white, 0, None)) * (f[1] - f[0]))
        bands.append(((lo, min(hi, fs / 2)), excess))
    (blo, bhi), _ = max(bands, key=lambda b: b[1])
    out["band_hz"] = [blo, bhi]
    out["band_excess_um2"] = {f"{lo:g}-{hi:g}": e for (lo, hi), e in bands}
    dv = np.diff(v, prepend=v[0])
    try:
        seg = segment(v)
        turn = np.zeros(len(v), bool)
        wdt = max(1, int(0.02 * fs))
        for i in seg.turning_points:
            turn[max(i - wdt, 0):i + wdt] = True
        labels = seg.labels
    except DataError:
        turn = np.zeros(len(v), bool)
        labels = np.sign(dv)
    still = held(v, fs)
    parts = {"ascending": (labels > 0) & ~turn & ~still,
             "descending": (labels < 0) & ~turn & ~still,
             "turning_points": turn & ~still, "holds": still}
    seg_rms = {k: rms(resid[m]) for k, m in parts.items() if m.sum() > 10}
    out["segment_rms_um"] = seg_rms
    out["segment"] = max(seg_rms, key=seg_rms.get)
    q = np.quantile(v, [1 / 3, 2 / 3])
    amp = {"low": v <= q[0], "mid": (v > q[0]) & (v <= q[1]), "high": v > q[1]}
    out["amplitude_rms_um"] = {k: rms(resid[m]) for k, m in amp.items() if m.sum() > 10}
    vo = rec.v.get(OTHER[axis])
    if vo is not None and np.ptp(vo) > 0:
        out["corr_other_input"] = float(np.corrcoef(resid, vo)[0, 1])
    return out


class GivenModel:
    """A model from a file as the base ("the sim"): prediction with the initial state
    and a constant offset re-estimated on the record, like every candidate."""

    effect = "given"
    params: dict = {}

    def __init__(self, stage_model: StageModel):
        self.model = stage_model

    def predict(self, rec: Record, axis: str) -> np.ndarray:
        """The given model's prediction on a record (no fit)."""
        from piezo_stage.core.identify.api import simulate_axis
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
    model: Candidate | None = None                   # the model with every kept effect


FIRST_SHRINK_PCT = 30.0  # the dominant effect must close this much of the held-out gap
STEP_SHRINK_PCT = 15.0   # each further effect this much of what is left
PAIR_POOL = 3           # no single effect closes the first 30 %: pairs among these best
TRIAL_BUDGET = 8         # alpha evaluations per candidate fit
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
    out = []
    if base_model is None or axis not in base_model.axes:
        return out
    if axis in base_model.coupling:
        out.append(("coupling", {}))
    for name, p in (base_effects or {}).items():
        p = dict(p or {})
        if axis in p.pop("axes", ["x", "y"]) and name in TRANSFORMS + ("drift",):
            out.append((name, p))
    return out


def diagnose_axis(fit: Record, holdout: Record, axis: str, effects: Sequence[str] = EFFECTS,
                  base_model: StageModel | None = None,
                  progress: Callable[[str], None] | None = None,
                  base_effects: dict | None = None) -> AxisDiagnosis:
    """Fit every candidate on FIT, score on HOLDOUT, then add effects one at a time
    (forward selection, each refitted jointly with the Duhem model and the effects
    kept before it) while the held-out gap keeps shrinking clearly. ``base_model`` (a
    StageModel, with ``base_effects`` from its file) replaces the FIT-identified Duhem
    model as the sim to compare with; what it already has is not a candidate.
    ``progress(what)`` is called after each candidate is fitted."""
    progress = progress or (lambda what="": None)
    for rec in (fit, holdout):
        if axis not in rec.v or axis not in rec.w:
            raise DataError(f"{rec.source}: no v{axis}/w{axis} for axis {axis}")
        check_identifiable(rec.v[axis], rec.source)
    notes = []
    if holdout is fit:
        notes.append("no HOLDOUT: scored on FIT itself, where extra freedom is not "
                     "penalised (record the excitation twice)")
    given = _given_effects(base_model, base_effects, axis)
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
    def candidate(e, on, kept):
        """fit_candidate; structure both ways (richer branches, and with play
        operators: memory), the one closer on HOLDOUT kept (as every candidate is
        judged), so memory is named only where it pays."""
        c = fit_candidate(fit, axis, e, on, kept)
        if e == "structure":
            m = fit_candidate(fit, axis, e, on, kept, memory=True)
            if rms(m.predict(holdout, axis) - holdout.w[axis]) < \
                    rms(c.predict(holdout, axis) - holdout.w[axis]):
                c = m
        return c
    base = fit_candidate(fit, axis, "none", kept=given)
    progress(f"{axis} none")
    cands = {"none": base}
    for e in testable:
        cands[e] = candidate(e, base, base.effects)
        progress(f"{axis} {e}")
    nf = noise_floor(holdout.w[axis])
    w_h = holdout.w[axis]
    n = len(w_h)
    sim = GivenModel(base_model) if base_model is not None and axis in base_model.axes \
        else base
    resid = sim.predict(holdout, axis) - w_h
    r_before = rms(resid)
    # a line the input does not cause (a floor vibration) is no model's to close: for
    # choosing effects it counts with the noise (the gap is what a model could close)
    dist0 = disturbance(holdout, axis, resid, nf)
    floor = float(np.hypot(nf, dist0["rms_um"])) if dist0 else nf
    g_before = _gap(r_before, floor)
    resids = {e: c.predict(holdout, axis) - w_h for e, c in cands.items()}
    scores = {e: rms(r) for e, r in resids.items()}
    ranking = []
    for e, c in cands.items():
        g_after = _gap(scores[e], floor)
        ranking.append({"effect": e, "rms_before_um": r_before, "rms_after_um": scores[e],
                        "gap_before_um": g_before, "gap_after_um": g_after,
                        "shrink_pct": 100.0 * (1 - g_after / g_before) if g_before > 0 else 0.0,
                        "shrink_pm_pct": shrink_uncertainty(resid, resids[e], floor,
                                                            holdout.fs_hz),
                        "fit_rms_um": c.fit_rms_um, "params": c.params})
    ranking.sort(key=lambda r: r["gap_after_um"])
    # forward selection: the best candidate joins when it shrinks the held-out gap
    # clearly; the rest are refitted with it in place and tried again
    steps, model, r_cur = [], None, r_before
    # (every candidate stays in: one that explains nothing on its own, as creep
    # beside a larger coupling, can show once the larger one is modelled)
    pool = {e: cands[e] for e in testable}
    tried = {}  # (a, b): b fitted on top of a, and its held-out RMS (the pairs)
    while pool:
        e, c = min(pool.items(), key=lambda kv: scores[kv[0]])
        g_cur, g_new = _gap(r_cur, floor), _gap(scores[e], floor)
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
            top = sorted(pool, key=scores.get)[:PAIR_POOL]
            pairs = [(a, b) for i, a in enumerate(top) for b in top[i + 1:]]
            if "delay" in pool and "dynamics" in pool and not {"delay", "dynamics"} <= set(top):
                # a resonance seen through a delay: neither alone may fit at all
                pairs.append(tuple(sorted(("delay", "dynamics"), key=scores.get)))
            best_pair = None
            for a, b in pairs:
                pair = candidate(b, pool[a], pool[a].effects)
                progress(f"{axis} {a}+{b}")
                r_pair = rms(pair.predict(holdout, axis) - w_h)
                tried[(a, b)] = (pair, r_pair)
                g_pair, g_a = _gap(r_pair, floor), _gap(scores[a], floor)
                if 100.0 * (1 - g_pair / g_cur) >= need \
                        and _significant(r_cur, r_pair, floor, n) \
                        and 100.0 * (1 - g_pair / g_a) >= STEP_SHRINK_PCT \
                        and (best_pair is None or g_pair < best_pair[0]):
                    best_pair = (g_pair, a, b)
            if best_pair is not None:
                e = best_pair[1]
                c, g_new = pool[e], _gap(scores[e], floor)
                step = 100.0 * (1 - g_new / g_cur) if g_cur > 0 else 0.0
                rule = (f"the pair rule: {e} and {best_pair[2]} together close "
                        f"{100.0 * (1 - best_pair[0] / g_cur):.0f} % of the gap (>= "
                        f"{need:.0f} %), which no effect does alone")
                need = 0.0  # the first of a pair that closes the gap together
        if not (_significant(r_cur, scores[e], floor, n) and step >= need):
            break
        # what fits as well at this step (the excitation cannot tell them apart)
        alike = [e2 for e2 in pool if e2 != e and _gap(scores[e2], floor) <=
                 1.02 * g_new + 0.02 * (g_cur - g_new)]
        if steps and len(alike) >= 2 and len(alike) == len(pool) - 1:
            break  # every candidate helps alike: the refit helps, not any one effect
        steps.append({"effect": e, "params": c.params, "rms_after_um": scores[e],
                      "gap_after_um": g_new, "step_shrink_pct": step,
                      "shrink_pct": 100.0 * (1 - g_new / g_before) if g_before else 0.0,
                      "equally_well": alike, "rule": rule})
        # polish the kept model's alphas fully, so that what the next candidates earn
        # is theirs and not a better alpha search riding along
        alphas, fitted, _ = fit_fast(c.reg, budget=POLISH_BUDGET, x0=c.alphas, step=0.1)
        if fitted.rms < c.fit_rms_um:
            was = (c.alphas, c.theta, c.fit_rms_um, c.effects)
            c.alphas, c.theta, c.fit_rms_um = alphas, fitted.theta, fitted.rms
            c.effects = _with_drift(c.effects, c.reg, c.theta, c.drift_tau_s)
            polished = rms(c.predict(holdout, axis) - w_h)
            if polished <= scores[e]:
                scores[e] = polished
                g_new = _gap(scores[e], floor)
                steps[-1].update(rms_after_um=scores[e], gap_after_um=g_new,
                                 shrink_pct=100.0 * (1 - g_new / g_before)
                                 if g_before else 0.0)
            else:  # closer on FIT, further on HOLDOUT: the extra freedom overfits
                c.alphas, c.theta, c.fit_rms_um, c.effects = was
        steps[-1]["shrink_pm_pct"] = shrink_uncertainty(
            resid, c.predict(holdout, axis) - w_h, floor, holdout.fs_hz)
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
                scores[e2] = rms(pool[e2].predict(holdout, axis) - w_h)
            progress(f"{axis} {'+'.join(x['effect'] for x in steps)}+{e2}")
    if model is not None:  # each effect's parameters as finally refitted (drift's)
        final = dict(model.effects)
        for st in steps:
            st["params"] = final.get(st["effect"], st["params"])
    loc = where(holdout, axis, resid, nf)
    verdict, reason = _decide(ranking, steps, g_before, floor, fit, holdout, axis)
    if verdict in ("none", "inconclusive"):
        steps, model = [], None
    if no_band and ({"delay", "dynamics"} & {st["effect"] for st in steps}
                    or "delay and dynamics" in reason or "dynamics and delay" in reason):
        notes.append("no broadband excitation (no chirp): a resonance above the "
                     "excitation's tones cannot be told from a delay (record the "
                     "protocol with its chirp: `excite` without `--chirp 0`)")
    if notes:
        reason = (reason + "; " if reason else "") + "; ".join(notes)
    final = (model.predict(holdout, axis) - w_h) if model is not None else resid
    dist = disturbance(holdout, axis, final, nf)
    budget = gap_budget(holdout, axis, resid, nf, g_before, steps)
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
    return first, (f"{first} shrinks the held-out gap by {steps[0]['shrink_pct']:.0f} % "
                   f"(chosen by {steps[0]['rule']})"
                   + (f"; with {said} ({steps[-1]['shrink_pct']:.0f} % in all)"
                      if len(steps) > 1 else ""))


# -- the gap budget ------------------------------------------------------------------

LOCK_ALPHAS = (3e-3, 0.03, 0.3)       # 1/V: hysteretic operators of the input
LOCK_TAUS = (0.003, 0.05, 1.0)         # s: their slow (creep-like, dynamic) responses
RIDGES = (1e-6, 1e-4, 1e-2, 1.0)      # on unit-norm features, chosen by cross-validation
LOCK_RES_N, LOCK_RES_MAX, LOCK_RES_ZETA = 6, 0.4, 0.15  # resonators: 50 Hz .. 0.4 fs
LOCK_BLOCK_S = 0.2                    # cross-validation folds: alternating blocks
LOCK_PLAYS = 8                        # play operators per input (hysteresis memory)


def input_locked(v: np.ndarray, v_other: np.ndarray, fs: float,
                 resid: np.ndarray) -> np.ndarray:
    """The part of ``resid`` that a rich hysteretic and dynamic function of the inputs
    (``v`` and ``v_other`` [V], sampled at ``fs``) predicts, two-fold cross-validated
    on the record itself (fitted on one fold, predicted on the other), so it holds
    what repeats with the input and not noise. -> that component (like resid)."""
    from piezo_stage.core._jit import duhem_regressors, lowpass_mean_columns
    from piezo_stage.core.identify.regress import _basis
    cols = []
    for u in (v, v_other):
        if u is None or np.ptp(u) <= 0:
            continue
        u = np.ascontiguousarray(u, dtype=float)
        B = _basis(u, float(u.min()), float(u.max()), 3)
        for alpha in LOCK_ALPHAS:
            X = duhem_regressors(u, float(u[0]), np.array([alpha, alpha]), B, B,
                                 np.empty((len(u), 2 * 4 + 1)))
            cols.append(X[:, :-1])
        cols.append(B)
        # memory (minor loops that close where they began): play operators
        cols.append(play_columns(u, np.ptp(u) * np.arange(1, LOCK_PLAYS + 1)
                                 / (2 * LOCK_PLAYS)))
        # fast dynamics (a resonance rung by a chirp): the input through a bank of
        # damped resonators, in two phases (the output and its one-sample lag)
        for fn in np.geomspace(50.0, LOCK_RES_MAX * fs, LOCK_RES_N):
            Y = Dynamics(fs, "resonance", float(fn), LOCK_RES_ZETA).apply(B[:, 1:]) - B[:, 1:]
            cols += [Y, np.vstack([Y[:1], Y[:-1]])]
    H = np.ascontiguousarray(np.hstack(cols))
    slow = [lowpass_mean_columns(np.array([np.exp(-1.0 / (fs * tau))]), H,
                                 np.empty_like(H)) for tau in LOCK_TAUS]
    F = np.hstack([H] + slow + [np.ones((len(resid), 1))])
    # folds of alternating 0.2 s blocks: both see every part of the excitation (each
    # axis is driven alone in turn: halves would train on one and predict the other;
    # a chirp sweeps ~40 Hz in a block, so both see every part of its band too)
    block = np.arange(len(resid)) // max(int(LOCK_BLOCK_S * fs), 1) % 2 == 0
    scale = np.sqrt(np.clip(np.einsum("ij,ij->j", F, F), 1e-30, None))
    folds = [(gram(F[tr] / scale, resid[tr])[:2], tr) for tr in (block, ~block)]
    # ridge: the features overlap (that is what makes them rich), and a fit meant to
    # predict the other fold must not extrapolate along directions its own fold
    # barely saw; its weight is the one that predicts the other fold best
    best = (np.inf, None)
    for ridge in RIDGES:
        pred = np.empty_like(resid)
        for (G, b), tr in folds:
            pred[~tr] = (F[~tr] / scale) @ np.linalg.solve(G + ridge * np.eye(len(G)), b)
        err = float(np.mean((resid - pred) ** 2))
        if err < best[0]:
            best = (err, pred)
    return best[1]


PEAK_RATIO = 20.0   # a narrowband line: this many times the residual's median PSD


def disturbance(rec: Record, axis: str, resid: np.ndarray, nf: float) -> dict | None:
    """Motion the input does not cause: the strongest narrow line in the residual's
    spectrum away from where the inputs have power (their tones, harmonics and step
    edges), when it stands clear of the residual's own floor. No model can remove it
    on held-out data, so it is reported with its size and band and the feedback
    bandwidth that would reject it (10x its frequency: |S| ~ f / f_bw, 20 dB).
    -> {freq_hz, band_hz, rms_um, feedback_bandwidth_hz} or None."""
    fs = rec.fs_hz
    r = resid - resid.mean()
    nper = int(min(len(r), 2 ** int(np.ceil(np.log2(max(fs * 4, 256))))))
    f, P = signal.welch(r, fs=fs, nperseg=nper)
    df = f[1] - f[0]
    quiet = np.ones(len(f), bool)
    for key in (axis, OTHER[axis]):
        u = rec.v.get(key)
        if u is None or np.ptp(u) <= 0:
            continue
        _, Pu = signal.welch(u - u.mean(), fs=fs, nperseg=nper)
        quiet &= Pu < 1e-4 * Pu.max()  # where the input has (next to) no power
        # and away from the harmonics of its tones (a hysteresis mismatch puts lines
        # there, caused by the input though the input has no power at them)
        # the input's tones, found at 1 Hz resolution (a tone played for a second or
        # two is spread over many fine bins), then placed on the fine ones: +-5 %
        # around each (the sidebands of a tone switched on and off) and +-1 % around
        # its harmonics, where a hysteresis mismatch puts lines
        fc, Pc = signal.welch(u - u.mean(), fs=fs, nperseg=int(min(len(u), fs)))
        peaks, _ = signal.find_peaks(Pc, prominence=1e-3 * Pc.max())
        for coarse in fc[peaks][fc[peaks] >= 0.5]:
            near = np.abs(f - coarse) <= 1.0      # the tone, to the fine resolution
            tone = float(f[near][np.argmax(Pu[near])])
            quiet &= np.abs(f - tone) > max(0.05 * tone, 1.0)
            for h in range(2, 11):
                quiet &= np.abs(f - h * tone) > 3 * df + 0.01 * h * tone
    quiet[f < 2.0] = False             # drift and creep live there
    if quiet.sum() < 20:
        return None
    floor = float(np.median(P[quiet]))
    low = f >= 2.0
    # where both inputs are held the input causes no line at all: a line that is
    # there too is a disturbance, whatever its frequency (so a vibration on a
    # harmonic of the excitation is still found); without such holds, only lines
    # away from the input's tones and harmonics are judged
    segs = _joint_holds(rec, axis)
    if segs:
        cand = signal.find_peaks(np.where(low, P, 0.0), height=PEAK_RATIO * floor)[0]
        cand = cand[np.argsort(P[cand])[::-1][:5]]
    else:
        cand = np.flatnonzero(quiet & (P > PEAK_RATIO * floor))
        cand = cand[np.argsort(P[cand])[::-1][:1]]
    for k in cand:
        lo, hi = max(k - 3, 0), min(k + 4, len(f))
        size = float(np.sqrt(np.sum(np.clip(P[lo:hi] - floor, 0, None)) * df))
        if size < 0.1 * nf:
            continue
        if segs and _line_rms(r, fs, f[k], segs) < 0.5 * size:
            continue  # absent while the inputs hold still: the input causes it
        return {"freq_hz": float(f[k]), "band_hz": [float(f[lo]), float(f[hi - 1])],
                "rms_um": size, "feedback_bandwidth_hz": 10.0 * float(f[k])}
    return None


def _joint_holds(rec: Record, axis: str, min_s=0.25, total_s=1.0):
    """Sample ranges where both inputs are held (>= min_s each, >= total_s in all)."""
    mask = held(rec.v[axis], rec.fs_hz, min_s)
    vo = rec.v.get(OTHER[axis])
    if vo is not None and np.ptp(vo) > 0:
        mask &= held(vo, rec.fs_hz, min_s)
    edges = np.flatnonzero(np.diff(np.concatenate([[0], mask.astype(np.int8), [0]])))
    segs = [(a, b) for a, b in zip(edges[::2], edges[1::2]) if b - a >= min_s * rec.fs_hz]
    return segs if sum(b - a for a, b in segs) >= total_s * rec.fs_hz else []


def _line_rms(r, fs, freq, segs):
    """RMS of the sinusoid at freq in r over the segments (each fitted on its own:
    the line's phase need not carry across)."""
    power, n = 0.0, 0
    for a, b in segs:
        t = np.arange(b - a) / fs
        A = np.column_stack([np.sin(2 * np.pi * freq * t), np.cos(2 * np.pi * freq * t),
                             np.ones(b - a)])
        c, *_ = np.linalg.lstsq(A, r[a:b], rcond=None)
        power += (c[0] ** 2 + c[1] ** 2) / 2 * (b - a)
        n += b - a
    return float(np.sqrt(power / n))


MIN_PERIODS = 3        # synchronous averaging: whole periods needed (the first dropped)


def input_period(v: np.ndarray, v_other: np.ndarray | None, fs: float,
                 min_s: float = 0.05) -> int | None:
    """The input's period in samples when the whole record repeats it (both axes'
    inputs, to within 0.1 % of the span), at least MIN_PERIODS times; else None."""
    from piezo_stage.core.identify.segmentation import voltage_noise
    v = np.asarray(v, float)
    n = v.size
    span = float(np.ptp(v))
    if span <= 0 or n < MIN_PERIODS * int(min_s * fs):
        return None
    x = v - v.mean()
    f = np.fft.rfft(x, 2 * n)
    ac = np.fft.irfft(f * np.conj(f))[:n]
    ac /= np.maximum(ac[0] * (n - np.arange(n)) / n, 1e-300)  # unbiased, normalised
    lo, hi = max(int(min_s * fs), 1), n // MIN_PERIODS
    if hi <= lo:
        return None
    seg = ac[lo:hi + 1]
    if seg.max() < 0.99:
        return None
    # the first peak of the correlation (>= 0.99), then its best-matching lag
    L0 = lo + int(np.flatnonzero(seg >= 0.99)[0])
    L1 = L0
    while L1 + 1 <= hi and seg[L1 + 1 - lo] >= 0.99:
        L1 += 1
    tol = 1e-3 * span + 5.0 * voltage_noise(v)

    def mismatch(L):
        worst = 0.0
        for u in (v, v_other):
            if u is None or np.ptp(u) <= 0:
                continue
            u = np.asarray(u, float)
            worst = max(worst, float(np.max(np.abs(u[L:] - u[:-L]))) /
                        max(tol, 1e-3 * np.ptp(u)))
        return worst
    L = min(range(L0, L1 + 1), key=mismatch)
    return L if L <= hi and mismatch(L) <= 1.0 else None


def synchronous_split(resid: np.ndarray, period: int) -> tuple[float, float, int]:
    """(locked, rest, periods used) [um]: the RMS of the residual's synchronous average
    over its whole periods (the first dropped: the hysteresis's state settles), less the
    average's noise bias (the rest's variance over the number of periods), and the RMS
    of what differs from period to period."""
    K = len(resid) // period
    segs = np.asarray(resid[period:K * period], float).reshape(K - 1, period)
    segs = segs - segs.mean()
    mean = segs.mean(axis=0)
    m = segs.shape[0]
    var_rest = float(np.sum((segs - mean) ** 2) / ((m - 1) * period)) if m > 1 else 0.0
    locked2 = float(np.mean(mean ** 2)) - var_rest / m
    return float(np.sqrt(max(locked2, 0.0))), float(np.sqrt(var_rest)), m


def gap_budget(holdout: Record, axis: str, resid: np.ndarray, nf: float, g_before: float,
               steps: list[dict]) -> dict:
    """Where the held-out residual goes [um]: the noise floor; the part locked to the
    input (cross-validated, ``input_locked``) and the rest above the noise; what each
    kept effect explains (the drop of the gap, in quadrature) and what is left. The
    parts add in quadrature: noise^2 + locked^2 + not_locked^2 against residual^2
    (``closure_pct`` says how closely), and explained^2 + unexplained^2 = gap^2."""
    # the budget's split at <= 1 kHz: the hysteretic features do not depend on the
    # rate and white noise keeps its per-sample level, so a subsampled record says the
    # same at a fraction of the cost
    k = max(1, int(holdout.fs_hz // 1000))
    centred = (resid - resid.mean())[::k]
    vo = holdout.v.get(OTHER[axis])
    r = rms(centred)
    period = input_period(holdout.v[axis], vo, holdout.fs_hz)
    if period is not None:
        # the input repeats: what repeats with it is the synchronous average over its
        # periods (model-free), less the average's own noise
        il, rest, used = synchronous_split(resid - resid.mean(), period)
        estimator = {"kind": "synchronous average", "periods": used,
                     "period_s": period / holdout.fs_hz}
    else:
        rest = rms(centred - input_locked(holdout.v[axis][::k],
                                          None if vo is None else vo[::k],
                                          holdout.fs_hz / k, centred))
        il = float(np.sqrt(max(r * r - rest * rest, 0.0)))
        estimator = {"kind": "regression", "why": "the input does not repeat"}
    nil = _gap(rest, nf)
    explained, g_prev = {}, g_before
    for s in steps:
        explained[s["effect"]] = float(np.sqrt(max(g_prev ** 2 - s["gap_after_um"] ** 2, 0)))
        g_prev = s["gap_after_um"]
    total = np.sqrt(nf ** 2 + il ** 2 + nil ** 2)
    return {"residual_rms_um": rms(resid), "noise_floor_um": nf, "gap_um": g_before,
            "input_locked_um": il, "not_input_locked_um": nil,
            "locked_estimator": estimator,
            "explained_um": explained, "unexplained_um": g_prev,
            "closure_pct": 100.0 * (total / r - 1.0) if r > 0 else 0.0}


@dataclass
class Diagnosis:
    """What ``diagnose`` found: ``json``, the --json contract (see the module docstring
    and the README; ``diagnosis["verdict"]`` reads it), and ``per_axis``, each axis's
    full diagnosis (its kept model and candidates: for reports and ``model``)."""

    json: dict
    per_axis: dict
    notes: list = field(default_factory=list)  # what ``model`` had to leave out

    def __getitem__(self, key: str) -> object:
        return self.json[key]

    def __contains__(self, key: str) -> bool:
        return key in self.json

    def model(self, fit: Record) -> tuple[StageModel, dict]:
        """The model with every kept effect, as ``gap --out-model`` writes it: (StageModel,
        effects). Each axis's Duhem model (and coupling) from its kept fit; the model
        file holds one parameter set per effect, so where both axes have one, the set of
        the axis where it explains the most. Voltage limits: 0-150 V widened to FIT's."""
        from piezo_stage.core.duhem import StageModel
        axes, coupling, effects, weight = {}, {}, {}, {}
        self.notes = []
        for a, d in self.per_axis.items():
            c = d.model or d.candidates["none"]
            if c.plays_V is not None:
                # the model file has no play operators (yet): their Duhem branches were
                # fitted beside them and are wrong without them; the kept effects but
                # the structure are refitted on FIT instead
                c = fit_candidate(fit, a, "none", kept=[(n, p) for n, p in c.effects
                                                        if n != "structure"])
                self.notes.append(f"axis {a}: structure's play operators are not in the "
                                  "model file format; the written model leaves them out")
            main, coup = c.reg.models(c.alphas, c.theta)
            axes[a] = main
            if coup is not None:
                coupling[a] = coup
            for name, params in c.model_effects().items():
                e = effects.setdefault(name, {"axes": []})
                e["axes"].append(a)
                w = d.budget.get("explained_um", {}).get(name, 0.0)
                if w >= weight.get(name, -1.0):
                    weight[name] = w
                    e.update(params)
        lim = (min(0.0, min(float(fit.v[a].min()) for a in axes)),
               max(150.0, max(float(fit.v[a].max()) for a in axes)))
        return StageModel(axes, coupling, lim), effects


def _axis_child(conn, fit, holdout, axis, args):
    effects, base_model, base_effects = args
    try:
        d = diagnose_axis(fit, holdout, axis, effects, base_model,
                          lambda what: conn.send(("progress", what)), base_effects)
        conn.send(("done", d))
    except BaseException as e:  # noqa: BLE001 -- re-raised in the parent
        conn.send(("error", e))
    finally:
        conn.close()


def _axes_apart(fit, holdout, axes, args, progress):
    """Each axis's diagnosis in a process of its own (forked: the records are not
    copied), progress relayed from them. Processes, not threads: the many small steps
    of the parameter searches hold the GIL, and two axes in two threads took 19 s
    where two processes take 12 s (the 35 s, 5 kHz record with four effects). One
    axis, or no fork (not Linux): in this process / in threads."""
    import multiprocessing as mp
    import sys
    if len(axes) == 1 or not (AXES_IN_PROCESSES and sys.platform.startswith("linux")):
        from concurrent.futures import ThreadPoolExecutor
        with ThreadPoolExecutor(max_workers=min(2, len(axes))) as pool:
            futures = {a: pool.submit(diagnose_axis, fit, holdout, a, args[0], args[1],
                                      progress, args[2]) for a in axes}
            return {a: f.result() for a, f in futures.items()}
    from multiprocessing.connection import wait
    ctx = mp.get_context("fork")
    procs, conns, per = {}, {}, {}
    try:
        for a in axes:
            r, w = ctx.Pipe(duplex=False)
            p = ctx.Process(target=_axis_child, args=(w, fit, holdout, a, args), daemon=True)
            p.start()
            w.close()
            procs[a], conns[r] = p, a
        while conns:
            for r in wait(list(conns)):
                a = conns[r]
                try:
                    kind, val = r.recv()
                except EOFError:
                    procs[a].join(5)
                    raise RuntimeError(f"axis {a}: its diagnosis process ended without a "
                                       f"result (exit code {procs[a].exitcode})") from None
                if kind == "progress":
                    progress(val)
                    continue
                del conns[r]
                r.close()
                if kind == "error":
                    raise val
                per[a] = val
    finally:
        for p in procs.values():
            if p.is_alive() and p.pid is not None and conns:
                p.terminate()
            p.join(5)
    return {a: per[a] for a in axes}


def diagnose(fit: Record, holdout: Record | None = None, effects: Sequence[str] = EFFECTS,
             axes: Sequence[str] | None = None, base_model: StageModel | None = None,
             progress: Callable[[str], None] | None = None,
             base_effects: dict | None = None) -> Diagnosis:
    """Diagnose the gap on every axis (see the module docstring). ``progress(what)`` is
    called after each candidate fit (in this thread: relayed from the axes' processes)."""
    t0 = time.perf_counter()
    holdout = holdout or fit
    axes = axes or [a for a in ("x", "y") if a in fit.w and a in holdout.w]
    if not axes:
        raise DataError("no axis with voltage and displacement in both records")
    for a in axes:
        if (a in fit.w) != (a in holdout.w):
            raise DataError(f"FIT and HOLDOUT have different channels (axis {a})")
    if len(fit.t) < 200 or len(holdout.t) < 200:
        raise DataError("records too short for a gap diagnosis (need >= 200 samples)")
    # the axes are independent problems, one per core; one BLAS thread each (two of
    # each on two cores fight, ~20 % slower). threadpoolctl is optional (rosdep has no
    # key for it): without it the diagnosis is the same, only slower on two axes.
    try:
        from threadpoolctl import threadpool_limits
    except ImportError:
        def threadpool_limits(_n):
            return contextlib.nullcontext()
    args = (effects, base_model, base_effects)
    with threadpool_limits(1 if len(axes) > 1 else None):
        per = _axes_apart(fit, holdout, axes, args, progress or (lambda what: None))
    worst = max(per.values(), key=lambda d: d.ranking[0]["gap_before_um"])
    out = {"verdict": worst.verdict, "reason": worst.reason, "ranking": worst.ranking,
           "where": worst.where, "noise_floor_um": worst.noise_floor_um,
           "effects": worst.effects, "budget": worst.budget,
           "axes": {a: {"verdict": d.verdict, "reason": d.reason, "ranking": d.ranking,
                        "where": d.where, "noise_floor_um": d.noise_floor_um,
                        "effects": d.effects, "budget": d.budget}
                    for a, d in per.items()},
           "holdout_is_fit": holdout is fit,
           "seconds": time.perf_counter() - t0}
    return Diagnosis(out, per)
