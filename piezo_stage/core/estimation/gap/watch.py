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
    model_doc: Doc | None = None
    seconds: float = 0.0
    error: str = ""


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
                            self.onset, self.rising, dict(self.level), dict(self.rose))

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
        if res.error or res.model_doc is None:
            return WatchEvent(at, onset, req.rising, "", 0.0, float("nan"), float("nan"),
                              False, res.error or "no model written")
        worst = max(req.rising, key=lambda a: res.gap_before_um.get(a, 0.0))
        named = [e for a in req.rising for e in res.named.get(a, []) if e]
        effect = "+".join(dict.fromkeys(named))
        g0, g1 = res.gap_before_um[worst], res.gap_after_um[worst]
        shrink = 100.0 * (1 - g1 / g0) if g0 > 0 else 0.0
        # never worse: closer on the rising axis, no further on any
        closer = res.rms_after_um[worst] < res.rms_before_um[worst] and all(
            res.rms_after_um[a] <= res.rms_before_um[a] * (1 + 1e-9)
            for a in res.rms_after_um)
        if not effect:
            why = "; ".join(f"{a}: {res.reason.get(a, '')}" for a in req.rising)
            return WatchEvent(at, onset, req.rising, "", shrink, g0, g1, False,
                              f"no effect named ({why})")
        if not closer:
            return WatchEvent(at, onset, req.rising, effect, shrink, g0, g1, False,
                              f"{effect} named, but its model is not closer on the newest "
                              "data on every axis: not handed on")
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


BOUNDED_FIRST = ("creep", "drift")  # of two alike, the first (its extrapolation is
                                    # bounded: a creep settles, a drift's ramp goes on)


def diagnose_window(req: WatchRequest) -> WatchResult:
    """The offline diagnosis (``diagnose``) of one window against the model in use,
    reduced to plain data (``WatchResult``): for a worker process. Where the effect
    named has another alike on this window that settles where it goes on (creep
    beside drift: on a periodic trajectory a creep's slow part is a slow shift of the
    mean, as a drift's), the window is diagnosed again without it and the one that
    settles handed on when it is as close (2 %): a model run on from the window must
    not run away (a drift's ramp fitted to a creep's first seconds did, 8 um in 30 s)."""
    import time

    from piezo_stage.core.errors import PiezoStageError
    t0 = time.perf_counter()
    try:
        if not req.effects:
            raise PiezoStageError("every effect watched for is in the model already")
        out = _diagnosis(req, req.effects)
        goes_on, settles = BOUNDED_FIRST[1], BOUNDED_FIRST[0]
        if settles in req.effects and any(goes_on in out.named.get(a, []) and settles in
                                          out.alike.get(a, []) for a in req.rising):
            other = _diagnosis(req, tuple(e for e in req.effects if e != goes_on))
            if other.model_doc is not None and all(
                    other.rms_after_um[a] <= 1.02 * out.rms_after_um[a] + 1e-4
                    for a in other.rms_after_um):
                other.alike = {a: sorted(set(v) | {goes_on}) for a, v in other.alike.items()}
                out = other
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
                 base_effects=have, limits_V=model.voltage_limits, history=k, live=True)
    for a, ax in d["axes"].items():
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
    if any(out.named.values()):
        out.model_doc = d.document()[0]
    return out


def model_in_use(model: StageModel, effects: EffectsBlock | None) -> Doc:
    """A model and its effects as the document the watch diagnoses against."""
    from piezo_stage.core.model.model_doc import checked_doc
    return checked_doc(model, effects or None)[0]
