"""The ``fast`` solver: variable projection over alpha, exact least squares for the rest.

The search runs on log(alpha) in [1e-5, 10] 1/V (a coupling term's: see below): a
coarse grid over a shared alpha, then Nelder-Mead over all alphas (one per branch, plus
one for a coupling term) from the best grid point. Each evaluation is one compiled
regressor pass and one small least-squares solve, so the whole fit of 10,000 samples
takes a fraction of a second.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np
from numpy.typing import ArrayLike
from scipy.optimize import minimize

from piezo_stage.core.estimation.identify.regress import DuhemRegression, Fit

LOG_ALPHA_BOUNDS = (np.log(1e-5), np.log(10.0))
# A coupling term's alpha stays above 1e-3 1/V and above a third of the smallest branch
# alpha (the same material forgets at a similar rate): a small effect leaves its alpha
# nearly unconstrained by the data (a few cycles fit equally well from 1e-3 to 0.1), and
# a term that hardly forgets integrates f |dv| into a drift nobody measured once the
# tracking moves the voltage much more than the identification record did.
LOG_COUPLING_ALPHA_MIN = np.log(1e-3)
COUPLING_ALPHA_SPAN = np.log(3.0)
GRID = 21


def fit_fast(reg: DuhemRegression, budget: int | None = None,
             progress: Callable[[int, float], None] | None = None,
             x0: ArrayLike | None = None, grid: int = GRID,
             step: float = 0.7) -> tuple[np.ndarray, Fit, list[float]]:
    """Returns (alphas, Fit, history) where history is the best RMS after each evaluation
    (the Fit's coefficients kept rising on every branch where ``reg.monotone_floor`` is
    set: ``DuhemRegression.monotone``).

    ``x0`` (alphas) skips the grid and polishes from there with a simplex of ``step``
    in log(alpha) (refits after a small change of the problem)."""
    history: list[float] = []
    best: dict[str, Any] = {"rms": np.inf, "alphas": None, "fit": None}
    k = reg.n_alpha
    lo, hi = LOG_ALPHA_BOUNDS
    lows = np.full(k, lo)
    if reg.v_other is not None:
        lows[-1] = LOG_COUPLING_ALPHA_MIN
    budget = budget or 400

    def objective(log_alphas: np.ndarray) -> float:
        la = np.clip(log_alphas, lows, hi)
        if reg.v_other is not None:  # the coupling forgets at least a third as fast
            la[-1] = max(la[-1], la[:-1].min() - COUPLING_ALPHA_SPAN)
        fit = reg.solve(np.exp(la))
        if fit.rms < best["rms"]:
            best.update(rms=fit.rms, alphas=np.exp(la), fit=fit)
        history.append(best["rms"])
        if progress:
            progress(len(history), best["rms"])
        return fit.rms if np.isfinite(fit.rms) else 1e300

    if x0 is None:
        g = np.linspace(lo, hi, grid)
        g_vals = [objective(np.full(k, x)) for x in g[: max(2, min(grid, budget // 3))]]
        start = np.full(k, g[int(np.argmin(g_vals))])
    else:
        start = np.log(np.resize(np.asarray(x0, float), k))
        objective(start)
    remaining = budget - len(history)
    if remaining > 0:
        simplex = [start] + [start + step * e for e in np.eye(k)]
        minimize(objective, start, method="Nelder-Mead",
                 options={"maxfev": remaining, "xatol": 1e-4, "fatol": 1e-9,
                          "initial_simplex": np.array(simplex)})
    alphas, fit = best["alphas"], best["fit"]
    if reg.monotone_floor is not None:
        alphas, fit = keep_rising(reg, alphas, fit, lows, hi, history)
    return alphas, fit, history


MONOTONE_BUDGET = 60  # the alphas' search again where the best fit's branch turned back
MONOTONE_COST = 1.1   # a fit kept rising replaces the free one within this factor of RMS


def keep_rising(reg: DuhemRegression, alphas: np.ndarray, fit: Fit,
                lows: np.ndarray | None = None, hi: float = LOG_ALPHA_BOUNDS[1],
                history: list[float] | None = None,
                near: bool = False) -> tuple[np.ndarray, Fit]:
    """The best fit (``alphas``, ``fit``) with every branch of the main law kept rising
    (``reg.monotone``, at least ``reg.monotone_floor``): at these alphas, else with the
    alphas searched again under that constraint; taken where its RMS is within
    MONOTONE_COST of the free fit's, else the free fit stays (a record whose law cannot
    keep its branches rising at a fair cost: its exact inverse may then take another
    root where a branch turns back). ``near``: the search from ``alphas`` alone (no
    grid of shared alphas, half the budget): a fit whose alphas are already the free
    optimum's, refitted under the constraint where it is cheap to (the gap's
    candidates, each written as scored)."""
    if reg.monotone_floor is None:
        return alphas, fit
    kept = reg.monotone(alphas, fit)
    if kept is fit:
        return alphas, fit
    if kept is not None and kept.rms <= fit.rms * MONOTONE_COST:
        return alphas, kept
    low = np.full(len(alphas), LOG_ALPHA_BOUNDS[0]) if lows is None else lows
    found = _search_monotone(reg, alphas, kept, low, hi,
                             history if history is not None else [], near)
    if found is not None and found[1].rms <= fit.rms * MONOTONE_COST:
        return found
    return alphas, fit


def _search_monotone(reg: DuhemRegression, alphas: np.ndarray, fit: Fit | None,
                     lows: np.ndarray, hi: float, history: list[float],
                     near: bool = False) -> tuple[np.ndarray, Fit] | None:
    """The alphas whose fit, kept rising on every branch, is closest (None: none
    found): a coarse grid of shared alphas and a simplex from the best of it and from
    ``alphas`` (whose kept fit is ``fit``, or None)."""
    best: dict[str, Any] = {"rms": np.inf if fit is None else fit.rms,
                            "alphas": np.asarray(alphas, float), "fit": fit}
    k = len(best["alphas"])

    def objective(log_alphas: np.ndarray) -> float:
        la = np.clip(log_alphas, lows, hi)
        a = np.exp(la)
        f = reg.monotone(a, reg.solve(a))
        if f is None or not np.isfinite(f.rms):
            return 1e300
        if f.rms < best["rms"]:
            best.update(rms=f.rms, alphas=a, fit=f)
        history.append(best["rms"])
        return f.rms
    starts = [np.log(best["alphas"])]
    if not near:
        g = np.linspace(LOG_ALPHA_BOUNDS[0], hi, 9)
        vals = [objective(np.full(k, x)) for x in g]
        starts.insert(0, np.full(k, g[int(np.argmin(vals))]))
    for start in starts:
        simplex = [start] + [start + 0.5 * e for e in np.eye(k)]
        minimize(objective, start, method="Nelder-Mead",
                 options={"maxfev": MONOTONE_BUDGET // 2, "xatol": 1e-3, "fatol": 1e-9,
                          "initial_simplex": np.array(simplex)})
    return None if best["fit"] is None else (best["alphas"], best["fit"])
