"""Output-error regression of the Duhem model for fixed alphas (variable projection).

For fixed alpha_asc and alpha_desc the discrete Duhem output (the paper's eq. 6) is linear in
the polynomial coefficients and in the initial output w_0 (see _jit.duhem_regressors),
so the output-error least-squares problem of the paper's eq. 9 is solved exactly by one
linear least-squares solve; only the alphas need a search. Polynomials are expanded in
Legendre polynomials of the voltage mapped to [-1, 1] over the record's span, which
keeps the regression well conditioned, and converted to power coefficients in volts at
the end.

Parameterisations (honest about identifiability):
* whole:     f (degree n) and g (degree m) separately -- identifiable, since rising
             samples see f + g and falling ones g - f with the same alpha;
* segmented: per branch only h = f + g (ascending) and h = g - f (descending) of
             degree max(n, m) -- f and g are not separately identifiable there;
* coupling:  optional whole-curve Duhem term driven by the other axis's voltage.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np
from numpy.polynomial import Legendre, Polynomial
from numpy.polynomial import legendre as L
from numpy.typing import ArrayLike

from piezo_stage.core._jit import as_f64, duhem_regressors, fold_branches
from piezo_stage.core.model.duhem import DuhemBranch, DuhemModel, DuhemState


def legendre_basis(v: np.ndarray, lo: float, hi: float, deg: int) -> np.ndarray:
    """Legendre polynomials 0..deg of v mapped from [lo, hi] to [-1, 1], as columns."""
    x = (2.0 * v - (lo + hi)) / (hi - lo) if hi > lo else np.zeros_like(v)
    return np.ascontiguousarray(L.legvander(x, deg))


def legendre_to_power(c: ArrayLike, lo: float, hi: float) -> np.ndarray:
    """Legendre coefficients on [lo, hi] -> power coefficients in v."""
    return Legendre(np.asarray(c, float), domain=[lo, hi]).convert(kind=Polynomial).coef


@dataclass
class Fit:
    """A least-squares fit: coefficients and the RMS of its residual."""
    theta: np.ndarray
    rms: float


def gram(X: np.ndarray, w: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
    """(X'X, X'w, w'w): all a least-squares fit needs. One pass of BLAS over the tall
    matrix; every later step is p x p."""
    return X.T @ X, X.T @ w, float(w @ w)


def gram_blocks(blocks: Sequence[np.ndarray],
                w: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
    """``gram`` of the columns side by side, without building the wide matrix."""
    if len(blocks) == 1:
        return gram(blocks[0], w)
    rows = [[bi.T @ bj for bj in blocks] for bi in blocks]
    return np.block(rows), np.concatenate([bi.T @ w for bi in blocks]), float(w @ w)


def solve_gram(G: np.ndarray, b: np.ndarray, ww: float, n: int) -> Fit:
    """The least-squares solution from the normal equations, on unit-norm columns (the
    Legendre basis keeps them well conditioned); a minimum-norm solve of the small
    system where they are not. RMS from r'r = w'w - 2 theta'b + theta'G theta."""
    scale = np.sqrt(np.clip(np.diag(G), 0.0, None))
    scale[scale == 0] = 1.0
    Gs = G / np.outer(scale, scale)
    bs = b / scale
    if np.linalg.cond(Gs) < 1e12:
        ts = np.linalg.solve(Gs, bs)
    else:
        ts = np.linalg.lstsq(Gs, bs, rcond=1e-13)[0]
    theta = ts / scale
    rr = ww - 2.0 * theta @ b + theta @ G @ theta
    return Fit(theta, float(np.sqrt(max(rr, 0.0) / n)))


class DuhemRegression:
    """Builds the regressors for one axis record and solves for fixed alphas.

    Parameters
    ----------
    v, w : arrays (N,)
        Voltage [V] and measured displacement [um].
    structure : {'whole', 'segmented'}
        One (alpha, f, g) for both branches, or one per branch.
    n, m : int
        Degrees of f and g.
    v_other : array (N,) or None
        The other axis's voltage, to fit a coupling term (whole, degrees 1 and 1).
    coupling_deg : int
        Degree of the coupling term's polynomial.
    coupling_state : bool
        Whether the coupling term's initial output is a free coefficient.

    Notes
    -----
    The attributes ``transform`` (a linear operator on the columns, X to E X: an
    unmodelled effect such as creep or dynamics acting after the hysteresis) and
    ``extra`` (fixed extra columns, e.g. a drift trend, appended after the transform)
    keep the fit one linear least-squares problem for fixed alphas; their
    coefficients come last in theta.
    """

    def __init__(self, v: ArrayLike, w: ArrayLike, structure: str = "segmented", n: int = 3,
                 m: int = 2, v_other: ArrayLike | None = None, coupling_deg: int = 1,
                 coupling_state: bool = True):
        self.v = as_f64(v)
        self.w = as_f64(w)
        self.structure = structure
        self.n, self.m = int(n), int(m)
        self.D = max(self.n, self.m)
        self.lo, self.hi = float(self.v.min()), float(self.v.max())
        self.B = legendre_basis(self.v, self.lo, self.hi, self.D)
        self.v_other = None if v_other is None else as_f64(v_other)
        self.cdeg = int(coupling_deg)
        # coupling_state=False pins the coupling's initial output to 0: a model meant for
        # inversion keeps every constant in the main term. Left free, a coupling whose
        # alpha goes to 0 becomes a permanent offset split against the main term's
        # initial state (the data cannot tell them apart), which the inverse, started
        # mid-run from a coupling output of 0, turns into a tracking offset.
        self.cstate = bool(coupling_state)
        if self.v_other is not None:
            self.olo, self.ohi = float(self.v_other.min()), float(self.v_other.max())
            self.Bo = legendre_basis(self.v_other, self.olo, self.ohi, self.cdeg)
        self.evaluations = 0
        # an operator on the columns (the gap's effects) and more columns after them
        self.transform: Callable[[np.ndarray], np.ndarray] | None = None
        self.extra: np.ndarray | None = None
        self._X = np.empty((self.v.size, 2 * (self.D + 1) + 1))
        if self.v_other is not None:
            self._Xo = np.empty((self.v.size, 2 * (self.cdeg + 1) + 1))
            self._Xc = np.empty((self.v.size, 2 * (self.cdeg + 1) + self.cstate))

    def __getstate__(self) -> dict:
        # the bases and work buffers follow from v (a fit's regression crosses a process
        # boundary in the gap diagnosis: without them it is the data and the settings)
        return {k: v for k, v in self.__dict__.items()
                if k not in ("B", "Bo", "_X", "_Xo", "_Xc")}

    def __setstate__(self, state: dict) -> None:
        self.__dict__.update(state)
        self.B = legendre_basis(self.v, self.lo, self.hi, self.D)
        self._X = np.empty((self.v.size, 2 * (self.D + 1) + 1))
        if self.v_other is not None:
            self.Bo = legendre_basis(self.v_other, self.olo, self.ohi, self.cdeg)
            self._Xo = np.empty((self.v.size, 2 * (self.cdeg + 1) + 1))
            self._Xc = np.empty((self.v.size, 2 * (self.cdeg + 1) + self.cstate))

    @property
    def n_alpha(self) -> int:
        """How many alphas the regression's model has."""
        return (1 if self.structure == "whole" else 2) + (self.v_other is not None)

    def _main_columns(self, a_asc, a_desc):
        X = duhem_regressors(self.v, self.v[0], np.array([a_asc, a_desc]), self.B, self.B,
                             self._X)
        if self.structure != "whole":
            return X  # already (ascending, descending, free): no copy
        d1 = self.D + 1
        Xa, Xd, free = X[:, :d1], X[:, d1:2 * d1], X[:, -1:]
        # theta = (f_0..f_n, g_0..g_m): rising sees f + g, falling g - f
        return np.hstack([Xa[:, :self.n + 1] - Xd[:, :self.n + 1],
                          Xa[:, :self.m + 1] + Xd[:, :self.m + 1], free])

    def _coupling_columns(self, a_c):
        X = duhem_regressors(self.v_other, self.v_other[0], np.array([a_c, a_c]), self.Bo,
                             self.Bo, self._Xo)
        return fold_branches(X, self.cdeg + 1, self.cstate, self._Xc)

    def blocks(self, alphas: ArrayLike) -> list[np.ndarray]:
        """The regressor columns for these alphas as blocks [main, coupling] (the main
        block is a buffer reused by the next call: use or copy it before then)."""
        alphas = np.atleast_1d(np.asarray(alphas, float))
        if self.structure == "whole":
            out = [self._main_columns(alphas[0], alphas[0])]
        else:
            out = [self._main_columns(alphas[0], alphas[1])]
        if self.v_other is not None:
            out.append(self._coupling_columns(alphas[-1]))
        return out

    def design(self, alphas: ArrayLike) -> np.ndarray:
        """The regressor columns (N, p) for these alphas."""
        b = self.blocks(alphas)
        return b[0] if len(b) == 1 else np.hstack(b)

    def column_blocks(self, alphas: Sequence[float]) -> list[np.ndarray]:
        """Every column of the fit for these alphas, in blocks: design blocks
        transformed, then the extra columns."""
        out = self.blocks(alphas)
        if self.transform is not None:
            out = [self.transform(b) for b in out]
        if self.extra is not None:
            out.append(self.extra)
        return out

    def columns(self, alphas: Sequence[float]) -> np.ndarray:
        """Every column of the fit for these alphas: design, transformed, extra."""
        b = self.column_blocks(alphas)
        return b[0] if len(b) == 1 else np.hstack(b)

    def solve(self, alphas: Sequence[float]) -> Fit:
        """Exact least squares in the coefficients for these alphas."""
        self.evaluations += 1
        return solve_gram(*gram_blocks(self.column_blocks(alphas), self.w), len(self.w))

    def predict(self, alphas: Sequence[float], theta: np.ndarray) -> np.ndarray:
        """The fitted output for these alphas and coefficients [um]."""
        return self.columns(alphas) @ theta

    def models(self, alphas: ArrayLike,
               theta: np.ndarray) -> tuple[DuhemModel, DuhemModel | None]:
        """(main DuhemModel, coupling DuhemModel or None) in power coefficients [V]."""
        alphas = np.atleast_1d(np.asarray(alphas, float))
        d1 = self.D + 1
        if self.structure == "whole":
            nf, ng = self.n + 1, self.m + 1
            f = legendre_to_power(theta[:nf], self.lo, self.hi)
            g = legendre_to_power(theta[nf:nf + ng], self.lo, self.hi)
            k = nf + ng
            w0 = theta[k]
            main = DuhemModel.whole(alphas[0], f, g, DuhemState(self.v[0], w0))
        else:
            ha = legendre_to_power(theta[:d1], self.lo, self.hi)
            hd = legendre_to_power(theta[d1:2 * d1], self.lo, self.hi)
            k = 2 * d1
            w0 = theta[k]
            main = DuhemModel(DuhemBranch.from_h(alphas[0], ha),
                              DuhemBranch.from_h(alphas[1], hd), DuhemState(self.v[0], w0))
        coupling = None
        if self.v_other is not None:
            c1 = self.cdeg + 1
            o = theta[k + 1:k + 1 + 2 * c1 + self.cstate]  # extra columns come after
            fc = legendre_to_power(o[:c1], self.olo, self.ohi)
            gc = legendre_to_power(o[c1:2 * c1], self.olo, self.ohi)
            w0c = float(o[2 * c1]) if self.cstate else 0.0
            coupling = DuhemModel.whole(alphas[-1], fc, gc, DuhemState(self.v_other[0], w0c))
            if self.olo < self.ohi:
                coupling = coupling.with_fit_range(self.olo, self.ohi)
        if self.lo < self.hi:  # past the record's voltages a branch continues from its end
            main = main.with_fit_range(self.lo, self.hi)
        return main, coupling


def coupling_term(v_other: ArrayLike, alpha: float,
                  deg: int = 1) -> tuple[np.ndarray, Callable[[np.ndarray], DuhemModel]]:
    """A coupling term for a model fitted by other means than ``DuhemRegression`` (the
    classes with memory): the whole-curve Duhem law of the other axis's voltage
    ``v_other`` [V] at a fixed ``alpha`` [1/V], f and g of degree ``deg``, its output 0
    at the record's first voltage. -> (columns (N, 2 (deg + 1)), linear in its
    coefficients; coefficients -> the coupling DuhemModel, as a model file holds it)."""
    reg = DuhemRegression(v_other, np.zeros(len(np.asarray(v_other))), "whole", n=deg,
                          m=deg)
    cols = reg.design([alpha])[:, :-1].copy()  # f and g; the initial output pinned at 0

    def model(coef: np.ndarray) -> DuhemModel:
        return reg.models([alpha], np.append(np.asarray(coef, float), 0.0))[0]
    return cols, model
