"""Play operators: the return-point memory a Duhem law lacks, as a model term
(``PlayOperators``) and as a hysteresis that is not our model class (``PlayHysteresis``:
a Prandtl-Ishlinskii law with a non-polynomial output envelope, for the simulated
stage's ``hysteresis`` option).

``PlayOperators`` is what a model file's ``play_operators`` block holds (the gap
diagnosis's ``structure`` with memory fits it): its output, linear in the weights, is
added to the axis's Duhem output, and the exact inverse (core/model/inverse.py) solves for
both at once.

The Duhem law we identify has polynomial branch shapes and no return-point memory: a
minor loop inside a major one does not close where it started. Real actuators have
both memory and branch shapes that are not cubic (issue 25). This law has them::

    z_j[k] = max(v[k] - r_j, min(v[k] + r_j, z_j[k-1]))      play operator, threshold r_j
    x[k]   = sum_j p_j z_j[k]                                 um (p_j um/V)
    w[k]   = x[k] + a * tanh((x[k] - c) / b)                  um, the envelope

The thresholds are evenly spaced from 0 to ``max_threshold_V``, the weights decay as
``weight_um_per_V * exp(-r_j / decay_V)``; ``a``, ``b``, ``c`` (``envelope``:
``scale_um``, ``width_um``, ``centre_um``) bend every branch alike by a tanh, which no
polynomial of low degree follows. Play operators wipe out their history above each
new extremum, so a minor loop closes where it began (return-point memory). The
envelope is monotone when ``scale_um > -width_um``.

The law knows its own truth: ``split`` of a record's residual is not needed here, the
plant's ``last_true`` is the true displacement as for every effect.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike

from piezo_stage.core.errors import ConfigError, ModelError
from piezo_stage.core.model._kernels import play_run, play_run_rate
from piezo_stage.core.types import Params

RATE_FILTER_S = 2e-3  # s: the rate a rate-dependent law sees is |dv/dt| low-passed
# s: a model's rate widening stays below the filter's time constant, so that the
# operators' sum never falls while the voltage rises (the exact inverse's one root)
MAX_RATE_WIDENING_S = 0.95 * RATE_FILTER_S
MAX_OPERATORS = 200  # a model or plant with more is not one we fit (16 by default)


@dataclass(frozen=True)
class PlayOperators:
    """Play operators' sum_j p_j z_j: thresholds ``thresholds_V`` (r_j >= 0 [V]),
    weights ``weights_um_per_V`` (p_j, any sign: fitted by least squares) and the
    state they start from, ``initial_V`` (z_j [V]). Rate independent, like the Duhem
    law, unless ``rate_widening_s`` (beta [s], below ``RATE_FILTER_S``) widens every
    threshold by beta x |dv/dt| low-passed (the loop widening with the input's rate:
    the gap diagnosis's ``rate``); a state is an array of z_j, updated in place by
    ``run``, and a rate-dependent law's also ``rate_state`` (the voltage before and
    the low-passed rate).

    With ``bands_V`` (one [low, high] pair [V] per operator) each operator's output is
    its state clipped to its band: sum_j p_j clip(z_j, low_j, high_j). A relay of the
    Preisach law with half-width r and centre c is up exactly when the play of
    threshold r is above c, so a band's output is the relays of half-width r_j and
    centres in [low_j, high_j] integrated: a discretized Preisach law whose density
    varies with the relay's centre as well as its width (``fit_preisach_class``). It
    keeps the play operators' wiping-out and congruency, and with non-negative weights
    it rises with the voltage on every branch. ``table`` is the compiled kernels' view
    (3, n): thresholds, band lows, band highs (+-inf without bands)."""

    thresholds_V: np.ndarray
    weights_um_per_V: np.ndarray
    initial_V: np.ndarray
    rate_widening_s: float = 0.0
    bands_V: np.ndarray | None = None
    table: np.ndarray = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        arrays = []
        for name in ("thresholds_V", "weights_um_per_V", "initial_V"):
            a = np.atleast_1d(np.array(getattr(self, name), dtype=float))
            if a.ndim != 1 or not np.all(np.isfinite(a)):
                raise ModelError(f"play operators: {name} must be a list of finite numbers")
            arrays.append(a)
        r, p, z = arrays
        if not 1 <= r.size <= MAX_OPERATORS or p.size != r.size or z.size != r.size:
            raise ModelError(f"play operators: thresholds_V, weights_um_per_V and "
                             f"initial_V need the same length, 1 to {MAX_OPERATORS} "
                             f"(got {r.size}, {p.size}, {z.size})")
        if np.any(r < 0):
            raise ModelError("play operators: thresholds_V must be >= 0")
        beta = self.rate_widening_s
        if isinstance(beta, bool) or not isinstance(beta, (int, float)) or \
                not 0.0 <= float(beta) < MAX_RATE_WIDENING_S:
            raise ModelError(f"play operators: rate_widening_s = {beta!r}: a number of "
                             f"seconds in [0, {MAX_RATE_WIDENING_S:g}) (at or past the "
                             f"rate filter's {RATE_FILTER_S:g} s the operators' sum "
                             "would fall while the voltage rises)")
        for name, a in zip(("thresholds_V", "weights_um_per_V", "initial_V"), arrays):
            object.__setattr__(self, name, a)
        object.__setattr__(self, "rate_widening_s", float(beta))
        if self.bands_V is not None:
            b = np.array(self.bands_V, dtype=float)
            if b.shape != (r.size, 2) or not np.all(np.isfinite(b)) or \
                    np.any(b[:, 0] >= b[:, 1]):
                raise ModelError("play operators: bands_V must hold one [low, high] pair "
                                 "of finite numbers, low < high, per operator")
            object.__setattr__(self, "bands_V", b)
        table = np.empty((3, r.size))
        table[0] = r
        table[1], table[2] = (-np.inf, np.inf) if self.bands_V is None else \
            (self.bands_V[:, 0], self.bands_V[:, 1])
        object.__setattr__(self, "table", table)

    @property
    def banded(self) -> bool:
        """Whether each operator's output is its state clipped to a band of its own (a
        discretized Preisach law: ``fit_preisach_class``)."""
        return self.bands_V is not None

    @classmethod
    def at_rest(cls, thresholds_V: ArrayLike, weights_um_per_V: ArrayLike, v0: float = 0.0,
                start: float = 0.0, rate_widening_s: float = 0.0,
                bands_V: ArrayLike | None = None) -> PlayOperators:
        """Operators whose state is z_j = v0 + start * r_j: at rest at ``v0`` (0), as
        a fall (+1) or a rise (-1) to v0 leaves them."""
        r = np.asarray(thresholds_V, dtype=float)
        return cls(r, np.asarray(weights_um_per_V, dtype=float), float(v0) + float(start) * r,
                   rate_widening_s, None if bands_V is None else np.asarray(bands_V, float))

    def moved(self, initial_V: ArrayLike) -> PlayOperators:
        """The same operators from the state ``initial_V`` [V]."""
        return PlayOperators(self.thresholds_V, self.weights_um_per_V,
                             np.asarray(initial_V, float), self.rate_widening_s,
                             self.bands_V)

    @property
    def rate_dependent(self) -> bool:
        """Whether the thresholds widen with the input's rate."""
        return self.rate_widening_s > 0.0

    def state(self) -> np.ndarray:
        """A fresh copy of the initial state (for ``run``)."""
        return self.initial_V.copy()

    def widening(self, dt_s: float, rate_state: np.ndarray | None = None) -> np.ndarray:
        """The compiled inverse's view of the rate widening, [decay, gain, widening
        before [V]] (core/model/_kernels.py's ``rate_widen``), for samples ``dt_s`` [s] apart
        from ``rate_state`` ([voltage before, low-passed rate]; None: at rest); zeros
        for a rate-independent law."""
        if not self.rate_dependent:
            return np.zeros(3)
        dt = _check_dt(dt_s)
        s = rate_smoothing(dt)
        rate = 0.0 if rate_state is None else float(rate_state[1])
        return np.array([1.0 - s, self.rate_widening_s * s / dt,
                         self.rate_widening_s * rate])

    def output(self, z: np.ndarray) -> float:
        """The operators' sum [um] in state ``z`` (z already at the present voltage)."""
        return float(self.weights_um_per_V @ np.clip(z, self.table[1], self.table[2]))

    def run(self, v: np.ndarray, z: np.ndarray, dt_s: float = 0.0,
            rate_state: np.ndarray | None = None) -> np.ndarray:
        """The operators' sum [um] over ``v`` [V] from state ``z`` (updated in place).
        A rate-dependent law needs the samples' spacing ``dt_s`` [s] (ModelError
        without it) and its ``rate_state`` ([voltage before, low-passed rate], updated
        in place; None: from rest at ``v[0]``)."""
        v = np.ascontiguousarray(v, dtype=float)
        out = np.empty(v.size)
        if self.rate_dependent and v.size:
            dt = _check_dt(dt_s)
            st = rate_state if rate_state is not None else np.array([v[0], 0.0])
            play_run_rate(v, st, dt, self.rate_widening_s,
                          rate_smoothing(dt), self.table,
                          self.weights_um_per_V, z, out)
        else:
            play_run(v, self.table, self.weights_um_per_V, z, out)
        return out

    def columns(self, v: ArrayLike) -> np.ndarray:
        """(N, n): each operator's output at unit weight over ``v`` [V], at rest at
        ``v[0]``, clipped to its band (the rate widening left out): the operators as
        regressors, their sum at these weights ``columns(v) @ weights_um_per_V``."""
        r, inv = np.unique(self.thresholds_V, return_inverse=True)
        z = play_columns(np.ascontiguousarray(v, dtype=float), r)[:, inv]
        return np.clip(z, self.table[1], self.table[2])

    def __eq__(self, other: object) -> bool:
        return isinstance(other, PlayOperators) and all(
            np.array_equal(getattr(self, k), getattr(other, k))
            for k in ("table", "weights_um_per_V", "initial_V")) and \
            self.rate_widening_s == other.rate_widening_s

    __hash__ = None  # type: ignore[assignment]  # arrays inside: equal, not hashable


