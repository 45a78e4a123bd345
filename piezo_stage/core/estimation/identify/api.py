"""One entry point for identification of one axis, whatever the solver."""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from piezo_stage.core.errors import DataError, SolverError
from piezo_stage.core.estimation.identify.options import IdentifyOptions
from piezo_stage.core.estimation.identify.prandtl import (
    Around,
    PrandtlIshlinskii,
    fit_pi_class,
    held_out_rms,
    min_slope,
)
from piezo_stage.core.estimation.identify.preisach import fit_preisach_class
from piezo_stage.core.estimation.identify.regress import DuhemRegression, coupling_term
from piezo_stage.core.estimation.identify.segmentation import (
    Segmentation,
    branch_monotone,
    inner_reversals,
    segment,
    voltage_noise,
)
from piezo_stage.core.estimation.record import Record, fitted_together
from piezo_stage.core.metrics import error_figures, noise_floor
from piezo_stage.core.model.duhem import (
    OTHER,
    AxisParts,
    DuhemModel,
    DuhemState,
    StageModel,
    voltage_limits_for,
)
from piezo_stage.core.types import Doc

METHODS = ("fast", "afsa", "afsa-bat")
MIN_BRANCH_SAMPLES = 20


# |correlation| of the two axes' voltages above which direct and coupling terms cannot
# be told apart (the same waveform on both axes: any split of the response fits)
COLLINEAR = 0.99


@dataclass
class AxisResult:
    """One axis's identification: model, fit figures, solver history."""
    axis: str
    method: str
    structure: str
    model: DuhemModel
    coupling: DuhemModel | None
    fit: Doc
    noise_floor_um: float
    evaluations: int
    seconds: float
    history: Doc
    notes: list = field(default_factory=list)

    def parts(self) -> AxisParts:
        """The axis as a stage model holds it (StageModel.from_fits)."""
        return AxisParts(self.model, self.coupling)
    branch_rms_um: Doc = field(default_factory=dict)
    delay_samples: int = 0   # the displacement lags the voltage by this many samples
    delay_s: float = 0.0     # ... [s]

    def to_json(self) -> Doc:
        """The result as the --json report's dict."""
        m = self.model
        params: dict[str, Any] = {"structure": m.structure,
                                  "initial_state": {"v_V": m.initial.v, "w_um": m.initial.w}}
        for name, b, asc in (("ascending", m.ascending, True),
                             ("descending", m.descending, False)):
            if m.structure == "whole":
                params.update(alpha=b.alpha, f=b.f.tolist(), g=b.g.tolist())
                break
            params[name] = {"alpha": b.alpha, "h": b.h(asc).tolist()}
        if self.coupling is not None:
            c = self.coupling.ascending
            params["coupling"] = {"alpha": c.alpha, "f": c.f.tolist(), "g": c.g.tolist()}
        return {
            "method": self.method, "structure": self.structure, "parameters": params,
            "fit_rms_um": self.fit["rms_um"], "fit_rms_pct": self.fit["rms_pct"],
            "max_err_um": self.fit["max_err_um"], "noise_floor_um": self.noise_floor_um,
            "branch_rms_um": self.branch_rms_um, "delay_s": self.delay_s,
            "delay_samples": self.delay_samples,
            "evaluations": self.evaluations, "seconds": self.seconds,
            "history": self.history, "notes": self.notes,
        }


def _axis_data(rec: Record, axis: str) -> tuple[np.ndarray, np.ndarray]:
    if axis not in rec.v or axis not in rec.w:
        raise DataError(f"{rec.source}: no v{axis}/w{axis} columns for axis {axis}")
    return rec.v[axis], rec.w[axis]


def check_identifiable(v: np.ndarray, source: str = "record") -> Segmentation:
    """Segment the voltage and refuse records that cannot support a fit."""
    seg = segment(v)
    if len(seg.turning_points) == 0:
        raise DataError(f"{source}: the voltage has no reversal; a hysteresis loop needs "
                        "rising and falling branches")
    for asc in (True, False):
        if seg.count(asc) < MIN_BRANCH_SAMPLES:
            raise DataError(f"{source}: too few samples on the "
                            f"{'ascending' if asc else 'descending'} branch "
                            f"({seg.count(asc)} < {MIN_BRANCH_SAMPLES})")
    return seg


