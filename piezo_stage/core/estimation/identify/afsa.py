"""Artificial fish swarm (``afsa``) and the paper's bat-improved swarm (``afsa-bat``).

Standard AFSA (Li Xiaolei, 2002), minimising the output error (the paper's eq. 9 as RMS):
each fish at X_i with food concentration Y_i = J(X_i) tries, every iteration,
* swarm:  move a random fraction of ``step`` towards the centre X_c of the fish
          within ``visual``, if Y_c < Y_i and the neighbourhood is not crowded
          (n_f / N < delta);
* follow: the same towards the best fish within ``visual``;
* prey:   when a behaviour fails, try up to ``try_number`` random points within
          ``visual`` and move towards the first better one;
* random: when prey fails too, a random move of at most ``step``;
keeps the better of its swarm and follow results, and a bulletin board keeps the best
fish ever seen.

AFSA-bat (the paper's section 3.2, eqs. 7-8): each fish also carries a velocity with a bat's
pulse frequency f = f_min + (f_max - f_min) beta, beta ~ U(0, 1):
    swarm  V_i <- f V_i + (X_c - X_i)/|X_c - X_i| rand step          (eq. 7)
    follow V_i <- f V_i + (X_best - X_i)/|X_best - X_i| rand step    (eq. 8)
and moves X_i + V_i; the follow behaviour heads for the bulletin board's global best
rather than the best neighbour.

Search space (both variants): log(alpha) and the polynomial coefficients in a Legendre
basis over the record's voltage span, each scaled to [0, 1]. Segmented models are
identified one branch at a time (the paper's section 3.2) over that branch's segments, each
started from the measured displacement at its turning point; the whole-curve model
over the whole record. Evaluations are batched and compiled; all runs are seeded.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import TYPE_CHECKING, Any

import numpy as np

from piezo_stage.core._jit import as_f64
from piezo_stage.core.estimation._kernels import branch_rms_batch, duhem_rms_batch, unbounded_rows
from piezo_stage.core.estimation.identify.regress import legendre_to_power
from piezo_stage.core.model.duhem import DuhemBranch, DuhemModel, DuhemState
from piezo_stage.core.types import Doc

if TYPE_CHECKING:  # annotations only (api imports this module)
    from piezo_stage.core.estimation.identify.options import IdentifyOptions
    from piezo_stage.core.estimation.identify.segmentation import Segmentation

DEFAULTS: dict[str, Any] = {"fish": 30, "iterations": 200, "visual": 0.3, "step": 0.1,
                             "delta": 0.618, "try_number": 5, "f_min": 0.0, "f_max": 0.9,
                             "alpha_bounds": (1e-3, 0.3)}


def _leg2pow_matrix(lo: float, hi: float, deg: int) -> np.ndarray:
    """The basis change as a matrix: column i is Legendre P_i on [lo, hi] in powers."""
    T = np.zeros((deg + 1, deg + 1))
    for i, c in enumerate(np.eye(deg + 1)):
        p = legendre_to_power(c, lo, hi)
        T[:p.size, i] = p
    return T


class _Problem:
    """Maps unit-cube positions to model parameters and batches the objective."""

    def __init__(self, lo_hi: tuple[float, float], n_coef_blocks: int, deg_list: list[int],
                 B: float, alpha_bounds: tuple[float, float]) -> None:
        self.la = np.log(alpha_bounds)
        self.degs = deg_list
        self.B = B
        self.dim = 1 + sum(d + 1 for d in deg_list)
        self.T = [_leg2pow_matrix(lo_hi[0], lo_hi[1], d) for d in deg_list]
        self.evaluations = 0

    def decode(self, X: np.ndarray) -> tuple[np.ndarray, list[np.ndarray]]:
        X = np.atleast_2d(X)
        alpha = np.exp(self.la[0] + X[:, 0] * (self.la[1] - self.la[0]))
        polys = []
        k = 1
        for d, T in zip(self.degs, self.T):
            c = (2 * X[:, k:k + d + 1] - 1) * self.B
            polys.append(c @ T.T)
            k += d + 1
        return alpha, polys


class _BranchProblem(_Problem):
    def __init__(self, v: np.ndarray, w: np.ndarray, seg: Segmentation, ascending: bool,
                 deg: int, B: float, alpha_bounds: tuple[float, float]) -> None:
        super().__init__((v.min(), v.max()), 1, [deg], B, alpha_bounds)
        self.v, self.w = v, w
        sign = 1 if ascending else -1
        starts, stops, vi, wi = [], [], [], []
        for a, b, s in seg.segments:
            if s != sign or b - a < 2:
                continue
            p = max(a - 1, 0)
            starts.append(a if a > 0 else 1)
            stops.append(b)
            vi.append(v[p])
            wi.append(np.mean(w[max(p - 2, 0):p + 3]))  # smoothed turning-point output
        self.starts = np.array(starts, np.int64)
        self.stops = np.array(stops, np.int64)
        self.vi, self.wi = as_f64(vi), as_f64(wi)

    def __call__(self, X: np.ndarray) -> np.ndarray:
        alpha, (H,) = self.decode(X)
        out = np.empty(alpha.size)
        self.evaluations += alpha.size
        return branch_rms_batch(self.v, self.w, self.starts, self.stops, self.vi, self.wi,
                                alpha, unbounded_rows(H), out)


class _WholeProblem(_Problem):
    def __init__(self, v: np.ndarray, w: np.ndarray, n: int, m: int, B: float,
                 alpha_bounds: tuple[float, float]) -> None:
        super().__init__((v.min(), v.max()), 2, [n, m], B, alpha_bounds)
        self.v, self.w = v, w
        self.D = max(n, m) + 1
        self.w0 = float(np.mean(w[:3]))

    def fg(self, X: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        alpha, (F, G) = self.decode(X)
        return alpha, F, G

    def __call__(self, X: np.ndarray) -> np.ndarray:
        alpha, F, G = self.fg(X)
        K = alpha.size
        Fp = np.zeros((K, self.D))
        Gp = np.zeros((K, self.D))
        Fp[:, :F.shape[1]] = F
        Gp[:, :G.shape[1]] = G
        H = unbounded_rows(np.stack([Gp + Fp, Gp - Fp], axis=1))
        A = np.ascontiguousarray(np.column_stack([alpha, alpha]))
        out = np.empty(K)
        self.evaluations += K
        return duhem_rms_batch(self.v, self.w, self.v[0], self.w0, A, H, out)


def swarm_minimize(J: Callable[[np.ndarray], np.ndarray], dim: int, rng: np.random.Generator,
                   bat: bool = False, budget: int | None = None,
                   progress: Callable[..., None] | None = None, label: str = "",
                   **kw: float) -> tuple[np.ndarray, float, Doc]:
    """Minimise J over [0, 1]^dim. Returns (best x, best value, history).

    history: {"best": best value per iteration, "evaluations": cumulative count}.
    """
    p: dict[str, Any] = {**DEFAULTS, **kw}
    N, iters = int(p["fish"]), int(p["iterations"])
    visual, step, delta, tries = p["visual"], p["step"], p["delta"], int(p["try_number"])
    X = rng.random((N, dim))
    Y = J(X)
    evals = N
    V = np.zeros((N, dim))
    b = int(np.argmin(Y))
    best_x, best_y = X[b].copy(), float(Y[b])
    hist: dict[str, list] = {"best": [best_y], "evaluations": [evals]}

    def toward(xi: np.ndarray, target: np.ndarray, scale: float) -> np.ndarray:
        d = target - xi
        nrm = np.linalg.norm(d)
        return xi if nrm == 0 else np.clip(xi + d / nrm * scale, 0.0, 1.0)

    def prey(i: int) -> np.ndarray:
        nonlocal evals
        cand = np.clip(X[i] + visual * rng.uniform(-1, 1, (tries, dim)), 0.0, 1.0)
        yc = J(cand)
        evals += tries
        better = np.flatnonzero(yc < Y[i])
        if better.size:
            return toward(X[i], cand[better[0]], rng.random() * step)
        return np.clip(X[i] + step * rng.uniform(-1, 1, dim), 0.0, 1.0)  # random

    for it in range(iters):
        if budget is not None and evals >= budget:
            break
        dist = np.linalg.norm(X[:, None, :] - X[None, :, :], axis=2)
        new_X = np.empty_like(X)
        for i in range(N):
            nb = np.flatnonzero((dist[i] < visual) & (np.arange(N) != i))
            crowded = (nb.size + 1) / N >= delta
            # swarm
            xs = None
            if nb.size and not crowded:
                xc = X[nb].mean(axis=0)
                yc = J(xc[None])[0]
                evals += 1
                if yc < Y[i]:
                    if bat:
                        f = p["f_min"] + (p["f_max"] - p["f_min"]) * rng.random()
                        d = xc - X[i]
                        V[i] = f * V[i] + d / max(np.linalg.norm(d), 1e-300) * rng.random() * step
                        xs = np.clip(X[i] + V[i], 0.0, 1.0)
                    else:
                        xs = toward(X[i], xc, rng.random() * step)
            if xs is None:
                xs = prey(i)
            # follow
            xf = None
            if bat:
                if best_y < Y[i]:
                    f = p["f_min"] + (p["f_max"] - p["f_min"]) * rng.random()
                    d = best_x - X[i]
                    Vf = f * V[i] + d / max(np.linalg.norm(d), 1e-300) * rng.random() * step
                    xf = np.clip(X[i] + Vf, 0.0, 1.0)
            elif nb.size and not crowded:
                j = nb[int(np.argmin(Y[nb]))]
                if Y[j] < Y[i]:
                    xf = toward(X[i], X[j], rng.random() * step)
            if xf is None:
                xf = prey(i)
            ys, yf = J(np.stack([xs, xf]))
            evals += 2
            if ys <= yf:
                new_X[i], Y[i] = xs, ys
            else:
                new_X[i], Y[i] = xf, yf
                if bat:
                    V[i] = xf - X[i]
            if Y[i] < best_y:
                best_x, best_y = new_X[i].copy(), float(Y[i])
        X = new_X
        hist["best"].append(best_y)
        hist["evaluations"].append(evals)
        if progress:
            progress(it + 1, best_y, label)
    return best_x, best_y, hist


def coefficient_bound(v: np.ndarray, w: np.ndarray, alpha_hi: float) -> float:
    """Box half-width for the Legendre coefficients [um/V]: H = dw/dv + alpha w
    (ascending; - alpha w descending) is at most alpha_hi max|w| + a few slopes."""
    slope = np.ptp(w) / max(np.ptp(v), 1e-12)
    return 1.5 * (alpha_hi * np.max(np.abs(w)) + 3 * slope)


def fit_swarm(v: np.ndarray, w: np.ndarray, seg: Segmentation, opts: IdentifyOptions,
              progress: Callable[..., None] | None = None) -> tuple[DuhemModel, int, Doc]:
    """Identify one axis with afsa or afsa-bat; returns (DuhemModel, evaluations, history)."""
    v, w = as_f64(v), as_f64(w)
    kw = {**DEFAULTS, **(opts.afsa or {})}
    rng = np.random.default_rng(opts.seed)
    bat = opts.method == "afsa-bat"
    B = coefficient_bound(v, w, kw["alpha_bounds"][1])
    swarm_kw = {k: kw[k] for k in ("fish", "iterations", "visual", "step", "delta",
                                   "try_number", "f_min", "f_max")}
    if opts.structure == "whole":
        whole = _WholeProblem(v, w, opts.n, opts.m, B, kw["alpha_bounds"])
        x, _, h = swarm_minimize(whole, whole.dim, rng, bat, opts.budget, progress, "whole",
                                 **swarm_kw)
        alpha, F, G = whole.fg(x)
        model = DuhemModel.whole(alpha[0], F[0], G[0], DuhemState(v[0], whole.w0))
        return model, whole.evaluations, {"whole": h["best"], "evaluations": h["evaluations"]}
    deg = max(opts.n, opts.m)
    branches, hist, total = {}, {}, 0
    for name, asc in (("ascending", True), ("descending", False)):
        prob = _BranchProblem(v, w, seg, asc, deg, B, kw["alpha_bounds"])
        budget = None if opts.budget is None else opts.budget // 2
        x, _, h = swarm_minimize(prob, prob.dim, rng, bat, budget, progress, name,
                                 **swarm_kw)
        alpha, (H,) = prob.decode(x)
        branches[name] = DuhemBranch.from_h(alpha[0], H[0])
        hist[name] = h["best"]
        hist[name + "_evaluations"] = h["evaluations"]
        total += prob.evaluations
    model = DuhemModel(branches["ascending"], branches["descending"],
                       DuhemState(v[0], float(np.mean(w[:3]))))
    return model, total, hist
