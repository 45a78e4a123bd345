"""The live watch: the gap node's diagnosis of its own buffer while the stage runs.

The residual of the stage against the model in use (``monitor.ResidualMonitor``) is
measured in blocks of ``block_s``. Its level after arming is the median block RMS over
``baseline_s`` (after ``settle_s``, the twin's zero and the start-up), its spread the
blocks' (a median absolute deviation). An axis *rises* when ``sustain_blocks`` blocks
in a row stand above ``rise`` x the level and ``sigmas`` spreads above it: never on one
burst. From the first of those blocks (the onset) the watch keeps ``fit_s`` of data
(FIT) and then ``holdout_s`` (HOLDOUT, the newest: its first second run, not scored),
and asks for the same diagnosis ``gap`` makes offline (``diagnose``) against the model
in use, with the effects it lacks among ``effects`` as candidates. The answer is handed
on only when it is never worse: an effect named, and the model written for it closer on
HOLDOUT than the model in use on every axis (``decide``).

The diagnosis is a plain function of plain data (``diagnose_window``), so a node can run
it in another process while the loop and the twin go on.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from piezo_stage.core.model.duhem import AXES, StageModel
from piezo_stage.core.types import Doc, EffectsBlock

# the refit's change where the axes move apart, against its change on the window: more
# than APART_RATIO x (plus APART_FLOOR_UM) and the window could not tell the axes' laws
# apart (both axes driven alike: each axis's own law and its coupling are collinear, and
# a refit can trade one for the other, 226 um against -182 um, seen). Measured on the
# watched runs (`bench watch`, docs/watch.md): a creep refit changes 1.1-2.4 x as much
# apart as on the window; the collinear refit that ran 6-9 um away, 7-47 x.
APART_RATIO = 4.0
APART_FLOOR_UM = 0.1
WATCH_EFFECTS = ("creep", "drift")  # what grows while a stage runs (warm-up, hours of
                                    # holding, a sensor's drift): each a few seconds of
                                    # diagnosis on a window; more may be asked for


@dataclass(frozen=True)
class WatchOptions:
    """How the watch judges a rise and what it diagnoses (see the module docstring)."""

    block_s: float = 1.0
    settle_s: float = 2.0
    baseline_s: float = 8.0
    rise: float = 1.5
    sigmas: float = 6.0
    sustain_blocks: int = 3
    fit_s: float = 6.0
    holdout_s: float = 3.0
    effects: tuple[str, ...] = WATCH_EFFECTS
    keep_s: float = 120.0     # samples kept past a window while it is diagnosed


@dataclass
class WatchRequest:
    """A window to diagnose: the voltages and displacements from the onset on (FIT
    then HOLDOUT), the model in use as its document, and what it started from."""

    fs_hz: float
    v: np.ndarray               # (n, 2) [V], x and y
    w: np.ndarray               # (n, 2) [um]
    n_fit: int
    model_doc: Doc
    effects: tuple[str, ...]
    start_index: int            # the window's first sample (the watch's count)
    rising: tuple[str, ...]     # the axes that rose
    gap_level_um: dict[str, float]   # the level after arming, per axis
    gap_rose_um: dict[str, float]    # the blocks' RMS that made the rise, per axis
    watched: tuple[str, ...] = ()    # every effect watched for (``creep``/``drift`` the
                                     # model in use has: refitted where they grew)


@dataclass
class WatchResult:
    """What ``diagnose_window`` found: per axis the verdict and the named effects, the
    held-out RMS of the model in use and of the model written for the named effects, and
    that model's document (None where the diagnosis failed: ``error``)."""

    verdict: dict[str, str] = field(default_factory=dict)
    named: dict[str, list[str]] = field(default_factory=dict)
    alike: dict[str, list[str]] = field(default_factory=dict)  # explain it as well
    rms_before_um: dict[str, float] = field(default_factory=dict)
    rms_after_um: dict[str, float] = field(default_factory=dict)
    gap_before_um: dict[str, float] = field(default_factory=dict)
    gap_after_um: dict[str, float] = field(default_factory=dict)
    reason: dict[str, str] = field(default_factory=dict)
    # how far the refit's prediction moves from the model in use's, on the window and
    # (the largest of) where one axis moves and the other holds still [um]
    change_um: dict[str, float] = field(default_factory=dict)
    change_apart_um: dict[str, float] = field(default_factory=dict)
    model_doc: Doc | None = None
    seconds: float = 0.0
    error: str = ""

    def apart_axes(self) -> list[str]:
        """The axes whose refit changes too much more where the axes move apart than on
        the window (``APART_RATIO``): its laws were not told apart there."""
        return [a for a, d in self.change_apart_um.items()
                if d > APART_RATIO * self.change_um.get(a, 0.0) + APART_FLOOR_UM]


