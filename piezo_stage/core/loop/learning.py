"""Learning feedforward for repeated motion (iterative learning control).

A periodic trajectory repeats its error from one period to the next. The learner adds a
correction c to the desired position before the feedforward and, after each period j,
updates it per DFT bin k from that period's measured error E_j:

    A_(j+1)(k) = Q(k) ((1 - gain_j) A_j(k) + gain_j (C_j(k) + L(k) E_j(k)))

with L = 1 / G (G: the model's effects the feedforward does not compensate, inverted
over the whole period: non-causal and stable), Q passing the bins where the design's
convergence factor stays below 1 - margin with every effect parameter off by
``perturb``, the gain full for FULL_GAIN_PERIODS and then falling to a running mean,
the applied correction shrunk by the noise (a non-negative garrote per bin), a bin
that grows past its best rolled back and damped, and a disturbed period (an error jump
past twice the last) not learned. C_j is what each sample was given (``offset``), not
the last update. The derivation, the noise rule and the disturbance rule:
docs/experiments.md, "How the learner works"; figures: docs/experiments.md and
docs/benchmarks.md.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from piezo_stage.core.errors import ConfigError
from piezo_stage.core.loop.compensation import (
    DynamicsInverse,
    EffectCompensator,
    PreviewedReference,
)
from piezo_stage.core.model.effects import effects_on
from piezo_stage.core.types import Doc, EffectsBlock, Params, PerAxis

EFFECTS_WITH_DYNAMICS = ("creep", "dynamics", "delay")  # drift ignores the input
NOISE_KAPPA = 1.5  # a bin is learned where it exceeds this many noise RMS
FULL_GAIN_PERIODS = 3  # periods learned at the full gain before it falls
DISTURBED_FACTOR = 2.0  # a period whose error RMS jumps past this times the last one's
DISTURBED_RUN = 3       # ... is skipped, unless this many in a row have (a lasting change)


def _scaled(params: Params, scale: Params | None) -> Params:
    sc = scale or {}
    out = {k: v for k, v in params.items() if k not in ("axes", "enabled")}
    for k, f in sc.items():
        if k in out:
            out[k] = [x * f for x in out[k]] if isinstance(out[k], list) else out[k] * f
    return out


def creep_response(params: Params, rate_hz: float, freqs_hz: np.ndarray) -> np.ndarray:
    """Creep (core/model/effects.py's form) at the control rate: 1 - gamma (1 - the mean of
    its low-passes (1 - p) / (1 - p z^-1), p = exp(-T / tau))."""
    z1 = np.exp(-2j * np.pi * np.asarray(freqs_hz, float) / rate_hz)
    poles = np.exp(-1.0 / (rate_hz * np.atleast_1d(np.asarray(
        params.get("tau_s", (0.05, 0.5, 5.0, 50.0)), float))))
    slow = np.mean([(1 - p) / (1 - p * z1) for p in poles], axis=0)
    return 1 - min(float(params.get("gamma", 0.03)), 0.99) * (1 - slow)


def held_dynamics_response(params: Params, delay_s: float, rate_hz: float,
                           freqs_hz: np.ndarray) -> np.ndarray:
    """Dynamics (and a transport delay) driven by a command held over each control
    period and read at the period's end, as the plant's sampled output: the delay's
    whole periods are a shift, its fraction the instant inside the held period at
    which the dynamics are read (core.compensation.DynamicsInverse's forward model:
    x+ = Ad x + Bd u, y = Cs x + Ds u). Without dynamics a fraction of a period is not
    seen at all: the held command has reached the output by the period's end."""
    f = np.asarray(freqs_hz, float)
    T = 1.0 / rate_hz
    whole = int(np.floor(delay_s / T + 1e-9))
    shift = np.exp(-2j * np.pi * f * whole * T)
    if not params:
        return shift
    kw = {k: params[k] for k in ("kind", "fn_hz", "zeta", "tau_s") if k in params}
    dyn = DynamicsInverse(rate_hz, delta_s=delay_s - whole * T, **kw)
    z = np.exp(2j * np.pi * f * T)
    n = dyn.Ad.shape[0]
    h = np.array([dyn.Ds + dyn.Cs @ np.linalg.solve(zk * np.eye(n) - dyn.Ad, dyn.Bd.ravel())
                  for zk in z])
    return h * shift


