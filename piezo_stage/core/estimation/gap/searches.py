"""The searches of the gap candidates' parameters: one-dimensional and profile
searches of a transform effect's parameters (creep, delay, dynamics) with the model's
other coefficients refitted by least squares at each step, the rate widening of play
operators, and the resonance seeds read off the data."""

from __future__ import annotations

from collections.abc import Callable, Sequence

import numpy as np
from numpy.typing import ArrayLike
from scipy import signal
from scipy.optimize import minimize, minimize_scalar

from piezo_stage.core.estimation.gap.operators import (
    CREEP_TAUS,
    identity,
    transform_ops,
)
from piezo_stage.core.estimation.identify.regress import (
    DuhemRegression,
    gram_blocks,
    solve_gram,
)
from piezo_stage.core.model.effects import Creep, Delay, Drift, Dynamics
from piezo_stage.core.model.play import MAX_RATE_WIDENING_S, play_columns
from piezo_stage.core.types import EffectsBlock, Params

Op = Callable[[np.ndarray], np.ndarray]  # a transform of a design's columns
Cost = Callable[[Params], float]  # an effect's parameters -> the fit's RMS [um]
# (cost, where to start or None) -> the parameters that minimise the cost
Search = Callable[[Cost, Params | None], Params]


def search_1d(f: Callable[[float], float], lo: float, hi: float, n_grid: int = 12,
              log: bool = False) -> tuple[float, float]:
    """The minimum of ``f`` over [lo, hi]: a grid (geometric with ``log``), then a
    bounded search between the best point's neighbours. -> (x, f(x))."""
    g = np.geomspace(lo, hi, n_grid) if log else np.linspace(lo, hi, n_grid)
    vals = [f(x) for x in g]
    i = int(np.argmin(vals))
    a, b = g[max(i - 1, 0)], g[min(i + 1, n_grid - 1)]
    r = minimize_scalar(f, bounds=(a, b), method="bounded", options={"xatol": (b - a) * 1e-3})
    return (r.x, r.fun) if r.fun <= vals[i] else (g[i], vals[i])


def delay_max_s(fs: float) -> float:
    """The longest delay the delay candidate searches [s] (20 ms, or 50 samples)."""
    return min(0.02, 50 / fs)


def delay_rows(effects: Sequence[tuple[str, EffectsBlock]], fs: float) -> int:
    """A record's first rows a model with these effects runs but does not fit: those
    whose output its delay takes from voltages before the record (held at the record's
    first voltage there, which a record cut from a run never was: on a measured stack's
    record that started moving, its 15 ms lag was found as 0.7 ms). 0 without a delay."""
    d = float(dict(effects).get("delay", {}).get("delay_s", 0.0))
    return int(np.ceil(d * fs - 1e-9))


