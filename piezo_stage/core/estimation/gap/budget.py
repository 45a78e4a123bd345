"""The gap budget: the held-out residual split into noise, input-locked and not
input-locked parts (synchronous averaging when the input repeats, a cross-validated
regression otherwise), the gap into what each kept effect explains, and the
uncertainty of a held-out shrink."""

from __future__ import annotations

import numpy as np

from piezo_stage.core.estimation.identify.regress import gram
from piezo_stage.core.estimation.record import Record
from piezo_stage.core.metrics import rms
from piezo_stage.core.model.duhem import OTHER
from piezo_stage.core.model.effects import Dynamics
from piezo_stage.core.model.play import play_columns
from piezo_stage.core.types import Doc


def gap_above_floor(r: float, nf: float) -> float:
    """The part of an RMS ``r`` above the floor ``nf``, in quadrature [um]."""
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
    if not (np.all(np.isfinite(before[:n])) and np.all(np.isfinite(after[:n]))):
        return float("nan")  # (a model that cannot be run there: no figure)
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


# -- the gap budget ------------------------------------------------------------------

LOCK_ALPHAS = (3e-3, 0.03, 0.3)       # 1/V: hysteretic operators of the input


LOCK_TAUS = (0.003, 0.05, 1.0)         # s: their slow (creep-like, dynamic) responses


RIDGES = (1e-6, 1e-4, 1e-2, 1.0)      # on unit-norm features, chosen by cross-validation


LOCK_RES_N, LOCK_RES_MAX, LOCK_RES_ZETA = 6, 0.4, 0.15  # resonators: 50 Hz .. 0.4 fs


LOCK_BLOCK_S = 0.2                    # cross-validation folds: alternating blocks


LOCK_PLAYS = 8                        # play operators per input (hysteresis memory)


def input_locked(v: np.ndarray, v_other: np.ndarray | None, fs: float,
                 resid: np.ndarray) -> np.ndarray:
    """The part of ``resid`` that a rich hysteretic and dynamic function of the inputs
    (``v`` and ``v_other`` [V], sampled at ``fs``) predicts, two-fold cross-validated
    on the record itself (fitted on one fold, predicted on the other), so it holds
    what repeats with the input and not noise. -> that component (like resid)."""
    from piezo_stage.core.estimation._kernels import duhem_regressors
    from piezo_stage.core.estimation.identify.regress import legendre_basis
    from piezo_stage.core.model._kernels import lowpass_mean_columns
    cols = []
    for u in (v, v_other):
        if u is None or np.ptp(u) <= 0:
            continue
        u = np.ascontiguousarray(u, dtype=float)
        B = legendre_basis(u, float(u.min()), float(u.max()), 3)
        for alpha in LOCK_ALPHAS:
            X = duhem_regressors(u, float(u[0]), np.array([alpha, alpha]), B, B,
                                 np.empty((len(u), 2 * 4 + 1)))
            cols.append(X[:, :-1])
        cols.append(B)
        # memory (minor loops that close where they began): play operators
        cols.append(play_columns(u, np.ptp(u) * np.arange(1, LOCK_PLAYS + 1)
                                 / (2 * LOCK_PLAYS)))
        # fast dynamics (a resonance rung by a chirp): the input through a bank of
        # damped resonators, in two phases (the output and its one-sample lag); a
        # record sampled too slowly to show any (below 50 / LOCK_RES_MAX Hz) has none
        bank = np.geomspace(50.0, LOCK_RES_MAX * fs, LOCK_RES_N) \
            if LOCK_RES_MAX * fs > 50.0 else ()
        for fn in bank:
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
    best: tuple[float, np.ndarray] = (np.inf, np.zeros_like(resid))
    for ridge in RIDGES:
        pred = np.empty_like(resid)
        for (G, b), tr in folds:
            pred[~tr] = (F[~tr] / scale) @ np.linalg.solve(G + ridge * np.eye(len(G)), b)
        err = float(np.mean((resid - pred) ** 2))
        if err < best[0]:
            best = (err, pred)
    return best[1]


MIN_PERIODS = 3        # synchronous averaging: whole periods needed (the first dropped)


def input_period(v: np.ndarray, v_other: np.ndarray | None, fs: float,
                 min_s: float = 0.05) -> int | None:
    """The input's period in samples when the whole record repeats it (both axes'
    inputs, to within 0.1 % of the span), at least MIN_PERIODS times; else None."""
    from piezo_stage.core.estimation.identify.segmentation import voltage_noise
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

    def mismatch(L: int) -> float:
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
               steps: list[dict]) -> Doc:
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
    nil = gap_above_floor(rest, nf)
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
