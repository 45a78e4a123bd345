"""The estimation's compiled kernels (core/_jit.py compiles them): the identification's
regressors and objectives (``duhem_regressors``, ``duhem_rms_batch``,
``branch_rms_batch``, ``fold_branches``, ``unbounded_rows``) and the gap's holds
(``hold_runs_kernel``); they build on the model's (``duhem_step``, ``branch_step``)."""

import numpy as np

from piezo_stage.core._jit import F64, I64, PREFIX, njit
from piezo_stage.core.model._kernels import branch_step, duhem_step


def unbounded_rows(h: F64) -> F64:
    """Branch rows (PREFIX) for polynomials ``h`` (..., D) with no fitted range: the
    polynomial everywhere (the identification's candidates)."""
    pre = np.zeros(h.shape[:-1] + (PREFIX,))
    pre[..., 0], pre[..., 1] = -np.inf, np.inf
    return np.ascontiguousarray(np.concatenate([pre, h], axis=-1))


@njit
def duhem_regressors(v: F64, v_prev: float, alpha: F64, basis_asc: F64, basis_desc: F64,
                     out: F64) -> F64:
    """Columns of the output-error regression for fixed alphas.

    For fixed alpha_b the recursion w_k = a_k w_{k-1} + a_k dv_k H_b(v_k), with
    a_k = 1/(1 + alpha_b |dv_k|), is linear in the coefficients of H_b: w = X theta.
    Column j of X is that recursion driven by one basis input alone (zero initial
    state); the last column is the free response to w_0 = 1. ``basis_asc[k, i]`` and
    ``basis_desc[k, i]`` are the basis functions evaluated at v_k (for example
    (v_k/s)**i); columns 0..pa-1 belong to the ascending branch, pa..pa+pd-1 to the
    descending one. With the same basis in both slots and equal alphas this also
    serves the whole-curve model.
    """
    n = v.shape[0]
    pa = basis_asc.shape[1]
    pd = basis_desc.shape[1]
    p = pa + pd
    state = np.zeros(p + 1)
    state[p] = 1.0
    for k in range(n):
        vk = v[k]
        dv = vk - v_prev
        if dv >= 0.0:
            a = 1.0 / (1.0 + alpha[0] * dv)
            for j in range(p + 1):
                state[j] *= a
            for j in range(pa):
                state[j] += a * dv * basis_asc[k, j]
        else:
            a = 1.0 / (1.0 - alpha[1] * dv)
            for j in range(p + 1):
                state[j] *= a
            for j in range(pd):
                state[pa + j] += a * dv * basis_desc[k, j]
        for j in range(p + 1):
            out[k, j] = state[j]
        v_prev = vk
    return out


@njit
def duhem_rms_batch(v: F64, w_meas: F64, v0: float, w0: float, alpha: F64, H: F64,
                    out: F64) -> F64:
    """RMS output error [um] of K candidate models over one record (the paper's eq. 9 without
    its 1/sqrt(N) factor, which does not change the minimiser).

    alpha: (K, 2), H: (K, 2, D); each candidate starts from (v0, w0).
    """
    n = v.shape[0]
    for c in range(alpha.shape[0]):
        vp = v0
        wp = w0
        acc = 0.0
        for k in range(n):
            wp = duhem_step(vp, wp, v[k], alpha[c], H[c])
            vk = v[k]
            e = wp - w_meas[k]
            acc += e * e
            vp = vk
        out[c] = np.sqrt(acc / n) if np.isfinite(acc) else 1e300
    return out


@njit
def branch_rms_batch(v: F64, w_meas: F64, starts: I64, stops: I64, v_init: F64,
                     w_init: F64, alpha: F64, H: F64, out: F64) -> F64:
    """RMS error of K single-branch candidates over that branch's segments only.

    Segment j runs over samples starts[j]..stops[j]-1 from the state
    (v_init[j], w_init[j]) (the turning point before it, taken from the data), so
    each branch can be identified on its own (the paper's section 3.2).
    alpha: (K,), H: (K, D).
    """
    for c in range(alpha.shape[0]):
        acc = 0.0
        cnt = 0
        for j in range(starts.shape[0]):
            vp = v_init[j]
            wp = w_init[j]
            for k in range(starts[j], stops[j]):
                wp = branch_step(vp, wp, v[k], alpha[c], H[c])
                e = wp - w_meas[k]
                acc += e * e
                cnt += 1
                vp = v[k]
        out[c] = np.sqrt(acc / max(cnt, 1)) if np.isfinite(acc) else 1e300
    return out


@njit
def fold_branches(X: F64, d1: int, free: bool, out: F64) -> F64:
    """Whole-curve columns from per-branch regressors X = [ascending (d1), descending
    (d1), free response]: f sees ascending - descending, g ascending + descending
    (rising sees f + g, falling g - f); the free response last when ``free``."""
    for k in range(X.shape[0]):
        for j in range(d1):
            out[k, j] = X[k, j] - X[k, d1 + j]
            out[k, d1 + j] = X[k, j] + X[k, d1 + j]
        if free:
            out[k, 2 * d1] = X[k, X.shape[1] - 1]
    return out


@njit
def hold_runs_kernel(v: F64, tol: float, need: int, out: I64) -> int:
    """Stretches of at least ``need`` samples over which v stays within ``tol`` (its
    whole excursion, not sample to sample): writes (start, stop) pairs to out (rows),
    returns how many."""
    n = v.shape[0]
    count = 0
    if n == 0:
        return 0
    start, lo, hi = 0, v[0], v[0]
    for k in range(1, n + 1):
        if k < n:
            lo2 = min(lo, v[k])
            hi2 = max(hi, v[k])
            if hi2 - lo2 <= tol:
                lo, hi = lo2, hi2
                continue
        if k - start >= need:
            out[count, 0] = start
            out[count, 1] = k
            count += 1
        if k < n:
            start, lo, hi = k, v[k], v[k]
    return count