def search_transform(effect: str, design_without: Callable[[Sequence[str]], np.ndarray],
                     extra: list, w: np.ndarray, fs: float,
                     kept: Sequence[tuple[str, Params]], rows: int = 0
                     ) -> tuple[Params, list[tuple[str, Params]]]:
    """A transform effect's parameters (creep, delay, dynamics) searched on FIT, the
    model's other coefficients refitted by least squares at each step over the rows
    from ``rows`` on (the columns run from the record's start; a delay's search over
    those its longest trial takes from before the record: ``delay_rows``).
    ``design_without(names)`` gives the model's columns through the kept transform
    effects except ``names``; ``extra`` are columns after them (a constant, a drift).
    -> (params, kept: a kept delay polished together with a resonance found now)."""
    kept = list(kept)
    if effect == "delay":  # every delay tried is judged on the rows none takes from
        rows = max(rows, delay_rows([("delay", {"delay_s": delay_max_s(fs)})], fs))
    # the kept operators applied once; the new effect's parameter search then filters
    # only what it must (creep: once in all)
    KX = np.array(design_without(()))  # (a copy: a design may be a reused buffer)
    wf = w[rows:]
    extra_f = [e[rows:] for e in extra]

    def solve(cols: np.ndarray) -> float:
        return solve_gram(*gram_blocks([cols[rows:]] + extra_f, wf), len(wf)).rms

    if effect == "creep":
        F = Creep(fs, tau_s=CREEP_TAUS).fast_part(KX)
        g, _ = search_1d(lambda g: solve(KX - g * F), 0.0, 0.3)
        return {"gamma": float(g), "tau_s": list(CREEP_TAUS)}, kept
    if effect == "delay":
        dmax = delay_max_s(fs)

        def search_delay(cost: Cost, p0: Params | None) -> Params:
            return {"delay_s": float(search_1d(lambda d: cost({"delay_s": d}), 0.0,
                                                dmax, n_grid=15)[0])}

        def delay_op(p: Params) -> Op:
            return Delay(fs, delay_s=p["delay_s"]).apply
        B = KX
        if "dynamics" in dict(kept):  # the pair's exact sampled form
            dyn = dict(kept)["dynamics"]
            B = design_without(("delay", "dynamics"))

            def delay_op(p: Params) -> Op:
                return _chain([("dynamics", dyn), ("delay", p)], fs)
        # the alternation starts from the whole-sample delay whose exact refit fits best
        # (held coefficients fitted without a delay take the lag's phase in and lead a
        # one-column search to a small delay: a measured stack's 3-sample lag was found
        # as 0.7 ms)
        whole = np.unique(np.round(np.linspace(0, np.floor(dmax * fs), 12)).astype(int))
        p0 = min(({"delay_s": k / fs} for k in whole), key=lambda p: solve(delay_op(p)(B)))
        found = _alternate(B, extra, w, search_delay, p0, delay_op, rows=rows)
        dyn0 = dict(kept).get("dynamics")
        if dyn0 is None or dyn0.get("kind") != "resonance":
            return found, kept
        # a resonance fitted before the delay took the delay's phase as well (a lag-like
        # resonance stood in for it): the two polished together, as where the
        # resonance comes second
        def pair_op(p: Params) -> Op:
            dyn_p = {k: v for k, v in p.items() if k != "delay_s"}
            return _chain([("dynamics", dyn_p), ("delay", {"delay_s": p["delay_s"]})], fs)
        both = _alternate(B, extra, w, lambda cost, q0: _polish_pair(q0, fs, cost),
                          {**dyn0, **found}, pair_op, rows=rows)
        d = {"delay_s": float(both.pop("delay_s"))}
        kept = [(n, both if n == "dynamics" else p) for n, p in kept]
        return d, kept
    if effect != "dynamics":
        raise ValueError(f"{effect} is not a transform effect")
    seeds = _resonance_seeds(KX, w, fs, extra)

    # from the data's peak and the last alternation's end
    def search(cost: Cost, p0: Params | None) -> Params:
        last = [(p0["fn_hz"], p0["zeta"])] if p0 and p0["kind"] == "resonance" else []
        return _search_dynamics(fs, cost, seeds + last if seeds else seeds)
    if "delay" not in dict(kept):
        return _alternate(KX, extra, w, search, None, lambda p: Dynamics(fs, **p).apply,
                          start=identity, rows=rows), kept
    d0 = dict(kept)["delay"]
    KB = design_without(("delay",))

    def dyn_op(p: Params) -> Op:
        return _chain([("dynamics", p), ("delay", d0)], fs)
    params = _alternate(KB, extra, w, search, None, dyn_op, start=Delay(fs, **d0).apply,
                        rows=rows)
    if seeds and params["kind"] == "resonance":
        # a delay fitted before the resonance took the resonance's phase as well (on a
        # record whose chirp excites it): the resonance and the delay polished together
        def pair_op(p: Params) -> Op:
            dyn_p = {k: v for k, v in p.items() if k != "delay_s"}
            return _chain([("dynamics", dyn_p), ("delay", {"delay_s": p["delay_s"]})], fs)
        both = _alternate(KB, extra, w, lambda cost, p0: _polish_pair(p0, fs, cost),
                          {**params, "delay_s": float(d0["delay_s"])}, pair_op, rows=rows)
        d = both.pop("delay_s")
        params = both
        kept = [(n, {**p, "delay_s": d} if n == "delay" else p) for n, p in kept]
    return params, kept


PLAY_STARTS = (0.0, 1.0, -1.0)  # operators at rest at v[0], after a fall, after a rise


RATE_MIN_GAIN = 0.01  # relative FIT RMS a widening must win over none to be kept