@dataclass
class WatchEvent:
    """One diagnosis of the live gap, as the gap node reports it."""

    at_s: float                 # the window's end, on the stage's clock from the first
    onset_s: float              # sample; the rise's first block
    rising: tuple[str, ...]
    effect: str                 # the effect named ('' for none)
    shrink_pct: float           # of the held-out gap, on the rising axes (the worst)
    gap_before_um: float
    gap_after_um: float
    handed_on: bool
    reason: str
    model_doc: Doc | None = None

    def values(self) -> dict[str, str]:
        """The event as /diagnostics values (strings)."""
        return {"watch_effect": self.effect or "none",
                "watch_shrink_pct": f"{self.shrink_pct:.1f}",
                "watch_gap_before_um": f"{self.gap_before_um:.4f}",
                "watch_gap_after_um": f"{self.gap_after_um:.4f}",
                "watch_handed_on": str(self.handed_on).lower(),
                "watch_onset_s": f"{self.onset_s:.3f}", "watch_at_s": f"{self.at_s:.3f}",
                "watch_axes": ",".join(self.rising), "watch_reason": self.reason}


class LiveWatch:
    """The rise detector and the window keeper of one model in use (module docstring).

    ``sample(v, w, r)`` per sample (voltages, displacement and residual per axis)
    returns a ``WatchRequest`` when a window is complete; ``decide(request, result)``
    makes the diagnosis a ``WatchEvent``; ``adopted()`` after a hand-on starts the
    watch over the new model (the level after arming kept)."""

    def __init__(self, fs_hz: float, model_doc: Doc, options: WatchOptions | None = None,
                 have: dict[str, list[str]] | Sequence[str] = ()) -> None:
        self.fs = float(fs_hz)
        self.opt = options or WatchOptions()
        self.model_doc = model_doc
        self.have = have_by_axis(have)  # effects the model in use has: no candidates
        o = self.opt
        self.block = max(1, int(round(o.block_s * self.fs)))
        self.n = 0
        self.ss = dict.fromkeys(AXES, 0.0)
        self.blocks: dict[str, list[float]] = {a: [] for a in AXES}
        self.level: dict[str, float] = {}
        self.spread: dict[str, float] = {}
        # the samples kept: a window and what comes while it is diagnosed (the twin of
        # a model handed on runs over them from the window's start: ``since``)
        self.ring = np.zeros((max(int((o.fit_s + o.holdout_s + o.keep_s) * self.fs),
                                  self._window() + 1), 4))
        self.onset: int | None = None   # the window's first sample, once risen
        self.rising: tuple[str, ...] = ()
        self.rose: dict[str, float] = {}
        self.quiet_until = 0            # blocks before this one do not rise (a hand-on)
        self.pending = False

    # -- per sample ---------------------------------------------------------------------
    def sample(self, v: dict[str, float], w: dict[str, float], r: dict[str, float]
               ) -> WatchRequest | None:
        """One sample: the voltages [V], displacement and residual [um] per axis ->
        the window to diagnose, once one is complete."""
        row = self.ring[self.n % len(self.ring)]
        row[0], row[1], row[2], row[3] = v["x"], v["y"], w["x"], w["y"]
        self.n += 1
        for a in AXES:
            self.ss[a] += r[a] * r[a]
        if self.n % self.block == 0:
            self._block_done()
        if self.onset is not None and not self.pending and \
                self.n - self.onset >= self._window():
            self.pending = True
            return self._request()
        return None

    def _window(self) -> int:
        return int(round((self.opt.fit_s + self.opt.holdout_s) * self.fs))

    def _block_done(self) -> None:
        o = self.opt
        for a in AXES:
            self.blocks[a].append(float(np.sqrt(self.ss[a] / self.block)))
            self.ss[a] = 0.0
        k = len(self.blocks["x"])  # blocks so far
        settle = int(np.ceil(o.settle_s / o.block_s))
        base = max(3, int(round(o.baseline_s / o.block_s)))
        if not self.level and k >= settle + base:
            for a in AXES:
                b = np.array(self.blocks[a][settle:settle + base])
                med = float(np.median(b))
                self.level[a] = med
                self.spread[a] = max(1.4826 * float(np.median(np.abs(b - med))), 0.02 * med)
            return
        if not self.level or self.onset is not None or k < self.quiet_until:
            return
        m = o.sustain_blocks
        up = tuple(a for a in AXES if len(self.blocks[a]) >= m and all(
            x > self.threshold(a) for x in self.blocks[a][-m:]))
        if up:
            self.rising = up
            self.rose = {a: float(np.sqrt(np.mean(np.square(self.blocks[a][-m:]))))
                         for a in up}
            self.onset = self.n - m * self.block

    def window_end(self) -> int | None:
        """Once risen, the count of samples at which the window is complete (its last
        sample's index + 1), else None."""
        return None if self.onset is None else self.onset + self._window()

    def threshold(self, a: str) -> float:
        """The block RMS above which axis ``a``'s gap has risen [um]."""
        o = self.opt
        return max(o.rise * self.level[a], self.level[a] + o.sigmas * self.spread[a])

    def since(self, index: int) -> np.ndarray | None:
        """The samples from the watch's ``index``-th on, (n, 4): vx, vy, wx, wy (None
        where they are no longer kept)."""
        if index < self.n - len(self.ring) or index > self.n:
            return None
        k = np.arange(index, self.n) % len(self.ring)
        return self.ring[k].copy()

    def _request(self) -> WatchRequest:
        assert self.onset is not None
        a = self.since(self.onset)
        assert a is not None  # (the ring holds a window at least)
        return WatchRequest(self.fs, a[:, :2], a[:, 2:],
                            int(round(self.opt.fit_s * self.fs)), self.model_doc,
                            tuple(e for e in self.opt.effects
                                  if not all(e in self.have.get(a, ()) for a in AXES)),
                            self.onset, self.rising, dict(self.level), dict(self.rose),
                            tuple(self.opt.effects))

    # -- the answer -----------------------------------------------------------------------
    def decide(self, req: WatchRequest, res: WatchResult) -> WatchEvent:
        """The diagnosis of ``req`` as an event: handed on when an effect is named on a
        rising axis and the model written for it is closer on HOLDOUT than the model in
        use on every axis (never worse); the watch goes on either way (a window that
        named nothing: from the next rise)."""
        at = (req.start_index + len(req.v)) / self.fs
        onset = req.start_index / self.fs
        self.onset, self.pending = None, False
        k = len(self.blocks["x"])
        self.quiet_until = k + self.opt.sustain_blocks  # a new rise: new blocks
        if res.error:
            return WatchEvent(at, onset, req.rising, "", 0.0, float("nan"), float("nan"),
                              False, res.error)
        worst = max(req.rising, key=lambda a: res.gap_before_um.get(a, 0.0))
        named = [e for a in req.rising for e in res.named.get(a, []) if e]
        effect = "+".join(dict.fromkeys(named)) if res.model_doc is not None else ""
        g0 = res.gap_before_um.get(worst, float("nan"))
        g1 = res.gap_after_um.get(worst, g0)
        shrink = 100.0 * (1 - g1 / g0) if g0 > 0 else 0.0
        if not effect:
            why = "; ".join(f"{a}: {res.reason.get(a, '')}" for a in req.rising)
            return WatchEvent(at, onset, req.rising, "", shrink, g0, g1, False,
                              f"no effect named ({why})")
        # never worse: closer on the rising axis, no further on any
        closer = res.rms_after_um[worst] < res.rms_before_um[worst] and all(
            res.rms_after_um[a] <= res.rms_before_um[a] * (1 + 1e-9)
            for a in res.rms_after_um)
        if not closer:
            return WatchEvent(at, onset, req.rising, effect, shrink, g0, g1, False,
                              f"{effect} named, but its model is not closer on the newest "
                              "data on every axis: not handed on")
        apart = res.apart_axes()
        if apart:
            a = apart[0]
            return WatchEvent(at, onset, req.rising, effect, shrink, g0, g1, False,
                              f"{effect} named, but the window moved the axes alike and "
                              f"the refit's laws are not told apart: on {a} it changes "
                              f"{res.change_apart_um[a]:.3g} um where the axes move apart, "
                              f"{res.change_um[a]:.3g} um on the window: not handed on")
        alike = sorted({e for a in req.rising for e in res.alike.get(a, [])} - set(named))
        return WatchEvent(at, onset, req.rising, effect, shrink, g0, g1, True,
                          f"{effect} grew on {', '.join(req.rising)}: the held-out gap "
                          f"{g0:.3g} um -> " + (f"{g1:.3g} um" if g1 > 0 else
                                                "within the noise floor") + " with it" + (
                              f" ({' and '.join(alike)} as well on this trajectory: not "
                              "told apart)" if alike else ""), res.model_doc)

    def adopted(self, model_doc: Doc, have: dict[str, list[str]] | Sequence[str]) -> None:
        """A handed-on model is now the one in use: later windows diagnose against it."""
        self.model_doc, self.have = model_doc, have_by_axis(have)