def free_response(v: np.ndarray, alpha: Sequence[float] | np.ndarray) -> np.ndarray:
    """The Duhem output's response to its initial value (w0 = 1): the running product
    of 1 / (1 + alpha |dv|), alpha = (ascending, descending) [1/V]."""
    dv = np.diff(v, prepend=v[0])
    return np.cumprod(1.0 / (1.0 + np.where(dv >= 0, alpha[0], alpha[1]) * np.abs(dv)))


def simulate_axis(model: DuhemModel, coupling: DuhemModel | None, v: np.ndarray,
                  v_other: np.ndarray | None, w_meas: np.ndarray | None = None) -> np.ndarray:
    """Model output over a record; with w_meas, the initial output is re-estimated
    (the Duhem state is the output itself: one least-squares scalar)."""
    if w_meas is not None:
        st = DuhemState(float(v[0]), 0.0)
        base, _ = model.simulate(v, st)
        free = free_response(v, model.kernel_params()[0])
        wc: np.ndarray | float = 0.0
        if coupling is not None and v_other is not None:
            wc, _ = coupling.simulate(v_other)
        r = w_meas - base - wc
        w0 = float(free @ r / (free @ free))
        return base + w0 * free + wc
    w, _ = model.simulate(v)
    if coupling is not None and v_other is not None:
        w = w + coupling.simulate(v_other)[0]
    return w


def coupling_wanted(v: np.ndarray, v_other: np.ndarray | None, axis: str,
                    opts: IdentifyOptions, notes: list) -> bool:
    """Whether axis ``axis`` gets a coupling term from the other axis's voltage
    ``v_other``: ``opts.coupling`` 'on', or 'auto' (the fast method) where the other
    axis moves (over 5 % of this one's span) and not in step with this one (a reason
    appended to ``notes`` where it does); DataError where 'on' cannot be met."""
    other = OTHER[axis]
    use_c = (opts.coupling == "on" or (opts.coupling == "auto" and opts.method == "fast"
             and v_other is not None and np.ptp(v_other) > 0.05 * np.ptp(v)))
    if use_c and v_other is None:
        raise DataError(f"coupling requested but the record has no v{other}")
    if use_c and v_other is not None:  # a coupling term needs the other axis on its own
        r = abs(float(np.corrcoef(v, v_other)[0, 1]))
        if r > COLLINEAR:
            why = (f"v{other} moved in step with v{axis} (correlation {r:.4f}), so a "
                   f"coupling term is not identifiable from this record; excite the axes "
                   f"separately or at different frequencies")
            if opts.coupling == "on":
                raise DataError(why)
            use_c = False
            notes.append("no coupling term: " + why)
    if use_c and opts.method != "fast":
        raise DataError("a coupling term is fitted by the fast method only")
    return use_c


def identify_axis(rec: Record, axis: str, opts: IdentifyOptions | None = None,
                  progress: Callable[..., None] | None = None) -> AxisResult:
    """Identify one axis of a record (the samples of its long holes left out:
    ``record.fitted_together``). Raises DataError on unusable data and SolverError
    when the solver does not improve on its starting point."""
    return fitted_together(rec, lambda r: _identify_axis(r, axis, opts, progress),
                           lambda res, r: {axis: predict_axis(res, r)[2]})


LAG_MAX = 5        # samples: identify's delay search (opts.delay 'auto')
DELAY_PAYS = 0.95  # a lag is taken where it fits at least this much better (FIT RMS)


def lagged(rec: Record, k: int) -> Record:
    """``rec`` with each displacement paired with the voltage ``k`` samples before it
    (the last ``k`` voltages and the first ``k`` displacements dropped): a model of
    the lagged record, delayed by ``k`` samples, is the model of the record."""
    if k <= 0:
        return rec
    n = len(rec)
    if n - k < 3:
        raise DataError(f"{rec.source}: {n} samples, too few for a lag of {k}")
    m = None if rec.measured is None else rec.measured[k:]
    return Record(rec.t[:n - k], {a: x[:n - k] for a, x in rec.v.items()},
                  {a: x[k:] for a, x in rec.w.items()}, rec.source, rec.voltage_exact, m)


