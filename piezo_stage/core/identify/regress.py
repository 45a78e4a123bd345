"""Output-error regression of the Duhem model for fixed alphas (variable projection).

For fixed alpha_asc and alpha_desc the discrete Duhem output (seed eq. 6) is linear in
the polynomial coefficients and in the initial output w_0 (see _jit.duhem_regressors),
so the output-error least-squares problem of seed eq. 9 is solved exactly by one
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

from dataclasses import dataclass

import numpy as np
from numpy.polynomial import legendre as L
from numpy.polynomial import Polynomial, Legendre

from piezo_stage.core._jit import as_f64, duhem_regressors
from piezo_stage.core.duhem import DuhemBranch, DuhemModel, DuhemState


def _basis(v, lo, hi, deg):
    x = (2.0 * v - (lo + hi)) / (hi - lo) if hi > lo else np.zeros_like(v)
    return np.ascontiguousarray(L.legvander(x, deg))


def _to_power(c, lo, hi):
    """Legendre coefficients on [lo, hi] -> power coefficients in v."""
    return Legendre(c, domain=[lo, hi]).convert(kind=Polynomial).coef


@dataclass
class Fit:
    theta: np.ndarray
    rms: float
    pred: np.ndarray


class DuhemRegression:
    """Builds the regressors for one axis record and solves for fixed alphas.

    Parameters
    ----------
    v, w : arrays (N,)
        Voltage [V] and measured displacement [um].
    structure : 'whole' or 'segmented'
    n, m : int
        Degrees of f and g.
    v_other : array (N,) or None
        The other axis's voltage, to fit a coupling term (whole, degrees 1 and 1).

    Attributes ``transform`` (a linear operator on the columns, X -> E X: an
    unmodelled effect such as creep or dynamics acting after the hysteresis) and
    ``extra`` (fixed extra columns, e.g. a drift trend, appended after the transform)
    keep the fit one linear least-squares problem for fixed alphas; their
    coefficients come last in theta.
    """

    def __init__(self, v, w, structure="segmented", n=3, m=2, v_other=None,
                 coupling_deg=1, coupling_state=True):
        self.v = as_f64(v)
        self.w = as_f64(w)
        self.structure = structure
        self.n, self.m = int(n), int(m)
        self.D = max(self.n, self.m)
        self.lo, self.hi = float(self.v.min()), float(self.v.max())
        self.B = _basis(self.v, self.lo, self.hi, self.D)
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
            self.Bo = _basis(self.v_other, self.olo, self.ohi, self.cdeg)
        self.evaluations = 0
        self.transform = None
        self.extra = None
        self._X = np.empty((self.v.size, 2 * (self.D + 1) + 1))
        if self.v_other is not None:
            self._Xo = np.empty((self.v.size, 2 * (self.cdeg + 1) + 1))

    @property
    def n_alpha(self):
        return (1 if self.structure == "whole" else 2) + (self.v_other is not None)

    def _main_columns(self, a_asc, a_desc):
        X = duhem_regressors(self.v, self.v[0], np.array([a_asc, a_desc]), self.B, self.B,
                             self._X)
        d1 = self.D + 1
        Xa, Xd, free = X[:, :d1], X[:, d1:2 * d1], X[:, -1:]
        if self.structure == "whole":
            # theta = (f_0..f_n, g_0..g_m): rising sees f + g, falling g - f
            cols = [Xa[:, :self.n + 1] - Xd[:, :self.n + 1], Xa[:, :self.m + 1] + Xd[:, :self.m + 1]]
        else:
            cols = [Xa, Xd]
        return np.hstack(cols + [free])

    def _coupling_columns(self, a_c):
        X = duhem_regressors(self.v_other, self.v_other[0], np.array([a_c, a_c]), self.Bo,
                             self.Bo, self._Xo)
        d1 = self.cdeg + 1
        Xa, Xd, free = X[:, :d1], X[:, d1:2 * d1], X[:, -1:]
        return np.hstack([Xa - Xd, Xa + Xd] + ([free] if self.cstate else []))

    def design(self, alphas):
        alphas = np.atleast_1d(np.asarray(alphas, float))
        if self.structure == "whole":
            X = self._main_columns(alphas[0], alphas[0])
        else:
            X = self._main_columns(alphas[0], alphas[1])
        if self.v_other is not None:
            X = np.hstack([X, self._coupling_columns(alphas[-1])])
        return X

    def solve(self, alphas) -> Fit:
        """Exact least squares in the coefficients for these alphas."""
        self.evaluations += 1
        X = self.design(alphas)
        if self.transform is not None:
            X = self.transform(X)
        if self.extra is not None:
            X = np.hstack([X, self.extra])
        scale = np.linalg.norm(X, axis=0)
        scale[scale == 0] = 1.0
        Xs = X / scale
        # normal equations on unit-norm columns (Legendre basis: well conditioned, and
        # 10x faster than a QR of the tall matrix); a QR solve when they are not
        G = Xs.T @ Xs
        if np.linalg.cond(G) < 1e12:
            theta = np.linalg.solve(G, Xs.T @ self.w)
        else:
            theta, *_ = np.linalg.lstsq(Xs, self.w, rcond=None)
        theta = theta / scale
        pred = X @ theta
        r = pred - self.w
        return Fit(theta, float(np.sqrt(np.mean(r * r))), pred)

    def models(self, alphas, theta):
        """(main DuhemModel, coupling DuhemModel or None) in power coefficients [V]."""
        alphas = np.atleast_1d(np.asarray(alphas, float))
        d1 = self.D + 1
        if self.structure == "whole":
            nf, ng = self.n + 1, self.m + 1
            f = _to_power(theta[:nf], self.lo, self.hi)
            g = _to_power(theta[nf:nf + ng], self.lo, self.hi)
            k = nf + ng
            w0 = theta[k]
            main = DuhemModel.whole(alphas[0], f, g, DuhemState(self.v[0], w0))
        else:
            ha = _to_power(theta[:d1], self.lo, self.hi)
            hd = _to_power(theta[d1:2 * d1], self.lo, self.hi)
            k = 2 * d1
            w0 = theta[k]
            main = DuhemModel(DuhemBranch.from_h(alphas[0], ha),
                              DuhemBranch.from_h(alphas[1], hd), DuhemState(self.v[0], w0))
        coupling = None
        if self.v_other is not None:
            c1 = self.cdeg + 1
            o = theta[k + 1:k + 1 + 2 * c1 + self.cstate]  # extra columns come after
            fc = _to_power(o[:c1], self.olo, self.ohi)
            gc = _to_power(o[c1:2 * c1], self.olo, self.ohi)
            w0c = float(o[2 * c1]) if self.cstate else 0.0
            coupling = DuhemModel.whole(alphas[-1], fc, gc, DuhemState(self.v_other[0], w0c))
        return main, coupling