def effects_of(effects: EffectsBlock | None) -> dict[str, list[str]]:
    """The enabled effects of a model file's effects block, per axis (a block for both
    axes, or a list of blocks with their own ``axes``)."""
    out: dict[str, list[str]] = {a: [] for a in AXES}
    for name, p in (effects or {}).items():
        for q in (p if isinstance(p, list) else [p]):
            if isinstance(q, dict) and q.get("enabled", True):
                for a in q.get("axes", AXES):
                    out.setdefault(a, []).append(name)
    return out


def have_by_axis(have: dict[str, list[str]] | Sequence[str]) -> dict[str, set[str]]:
    """Effects a model has, per axis (a plain list: on every axis)."""
    if isinstance(have, dict):
        return {a: set(v) for a, v in have.items()}
    return {a: set(have) for a in AXES}


def diagnose_window(req: WatchRequest) -> WatchResult:
    """The offline diagnosis (``diagnose``) of one window against the model in use,
    reduced to plain data (``WatchResult``): for a worker process. Where it names creep
    or drift on the rising axes (what grows while a stage runs), the model handed on is
    the model in use with that effect added and every law kept (``locked_refit``), of
    the two the one closer on HOLDOUT (``locked_choice``: creep where alike, as it
    settles; a drift's ramp fitted to a creep's first seconds ran 8 um away in 30 s);
    an effect the model has already is fitted again where the gap grew. Another effect
    named: the whole refit ``gap --out-model`` writes. Every figure is the model's as
    the twin runs it (``window_rms``)."""
    import time

    from piezo_stage.core.errors import PiezoStageError
    t0 = time.perf_counter()
    try:
        out = _diagnosis(req, req.effects)
    except PiezoStageError as e:
        out = WatchResult(error=str(e))
    out.seconds = time.perf_counter() - t0
    return out