def unbanded(thresholds_V: ArrayLike) -> np.ndarray:
    """The compiled kernels' operator table (3, n) of plain play operators: thresholds
    ``thresholds_V`` [V], bands unbounded."""
    r = np.asarray(thresholds_V, dtype=float)
    return np.vstack([r, np.full(r.size, -np.inf), np.full(r.size, np.inf)])


def rate_smoothing(dt_s: float) -> float:
    """The rate filter's coefficient per sample ``dt_s`` [s] apart (first order, time
    constant ``RATE_FILTER_S``)."""
    return float(1.0 - np.exp(-float(dt_s) / RATE_FILTER_S))


def _check_dt(dt_s: float) -> float:
    dt = float(dt_s)
    if not (np.isfinite(dt) and dt > 0.0):
        raise ModelError("play operators whose thresholds widen with the rate need the "
                         "samples' spacing (a sample rate)")
    return dt


def play_columns(v: np.ndarray, thresholds_V: np.ndarray, start: float = 0.0,
                 beta: float = 0.0, fs: float = 0.0) -> np.ndarray:
    """One column per play operator (threshold r [V]): the memory a Duhem law lacks, as
    regressors (core/model/play.py's law, unit weights). Each starts at v[0] + start * r: at
    rest (0), or as left by a fall (+1) or a rise (-1) to v[0] before the record.
    ``beta`` > 0 [s] widens the thresholds by beta x |dv/dt| (low-passed; the samples
    ``fs`` [Hz] apart), as the model file's ``rate_widening_s``."""
    v = np.ascontiguousarray(v, dtype=float)
    out = np.empty((v.size, len(thresholds_V)))
    dt = 1.0 / fs if beta > 0.0 else 0.0
    for j, r in enumerate(thresholds_V):
        op = PlayOperators.at_rest([float(r)], [1.0], float(v[0]), start, beta)
        out[:, j] = op.run(v, op.state(), dt)
    return out