def delayed(x: np.ndarray, k: int) -> np.ndarray:
    """``x`` delayed by ``k`` samples, its first value held before it."""
    x = np.asarray(x, float)
    return x if k <= 0 else np.concatenate([np.full(k, x[0]), x[:-k]])


def choose_lag(rec: Record, axis: str, base: AxisResult,
               lags: Sequence[int] = tuple(range(LAG_MAX + 1))) -> tuple[int, dict[int, float]]:
    """How many samples the displacement lags the voltage (a DAQ that reads its input
    a sample after it writes its output; a sensor's latency): ``base``, the Duhem law
    fitted at no lag, has its regression solved exactly at its alphas for each lag;
    the best lag is taken only where it fits at least ``DELAY_PAYS`` better than none.
    -> (lag [samples], {lag: FIT RMS [um]})."""
    alphas = [base.model.ascending.alpha] if base.structure == "whole" else \
        [base.model.ascending.alpha, base.model.descending.alpha]
    if base.coupling is not None:
        alphas.append(base.coupling.ascending.alpha)
    n, m = base_degree(base)
    rms = {}
    for k in lags:
        if len(rec) - k < 100:
            break
        r = lagged(rec, k)
        v, w = _axis_data(r, axis)
        if not rec.voltage_exact and voltage_noise(v) > 1e-4 * np.ptp(v):
            v = branch_monotone(v)
        vo = r.v.get(OTHER[axis]) if base.coupling is not None else None
        reg = DuhemRegression(v, w, base.structure, n, m, vo, coupling_state=False)
        rms[k] = reg.solve(alphas).rms
    best = min(rms, key=rms.__getitem__)
    return (best if rms[best] < DELAY_PAYS * rms[0] else 0), rms


def base_degree(res: AxisResult) -> tuple[int, int]:
    """(n, m) of an identified axis's branch polynomials."""
    if res.structure == "whole":
        return res.model.ascending.f.size - 1, res.model.ascending.g.size - 1
    d = max(res.model.ascending.h(True).size, res.model.descending.h(False).size) - 1
    return d, max(d - 1, 0)


def delay_samples(opts: IdentifyOptions, fs_hz: float) -> int | None:
    """The lag [samples] ``opts.delay`` fixes (None: 'auto', found from the record)."""
    if opts.delay == "auto":
        return None
    try:
        d = float(opts.delay)
    except (TypeError, ValueError):
        raise DataError(f"delay {opts.delay!r}: give auto or seconds >= 0") from None
    if not np.isfinite(d) or d < 0:
        raise DataError(f"delay {d!r}: give auto or seconds >= 0")
    return int(round(d * fs_hz))


def _identify_axis(rec: Record, axis: str, opts: IdentifyOptions | None,
                   progress: Callable[..., None] | None) -> AxisResult:
    """``identify_axis`` on the record as it is: the lag ``opts.delay`` asks for
    (found where 'auto'), then the fit (``_fit_axis``)."""
    from dataclasses import replace
    opts = opts or IdentifyOptions()
    lag = delay_samples(opts, rec.fs_hz)
    if lag is None and opts.method != "fast":
        lag = 0  # (the paper's swarms: as the paper fits them)
    base = None
    if lag is None:
        base = _fit_axis(rec, axis, opts, progress)
        lag, _ = choose_lag(rec, axis, base)
        if lag == 0:
            return base
    if lag == 0:
        return _fit_axis(rec, axis, opts, progress)
    res = _fit_axis(lagged(rec, lag), axis, replace(opts, delay=0.0), progress)
    res.delay_samples, res.delay_s = lag, lag * rec.dt
    ms = f"{lag} sample(s) ({lag * rec.dt * 1e3:.4g} ms)"
    if base is not None:  # the same figure, over the same samples, with the lag and not
        _, w, p0, _ = fit_prediction(base, rec)
        without = float(np.sqrt(np.mean((w - p0)[lag:] ** 2)))
        res.notes.append(f"the displacement lags the voltage by {ms}: fitted with that "
                         f"delay, FIT RMS {res.fit['rms_um']:.4g} um (the table's, after "
                         f"the record's first {lag} sample(s), which the lag takes from "
                         f"before it) against {without:.4g} um without it; the model "
                         "file holds it as its delay effect")
    else:
        res.notes.append(f"fitted with a delay of {ms}")
    return res