def _diagnosis(req: WatchRequest, effects: tuple[str, ...]) -> WatchResult:
    """One diagnosis of ``req``'s window with these candidate effects."""
    from piezo_stage.core.estimation.gap import diagnose
    from piezo_stage.core.estimation.record import Record
    from piezo_stage.core.model.model_doc import model_from_dict
    out = WatchResult()
    model, have = model_from_dict(req.model_doc, "the model in use")
    t = np.arange(len(req.v)) / req.fs_hz
    k = req.n_fit

    def rec(s: slice, what: str) -> Record:
        return Record(t[s] - t[s][0], {"x": req.v[s, 0], "y": req.v[s, 1]},
                      {"x": req.w[s, 0], "y": req.w[s, 1]}, source=f"live {what}",
                      voltage_exact=True)
    # HOLDOUT is the whole window with FIT as its history: every model runs from the
    # window's start, and the sensor's zero is FIT's (a drift's level is its gap)
    d = diagnose(rec(slice(0, k), "FIT"), rec(slice(0, None), "HOLDOUT"), effects=effects,
                 axes=[a for a in AXES if a in model.axes], base_model=model,
                 base_effects=have, limits_V=model.voltage_limits, history=k,
                 live=True) if effects else None
    if d is None:
        out.reason = {a: "every effect watched for is in the model already" for a in AXES}
    for a, ax in (d["axes"] if d is not None else {}).items():
        out.verdict[a] = ax["verdict"]
        out.reason[a] = ax["reason"]
        out.named[a] = [s["effect"] for s in ax["effects"] if not s.get("shape_of")]
        eff = [r for r in ax["ranking"] if r["effect"] != "none"]
        if out.named[a] and eff:
            g = eff[0]["gap_after_um"] * 1.02 + 1e-3
            out.alike[a] = [r["effect"] for r in eff[:2] if r["effect"] not in
                            out.named[a] and r["gap_after_um"] <= g]
        none = next(r for r in ax["ranking"] if r["effect"] == "none")
        out.rms_before_um[a] = float(none["rms_after_um"])
        out.gap_before_um[a] = float(none["gap_after_um"])
        out.rms_after_um[a] = float(ax["written"]["rms_after_um"])
        out.gap_after_um[a] = float(ax["written"]["gap_after_um"])
    have_ax = have_by_axis(effects_of(req.model_doc.get("effects")))
    grown = {a: [e for e in LOCKED if e in req.watched and e in have_ax.get(a, ())]
             for a in req.rising}  # in the model already: it may have grown
    if any(out.named.get(a) or grown[a] for a in req.rising):
        named = {a: out.named.get(a, []) for a in req.rising}
        if all(set(e) <= set(LOCKED) for e in named.values()):
            # what grows while a stage runs, added to the model in use: its laws kept;
            # of creep and drift, the one closer on HOLDOUT (creep where alike)
            named, why, alike = locked_choice(req, named)
            out.named.update(named)
            out.reason.update(why)
            out.alike.update(alike)
            out.model_doc = locked_refit(req, named) if any(named.values()) else None
        else:  # another effect named: the whole refit gap --out-model would write
            assert d is not None
            out.model_doc = d.document()[0]
    # the figures, each model's as the twin runs it (one model, one figure): from the
    # window's start, zeroed on FIT, scored on HOLDOUT
    for doc, rms, gap in ((req.model_doc, out.rms_before_um, out.gap_before_um),
                          (out.model_doc, out.rms_after_um, out.gap_after_um)):
        if doc is not None:
            rms.update(window_rms(doc, req))
            gap.update({a: gap_um(x, req.gap_level_um.get(a, 0.0)) for a, x in rms.items()})
    if out.model_doc is not None:
        out.change_um, out.change_apart_um = model_change(req.model_doc, out.model_doc,
                                                          req.v, req.fs_hz)
    return out


