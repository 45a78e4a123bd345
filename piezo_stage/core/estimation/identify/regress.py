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

from piezo_stage.core._jit import as_f64
from piezo_stage.core.estimation._kernels import duhem_regressors, fold_branches
from piezo_stage.core.model.duhem import DuhemBranch, DuhemModel, DuhemState
from piezo_stage.core.types import Doc


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
    The attributes ``beside`` (fixed columns of the hysteresis beside the Duhem law,
    e.g. play operators: part of its output, so after the law's and the coupling's
    columns, under the transform with them), ``transform`` (a linear operator on the
    columns, X to E X: an unmodelled effect such as creep or dynamics acting after the
    hysteresis, as the plant applies it) and ``extra`` (fixed extra columns, e.g. a
    drift trend, appended after the transform) keep the fit one linear least-squares
    problem for fixed alphas; their coefficients come last in theta, in that order.
    """

    def __init__(self, v: ArrayLike, w: ArrayLike, structure: str = "segmented", n: int = 3,
                 m: int = 2, v_other: ArrayLike | None = None, coupling_deg: int = 1,
                 coupling_state: bool = True) -> None:
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
        # more columns of the hysteresis, an operator on the columns (the gap's
        # effects) and more columns after them
        self.beside: np.ndarray | None = None
        # the record's first rows are run, not fitted (a delay's first outputs hold
        # voltages from before the record, which a record cut from a run never had)
        self.fit_from = 0
        self.transform: Callable[[np.ndarray], np.ndarray] | None = None
        self.extra: np.ndarray | None = None
        # the least slope [um/V] the main law keeps on every branch (``monotone``), or
        # None: its coefficients free
        self.monotone_floor: float | None = None
        self._X = np.empty((self.v.size, 2 * (self.D + 1) + 1))
        if self.v_other is not None:
            self._Xo = np.empty((self.v.size, 2 * (self.cdeg + 1) + 1))
            self._Xc = np.empty((self.v.size, 2 * (self.cdeg + 1) + self.cstate))

    def __getstate__(self) -> Doc:
        # the bases and work buffers follow from v (a fit's regression crosses a process
        # boundary in the gap diagnosis: without them it is the data and the settings)
        return {k: v for k, v in self.__dict__.items()
                if k not in ("B", "Bo", "_X", "_Xo", "_Xc")}

    def __setstate__(self, state: Doc) -> None:
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

    def _main_columns(self, a_asc: float, a_desc: float,
                      v: np.ndarray | None = None) -> np.ndarray:
        if v is None:
            X = duhem_regressors(self.v, self.v[0], np.array([a_asc, a_desc]), self.B,
                                 self.B, self._X)
        else:  # another path, in this record's basis (from the same initial state)
            B = legendre_basis(v, self.lo, self.hi, self.D)
            X = duhem_regressors(v, v[0], np.array([a_asc, a_desc]), B, B,
                                 np.empty((v.size, 2 * (self.D + 1) + 1)))
        if self.structure != "whole":
            return X  # already (ascending, descending, free): no copy
        d1 = self.D + 1
        Xa, Xd, free = X[:, :d1], X[:, d1:2 * d1], X[:, -1:]
        # theta = (f_0..f_n, g_0..g_m): rising sees f + g, falling g - f
        return np.hstack([Xa[:, :self.n + 1] - Xd[:, :self.n + 1],
                          Xa[:, :self.m + 1] + Xd[:, :self.m + 1], free])

    def _coupling_columns(self, a_c: float) -> np.ndarray:
        assert self.v_other is not None  # (only a regression with coupling has them)
        X = duhem_regressors(self.v_other, self.v_other[0], np.array([a_c, a_c]), self.Bo,
                             self.Bo, self._Xo)
        return fold_branches(X, self.cdeg + 1, self.cstate, self._Xc)

    def blocks(self, alphas: ArrayLike) -> list[np.ndarray]:
        """The regressor columns of the hysteresis for these alphas as blocks [main,
        coupling, beside] (the main block is a buffer reused by the next call: use or
        copy it before then)."""
        alphas = np.atleast_1d(np.asarray(alphas, float))
        if self.structure == "whole":
            out = [self._main_columns(alphas[0], alphas[0])]
        else:
            out = [self._main_columns(alphas[0], alphas[1])]
        if self.v_other is not None:
            out.append(self._coupling_columns(alphas[-1]))
        if self.beside is not None:
            out.append(self.beside)
        return out

    def design(self, alphas: ArrayLike) -> np.ndarray:
        """The regressor columns (N, p) for these alphas."""
        b = self.blocks(alphas)
        return b[0] if len(b) == 1 else np.hstack(b)

    def column_blocks(self, alphas: ArrayLike) -> list[np.ndarray]:
        """Every column of the fit for these alphas, in blocks: design blocks
        transformed, then the extra columns; the rows fitted (from ``fit_from``)."""
        out = self.blocks(alphas)
        if self.transform is not None:
            out = [self.transform(b) for b in out]
        if self.extra is not None:
            out.append(self.extra)
        return [b[self.fit_from:] for b in out] if self.fit_from else out

    @property
    def fitted_w(self) -> np.ndarray:
        """The displacement of the rows fitted (from ``fit_from``) [um]."""
        return self.w[self.fit_from:]

    def columns(self, alphas: ArrayLike) -> np.ndarray:
        """Every column of the fit for these alphas: design, transformed, extra."""
        b = self.column_blocks(alphas)
        return b[0] if len(b) == 1 else np.hstack(b)

    def solve(self, alphas: Sequence[float]) -> Fit:
        """Exact least squares in the coefficients for these alphas."""
        self.evaluations += 1
        w = self.fitted_w
        return solve_gram(*gram_blocks(self.column_blocks(alphas), w), len(w))

    def predict(self, alphas: Sequence[float], theta: np.ndarray) -> np.ndarray:
        """The fitted output for these alphas and coefficients over the rows fitted
        [um]."""
        return self.columns(alphas) @ theta

    def monotone(self, alphas: ArrayLike, fit: Fit) -> Fit | None:
        """``fit`` (for these alphas) with the main law kept rising on every branch by
        at least ``monotone_floor`` over the record and over ``probe_voltages`` (the
        major loop, minor loops from its ends and nested loops, over the branch
        polynomials' range within 0-150 V widened to the record's): a law whose branch
        turns back (a descending branch whose shape h goes negative where its memory's
        pull alpha w does not make up for it) has no one voltage for a displacement, and
        our exact inverse then takes another root (by 9 V on a rate-dependent stage's
        rising triangles). ``fit`` itself where it already rises everywhere there (or
        no floor is set); None where no coefficients can."""
        if self.monotone_floor is None or not self.hi > self.lo:
            return fit
        from piezo_stage.core.model.duhem import polynomial_range, voltage_limits_for
        plo, phi = polynomial_range((self.lo, self.hi))
        alo, ahi = voltage_limits_for([self.v])
        probe = probe_voltages(float(self.v[0]), max(plo, alo), min(phi, ahi))
        th = monotone_theta(self, alphas, fit.theta, self.monotone_floor, probe)
        if th is None or th is fit.theta:
            return None if th is None else fit
        r = self.fitted_w - self.columns(alphas) @ th
        return Fit(th, float(np.sqrt(np.mean(r ** 2))))

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


def _slope_rows(reg: DuhemRegression, alphas: ArrayLike,
                v: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """(rows, dv): for each sample k that moves, the row c_k of the main law's
    coefficients with c_k theta = h_b(v_k) - alpha_b sign(dv_k) w_(k-1) (its branch b's
    shape less its memory's pull): the law's step dw_k has the sign of dv_k times this
    (w_k - w_(k-1) = dv_k c_k theta / (1 + alpha_b |dv_k|)), so the output rises with
    the voltage on every branch exactly where every c_k theta >= 0. Over the record, or
    over another path ``v`` from the record's initial state (its first voltage the
    record's; within the branch polynomials' range, where the basis is the law)."""
    alphas = np.atleast_1d(np.asarray(alphas, float))
    if v is None:
        v, B = reg.v, reg.B
        X = reg.blocks(alphas)[0].copy()  # the main law's output columns (w_0 last)
    else:
        B = legendre_basis(v, reg.lo, reg.hi, reg.D)
        a_d = alphas[0] if reg.structure == "whole" else alphas[1]
        X = reg._main_columns(alphas[0], a_d, v)
        if reg.structure == "whole":
            X = X.copy()
    p = X.shape[1]
    prev = np.vstack([np.eye(1, p, p - 1), X[:-1]])  # w_(k-1) (w_0 before the first)
    dv = np.diff(v, prepend=v[0])
    up = dv >= 0
    H = np.zeros((v.size, p))
    if reg.structure == "whole":
        nf, ng = reg.n + 1, reg.m + 1
        H[:, :nf] = np.where(up[:, None], 1.0, -1.0) * B[:, :nf]
        H[:, nf:nf + ng] = B[:, :ng]
        a = np.full(v.size, alphas[0])
    else:
        d1 = reg.D + 1
        H[:, :d1] = np.where(up[:, None], B, 0.0)
        H[:, d1:2 * d1] = np.where(up[:, None], 0.0, B)
        a = np.where(up, alphas[0], alphas[1])
    rows = H - (a * np.sign(dv))[:, None] * prev
    moves = dv != 0
    return rows[moves], dv[moves]


def monotone_theta(reg: DuhemRegression, alphas: ArrayLike, theta: np.ndarray,
                   floor: float, probe: np.ndarray | None = None,
                   rounds: int = 6) -> np.ndarray | None:
    """The least-squares coefficients for these alphas (every column of the fit, as
    ``solve``) under the constraint that the main law's output rises with the voltage
    on every branch by at least ``floor`` [um/V] at every step of the record
    (``_slope_rows``); ``theta`` when it already does, None when no coefficients do.
    A least-squares problem with linear inequality constraints, solved as Lawson and
    Hanson's least distance programme (one non-negative least squares on the
    constraints' rows), with the constraints the unconstrained fit breaks or nearly
    breaks, more added while any is broken."""
    from scipy.optimize import nnls
    rows, _ = _slope_rows(reg, alphas)
    if probe is not None:
        rows = np.vstack([rows, _slope_rows(reg, alphas, probe)[0]])
    p_main = rows.shape[1]
    k = len(theta)
    G = np.zeros((rows.shape[0], k))
    G[:, :p_main] = rows
    c = G @ theta
    if np.all(c >= floor * (1 - 1e-9)):
        return theta
    A = reg.columns(alphas)
    scale = np.sqrt(np.clip(np.einsum("ij,ij->j", A, A), 1e-300, None))
    As = A / scale  # unit columns: a well-conditioned factor
    Rf = np.asarray(np.linalg.qr(As, mode="r"))
    q = np.linalg.solve(Rf.T, As.T @ reg.fitted_w)
    Rinv = np.linalg.inv(Rf)
    Gs = G / scale  # in the scaled coefficients
    E = Gs @ Rinv
    f = floor - E @ q
    active = np.flatnonzero(c < floor + 0.1 * max(float(np.median(np.abs(c))), floor))
    for _ in range(rounds):
        M = np.vstack([E[active].T, f[active][None, :]])
        e = np.zeros(M.shape[0])
        e[-1] = 1.0
        u, _ = nnls(M, e, maxiter=50 * M.shape[1])
        r = M @ u - e
        if abs(r[-1]) < 1e-12:
            return None  # the constraints cannot all hold
        z = -r[:-1] / r[-1]
        ts = Rinv @ (z + q)
        th = ts / scale
        broken = np.flatnonzero(G @ th < floor * (1 - 1e-6) - 1e-12)
        new = np.setdiff1d(broken, active)
        if new.size == 0:
            return th
        active = np.union1d(active, new)
    return None  # (still broken after every round)


def probe_voltages(v0: float, lo: float, hi: float, steps: int = 100) -> np.ndarray:
    """A voltage path from ``v0`` over [lo, hi] with reversals of every size: the
    major loop, minor loops hanging from its top and its bottom, and loops nested about
    the middle; ``steps`` samples per full span, and eight more right after each
    reversal, from 1e-4 of the segment on."""
    s = hi - lo
    turns = [hi, lo, hi]
    for f in (0.1, 0.3, 0.6):
        turns += [hi - f * s, hi]
    turns += [lo]
    for f in (0.1, 0.3, 0.6):
        turns += [lo + f * s, lo]
    mid = 0.5 * (lo + hi)
    for f in (0.45, 0.3, 0.15, 0.05, 0.15, 0.3, 0.45):
        turns += [mid + f * s, mid - f * s]
    path = [np.array([v0])]
    for a, b in zip([v0] + turns[:-1], turns):
        # dense right after each reversal, where a branch's slope is least
        n = max(2, int(abs(b - a) / s * steps))
        u = np.concatenate([np.geomspace(1e-4, 0.5 / n, 8), np.linspace(1.0 / n, 1.0, n)])
        path.append(a + (b - a) * u)
    return np.concatenate(path)