def _fit_axis(rec: Record, axis: str, opts: IdentifyOptions,
              progress: Callable[..., None] | None) -> AxisResult:
    """One axis's Duhem law fitted to ``rec`` as it stands (no lag)."""
    if opts.method not in METHODS:
        raise DataError(f"unknown method {opts.method!r}; use one of {', '.join(METHODS)}")
    if opts.structure not in ("whole", "segmented"):
        raise DataError("structure must be whole or segmented")
    v, w = _axis_data(rec, axis)
    seg = check_identifiable(v, rec.source)
    notes = []
    if not rec.voltage_exact and voltage_noise(v) > 1e-4 * np.ptp(v):  # measured, noisy
        v = branch_monotone(v, seg)
        notes.append("the voltage is noisy (measured, not commanded): micro-reversals "
                     "inside each branch were removed before fitting")
    v_other = rec.v.get(OTHER[axis])
    use_c = coupling_wanted(v, v_other, axis, opts, notes)
    if opts.structure == "segmented":
        notes.append("segmented: within one branch only h = f + g (ascending) and "
                     "h = g - f (descending) are identifiable; reported as h")
    t0 = time.perf_counter()
    if opts.method == "fast":
        from piezo_stage.core.estimation.identify.fast import fit_fast
        reg = DuhemRegression(v, w, opts.structure, opts.n, opts.m,
                              v_other if use_c else None, coupling_state=False)
        reg.monotone_floor = min_slope(v, w)  # every branch rises: one exact inverse
        alphas, fit, hist = fit_fast(reg, opts.budget, progress)
        model, coupling = reg.models(alphas, fit.theta)
        evaluations = reg.evaluations
        history = {"best_rms_um": hist}
    else:
        from piezo_stage.core.estimation.identify.afsa import fit_swarm
        model, evaluations, history = fit_swarm(v, w, seg, opts, progress)
        model = model.with_fit_range(float(v.min()), float(v.max()))
        coupling = None
    seconds = time.perf_counter() - t0
    pred = simulate_axis(model, coupling, v, v_other)
    fig = error_figures(w, pred)
    if not np.isfinite(fig["rms_um"]):
        raise SolverError(f"axis {axis}: {opts.method} produced a non-finite model")
    # the trivial model: a constant at the mean; a solver that cannot beat it failed
    trivial = float(np.std(w))
    if fig["rms_um"] >= trivial:
        raise SolverError(f"axis {axis}: {opts.method} did not improve on a constant "
                          f"(rms {fig['rms_um']:.4g} um >= {trivial:.4g} um); no model written")
    e = pred - w
    branch = {name: float(np.sqrt(np.mean(e[seg.mask(asc)] ** 2)))
              for name, asc in (("ascending", True), ("descending", False))}
    return AxisResult(axis, opts.method, opts.structure, model, coupling,
                      {"rms_um": fig["rms_um"], "rms_pct": fig["rms_pct"],
                       "max_err_um": fig["max_err_um"], "range_um": fig["range_um"]},
                      noise_floor(w), evaluations, seconds, history, notes, branch)


def predict_axis(res: AxisResult,
                 rec: Record) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """An identified axis's output over a record (initial output re-estimated; a
    noisy voltage is made monotone per branch as for identification).
    -> (v [V], measured w [um], model output [um])."""
    v, w = _axis_data(rec, res.axis)
    if not rec.voltage_exact and voltage_noise(v) > 1e-4 * np.ptp(v):
        v = branch_monotone(v)
    v_other = rec.v.get(OTHER[res.axis])
    if res.coupling is not None and v_other is None:
        raise DataError(f"{rec.source}: the model has coupling but the record has no "
                        f"v{OTHER[res.axis]}")
    k = res.delay_samples
    if k:  # the model of the lagged record, delayed
        n = len(v)
        vo = None if v_other is None else v_other[:n - k]
        pred = simulate_axis(res.model, res.coupling, v[:n - k], vo, w_meas=w[k:])
        return v, w, np.concatenate([np.full(k, pred[0]), pred])
    return v, w, simulate_axis(res.model, res.coupling, v, v_other, w_meas=w)