def gap_um(rms: float, floor: float) -> float:
    """The part of an RMS above the noise floor [um] (``gap``'s: in quadrature)."""
    return float(np.sqrt(max(rms * rms - floor * floor, 0.0)))


LOCKED = ("creep", "drift")  # the effects the watch adds to the model in use as it is
LOCKED_SHRINK = 0.3  # of the held-out gap, at least, for an effect to be added (gap's
                     # FIRST_SHRINK_PCT for the first effect)
CREEP_TAU_S = (0.05, 0.5, 5.0, 50.0)  # the creep's decades (the plant file's default)


def locked_refit(req: WatchRequest, named: dict[str, list[str]]) -> Doc:
    """The model in use with the effects ``named`` per rising axis added, their
    parameters fitted on FIT with every law of the model in use kept: the window drives
    both axes alike more often than not (the default trajectory), and there an axis's
    own law and its coupling cannot be told apart, so a whole refit trades one for the
    other (it did: 226 um against -182 um) and runs away once the feedforward drives the
    axes apart. Each effect is linear in its parameters on the model in use's output: a
    creep's gamma on its fast part (``Creep.fast_part``), a drift's rate on t (over
    seconds a drift is a ramp: its saturating part, fitted on 5 s, ran 1.6 x the level
    where the ramp alone stays within 1.25 x; a later rise fits it again), with the
    sensor's zero. FIT's first second, where the twin settles from its initial state,
    is not fitted (``settle_samples``)."""
    import copy

    from piezo_stage.core.model.effects import Creep, Drift
    from piezo_stage.core.model.model_doc import model_from_dict
    from piezo_stage.core.model.plant import Plant
    doc = copy.deepcopy(req.model_doc)
    effects = doc.setdefault("effects", {})
    had = have_by_axis(effects_of(effects))
    for a, names in named.items():  # one the model has: fitted again from the window
        for e in names:
            if e in had.get(a, ()):
                _drop_axis(effects, e, a)
    _start_at(doc, req.v[0])
    model, have = model_from_dict(doc, "the model in use")
    fs, k = req.fs_hz, req.n_fit
    y0 = Plant.of_model(model, have, fs).run(req.v[:, 0], req.v[:, 1])
    tau = max(k / fs, 1.0) / 3.0
    for i, a in enumerate(AXES):
        if a not in named or a not in y0:
            continue
        names = [e for e in LOCKED if e in named[a]]
        cols, what = [np.ones(len(req.v))], []
        for e in names:
            if e == "creep":
                cols.append(-Creep(fs, 0.0, CREEP_TAU_S).fast_part(y0[a][:, None])[:, 0])
                what.append(("creep", 1))
            else:
                cols.append(Drift.columns(len(req.v), fs, tau)[:, 0])
                what.append(("drift", 1))
        X = np.column_stack(cols)
        s0 = settle_samples(req)  # the twin's start from its initial state: not fitted
        theta = np.linalg.lstsq(X[s0:k], req.w[s0:k, i] - y0[a][s0:k], rcond=None)[0]
        j = 1
        for e, m in what:
            if e == "creep":  # a creep fraction in [0, 0.5]: none below, bounded above
                block: Doc = {"axes": [a], "gamma": float(np.clip(theta[j], 0.0, 0.5)),
                              "tau_s": list(CREEP_TAU_S)}
            else:
                block = {"axes": [a], "rate_um_per_s": float(theta[j]),
                         "amplitude_um": 0.0, "tau_s": float(tau)}
            j += m
            cur = effects.get(e)
            if cur is None:
                effects[e] = [block]
            else:  # (a block for both axes would have left it no candidate here)
                effects[e] = (cur if isinstance(cur, list) else [cur]) + [block]
    model_from_dict(doc, "the watch's refit")  # our own loader takes it
    return doc