def rate_search(reg: DuhemRegression, alphas: ArrayLike, kept: Sequence[tuple[str, Params]],
                plays: np.ndarray, v: np.ndarray, w: np.ndarray, fs: float,
                tau: float | None) -> float:
    """The play thresholds' rate widening beta [s] that fits FIT best, the Duhem alphas
    held at ``alphas`` (each trial is one exact least squares over the operators'
    columns at that beta); 0 unless it beats no widening on FIT by ``RATE_MIN_GAIN``
    (a record at one rate does not show how the loop grows with the rate)."""
    fixed_op = transform_ops(kept, fs)
    KX = reg.design(np.asarray(alphas, float))
    KX = fixed_op(KX) if fixed_op is not None else KX
    drift = [Drift.columns(len(v), fs, tau)] if tau is not None else []

    s = reg.fit_from

    def cost(beta: float) -> float:
        P, _ = play_start_columns(v, w, plays, reg.B, float(beta), fs)
        P = fixed_op(P) if fixed_op is not None else P  # (part of the hysteresis)
        return solve_gram(*gram_blocks([X[s:] for X in [KX, P] + drift], w[s:]),
                          len(w) - s).rms
    beta, best = search_1d(cost, 0.0, MAX_RATE_WIDENING_S * 0.999, n_grid=8)
    return float(beta) if best < cost(0.0) * (1.0 - RATE_MIN_GAIN) else 0.0


def play_start_columns(v: np.ndarray, w: np.ndarray, thresholds_V: np.ndarray,
                       others: np.ndarray | None = None, beta: float = 0.0,
                       fs: float = 0.0) -> tuple[np.ndarray, float]:
    """(columns, start): the play columns of the start (PLAY_STARTS) that, with
    ``others`` (columns) and a constant, explains ``w`` best: the operators' state
    before a record is not known, and a record cut from a run (a scan's later cycles)
    did not start at rest. Chosen like the free response and the offset, from the
    record itself."""
    best: tuple[float, np.ndarray | None, float] = (np.inf, None, 0.0)
    for start in PLAY_STARTS:
        P = play_columns(v, thresholds_V, start, beta, fs)
        A = np.column_stack([P] + ([others] if others is not None else [])
                            + [np.ones(len(v))])
        coef, *_ = np.linalg.lstsq(A, w, rcond=None)
        err = float(np.sum((w - A @ coef) ** 2))
        if err < best[0]:
            best = (err, P, start)
    assert best[1] is not None  # (PLAY_STARTS is not empty)
    return best[1], best[2]


def columns_without(reg: DuhemRegression, alphas: ArrayLike,
                    kept: Sequence[tuple[str, Params]], names: Sequence[str],
                    fs: float) -> np.ndarray:
    """The design for these alphas with the kept transform effects applied, except
    ``names``."""
    op = transform_ops([(n, p) for n, p in kept if n not in names], fs)
    KX = reg.design(alphas)
    return op(KX) if op is not None else KX


def _polish_pair(p0: Params | None, fs: float, cost: Cost, maxfev: int = 40) -> Params:
    """A resonance and a delay searched together (Nelder-Mead over log fn, log zeta and
    the delay, from ``p0`` {kind, fn_hz, zeta, delay_s}, where the separate searches
    ended): separately, each takes part of the other's phase (found 824 Hz and 0.62 ms
    for 800 Hz and 0.5 ms). Returns the better of p0 and the search's end."""
    assert p0 is not None  # (the separate searches' end)

    def params(x: np.ndarray) -> Params:
        return {"kind": "resonance", "fn_hz": float(np.exp(x[0])),
                "zeta": float(np.exp(x[1])), "delay_s": float(x[2])}

    def f(x: np.ndarray) -> float:
        p = params(x)
        return cost(p) if p["fn_hz"] < fs / 2.02 and 0 <= p["delay_s"] <= 0.02 else 1e300
    x0 = np.array([np.log(p0["fn_hz"]), np.log(p0["zeta"]), p0["delay_s"]])
    simplex = [x0, x0 + [0.03, 0, 0], x0 + [0, 0.2, 0], x0 + [0, 0, 0.5 / fs]]
    r = minimize(f, x0, method="Nelder-Mead",
                 options={"maxfev": maxfev, "xatol": 1e-4, "initial_simplex": simplex})
    return params(r.x if r.fun <= f(x0) else x0)


ALTERNATIONS = 4  # profile searches per effect fit, at most


# One of the two speed-ups of the diagnosis, switchable so that ``bench gap`` measures
# the path without it in the same run: the one-column searches (False: every search
# step filters every column, the exact cost); the other is gap.AXES_IN_PROCESSES
ONE_COLUMN_SEARCH = True


def _chain(effects: Sequence[tuple[str, Params]], fs: float) -> Op:
    """The operator of these transform effects one after another (never none:
    ``effects`` holds at least the one searched)."""
    op = transform_ops(effects, fs)
    assert op is not None
    return op