def fit_prediction(res: AxisResult,
                   rec: Record) -> tuple[np.ndarray, np.ndarray, np.ndarray, int]:
    """An identified axis over the record it was fitted on, as its fit figures (the
    table's, the note's, the figure's) take it: the model from its own initial state
    (as its file holds it), delayed by its lag (the voltage made monotone per branch
    where it was for the fit). The lag's first samples take voltages from before the
    record: they are left out of every fit figure. -> (v [V], measured w [um], model
    output [um], the samples left out at the start)."""
    v, w = _axis_data(rec, res.axis)
    if not rec.voltage_exact and voltage_noise(v) > 1e-4 * np.ptp(v):
        v = branch_monotone(v)
    vo = rec.v.get(OTHER[res.axis]) if res.coupling is not None else None
    k = res.delay_samples
    pred = simulate_axis(res.model, res.coupling, v[:len(v) - k],
                         None if vo is None else vo[:len(v) - k])
    return v, w, np.concatenate([np.full(k, pred[0]), pred]) if k else pred, k


def validate_axis(res: AxisResult, rec: Record) -> Doc:
    """Error of an identified axis on another record (initial output re-estimated)."""
    _, w, pred = predict_axis(res, rec)
    fig = error_figures(w, pred)
    return {"validate_rms_um": fig["rms_um"], "validate_rms_pct": fig["rms_pct"],
            "validate_max_err_um": fig["max_err_um"], "validate_noise_floor_um": noise_floor(w)}


STRUCTURE_DEGREES = (3, 4, 5, 6, 7)  # identify --structure auto: branch degrees tried
HELD_OUT_FRACTION = 0.4              # the record's last 40 % judges them


def choose_degree(rec: Record, axis: str, opts: IdentifyOptions,
                  degrees: Sequence[int] = STRUCTURE_DEGREES) -> tuple[int, dict[int, float]]:
    """The branch degree (f of degree d, g of d - 1) that predicts the record's own
    later cycles best: each is fitted on the first 60 % of the span where the axis
    moves and judged on the last 40 %
    (initial output re-estimated, as for --validate); the smallest within 2 % of the
    best wins (a higher degree must pay on held-out data). -> (d, {d: held-out RMS})."""
    from dataclasses import replace
    # the span where this axis moves (a protocol drives the axes in turn), split there
    first, last = _later_cycles(rec, axis)
    held = {}
    for d in degrees:
        r = identify_axis(first, axis, replace(opts, n=d, m=max(d - 1, 0)))
        held[d] = validate_axis(r, last)["validate_rms_um"]
    best = min(held.values())
    return min(d for d, e in held.items() if e <= 1.02 * best), held


CLASSES = ("duhem", "pi", "preisach", "auto")  # identify --class


def _later_cycles(rec: Record, axis: str) -> tuple[Record, Record]:
    """(the first 60 % of the span where ``axis`` moves, the last 40 %)."""
    v = np.asarray(rec.v[axis], float)
    moves = np.flatnonzero(np.abs(np.diff(v)) > 1e-9 * max(np.ptp(v), 1e-300))
    lo, hi = (int(moves[0]), int(moves[-1]) + 2) if moves.size else (0, len(v))
    cut = lo + int((hi - lo) * (1 - HELD_OUT_FRACTION))

    def part(sl: slice, name: str) -> Record:
        piece = rec.slice(sl.start, sl.stop)
        piece.source = f"{rec.source} ({name})"
        return piece
    first, last = part(slice(lo, cut), "first 60 %"), part(slice(cut, hi), "last 40 %")
    for piece in (first, last):
        check_identifiable(piece.v[axis], piece.source)
    return first, last


# --class auto on a record without minor loops: the class chosen, and why
MAJOR_LOOPS_ONLY = (
    "the record's reversals all lie at its two ends (major loops only): the classes "
    "fit a major loop alike and differ in the minor loops it does not hold; the "
    "Prandtl-Ishlinskii class is chosen, whose minor loops follow from its major loop "
    "(Masing's rule; from such a record it predicted a measured PI P-885 stack's "
    "nested loops several times closer than the Duhem law and the Preisach class). "
    "To choose on data, calibrate with nested minor loops: piezo-stage excite --nested")