KEYS = ("kind", "axes", "operators", "max_threshold_V", "weight_um_per_V", "decay_V",
        "envelope", "rate_widening_s")


@dataclass
class PlayHysteresis:
    """The law with its parameters (see the module docstring); ``z`` is its state."""

    thresholds_V: np.ndarray
    weights_um_per_V: np.ndarray
    scale_um: float
    width_um: float
    centre_um: float
    rate_widening_s: float = 0.0  # thresholds r_j + this x |dv/dt|: a rate-dependent law
    table: np.ndarray = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        self.table = unbanded(self.thresholds_V)  # the compiled kernels' view

    @classmethod
    def from_params(cls, params: Params, where: str = "hysteresis") -> PlayHysteresis:
        """From a plant file's ``hysteresis`` block; ConfigError naming the key."""
        unknown = set(params) - set(KEYS)
        if unknown:
            raise ConfigError(f"{where}: unknown key(s) {sorted(unknown)}")
        if params.get("kind", "prandtl-ishlinskii") != "prandtl-ishlinskii":
            raise ConfigError(f"{where}.kind: only 'prandtl-ishlinskii' is known")

        def num(d: Params, key: str, default: float, lo: float, hi: float,
                w: str = where) -> float:
            x = d.get(key, default)
            if isinstance(x, bool) or not isinstance(x, (int, float)) or \
                    not lo <= float(x) <= hi:
                raise ConfigError(f"{w}.{key} = {x!r}: a number in [{lo:g}, {hi:g}]")
            return float(x)
        n = int(num(params, "operators", 16, 1, 200))
        top = num(params, "max_threshold_V", 120.0, 0.0, 1e4)
        w0 = num(params, "weight_um_per_V", 0.4, 0.0, 1e3)
        decay = num(params, "decay_V", 40.0, 1e-3, 1e6)
        env = params.get("envelope") or {}
        if not isinstance(env, dict) or set(env) - {"scale_um", "width_um", "centre_um"}:
            raise ConfigError(f"{where}.envelope: a mapping of scale_um, width_um, "
                              "centre_um")
        a = num(env, "scale_um", 0.0, -1e3, 1e3, f"{where}.envelope")
        b = num(env, "width_um", 10.0, 1e-6, 1e4, f"{where}.envelope")
        c = num(env, "centre_um", 0.0, -1e4, 1e4, f"{where}.envelope")
        if a <= -b:
            raise ConfigError(f"{where}.envelope: scale_um must be > -width_um (a "
                              "monotone envelope)")
        beta = num(params, "rate_widening_s", 0.0, 0.0, 1.0)
        r = np.linspace(0.0, top, n)
        return cls(r, w0 * np.exp(-r / decay), a, b, c, beta)

    @staticmethod
    def rate_state(v0: float = 0.0) -> np.ndarray:
        """A rate-dependent law's state at rest at ``v0`` [V]: [voltage, rate]."""
        return np.array([float(v0), 0.0])

    def rest(self, v0: float = 0.0) -> np.ndarray:
        """The operators' state at rest at ``v0`` [V]."""
        return np.full(self.thresholds_V.size, float(v0))

    def run(self, v: np.ndarray, z: np.ndarray, dt_s: float = 0.0,
            rate_state: np.ndarray | None = None) -> np.ndarray:
        """Displacement [um] over ``v`` [V] from state ``z`` (updated in place). A
        rate-dependent law also needs the samples' spacing ``dt_s`` [s] and its rate
        state (``rate_state()``, updated in place; None: from rest at ``v[0]``)."""
        x = np.empty(v.size)
        v = np.ascontiguousarray(v, dtype=float)
        table = self.table
        if self.rate_widening_s > 0.0 and dt_s > 0.0 and v.size:
            st = self.rate_state(v[0]) if rate_state is None else rate_state
            smooth = rate_smoothing(dt_s)
            play_run_rate(v, st, float(dt_s), self.rate_widening_s, float(smooth),
                          table, self.weights_um_per_V, z, x)
        else:
            play_run(v, table, self.weights_um_per_V, z, x)
        return self.envelope(x)

    def envelope(self, x: np.ndarray) -> np.ndarray:
        """The static output bend [um] of the operators' sum ``x`` [um]."""
        return x + self.scale_um * np.tanh((x - self.centre_um) / self.width_um)