def effects_response(effects: EffectsBlock | None, axis: str, rate_hz: float, freqs_hz: np.ndarray,
                     scale: Params | None = None) -> np.ndarray:
    """The axis's effects chain (creep, dynamics, delay; drift ignores the input) as the
    sampled plant shows it at the control rate, every parameter times ``scale``'s
    factor for it (a perturbed model)."""
    on = {name: _scaled(p, scale) for name, p in effects_on(effects, axis).items()
          if name in EFFECTS_WITH_DYNAMICS}
    g = np.ones(len(freqs_hz), complex)
    if "creep" in on:
        g = g * creep_response(on["creep"], rate_hz, freqs_hz)
    if "dynamics" in on or "delay" in on:
        g = g * held_dynamics_response(on.get("dynamics", {}),
                                       float(on.get("delay", {}).get("delay_s", 0.0)),
                                       rate_hz, freqs_hz)
    return g


def loop_response(effects: EffectsBlock | None, axis: str, rate_hz: float, freqs_hz: np.ndarray,
                  compensator: EffectCompensator | None = None, scale: Params | None = None,
                  model: Doc | None = None) -> np.ndarray:
    """From a correction of the desired position to the stage's position: the effects
    chain (``effects``, perhaps perturbed by ``scale``) times what the feedforward's
    ``compensator`` (a core.compensation.EffectCompensator, or None) does about the
    *model's* effects (``model``; ``effects`` when not given): the delay's whole periods
    run ahead, creep divided out, and where the dynamics are inverted, the dynamics read
    at the delay's fraction divided out."""
    f = np.asarray(freqs_hz, float)
    model = effects_on(effects if model is None else model, axis)
    g = effects_response(effects, axis, rate_hz, f, scale)
    if compensator is None:
        return g
    # the time advance: the lead without the samples a stable inverse only previews
    lead = (compensator.lead_ticks.get(axis, 0) -
            compensator.preview_ticks.get(axis, 0)) / rate_hz
    g = g * np.exp(2j * np.pi * f * lead)
    if axis in compensator.creep:
        g = g / creep_response(model["creep"], rate_hz, f)
    if axis in compensator.dynamics:
        frac = float(model.get("delay", {}).get("delay_s", 0.0)) - lead \
            if "delay" in model else 0.0
        g = g / held_dynamics_response(model["dynamics"], frac, rate_hz, f)
    return g


@dataclass
class LearningDesign:
    """One axis's learning filter for a period of ``n`` samples at ``rate_hz``: per DFT
    bin the learning filter ``learn``, the zero-phase robustness filter ``q``; the passed
    band's edge ``cutoff_hz``; ``worst_factor``: the largest Q |1 - gain L G| over the
    bins and the perturbed models (< 1: monotonic convergence), ``nominal_factor`` the
    same on the model itself."""
    n: int
    rate_hz: float
    gain: float
    learn: np.ndarray
    q: np.ndarray
    cutoff_hz: float
    worst_factor: float
    nominal_factor: float

    def describe(self) -> str:
        """One line: the band learned and the convergence check."""
        ok = "met" if self.worst_factor < 1.0 else "NOT met"
        return (f"learning up to {self.cutoff_hz:.0f} Hz, gain {self.gain:g}; convergence "
                f"factor {self.nominal_factor:.2f} on the model, {self.worst_factor:.2f} "
                f"with its parameters off by the design's margin ({ok}: < 1)")


def _scales(effects: EffectsBlock, perturb: float) -> list[dict[str, float]]:
    """Every parameter of the effects off by +-perturb, one at a time and all together."""
    names = {"delay_s", "fn_hz", "zeta", "gamma", "tau_s"}
    present = sorted({k for p in (effects or {}).values() for k in p} & names)
    out: list[dict[str, float]] = [{}]
    for k in present:
        out += [{k: 1 + perturb}, {k: 1 - perturb}]
    if present:
        out += [{k: 1 + perturb for k in present}, {k: 1 - perturb for k in present}]
    return out