def choose_class(rec: Record, axis: str, opts: IdentifyOptions | None = None,
                 limits_V: tuple | None = None) -> tuple[str, Doc, list]:
    """``identify --class auto``: the model class that predicts the record's own later
    cycles best, each fitted on the first 60 % of the span where the axis moves and
    judged on the last 40 % (offset removed; the first 10 % of it, where each model's
    unknown start state shows, left out), all with the lag the Duhem law's fit finds
    (``opts.delay``). Each class must pay against the simpler ones before it (the
    Duhem law, the Prandtl-Ishlinskii class, the discretized Preisach class, in that
    order): it wins only 2 % closer; the memory classes' thresholds reach half the
    amplifier's ``limits_V`` (else 0-150 V widened to the record's). A record with no
    minor loops (``inner_reversals``) cannot tell the classes apart where they differ:
    the Prandtl-Ishlinskii class then (``MAJOR_LOOPS_ONLY``, the note that says so).
    -> (class, {class: held-out RMS um}, notes)."""
    from dataclasses import replace
    first, last = _later_cycles(rec, axis)
    skip = 0.1 * (last.t[-1] - last.t[0])
    w = last.w[axis]
    res = identify_axis(first, axis, opts)
    held = {"duhem": held_out_rms(predict_axis(res, last)[2], w, last.fs_hz, skip)}
    same_lag = replace(opts or IdentifyOptions(), delay=res.delay_s)
    for name in ("pi", "preisach"):
        model = fit_class_axis(first, axis, name, same_lag, limits_V)
        held[name] = held_out_rms(model.predict(last, axis), w, last.fs_hz, skip)
    if inner_reversals(rec.v[axis]) == 0:
        return "pi", held, [MAJOR_LOOPS_ONLY]
    best = "duhem"
    for name in ("pi", "preisach"):
        if held[name] < 0.98 * held[best]:
            best = name
    return best, held, []


@dataclass
class ClassFit:
    """One axis's class with memory (``identify --class pi|preisach``): ``law`` (a
    PrandtlIshlinskii, banded operators for Preisach), its ``coupling`` term (a
    DuhemModel driven by the other axis's voltage, or None), ``notes`` and the lag of
    the displacement behind the voltage it was fitted with (``delay_samples``)."""
    law: PrandtlIshlinskii
    coupling: DuhemModel | None
    notes: list = field(default_factory=list)
    delay_samples: int = 0
    delay_s: float = 0.0

    def parts(self, v0: float) -> AxisParts:
        """The axis as a stage model holds it, at rest at voltage ``v0`` as fitted: a
        Duhem law that is exactly the class's linear term, its play operators beside
        it, its coupling term."""
        law, plays = self.law.to_model(v0)
        return AxisParts(law, self.coupling, plays)

    def predict(self, rec: Record, axis: str) -> np.ndarray:
        """The output over ``rec`` [um] (operators at rest at its first voltage,
        coupling from rest at the other axis's, delayed by the lag), the constant
        fitted there."""
        pred = self.law.predict(rec.v[axis])
        if self.coupling is not None:
            vo = rec.v.get(OTHER[axis])
            if vo is None:
                raise DataError(f"{rec.source}: the model has coupling but the record "
                                f"has no v{OTHER[axis]}")
            pred = pred + self.coupling.simulate(vo, DuhemState(float(vo[0]), 0.0))[0]
        pred = delayed(pred, self.delay_samples)
        return pred + float(np.mean(rec.w[axis] - pred))


def fit_class_axis(rec: Record, axis: str, kind: str, opts: IdentifyOptions | None = None,
                   limits_V: tuple | None = None) -> ClassFit:
    """The class ``kind`` ('pi' or 'preisach') of one axis of ``rec``, thresholds up to
    half the amplifier's ``limits_V`` (else 0-150 V widened to the record's), with a
    coupling term where ``opts.coupling`` asks for one as for the Duhem law
    (``coupling_wanted``): a whole-curve Duhem law of the other axis's voltage at the
    alpha the Duhem law's fit of the same record finds for it, its coefficients fitted
    together with the class's weights; fitted with the lag ``opts.delay`` gives (where
    'auto', the one the Duhem law's fit of the record finds). The samples of the
    record's long holes are left out (``record.fitted_together``)."""
    return fitted_together(rec, lambda r: _fit_class_axis(r, axis, kind, opts, limits_V),
                           lambda fitted, r: {axis: fitted.predict(r, axis)})