def _start_at(doc: Doc, v0: np.ndarray) -> None:
    """``doc``'s laws (each axis's and its coupling's) start where they stand at the
    window's first voltages ``v0`` (x, y), moved there from their initial states: a
    twin run from the window's start then starts its effects at rest at its first
    output, as an effect that began there does (the plant's ``changes``; creep's
    ``fast_part`` from rest at the first row), not at the model's old initial output."""
    from piezo_stage.core.model.duhem import DuhemHysteresis
    from piezo_stage.core.model.model_doc import model_from_dict
    model, _ = model_from_dict(doc, "the model in use")
    for i, a in enumerate(AXES):
        if a not in model.axes or a not in doc.get("axes", {}):
            continue
        parts = [(doc["axes"][a], model.axes[a], v0[i])]
        if a in model.coupling and isinstance(doc["axes"][a].get("coupling"), dict):
            parts.append((doc["axes"][a]["coupling"], model.coupling[a], v0[1 - i]))
        for block, law, v in parts:
            h = DuhemHysteresis(law)
            h.step(float(v))
            block["initial_state"] = {"v_V": float(h.v), "w_um": float(h.w)}


def _drop_axis(effects: Doc, name: str, axis: str) -> None:
    """Effect ``name``'s blocks in ``effects`` (a model document's) without ``axis``."""
    blocks = effects.get(name)
    kept = []
    for b in (blocks if isinstance(blocks, list) else [blocks]):
        if not isinstance(b, dict):
            continue
        axes = [x for x in b.get("axes", AXES) if x != axis]
        if axes:
            kept.append({**b, "axes": axes})
    if kept:
        effects[name] = kept
    else:
        effects.pop(name, None)


