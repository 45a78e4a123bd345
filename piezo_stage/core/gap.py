"""Sim-to-real gap diagnosis: where the simulator and the stage disagree, which
unmodelled effect causes it, and how far the gap shrinks once that effect is added.

Base model ("the sim"): the segmented Duhem model per axis, identified on FIT (or
given). Candidates, each a small physical operator from core/effects.py added to the
sim and fitted on FIT *together with* the Duhem coefficients (the effect operator is
linear, so E(X theta) = E(X) theta: for fixed alphas and effect parameters it is one
least-squares problem; the effect's own parameters are searched):

    creep     w = E_creep(H(v)), log-like relaxation bank, gamma searched
    dynamics  w = G(s) H(v), resonance (fn, zeta) or lag (tau), the better of the two
    delay     w(t) = H(v)(t - d), d searched
    drift     w = H(v) + a t + b (1 - exp(-t / tau)), input independent
    coupling  w = H(v) + H_c(v_other), a Duhem term driven by the other axis
    none      the base model alone

Every candidate is scored on HOLDOUT (a different record): the initial Duhem state
and a constant sensor offset are re-estimated there, the same for all. The gap is the
part of the residual above the noise floor, sqrt(max(rms^2 - nf^2, 0)); shrink =
100 (1 - gap_after / gap_before).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np
from scipy import signal
from scipy.optimize import minimize, minimize_scalar

from piezo_stage.core.duhem import OTHER
from piezo_stage.core.effects import Creep, Delay, Drift, Dynamics
from piezo_stage.core.errors import DataError
from piezo_stage.core.identify.api import check_identifiable
from piezo_stage.core.identify.fast import fit_fast
from piezo_stage.core.identify.regress import DuhemRegression
from piezo_stage.core.identify.segmentation import segment
from piezo_stage.core.metrics import noise_floor, rms
from piezo_stage.core.record import Record

EFFECTS = ("creep", "dynamics", "delay", "drift", "coupling")
CREEP_TAUS = (0.05, 0.5, 5.0, 50.0)
MIN_HOLD_S = 1.0


@dataclass
class Candidate:
    effect: str
    params: dict
    alphas: np.ndarray
    theta: np.ndarray
    reg: DuhemRegression
    fit_rms_um: float
    op: object = None              # callable X -> E(X) (columns) or None
    drift_tau_s: float | None = None

    def predict(self, rec: Record, axis: str):
        """Prediction on another record; initial state and offset re-estimated."""
        v = rec.v[axis]
        v_other = rec.v.get(OTHER[axis])
        main, coup = self.reg.models(self.alphas, self.theta)
        # columns: model output from w0 = 0, free response (w0 = 1), constant offset
        st0 = main.initial.__class__(float(v[0]), 0.0)
        base, _ = main.simulate(v, st0)
        a, _ = main.kernel_params()
        dv = np.diff(v, prepend=v[0])
        free = np.cumprod(1.0 / (1.0 + np.where(dv >= 0, a[0], a[1]) * np.abs(dv)))
        cols = [base, free]
        if coup is not None:
            # the coupling term from its fitted state (its constant part is tied to its
            # f_0), plus its own free response, re-estimated like the main one
            ac, _ = coup.kernel_params()
            dvo = np.diff(v_other, prepend=v_other[0])
            cols[0] = base + coup.simulate(v_other, coup.initial.__class__(
                float(v_other[0]), coup.initial.w))[0]
            cols.append(np.cumprod(1.0 / (1.0 + np.where(dvo >= 0, ac[0], ac[1]) * np.abs(dvo))))
        cols = np.column_stack(cols)
        if self.op is not None:
            cols = self.op(cols)
        fixed = cols[:, 0]
        if self.drift_tau_s is not None:
            k = len(self.theta) - 2
            fixed = fixed + Drift.columns(len(v), rec.fs_hz, self.drift_tau_s) @ self.theta[k:]
        A = np.column_stack([cols[:, 1:], np.ones(len(v))])
        coef, *_ = np.linalg.lstsq(A, rec.w[axis] - fixed, rcond=None)
        return fixed + A @ coef

    def model_effect(self):
        """The effect as model-file / plant parameters (None for none and coupling)."""
        return None if self.effect in ("none", "coupling") else dict(self.params)


def _search_1d(f, lo, hi, n_grid=12, log=False):
    g = np.geomspace(lo, hi, n_grid) if log else np.linspace(lo, hi, n_grid)
    vals = [f(x) for x in g]
    i = int(np.argmin(vals))
    a, b = g[max(i - 1, 0)], g[min(i + 1, n_grid - 1)]
    r = minimize_scalar(f, bounds=(a, b), method="bounded", options={"xatol": (b - a) * 1e-3})
    return (r.x, r.fun) if r.fun <= vals[i] else (g[i], vals[i])


def fit_candidate(rec: Record, axis: str, effect: str, base: Candidate | None = None):
    """Fit the base model and one effect together on rec. Returns a Candidate."""
    v, w = rec.v[axis], rec.w[axis]
    fs = rec.fs_hz
    v_other = rec.v.get(OTHER[axis]) if effect == "coupling" else None
    reg = DuhemRegression(v, w, "segmented", v_other=v_other)
    if effect in ("none", "coupling"):
        if effect == "coupling":  # the base's alphas, plus one for the coupling term
            x0 = np.append(base.alphas, base.alphas.mean())
            alphas, fit, _ = fit_fast(reg, budget=60, x0=x0)
        else:
            alphas, fit, _ = fit_fast(reg, budget=100, grid=11)
        return Candidate(effect, {}, alphas, fit.theta, reg, fit.rms)
    alphas = base.alphas
    params, op, tau = {}, None, None
    if effect == "drift":
        tau = max(rec.t[-1] - rec.t[0], 1.0) / 3.0
        reg.extra = Drift.columns(len(v), fs, tau)
    else:
        def make(p):
            if effect == "creep":
                return Creep(fs, gamma=p, tau_s=CREEP_TAUS).apply
            if effect == "delay":
                return Delay(fs, delay_s=p).apply
            raise AssertionError

        def obj_for(mk):
            def f(p):
                try:
                    reg.transform = mk(p)
                except ValueError:
                    return 1e300
                return reg.solve(alphas).rms
            return f

        if effect == "creep":
            g, _ = _search_1d(obj_for(make), 0.0, 0.3)
            params, op = {"gamma": float(g), "tau_s": list(CREEP_TAUS)}, make(g)
        elif effect == "delay":
            d, _ = _search_1d(obj_for(make), 0.0, min(0.02, 50 / fs), n_grid=21)
            params, op = {"delay_s": float(d)}, make(d)
        else:  # dynamics: resonance or lag, keep the better
            nyq = fs / 2
            res_f = obj_for(lambda p: Dynamics(fs, "resonance", fn_hz=float(np.exp(p[0])),
                                               zeta=float(np.exp(p[1]))).apply)
            best = (np.inf, None)
            for fn in np.geomspace(5.0, nyq / 1.25, 10):
                for z in (0.03, 0.15, 0.6):
                    val = res_f((np.log(fn), np.log(z)))
                    if val < best[0]:
                        best = (val, (np.log(fn), np.log(z)))
            r = minimize(res_f, best[1], method="Nelder-Mead",
                         options={"maxfev": 40, "xatol": 1e-3})
            x = r.x if r.fun < best[0] else best[1]
            fn, z = float(np.exp(x[0])), float(np.exp(x[1]))
            if not fn < nyq / 1.01:
                fn = nyq / 1.05
            lag_f = obj_for(lambda tau: Dynamics(fs, "lag", tau_s=tau).apply)
            tau_l, lag_val = _search_1d(lag_f, 0.2 / fs, 0.1, log=True)
            if lag_val < min(r.fun, best[0]):
                params = {"kind": "lag", "tau_s": float(tau_l)}
                op = Dynamics(fs, "lag", tau_s=tau_l).apply
            else:
                params = {"kind": "resonance", "fn_hz": fn, "zeta": z}
                op = Dynamics(fs, "resonance", fn_hz=fn, zeta=z).apply
        reg.transform = op
    # the alphas again, with the effect in place (base and effect fitted together)
    alphas, fit, _ = fit_fast(reg, budget=25, x0=alphas, step=0.2)
    if effect == "drift":
        k = len(fit.theta) - 2
        params = {"rate_um_per_s": float(fit.theta[k]), "amplitude_um": float(fit.theta[k + 1]),
                  "tau_s": float(tau)}
    return Candidate(effect, params, alphas, fit.theta, reg, fit.rms, op, tau)


def _gap(r, nf):
    return float(np.sqrt(max(r * r - nf * nf, 0.0)))


def holds(v, fs, min_s=MIN_HOLD_S):
    """Lengths [s] of the stretches where the voltage stays put (within 0.1 % span)."""
    dv = np.abs(np.diff(v))
    still = dv <= 1e-3 * max(np.ptp(v), 1e-12)
    out, run = [], 0
    for s in still:
        run = run + 1 if s else 0
        if run == int(min_s * fs):
            out.append(run)
    return out


def where(rec: Record, axis: str, resid, nf):
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
    still = np.abs(dv) <= 1e-3 * max(np.ptp(v), 1e-12)
    parts = {"ascending": (labels > 0) & ~turn & ~still, "descending": (labels < 0) & ~turn & ~still,
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

    def __init__(self, stage_model):
        self.model = stage_model

    def predict(self, rec: Record, axis: str):
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
    axis: str
    verdict: str
    reason: str
    ranking: list
    where: dict
    noise_floor_um: float
    candidates: dict = field(default_factory=dict)


def diagnose_axis(fit: Record, holdout: Record, axis: str, effects=EFFECTS,
                  base_model=None, progress=None) -> AxisDiagnosis:
    """Fit every candidate on FIT, score on HOLDOUT, decide. ``base_model`` (a
    StageModel) replaces the FIT-identified Duhem model as the sim to compare with.
    ``progress(what)`` is called after each candidate is fitted."""
    progress = progress or (lambda what="": None)
    for rec in (fit, holdout):
        if axis not in rec.v or axis not in rec.w:
            raise DataError(f"{rec.source}: no v{axis}/w{axis} for axis {axis}")
        check_identifiable(rec.v[axis], rec.source)
    notes = []
    base = fit_candidate(fit, axis, "none")
    progress(f"{axis} none")
    cands = {"none": base}
    for e in effects:
        if e == "coupling":
            vo_f, vo_h = fit.v.get(OTHER[axis]), holdout.v.get(OTHER[axis])
            if vo_f is None or vo_h is None or np.ptp(vo_f) < 1.0:
                notes.append("coupling not tested: the other axis's voltage does not move")
                continue
        cands[e] = fit_candidate(fit, axis, e, base)
        progress(f"{axis} {e}")
    nf = noise_floor(holdout.w[axis])
    w_h = holdout.w[axis]
    sim = GivenModel(base_model) if base_model is not None and axis in base_model.axes \
        else base
    r_before = rms(sim.predict(holdout, axis) - w_h)
    g_before = _gap(r_before, nf)
    ranking = []
    for e, c in cands.items():
        r_after = rms(c.predict(holdout, axis) - w_h)
        g_after = _gap(r_after, nf)
        ranking.append({"effect": e, "rms_before_um": r_before, "rms_after_um": r_after,
                        "gap_before_um": g_before, "gap_after_um": g_after,
                        "shrink_pct": 100.0 * (1 - g_after / g_before) if g_before > 0 else 0.0,
                        "fit_rms_um": c.fit_rms_um, "params": c.params})
    ranking.sort(key=lambda r: r["gap_after_um"])
    resid = sim.predict(holdout, axis) - w_h
    loc = where(holdout, axis, resid, nf)
    verdict, reason = _decide(ranking, g_before, nf, fit, holdout, axis)
    if notes:
        reason = (reason + "; " if reason else "") + "; ".join(notes)
    return AxisDiagnosis(axis, verdict, reason, ranking, loc, nf, cands)


def _decide(ranking, g_before, nf, fit, holdout, axis):
    eff = [r for r in ranking if r["effect"] != "none"]
    if not eff:
        return "inconclusive", "no candidate effect could be tested"
    best = eff[0]
    # a held-out improvement counts when it is well above what chance gives on this
    # many samples (the MSE of white noise fluctuates by nf^2 sqrt(2/N))
    n = len(holdout.t)
    gain = best["rms_before_um"] ** 2 - best["rms_after_um"] ** 2
    significant = gain > max(0.05 * nf ** 2, 10 * nf ** 2 * np.sqrt(2.0 / n))
    if g_before <= 0.5 * nf and not (significant and best["shrink_pct"] >= 50.0):
        return "none", f"the residual is at the noise floor (gap {g_before:.3g} um, " \
                       f"noise {nf:.3g} um)"
    if best["shrink_pct"] < 30.0:
        return "inconclusive", (f"no candidate closes the gap ({g_before:.3g} um): best "
                                f"{best['effect']} shrinks it by {best['shrink_pct']:.0f} %")
    if best["effect"] in ("creep", "drift"):
        if not holds(fit.v[axis], fit.fs_hz) or not holds(holdout.v[axis], holdout.fs_hz):
            return "inconclusive", (f"no holds longer than {MIN_HOLD_S:g} s: creep cannot be "
                                    "separated from drift")
    if len(eff) > 1 and eff[1]["gap_after_um"] <= best["gap_after_um"] * 1.02 + 1e-3 and \
            eff[1]["shrink_pct"] >= 30.0:
        return "inconclusive", (f"{best['effect']} and {eff[1]['effect']} explain the gap "
                                "equally well on this excitation")
    return best["effect"], f"{best['effect']} shrinks the held-out gap by " \
                           f"{best['shrink_pct']:.0f} %"


def diagnose(fit: Record, holdout: Record | None = None, effects=EFFECTS, axes=None,
             base_model=None, progress=None) -> dict:
    """The --json contract (see the module docstring and the README). ``progress(what)``
    is called after each candidate fit (from the axes' threads)."""
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
    # the axes are independent problems; the compiled loops, lfilter and BLAS release
    # the GIL, so two threads use both cores
    from concurrent.futures import ThreadPoolExecutor
    with ThreadPoolExecutor(max_workers=min(2, len(axes))) as pool:
        futures = {a: pool.submit(diagnose_axis, fit, holdout, a, effects, base_model,
                                  progress) for a in axes}
        per = {a: f.result() for a, f in futures.items()}
    worst = max(per.values(), key=lambda d: d.ranking[0]["gap_before_um"])
    out = {"verdict": worst.verdict, "reason": worst.reason, "ranking": worst.ranking,
           "where": worst.where, "noise_floor_um": worst.noise_floor_um,
           "axes": {a: {"verdict": d.verdict, "reason": d.reason, "ranking": d.ranking,
                        "where": d.where, "noise_floor_um": d.noise_floor_um}
                    for a, d in per.items()},
           "holdout_is_fit": holdout is fit,
           "seconds": time.perf_counter() - t0}
    out["_diagnoses"] = per  # for report writing; dropped from the JSON
    return out