def _fit_class_axis(rec: Record, axis: str, kind: str, opts: IdentifyOptions | None,
                    limits_V: tuple | None) -> ClassFit:
    from dataclasses import replace
    opts = opts or IdentifyOptions()
    v, w = _axis_data(rec, axis)
    check_identifiable(v, rec.source)
    notes: list = []
    v_other = rec.v.get(OTHER[axis])
    use_c = v_other is not None and coupling_wanted(v, v_other, axis, opts, notes)
    lag = delay_samples(opts, rec.fs_hz)
    duhem = None
    if use_c or lag is None:  # the Duhem law's fit: its coupling's alpha, its lag
        duhem = identify_axis(rec, axis, replace(opts, coupling="on" if use_c else "off"))
        if lag is None:
            lag = duhem.delay_samples
            notes += [n for n in duhem.notes if "lags the voltage" in n]
    if lag:
        rec = lagged(rec, lag)
        v, w = _axis_data(rec, axis)
        v_other = rec.v.get(OTHER[axis])
    around, model_of = None, None
    if use_c and duhem is not None and v_other is not None:
        assert duhem.coupling is not None  # (asked for: "on")
        cols, model_of = coupling_term(v_other, duhem.coupling.ascending.alpha)
        around = Around(coupled=cols)
        notes.append(f"coupling from v{OTHER[axis]}: its alpha from the Duhem law's fit "
                     "of the same record, its coefficients fitted with the class")
    lo, hi = voltage_limits_for(list(rec.v.values()), limits_V)
    fit = fit_preisach_class if kind == "preisach" else fit_pi_class
    law = fit(v, w, reach_V=(hi - lo) / 2, around=around)
    coupling = model_of(law.around[:around.coupled.shape[1]]) \
        if model_of is not None and around is not None and around.coupled is not None \
        else None
    return ClassFit(law, coupling, notes, lag, lag * rec.dt)


def delay_effect(fits: Doc) -> Doc:
    """The model file's ``effects`` for the lags of identified axes ({axis: AxisResult
    or ClassFit}): each lagging axis's own delay (one entry for the axes that share
    it), {} where none lags."""
    from piezo_stage.core.model.effects import effects_block
    return effects_block({a: {"delay": {"delay_s": float(f.delay_s)}}
                          for a, f in sorted(fits.items()) if f.delay_s > 0})


@dataclass
class StageFit:
    """Every identified axis of a record put together: ``model`` (the StageModel with
    its coupling terms and the amplifier's voltage limits), ``results`` {axis:
    AxisResult} and ``skipped`` {axis: why} (``identify_stage(..., skip_unusable=True)``)."""
    model: StageModel
    results: Doc
    skipped: Doc = field(default_factory=dict)

    @property
    def effects(self) -> Doc:
        """The model file's ``effects``: the delay of the axes that lag."""
        return delay_effect(self.results)


def identify_stage(rec: Record, axes: Sequence[str],
                   opts: IdentifyOptions | Doc | None = None,
                   limits_V: tuple | None = None,
                   progress_for: Callable[[str], Callable[..., None] | None] | None = None,
                   skip_unusable: bool = False) -> StageFit:
    """Identify ``axes`` of ``rec`` (``opts`` one IdentifyOptions, or one per axis) and
    build the stage model. Its voltage limits follow one rule wherever a model is
    written (``identify``, ``refit``, the identifier node): the amplifier's
    ``limits_V``, else 0-150 V widened to take the record's voltages
    (duhem.voltage_limits_for; DataError when the record leaves the amplifier's).
    ``progress_for(axis)`` gives each axis's solver callback. ``skip_unusable``: an
    axis whose record cannot be identified (not excited, no solver converged) is left
    out and said in ``skipped``, DataError only when none is left."""
    lim = voltage_limits_for(list(rec.v.values()), limits_V)  # before any fit
    results, skipped = {}, {}
    for a in axes:
        o = opts.get(a) if isinstance(opts, dict) else opts
        try:
            results[a] = identify_axis(rec, a, o, progress_for(a) if progress_for else None)
        except (DataError, SolverError) as e:
            if not skip_unusable:
                raise
            skipped[a] = str(e)
    if not results:
        raise DataError("; ".join(f"{a}: {why}" for a, why in skipped.items())
                        or f"{rec.source}: no axis to identify")
    model = StageModel.from_fits({a: r.parts() for a, r in results.items()}, lim)
    return StageFit(model, results, skipped)