def design(n: int, rate_hz: float, effects: EffectsBlock | None = None, axis: str = "x",
           compensator: EffectCompensator | None = None, gain: float = 1.0,
           perturb: float = 0.01,
           margin: float = 0.05, max_cutoff_hz: float | None = None) -> LearningDesign:
    """The learning filter and the robustness filter for one axis (see the module).

    Parameters
    ----------
    n : int
        Samples per period.
    rate_hz : float
        The control rate [Hz].
    effects : dict, optional
        The model's effects (as the model file has them).
    axis : str
        The axis.
    compensator : EffectCompensator, optional
        What the feedforward does about the effects (None: nothing).
    gain : float
        The largest learning gain used, in (0, 1].
    perturb : float
        The relative error of every effect parameter the design must survive (1 %
        by default: the gap diagnosis finds a resonance and a delay to a fraction of
        that; a resonance near or above the Nyquist frequency moves its alias by far
        more than its own error, which a larger margin answers by learning nothing
        near the alias).
    margin : float
        Learn only where the worst factor stays below 1 - margin.
    max_cutoff_hz : float, optional
        An upper edge for the learned band (default 0.4 x the rate).

    Returns
    -------
    LearningDesign
        The filters and the convergence check.
    """
    if n < 4 or not 0 < gain <= 1 or not 0 <= perturb < 1:
        raise ConfigError("learning: a period of >= 4 samples, gain in (0, 1], perturb "
                          "in [0, 1)")
    f = np.fft.rfftfreq(n, 1.0 / rate_hz)
    g = loop_response(effects, axis, rate_hz, f, compensator)
    ok = np.abs(g) >= 0.1
    learn = np.where(ok, 1.0 / np.where(ok, g, 1.0), 0.0)
    worst = np.zeros(f.size)
    for sc in _scales(effects_on(effects, axis), perturb):
        gt = loop_response(effects, axis, rate_hz, f, compensator, sc, model=effects)
        worst = np.maximum(worst, np.abs(1 - gain * learn * gt))
    edge = 0.4 * rate_hz if max_cutoff_hz is None else min(max_cutoff_hz, 0.4 * rate_hz)
    bad = np.flatnonzero((worst >= 1 - margin) & (f > 0) | (f > edge))
    last = (bad[0] - 1) if bad.size else f.size - 1
    cutoff = float(f[max(last, 0)])
    q = np.zeros(f.size)
    q[:last + 1] = 1.0
    if bad.size and f[bad[0]] <= edge and cutoff > 0:
        # cut for robustness: a raised-cosine roll-off over the top quarter of the
        # passed band (zero phase), so no bin next to an untrusted one learns fully
        roll = (f > 0.75 * cutoff) & (f <= cutoff)
        q[roll] = 0.5 * (1 + np.cos(np.pi * (f[roll] - 0.75 * cutoff) / (0.25 * cutoff)))
    q[0] = 1.0
    nominal = np.abs(1 - gain * learn * g)
    return LearningDesign(n, rate_hz, gain, learn, q, cutoff, float(np.max(q * worst)),
                          float(np.max(q * nominal)))