def locked_choice(req: WatchRequest, named: dict[str, list[str]]
                  ) -> tuple[dict[str, list[str]], dict[str, str], dict[str, list[str]]]:
    """Per axis where an effect was named: of the ``LOCKED`` effects the window may add
    there, the one whose ``locked_refit`` is closer on HOLDOUT (``window_rms``), creep
    where the two are alike (within 2 %: it settles, where a drift's ramp runs on). On a
    running periodic trajectory a creep's slow part is a slow shift of the mean, as a
    drift's, and the whole diagnosis names either; the model handed on is the locked one,
    so its figure chooses. An axis where the choice closes less than ``LOCKED_SHRINK`` of
    the held-out gap gets none (why, per axis); the others as close (2 %) are said alike.
    -> (named, why, alike), per axis."""
    have = have_by_axis(effects_of(req.model_doc.get("effects")))
    out, why, alike = dict(named), {}, {}
    before = window_rms(req.model_doc, req)
    for a, names in named.items():
        grown = [e for e in LOCKED if e in req.watched and e in have.get(a, ())]
        if names:  # named by the diagnosis: it, the others it may add, or a regrowth
            cands = [e for e in LOCKED if e in names or e in grown or (
                e in req.effects and e not in have.get(a, ()))]
        else:      # nothing new named: what the model has may have grown
            cands = grown
        if not cands:
            out[a] = []
            continue
        rms = {e: window_rms(locked_refit(req, {a: [e]}), req)[a] for e in cands}
        best = min(rms, key=lambda e: rms[e])
        if "creep" in rms and rms["creep"] <= 1.02 * rms[best]:
            best = "creep"
        alike[a] = [e for e in rms if e != best and rms[e] <= 1.02 * rms[best]]
        floor = req.gap_level_um.get(a, 0.0)
        g0, g1 = gap_um(before[a], floor), gap_um(rms[best], floor)
        if g1 > (1 - LOCKED_SHRINK) * g0:  # too little to hand on: a ramp fitted to a
            out[a] = []                    # gap it hardly closes runs on (seen: 14 x)
            how = "refitted in" if best in have.get(a, ()) else "added to"
            why[a] = ((f"{' or '.join(names)} named, but " if names else "")
                      + f"{best} {how} the model in use closes "
                      f"{100 * (1 - g1 / g0) if g0 > 0 else 0:.0f} % of the held-out "
                      f"gap ({g0:.3g} um), under {100 * LOCKED_SHRINK:.0f} %")
            continue
        out[a] = [best]
    return out, why, alike


def window_rms(doc: Doc, req: WatchRequest) -> dict[str, float]:
    """A model's RMS on the window's HOLDOUT per axis [um], run as the twin runs a model
    handed on: from the window's start, its zero FIT's mean residual after its first
    second (``settle_samples``: the twin's start from its initial state), HOLDOUT's
    first second run, not scored."""
    from piezo_stage.core.model.model_doc import model_from_dict
    from piezo_stage.core.model.plant import Plant
    m, e = model_from_dict(doc, "a watched model")
    y = Plant.of_model(m, e, req.fs_hz).run(req.v[:, 0], req.v[:, 1])
    k, s = req.n_fit, req.n_fit + int(round(req.fs_hz))
    s0 = settle_samples(req)
    out = {}
    for i, a in enumerate(AXES):
        if a in y:
            r = req.w[:, i] - y[a]
            out[a] = float(np.sqrt(np.mean((r[s:] - np.mean(r[s0:k])) ** 2)))
    return out


def settle_samples(req: WatchRequest) -> int:
    """The window's first samples a twin run from the window's start needs to settle
    from its model's initial state (1 s, at most half of FIT): neither fitted nor
    part of the twin's zero (``ResidualMonitor.switch``'s ``settle``)."""
    return min(int(round(req.fs_hz)), req.n_fit // 2)


def model_change(before: Doc, after: Doc, v: np.ndarray, fs_hz: float
                 ) -> tuple[dict[str, float], dict[str, float]]:
    """How far ``after``'s prediction is from ``before``'s per axis [um RMS, each run's
    mean removed: the twin's zero is its own], driven by the window's voltages ``v``
    ((n, 2)), and the largest where one axis moves as in the window and the other is
    held at its first voltage (what a window that drove both alike cannot tell)."""
    from piezo_stage.core.model.model_doc import model_from_dict
    from piezo_stage.core.model.plant import Plant

    def run(doc: Doc, vx: np.ndarray, vy: np.ndarray) -> dict[str, np.ndarray]:
        m, e = model_from_dict(doc, "a watched model")
        return Plant.of_model(m, e, fs_hz).run(vx, vy)

    def diff(vx: np.ndarray, vy: np.ndarray) -> dict[str, float]:
        b, a = run(before, vx, vy), run(after, vx, vy)
        return {ax: float(np.std(a[ax] - b[ax])) for ax in AXES if ax in a and ax in b}

    vx, vy = v[:, 0], v[:, 1]
    on = diff(vx, vy)
    # the axis held where the window starts (the refit's initial state: no step)
    probes = [diff(vx, np.full_like(vy, vy[0])), diff(np.full_like(vx, vx[0]), vy)]
    return on, {ax: max(p[ax] for p in probes) for ax in on}


def model_in_use(model: StageModel, effects: EffectsBlock | None) -> Doc:
    """A model and its effects as the document the watch diagnoses against."""
    from piezo_stage.core.model.model_doc import checked_doc
    return checked_doc(model, effects or None)[0]
