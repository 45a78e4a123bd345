"""Unmodelled effects: small physical operators shared by the plant and the gap diagnosis.

Each effect acts on one axis's displacement signal [um] sampled at a fixed rate
``fs_hz``. The stateful classes process a signal in consecutive chunks, so a batch run
and a sample-by-sample run give identical results; ``reset`` returns to rest.

* creep     -- after a step the displacement keeps moving towards its final value,
               logarithmically in time (a bank of first-order relaxations, one per
               decade of time constant, each weighted equally).
* dynamics  -- linear mechanical dynamics after the hysteresis: a lightly damped
               resonance (fn_hz, zeta) or a first-order lag (tau_s); unit DC gain.
* delay     -- pure transport delay (sensor and acquisition latency), linear
               interpolation between samples for a fractional delay.
* drift     -- slow thermal trend that ignores the input: a ramp plus a first-order
               settling term.
Coupling (displacement caused by the other axis) is part of the hysteresis model
(:class:`piezo_stage.core.model.duhem.StageModel`) since it has its own hysteresis.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np
from numpy.typing import ArrayLike

from piezo_stage.core.errors import ConfigError
from piezo_stage.core.model._kernels import delay_columns
from piezo_stage.core.types import AxisEffects, Doc, EffectsBlock, Params, PerAxis

EFFECTS = ("creep", "dynamics", "delay", "drift")
AXES_OF_EFFECTS = ("x", "y")  # an effect without ``axes`` acts on both


def _positive(name: str, x: float) -> float:
    x = float(x)
    if not np.isfinite(x) or x <= 0:
        raise ConfigError(f"{name} must be > 0, got {x}")
    return x


def _signal() -> Any:
    """scipy.signal, imported where a filter is first built: the import takes ~0.6 s
    (scipy.stats with it), and the nodes that load a model file without building one
    (the identifier, the gap node) start that much sooner."""
    from scipy import signal
    return signal


def from_rest(op: Callable[[np.ndarray], np.ndarray], X: np.ndarray) -> np.ndarray:
    """A linear, unit-gain operator ``op`` (zero state) on the columns of X as if each
    had rested at its first row before the record: X[0] + op(X - X[0]). A stage's
    record starts in a state, not from zero: a measured displacement near -120 um
    (a sensor's offset) is no step into a delay or a creep at the first sample (from
    zero, a delay of one sample cost 2 um RMS on a measured stack's record, and the
    diagnosis rejected the delay the stage has)."""
    X = np.asarray(X, float)
    x0 = X[:1]
    return x0 + op(np.ascontiguousarray(X - x0))


class _LinearFilter:
    """An IIR filter y = (b/a) x with carried state (scipy lfilter with zi)."""

    def __init__(self, b: ArrayLike, a: ArrayLike) -> None:
        self.b = np.asarray(b, float)
        self.a = np.asarray(a, float)
        self._lfilter, self._lfilter_zi = _signal().lfilter, _signal().lfilter_zi
        self.reset()

    def reset(self, x0: float = 0.0) -> None:
        # start at rest with input and output at x0 (steady state of a unit-DC filter)
        self.zi = self._lfilter_zi(self.b, self.a) * x0

    def process(self, x: ArrayLike) -> np.ndarray:
        y, self.zi = self._lfilter(self.b, self.a, x, zi=self.zi)
        return y


def _lfilter_cols(b: np.ndarray, a: np.ndarray, X: np.ndarray) -> np.ndarray:
    """Columns of X filtered from rest (compiled: scipy's lfilter along axis 0 of a
    row-major array is several times slower)."""
    from piezo_stage.core.model._kernels import iir_columns
    X = np.ascontiguousarray(X, dtype=float)
    if X.ndim == 1:
        return iir_columns(np.asarray(b, float), np.asarray(a, float), X[:, None],
                           np.empty((X.size, 1)))[:, 0]
    a = np.asarray(a, float)
    return iir_columns(np.asarray(b, float) / a[0], a / a[0], X, np.empty_like(X))


class Creep:
    """Logarithmic creep: y = x - gamma * sum_i (x - LP_tau_i(x)) / n_tau.

    After a step of size d the output jumps by d (1 - gamma) and then creeps towards d,
    covering an equal share in each decade of time between min(tau) and max(tau):
    the log(t) signature of piezo creep. gamma is the creep fraction (0.01 .. 0.1).
    """

    def __init__(self, fs_hz: float, gamma: float = 0.03,
                 tau_s: Sequence[float] = (0.05, 0.5, 5.0, 50.0)) -> None:
        self.gamma = float(gamma)
        if not 0 <= self.gamma < 1:
            raise ConfigError(f"creep gamma must be in [0, 1), got {gamma}")
        self.tau_s = tuple(_positive("creep tau_s", t) for t in np.atleast_1d(tau_s))
        dt = 1.0 / fs_hz
        self._lps = []
        for tau in self.tau_s:
            p = np.exp(-dt / tau)
            self._lps.append(_LinearFilter([1 - p], [1, -p]))

    def reset(self, x0: float = 0.0) -> None:
        """At rest with input and output at ``x0``."""
        for lp in self._lps:
            lp.reset(x0)

    def process(self, x: ArrayLike) -> np.ndarray:
        """The next chunk of the signal through the operator (state carried)."""
        x = np.asarray(x, float)
        slow = sum(lp.process(x) for lp in self._lps) / len(self._lps)
        return x - self.gamma * (x - slow)

    def apply(self, X: np.ndarray) -> np.ndarray:
        """The operator on columns of X from rest at their first row (linear: E(X
        theta) = E(X) theta; see ``from_rest``)."""
        return X - self.gamma * self.fast_part(X)

    def fast_part(self, X: np.ndarray) -> np.ndarray:
        """X - mean of the low-passes of X, from rest at the first row: the operator is
        X - gamma * fast_part(X), so a search over gamma filters once."""
        from piezo_stage.core.model._kernels import lowpass_mean_columns
        X = np.ascontiguousarray(X, dtype=float)
        cols = X if X.ndim == 2 else X[:, None]
        cols = np.ascontiguousarray(cols - cols[:1])  # from rest (from_rest)
        poles = np.array([-lp.a[1] for lp in self._lps])
        slow = lowpass_mean_columns(poles, cols, np.empty_like(cols))
        return (cols - slow).reshape(X.shape)


def _sampled_late(num: ArrayLike, den: ArrayLike, dt: float,
                  delta: float) -> tuple[np.ndarray, np.ndarray]:
    """(b, a) of continuous dynamics num/den driven by an input held over each period,
    its output read ``delta`` before the period's end (a transport delay's fraction of
    a period, the whole periods being a plain shift): with the state x_k at the end of
    period k, x_k = Phi(T) x_(k-1) + Gamma(T) u_k and y_k = C Phi(T - delta) x_(k-1) +
    C Gamma(T - delta) u_k (the modified z-transform; delta = 0 is the ZOH form)."""
    from scipy.linalg import expm
    signal = _signal()
    A, B, C, _ = signal.tf2ss(num, den)
    n = A.shape[0]

    def phi_gamma(tau: float) -> tuple[np.ndarray, np.ndarray]:
        M = np.zeros((n + 1, n + 1))
        M[:n, :n], M[:n, n:] = A * tau, B * tau
        E = expm(M)
        return E[:n, :n], E[:n, n:]
    P, G = phi_gamma(dt)
    P2, G2 = phi_gamma(dt - delta)
    b, a = signal.ss2tf(P, G, C @ P2, C @ G2)
    return np.ravel(b), np.ravel(a)


class Dynamics:
    """Linear dynamics with unit DC gain, discretised with a zero-order hold.

    kind='resonance': wn^2 / (s^2 + 2 zeta wn s + wn^2), wn = 2 pi fn_hz.
    kind='lag':       1 / (tau_s s + 1).

    ``delay_frac_s`` > 0: the output is read that long before the end of the hold
    period (a transport delay's fraction of a sample; the gap diagnosis pairs it with
    the delay's whole samples, the exact sampled form of dynamics followed by a delay).
    """

    def __init__(self, fs_hz: float, kind: str = "resonance", fn_hz: float = 800.0,
                 zeta: float = 0.05, tau_s: float = 0.5e-3, delay_frac_s: float = 0.0) -> None:
        self.kind = kind
        dt = 1.0 / fs_hz
        if kind == "resonance":
            self.fn_hz = _positive("dynamics fn_hz", fn_hz)
            self.zeta = _positive("dynamics zeta", zeta)
            if self.fn_hz >= fs_hz / 2:
                raise ConfigError(f"resonance {fn_hz} Hz is above Nyquist of {fs_hz} Hz")
            wn = 2 * np.pi * self.fn_hz
            num, den = [wn ** 2], [1, 2 * self.zeta * wn, wn ** 2]
        elif kind == "lag":
            self.tau_s = _positive("dynamics tau_s", tau_s)
            num, den = [1.0], [self.tau_s, 1.0]
        else:
            raise ConfigError(f"dynamics kind must be 'resonance' or 'lag', got {kind!r}")
        if not 0.0 <= delay_frac_s < dt:
            raise ConfigError(f"dynamics delay_frac_s must be in [0, {dt:g}) s, got "
                              f"{delay_frac_s}")
        if delay_frac_s > 0.0:
            self._f = _LinearFilter(*_sampled_late(num, den, dt, delay_frac_s))
            return
        bd, ad, _ = _signal().cont2discrete((num, den), dt, method="zoh")
        # ZOH discretisation gives y at the *start* of the next hold interval (b[0] = 0);
        # the plant reads its sensor at the *end* of the interval in which the input
        # was applied, so drop that one-sample shift: y_k answers x_k held over [k-1, k]
        bd = np.ravel(bd)
        assert abs(bd[0]) < 1e-12
        self._f = _LinearFilter(bd[1:], ad)

    @property
    def coefficients(self) -> tuple[np.ndarray, np.ndarray]:
        """(b, a) of the sampled filter, y = (b / a) x at the operator's rate."""
        return self._f.b.copy(), self._f.a.copy()

    def reset(self, x0: float = 0.0) -> None:
        """At rest with input and output at ``x0``."""
        self._f.reset(x0)

    def process(self, x: ArrayLike) -> np.ndarray:
        """The next chunk of the signal through the filter (state carried)."""
        return self._f.process(np.asarray(x, float))

    def apply(self, X: np.ndarray) -> np.ndarray:
        """The filter on the columns of X from rest at their first row (for the gap
        diagnosis; see ``from_rest``)."""
        X = np.asarray(X, float)
        return from_rest(lambda Y: _lfilter_cols(self._f.b, self._f.a, Y), X)


class Delay:
    """Pure delay of ``delay_s`` seconds (fractional samples by linear interpolation)."""

    def __init__(self, fs_hz: float, delay_s: float = 0.5e-3) -> None:
        self.delay_s = float(delay_s)
        if not np.isfinite(self.delay_s) or self.delay_s < 0:
            raise ConfigError(f"delay_s must be >= 0, got {delay_s}")
        d = self.delay_s * fs_hz
        self._n = int(np.floor(d))
        self._frac = d - self._n
        self.reset()

    def reset(self, x0: float = 0.0) -> None:
        """The delay line filled with ``x0``."""
        self._buf = np.full(self._n + 1, float(x0))

    def process(self, x: ArrayLike) -> np.ndarray:
        """The next chunk of the signal, delayed (state carried)."""
        ext = np.concatenate([self._buf, np.asarray(x, float)])[:, None]
        # the column formula over the line's state and the new samples: x_k sits at
        # index k + n + 1 of ext, so its output is row k + n + 1
        y = delay_columns(ext, self._n, self._frac, np.empty_like(ext))[self._n + 1:, 0]
        self._buf = ext[-(self._n + 1):, 0].copy()
        return y

    def apply(self, X: np.ndarray) -> np.ndarray:
        """The delay on the columns of X, each column's first row held before the
        start (see ``from_rest``)."""
        X = np.asarray(X, float)
        flat = X.ndim == 1
        X2 = np.ascontiguousarray(X[:, None] if flat else X)
        out = from_rest(lambda Y: delay_columns(Y, self._n, self._frac, np.empty_like(Y)),
                        X2)
        return out[:, 0] if flat else out


class Drift:
    """Thermal drift independent of the input: rate * t + amplitude * (1 - exp(-t/tau))."""

    def __init__(self, fs_hz: float, rate_um_per_s: float = 0.01, amplitude_um: float = 0.5,
                 tau_s: float = 60.0) -> None:
        self.dt = 1.0 / fs_hz
        self.rate = float(rate_um_per_s)
        self.amplitude = float(amplitude_um)
        self.tau_s = _positive("drift tau_s", tau_s)
        self.reset()

    def reset(self, x0: float = 0.0) -> None:
        """Back to t = 0."""
        self._k = 0

    def process(self, x: ArrayLike) -> np.ndarray:
        """The next chunk of the signal plus the drift over its time span."""
        x = np.asarray(x, float)
        t = (self._k + np.arange(x.size)) * self.dt
        self._k += x.size
        return x + self.rate * t + self.amplitude * (1 - np.exp(-t / self.tau_s))

    @staticmethod
    def columns(n: int, fs_hz: float, tau_s: float) -> np.ndarray:
        """The drift's two shapes over n samples: t [s] and 1 - exp(-t / tau)."""
        t = np.arange(n) / fs_hz
        return np.column_stack([t, 1 - np.exp(-t / tau_s)])


_CLASSES = {"creep": Creep, "dynamics": Dynamics, "delay": Delay, "drift": Drift}
_PARAMS = {
    "creep": ("gamma", "tau_s"),
    "dynamics": ("kind", "fn_hz", "zeta", "tau_s", "delay_frac_s"),
    "delay": ("delay_s",),
    "drift": ("rate_um_per_s", "amplitude_um", "tau_s"),
}


# What a model or plant file (or a model message) may say of each effect: every key
# known, every number finite and within what a piezo stage can physically show. A 1e9 s
# delay, a negative damping or a 1e-9 Hz resonance is refused here, once, for every
# consumer (plant, feedforward, gap, the model topic). Ranges: [lo, hi] inclusive.
EFFECT_RANGES = {
    "creep": {"gamma": (0.0, 0.5), "tau_s": (1e-4, 1e5)},
    "dynamics": {"fn_hz": (1.0, 1e6), "zeta": (1e-3, 10.0), "tau_s": (1e-7, 10.0)},
    "delay": {"delay_s": (0.0, 0.1)},
    "drift": {"rate_um_per_s": (-100.0, 100.0), "amplitude_um": (-1000.0, 1000.0),
              "tau_s": (1e-3, 1e7)},
}
MAX_CREEP_TAUS = 8


def _in_range(where: str, x: Any, lo: float, hi: float) -> float:
    if isinstance(x, bool) or not isinstance(x, (int, float, str)):
        raise ConfigError(f"{where}: expected a number, got {x!r}")
    try:
        v = float(x)
    except ValueError:
        raise ConfigError(f"{where}: expected a number, got {x!r}") from None
    if not np.isfinite(v) or not lo <= v <= hi:
        raise ConfigError(f"{where} = {v:g} is outside [{lo:g}, {hi:g}]")
    return v


def validate_effects(effects: EffectsBlock | None, where: str = "effects") -> EffectsBlock:
    """The ``effects`` block of a model or plant file, checked and normalised.

    Each effect a mapping with only its own parameters (``EFFECT_RANGES``, ``kind``
    for dynamics) and the common ``enabled`` (a boolean) and ``axes`` (a list of x/y);
    every number finite and in its range. An effect whose axes differ in their
    parameters is a list of such mappings, each naming its ``axes`` (no axis in two):
    ``creep: [{axes: [x], gamma: 0.03}, {axes: [y], gamma: 0.05}]``. Raises
    ConfigError naming the key.

    Parameters
    ----------
    effects : dict or None
        {name: {param: value, ...} or [{param: value, ...}, ...]} as in a model or
        plant file.
    where : str
        What to call the block in an error.

    Returns
    -------
    dict
        The same block with numbers as floats (creep ``tau_s`` as a list).
    """
    if effects is None:
        return {}
    if not isinstance(effects, dict):
        raise ConfigError(f"{where} must be a mapping")
    out: Doc = {}
    for name, p in effects.items():
        w = f"{where}.{name}"
        if name not in EFFECT_RANGES:
            raise ConfigError(f"{where}: unknown effect {name!r}; known: {', '.join(EFFECTS)}")
        if isinstance(p, list):
            if not p:
                raise ConfigError(f"{w}: an empty list (one mapping per set of axes)")
            items = [_checked_effect(name, x, f"{w}[{i}]") for i, x in enumerate(p)]
            seen: set = set()
            for i, x in enumerate(items):
                if "axes" not in x:
                    raise ConfigError(f"{w}[{i}]: a list's entries each name their axes")
                twice = seen & set(x["axes"])
                if twice:
                    raise ConfigError(f"{w}[{i}]: axis {sorted(twice)[0]} has a parameter "
                                      "set already")
                seen |= set(x["axes"])
            out[name] = items
        else:
            out[name] = _checked_effect(name, p, w)
    return out


def _checked_effect(name: str, p: object, w: str) -> Params:
    """One effect's mapping, checked and normalised (``validate_effects``)."""
    if p is None:
        p = {}
    if not isinstance(p, dict):
        raise ConfigError(f"{w} must be a mapping")
    ranges = EFFECT_RANGES[name]
    known = set(ranges) | {"enabled", "axes"} | ({"kind"} if name == "dynamics" else set())
    unknown = sorted(str(k) for k in p if k not in known)
    if unknown:
        raise ConfigError(f"{w}: unknown parameter(s) {unknown}; known: "
                          f"{', '.join(sorted(known))}")
    q: dict[str, object] = {}
    for k, x in p.items():
        if k == "enabled":
            if not isinstance(x, bool):
                raise ConfigError(f"{w}.enabled must be true or false, got {x!r}")
            q[k] = x
        elif k == "axes":
            if not isinstance(x, (list, tuple)) or not x or \
                    not all(a in ("x", "y") for a in x):
                raise ConfigError(f"{w}.axes must be a list of x and/or y, got {x!r}")
            q[k] = list(x)
        elif k == "kind":
            if x not in ("resonance", "lag"):
                raise ConfigError(f"{w}.kind must be resonance or lag, got {x!r}")
            q[k] = x
        elif name == "creep" and k == "tau_s":
            taus = list(x) if isinstance(x, (list, tuple)) else [x]
            if not 1 <= len(taus) <= MAX_CREEP_TAUS:
                raise ConfigError(f"{w}.tau_s: 1 to {MAX_CREEP_TAUS} time constants")
            q[k] = [_in_range(f"{w}.tau_s", t, *ranges[k]) for t in taus]
        else:
            q[k] = _in_range(f"{w}.{k}", x, *ranges[k])
    return q


def _entries(p: Params | list | None) -> list[dict]:
    """An effect's entries: its mapping, or each of its list's."""
    if p is None:
        return [{}]
    return [dict(x or {}) for x in p] if isinstance(p, list) else [dict(p)]


def sampled_pair(on: AxisEffects, fs_hz: float) -> AxisEffects:
    """An axis's effects ({name: params}) as they act at a rate ``fs_hz`` where it
    has both dynamics and a delay: the delay's whole samples a plain shift, its fraction
    the instant the dynamics' output is read within a sample (``Dynamics``'s
    ``delay_frac_s``): the exact sampled form of dynamics then a delay for an input
    held over each sample, which linear interpolation of the fraction only approximates
    (it biased the resonance and delay a diagnosis found: 824 Hz and 0.62 ms for 800 Hz
    and 0.5 ms). The plant, the gap's fits and the feedforward's inverse all take this
    form. Otherwise ``on`` as it is."""
    if "delay" not in on or "dynamics" not in on:
        return on
    d = float(on["delay"]["delay_s"])
    whole = math.floor(d * fs_hz + 1e-9)
    frac = max(0.0, d - whole / fs_hz)
    frac = frac if frac < 1.0 / fs_hz * (1 - 1e-9) else 0.0
    return {n: ({"delay_s": whole / fs_hz} if n == "delay" else
                {**p, "delay_frac_s": frac} if n == "dynamics" else p) for n, p in on.items()}


def effects_on(effects: EffectsBlock | None, axis: str) -> AxisEffects:
    """The effects that act on ``axis``, each as its parameters alone ({name: params},
    no ``axes`` or ``enabled``): the one reading of a model or plant file's ``effects``
    block per axis (an entry without ``axes`` acts on both; ``enabled: false`` on none)."""
    out: AxisEffects = {}
    for name, p in (effects or {}).items():
        for e in _entries(p):
            if e.pop("enabled", True) and axis in e.pop("axes", AXES_OF_EFFECTS):
                out[name] = e
    return out



def effects_block(per_axis: PerAxis[AxisEffects]) -> EffectsBlock:
    """The ``effects`` block of a model file from each axis's effects ({axis: {name:
    params}}, as ``effects_on`` reads them back): one mapping per effect whose axes share
    its parameters, else one entry per axis."""
    out: Doc = {}
    names = [n for n in EFFECTS if any(n in e for e in per_axis.values())]
    for name in names:
        sets: list[dict] = []
        for a, eff in per_axis.items():
            if name not in eff:
                continue
            p = {k: v for k, v in eff[name].items() if k not in ("axes", "enabled")}
            same = next((s for s in sets if {k: v for k, v in s.items() if k != "axes"}
                         == p), None)
            if same is not None:
                same["axes"].append(a)
            else:
                sets.append({"axes": [a], **p})
        out[name] = sets[0] if len(sets) == 1 else sets
    return out


def make_effect(name: str, fs_hz: float, params: Params) -> Creep | Dynamics | Delay | Drift:
    """Build effect ``name`` from a parameter dict (unknown keys are an error)."""
    if name not in _CLASSES:
        raise ConfigError(f"unknown effect {name!r}; known: {', '.join(EFFECTS)}")
    params = dict(params or {})
    unknown = set(params) - set(_PARAMS[name])
    if unknown:
        raise ConfigError(f"effect {name}: unknown parameter(s) {sorted(unknown)}")
    try:
        return _CLASSES[name](fs_hz, **params)
    except (TypeError, ValueError) as e:
        if isinstance(e, ConfigError):
            raise
        raise ConfigError(f"effect {name}: {e}") from None


def enabled_effects(effects: EffectsBlock, where: str = "effects") -> EffectsBlock:
    """Keep the effects with enabled: true (default true when the key is absent);
    the block checked by the one validation every model and plant file shares
    (core/model/effects.py validate_effects)."""
    out: Doc = {}
    for name, p in validate_effects(effects, where).items():
        if isinstance(p, list):
            kept = [x for x in p if x.pop("enabled", True)]
            if kept:
                out[name] = kept
        elif p.pop("enabled", True):
            out[name] = p
    return out