def _alternate(B: np.ndarray, extra: Sequence[np.ndarray], w: np.ndarray, search: Search,
               p0: Params | None, make_op: Callable[[Params], Op], start: Op | None = None,
               rows: int = 0) -> Params:
    """An effect's parameters searched with the Duhem coefficients held, alternating
    with their exact refit (block coordinate descent; each step lowers the exact cost,
    and its fixed point is where neither block can improve, the joint optimum's).

    ``B``: the design the effect's operator acts on (alphas fixed); ``extra``: columns
    appended after it; ``make_op(params)``: that operator; ``search(cost, params)``
    -> params minimising cost(params) (from ``params``, or None); ``start``: the
    operator of the fit to begin from (default ``make_op(p0)``). Held coefficients make
    the cost one column through the operator, scaled by least squares (the scale keeps
    it an exact-model value: c theta is a coefficient vector too): ~15x cheaper than
    filtering every column of B, and the refit after each search keeps it exact.
    ``rows``: the rows before it are run (the operator acts from the record's start),
    not fitted."""
    k = B.shape[1]
    E = np.column_stack(extra)[rows:] if extra else None
    wf = w[rows:]

    def refit(op: Op) -> tuple[float, np.ndarray, np.ndarray]:
        fit = solve_gram(*gram_blocks([op(B)[rows:]] + [e[rows:] for e in extra], wf),
                         len(wf))
        p = B @ fit.theta[:k]
        r = wf - E @ fit.theta[k:] if E is not None else wf
        return fit.rms, p, r

    if not ONE_COLUMN_SEARCH:
        return search(lambda q: refit(make_op(q))[0], p0)
    if start is None:
        assert p0 is not None  # (a first operator, or the parameters to make it from)
        start = make_op(p0)
    best, p, r = refit(start)
    params = p0
    for _ in range(ALTERNATIONS):
        rr = float(r @ r)

        def cost(q: Params, p: np.ndarray = p, r: np.ndarray = r, rr: float = rr) -> float:
            y = make_op(q)(p)[rows:]
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
    assert params is not None  # (the first pass always takes its search's end)
    return params


def _resonance_seeds(KX: np.ndarray, w: np.ndarray, fs: float, extra: Sequence[np.ndarray] = (),
                     min_coherence: float = 0.9, min_peak: float = 1.3,
                     min_bins: int = 20) -> list[tuple[float, float]]:
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


def _search_dynamics(fs: float, cost: Cost,
                     seeds: Sequence[tuple[float, float]] = ()) -> Params:
    """A resonance (fn, zeta) or a first-order lag (tau), whichever fits better; the
    coarse grid plus ``seeds`` [(fn, zeta)] found in the data start the search."""
    nyq = fs / 2

    def res_f(x: Sequence[float]) -> float:
        try:
            return cost({"kind": "resonance", "fn_hz": float(np.exp(x[0])),
                         "zeta": float(np.exp(x[1]))})
        except ValueError:  # above Nyquist
            return 1e300
    best: tuple[float, tuple[float, float] | None] = (np.inf, None)
    seeds = [s for s in seeds if s[0] < nyq / 1.01]
    # a peak in the data says where the resonance is: the coarse grid only without one
    grid = [] if seeds else [(fn, z) for fn in np.geomspace(5.0, nyq / 1.25, 8)
                             for z in (0.03, 0.15, 0.6)]
    for fn, z in grid + seeds:
        val = res_f((np.log(fn), np.log(z)))
        if val < best[0]:
            best = (val, (np.log(fn), np.log(z)))
    start = best[1]
    assert start is not None  # the grid, or the seeds where there are any
    r = minimize(res_f, start, method="Nelder-Mead", options={"maxfev": 60, "xatol": 1e-3})
    x = r.x if r.fun < best[0] else start
    fn, z = float(np.exp(x[0])), float(np.exp(x[1]))
    if not fn < nyq / 1.01:
        fn = nyq / 1.05
    if seeds:  # a resonance peak: not a lag
        return {"kind": "resonance", "fn_hz": fn, "zeta": z}
    tau_l, lag_val = search_1d(lambda tau: cost({"kind": "lag", "tau_s": tau}), 0.2 / fs,
                                0.1, n_grid=9, log=True)
    if lag_val < min(r.fun, best[0]):
        return {"kind": "lag", "tau_s": float(tau_l)}
    return {"kind": "resonance", "fn_hz": fn, "zeta": z}