class PeriodicLearner:
    """The correction of each axis over one period, learned period by period.

    ``offset(k)``: the correction at sample ``k`` of the trajectory (the period's
    sample ``k mod n``). ``update(errors)``: one whole period's errors (desired -
    measured, per axis, n samples in the period's own order) learned. ``limit_um``
    bounds the correction (a safety bound: what learning may add to any target).
    """

    def __init__(self, designs: dict[str, LearningDesign], gain_floor: float = 0.05,
                 limit_um: float = 5.0) -> None:
        ns = {d.n for d in designs.values()}
        if len(ns) != 1:
            raise ConfigError("learning: every axis needs the same period")
        self.n = ns.pop()
        self.designs, self.gain_floor, self.limit_um = designs, float(gain_floor), limit_um
        self.reset()

    def reset(self) -> None:
        """Forget what was learned (a new trajectory)."""
        self.c = {a: np.zeros(self.n) for a in self.designs}
        self.acc = {a: np.zeros(self.n // 2 + 1, complex) for a in self.designs}
        self.bin_gain = {a: np.ones(d.q.size) for a, d in self.designs.items()}
        # each bin's smallest error so far, the correction that gave it, and each bin's
        # error before learning
        self._best: dict[str, np.ndarray | None] = {a: None for a in self.designs}
        self._best_acc: dict[str, np.ndarray | None] = {a: None for a in self.designs}
        self._first: dict[str, np.ndarray | None] = {a: None for a in self.designs}
        self.periods, self.learned, self.skipped, self.damped = 0, 0, 0, 0
        self.applied = 0  # periods learned that ran on a learned correction throughout
        self.disturbed = 0  # periods not learned: their error jumped (a host pause)
        self._last_rms: dict[str, float] | None = None
        self._run = 0
        # sensor noise, from the data
        self.noise_um: dict[str, float | None] = {a: None for a in self.designs}
        self._e_prev: dict[str, tuple[np.ndarray, np.ndarray] | None] = {
            a: None for a in self.designs}
        self._j: int | None = None
        self._done = False
        self._buf = {a: np.full(self.n, np.nan) for a in self.designs}
        self._ubuf = {a: np.full(self.n, np.nan) for a in self.designs}
        self._used: dict[int, Doc] = {}  # trajectory sample -> its correction (offset)
        self._gen = 0    # updates so far: the generation of the present correction
        self._gbuf = np.zeros(self.n, int)  # each sample's correction's generation
        self._period_gen: int | None = None

    def observe(self, k: int, error: PerAxis[float]) -> bool:
        """One sample's error [um] (desired - measured) at trajectory sample ``k``;
        learns as soon as the period's last sample has come with every other one (so the
        next period's first sample already gets the new correction). A period that
        misses a sample (a missed tick) is skipped and counted. True when it learned.
        The correction each sample was given (``offset``) is what the period is learned
        against: a command is computed ahead of its tick (the loop's look-ahead), so the
        first samples of a period got the correction from before the last update."""
        j, i = int(k) // self.n, int(k) % self.n
        if j != self._j:
            if self._j is not None and not self._done:
                self.skipped += 1  # the period before ended without all its samples
            for b in (*self._buf.values(), *self._ubuf.values()):
                b[:] = np.nan
            self._j, self._done = j, False
        used = self._used.pop(int(k), None)
        self._gbuf[i] = used.get("gen", self._gen) if used else self._gen
        for a, b in self._buf.items():
            b[i] = error[a]
            self._ubuf[a][i] = used.get(a, self.c[a][i]) if used else self.c[a][i]
        if i == self.n - 1 and not self._done:
            self._done = True
            # forget what was given to samples already learned (or never to be)
            self._used = {q: u for q, u in self._used.items() if q > k}
            if all(np.all(np.isfinite(b)) for b in self._buf.values()):
                self._period_gen = int(self._gbuf.min())
                self.update(self._buf, self._ubuf)
                return True
            self.skipped += 1
        return False

    @property
    def gain(self) -> float:
        """The gain of the next update: full until ``FULL_GAIN_PERIODS`` periods have
        been learned that ran on a learned correction throughout (``applied``; a
        correction reaches the stage a look-ahead after its update, in real time or
        behind a preview inverse a period or more), falling from there (``learned``
        counts every period learned, ``periods`` every period seen, the first only
        measured)."""
        g0 = max(d.gain for d in self.designs.values())
        i = self.applied - FULL_GAIN_PERIODS + 1
        return g0 if i <= 0 else max(self.gain_floor, g0 / (1 + g0 * i))

    @property
    def averaged(self) -> float:
        """How many periods' worth of noise the accumulated correction holds after the
        next update: one while the gain is full, then the periods in the running mean,
        at most what an exponential mean at the gain's floor holds, (2 - floor) /
        floor."""
        f = self.gain_floor
        j = max(self.applied - FULL_GAIN_PERIODS + 2, 1)
        return float(min(j, (2 - f) / f)) if f > 0 else float(j)

    def offset(self, k: int, axes: tuple | None = None) -> PerAxis[float]:
        """The correction [um] at sample ``k`` of the trajectory, kept as what sample
        ``k`` of ``axes`` (default: every axis) was given, for learning its period."""
        i = int(k) % self.n
        out = {a: float(c[i]) for a, c in self.c.items()}
        used = self._used.setdefault(int(k), {})
        for a in (axes or out):
            used[a] = out[a]
        used["gen"] = self._gen
        return out

    def update(self, errors: PerAxis[np.ndarray],
               applied: PerAxis[np.ndarray] | None = None) -> None:
        """Learn one period's errors [um] (desired - measured) made with the correction
        ``applied`` (per axis, n samples; default ``c``, the present correction)."""
        errors = {a: np.asarray(errors[a], float) for a in self.designs}
        for a, e in errors.items():
            if e.shape != (self.n,) or not np.all(np.isfinite(e)):
                raise ConfigError(f"learning: axis {a} needs {self.n} finite errors")
        if self._disturbed_period(errors):
            self._period_gen = None
            return
        g, learned = self.gain, False
        for a, d in self.designs.items():
            e = errors[a]
            u = self.c[a] if applied is None else np.asarray(applied[a], float)
            E, U = np.fft.rfft(e), np.fft.rfft(u)
            if not self._noise(a, E, U):
                continue  # the first period only measures
            learned = True
            self._guard(a, E)
            # what this period asks for, given what was applied during it: the running
            # mean of these is the correction, whatever the threshold let through
            asked = U + d.learn * E
            gk = g * self.bin_gain[a]
            self.acc[a] = d.q * ((1 - gk) * self.acc[a] + gk * asked)
            # what the running mean of the periods can tell from noise: each bin of the
            # accumulated correction carries |L| sigma sqrt(n / periods) of it
            sigma = self.noise_um[a]  # (measured: _noise returned True)
            assert sigma is not None
            thr = self.kappa(a) * sigma * np.abs(d.learn) * np.sqrt(self.n / self.averaged)
            mag = np.abs(self.acc[a])
            keep = mag > thr
            ratio = np.where(keep, thr / np.where(keep, mag, 1.0), 1.0)
            C = self.acc[a] * np.where(keep, 1.0 - ratio ** 2, 0.0)  # the garrote
            self.c[a] = np.clip(np.fft.irfft(C, self.n), -self.limit_um, self.limit_um)
        self.periods += 1
        self.learned += learned
        gen = self._gen if self._period_gen is None else self._period_gen
        self._period_gen = None
        self.applied += learned and gen >= 1
        self._gen += learned

    def _disturbed_period(self, errors: PerAxis[np.ndarray]) -> bool:
        """A period whose error RMS on some axis is more than DISTURBED_FACTOR times the
        last learned period's, plus three noise RMS, was disturbed (a host pause: the
        driver held a late command, the stage stood while the motion went on): it is not
        learned (``disturbed`` counts it), nor shown to the guard, which would slow
        every bin it raised. A change that lasts (DISTURBED_RUN periods in a row) is
        the loop's own and is learned from there."""
        rms = {a: float(np.sqrt(np.mean(np.square(errors[a])))) for a in self.designs}
        last = self._last_rms
        if last and self._run < DISTURBED_RUN and any(
                rms[a] > DISTURBED_FACTOR * last[a] + 3.0 * (self.noise_um[a] or 0.0)
                for a in rms):
            self._run += 1
            self.disturbed += 1
            return True
        self._run, self._last_rms = 0, rms
        return False

    def kappa(self, axis: str) -> float:
        """The threshold in noise RMS of a bin: NOISE_KAPPA, or more where the passed
        band has so many bins that more than about two of pure noise would pass it
        (a bin's noise magnitude is Rayleigh: exp(-kappa^2) of them exceed kappa)."""
        bins = int(np.count_nonzero(self.designs[axis].q))
        return max(NOISE_KAPPA, float(np.sqrt(np.log(max(bins, 1) / 2.0))))

    def _noise(self, a: str, E: np.ndarray, applied: np.ndarray) -> bool:
        """Update the sensor-noise estimate from this period's error spectrum: the change
        from the last period, less what the change of the applied correction explains
        (through the model, 1 / L), is the noise's (twice its variance). False for the
        first period (nothing to compare with)."""
        d = self.designs[a]
        prev, self._e_prev[a] = self._e_prev[a], (E.copy(), applied)
        if prev is None:
            return False
        E0, applied0 = prev
        g_model = np.where(d.learn != 0, 1.0 / np.where(d.learn != 0, d.learn, 1.0), 0.0)
        diff = np.fft.irfft(E - E0 + g_model * (applied - applied0), self.n)
        sigma = 1.4826 * float(np.median(np.abs(diff))) / np.sqrt(2.0)
        old = self.noise_um[a]
        self.noise_um[a] = sigma if old is None else 0.8 * old + 0.2 * sigma
        return True

    def _guard(self, a: str, E: np.ndarray) -> None:
        """A bin whose error has grown well past the smallest it reached (1.5 x, plus
        three noise RMS of a bin) and past the error it had before learning is learning
        the wrong way (its loop is further from the model than the design allowed for):
        its correction goes back to what it was at that smallest error and its gain
        drops to a quarter. Called before the period's update, with the error the
        present correction gave."""
        mag = np.abs(E)
        best, kept, first = self._best[a], self._best_acc[a], self._first[a]
        if best is None or kept is None or first is None:
            self._best[a], self._best_acc[a] = mag.copy(), self.acc[a].copy()
            self._first[a] = mag.copy()
            return
        noise = 3.0 * (self.noise_um[a] or 0.0) * np.sqrt(self.n)
        worse = (mag > 1.5 * best + noise) & (self.designs[a].q > 0)
        # and past the error it had before learning: a bin that rises for a few periods
        # after an unusually good one (a saturated command answers a change of the
        # correction out of proportion) but stays below where it started is still
        # learning, and slowing it there stalled it for good
        worse &= mag > first + noise
        worse[0] = False  # an offset that grows is drift or creep: learned, not damped
        self.acc[a][worse] = kept[worse]
        self.bin_gain[a][worse] *= 0.25
        self.damped += int(worse.sum())
        better = mag < best
        best[better], kept[better] = mag[better], self.acc[a][better]

    def noise_factor(self, axis: str) -> float:
        """How much of white sensor noise's RMS the correction would carry at the
        current gain, in steady state: the share of the band Q passes, times the
        first-order learning recursion's gain / sqrt(gain (2 - gain))."""
        d, g = self.designs[axis], self.gain
        share = float(np.sum((d.q * self.bin_gain[axis]) ** 2 * np.abs(d.learn) ** 2)
                      / d.q.size)
        return float(np.sqrt(share * g / (2 - g)))


class LearnedFeedforward:
    """Learning as the feedforward runs it: a :class:`PeriodicLearner` for the
    trajectory's period, fed with each measured sample's error against what was asked
    for that sample, its correction applied through the reference
    (core.compensation.PreviewedReference.set_learner). Everything is by sample stamp,
    so the feedforward's look-ahead and missed ticks change nothing.

    ``configure`` (period, gain, effects, compensator) builds it anew; ``enabled``
    switches it (off: nothing applied, what was learned is kept); ``reset`` forgets
    (a new trajectory)."""

    def __init__(self, reference: PreviewedReference, dt_ns: int,
                 axes: tuple = ("x", "y")) -> None:
        self.ref, self.dt_ns, self.axes = reference, int(dt_ns), tuple(axes)
        self.learner: PeriodicLearner | None = None
        self.enabled, self.why = False, "off"
        self.asked: dict[int, tuple] = {}  # stamp [ns] -> (trajectory sample, {axis: um})

    def configure(self, period_s: float, gain: float = 1.0, effects: EffectsBlock | None = None,
                  compensator: EffectCompensator | None = None) -> None:
        """A learner for ``period_s`` (0: none) at the reference's rate."""
        self.learner, self.asked = None, {}
        n = int(round(period_s * 1e9 / self.dt_ns))
        if period_s <= 0:
            self.why = "off (no learning_period_s)"
        elif abs(n * self.dt_ns - period_s * 1e9) > 1e-3 * self.dt_ns or n < 4:
            self.why = (f"off: a period of {period_s:g} s is not a whole number (>= 4) of "
                        f"control periods")
        else:
            rate = 1e9 / self.dt_ns
            self.learner = PeriodicLearner({a: design(n, rate, effects, a, compensator, gain)
                                            for a in self.axes})
            self.why = ""
        self.ref.set_learner(self.learner if self.enabled else None)

    def enable(self, on: bool) -> None:
        """Apply the learned correction (and go on learning) or not."""
        self.enabled = bool(on)
        self.ref.set_learner(self.learner if self.enabled else None)

    def reset(self) -> None:
        """Forget what was learned (a new trajectory)."""
        self.asked = {}
        if self.learner is not None:
            self.learner.reset()

    def note(self, target_ns: int, desired: PerAxis[float]) -> None:
        """What was asked for the sample at ``target_ns`` (while a trajectory runs)."""
        if self.learner is None or not self.enabled:
            return
        k = self.ref.sample_index(target_ns)
        if k is not None:
            self.asked[int(target_ns)] = (k, dict(desired))

    def measured(self, stamp_ns: int, w: PerAxis[float]) -> None:
        """The measured position of the sample at ``stamp_ns``: its error is learned."""
        got = self.asked.pop(int(stamp_ns), None)
        self.asked = {t: v for t, v in self.asked.items() if t > stamp_ns}
        if got is None or self.learner is None:
            return
        k, d = got
        self.learner.observe(k, {a: d[a] - w[a] for a in self.axes})

    def describe(self) -> str:
        """One line for the diagnostics."""
        if self.learner is None or not self.enabled:
            return "learning " + (self.why or "off")
        le = self.learner
        noise = ", ".join(f"{a} {v:.3f}" for a, v in le.noise_um.items() if v is not None)
        return (f"learning: {le.learned} periods learned ({le.skipped} skipped, "
                f"{le.disturbed} disturbed, {le.damped} bins slowed), noise {noise or '-'} um; "
                + next(iter(le.designs.values())).describe())
