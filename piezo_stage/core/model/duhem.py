"""Duhem hysteresis: forward model, whole-curve and segmented, batch and per sample.

Continuous law (the paper's eq. 1), input voltage v [V], output displacement w [um]::

    dw/dt = alpha |dv/dt| (f(v) - w) + dv/dt g(v)

Implicit Euler on the voltage increment dv_k = v_k - v_{k-1} (the paper's eq. 6) gives::

    w_k (1 + alpha |dv_k|) = w_{k-1} + |dv_k| F(v_k) + dv_k G(v_k)

where, following the paper's eq. 6 literally, the polynomials F = sum f_i v**i and
G = sum g_j v**j already carry the factor alpha of eq. 1 (F = alpha f_eq1); f_i and
g_j are in um/V per V**i. On an ascending step (dv >= 0) only H_asc = F + G enters,
on a descending step only H_desc = G - F::

    w_k = (w_{k-1} + dv_k H_b(v_k)) / (1 + alpha_b |dv_k|)

so within one branch f_i and g_i of the same power are not separately identifiable.
The *segmented* model (the paper's eqs. 2-3) has its own (alpha, f, g) per branch; the
*whole-curve* model shares one set. The state (v_{k-1}, w_{k-1}) is carried across
reversals, so the output is continuous whatever the branch. The recursion only sees
the sequence of voltages, never time: the law is rate independent.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import ArrayLike

from piezo_stage.core._jit import PREFIX, as_f64
from piezo_stage.core.errors import DataError, ModelError
from piezo_stage.core.model._kernels import duhem_run, duhem_step
from piezo_stage.core.model.play import PlayOperators
from piezo_stage.core.types import Doc, Params, PerAxis


def _coeffs(x: ArrayLike, name: str) -> np.ndarray:
    a = np.atleast_1d(np.asarray(x, dtype=float))
    if a.ndim != 1 or a.size == 0:
        raise ModelError(f"{name} must be a non-empty list of numbers")
    if not np.all(np.isfinite(a)):
        raise ModelError(f"{name} has a non-finite coefficient")
    return a


@dataclass(frozen=True)
class DuhemBranch:
    """One parameter set (alpha, f, g) in the paper's eq. 6 convention.

    Parameters
    ----------
    alpha : float
        Weight coefficient [1/V], > 0.
    f, g : array_like
        Polynomial coefficients, lowest power first [um/V per V**i].
    reduced : bool
        True when only the identifiable combination is known (then f = 0, g = h with
        h = f + g on an ascending branch, h = g - f on a descending one).
    """

    alpha: float
    f: np.ndarray
    g: np.ndarray
    reduced: bool = False

    def __post_init__(self) -> None:
        if not np.isfinite(self.alpha) or self.alpha <= 0:
            raise ModelError(f"alpha must be finite and > 0, got {self.alpha}")
        object.__setattr__(self, "alpha", float(self.alpha))
        object.__setattr__(self, "f", _coeffs(self.f, "f"))
        object.__setattr__(self, "g", _coeffs(self.g, "g"))

    @classmethod
    def from_h(cls, alpha: float, h: ArrayLike) -> DuhemBranch:
        """A branch known only by its identifiable polynomial h (f = 0, g = h)."""
        return cls(alpha, np.zeros(1), _coeffs(h, "h"), reduced=True)

    def h(self, ascending: bool) -> np.ndarray:
        """The polynomial this branch applies: f + g ascending, g - f descending."""
        d = max(self.f.size, self.g.size)
        f = np.pad(self.f, (0, d - self.f.size))
        g = np.pad(self.g, (0, d - self.g.size))
        return g + f if ascending else g - f

    def __eq__(self, other: object) -> bool:
        return (isinstance(other, DuhemBranch) and self.alpha == other.alpha
                and np.array_equal(self.f, other.f) and np.array_equal(self.g, other.g))

    __hash__ = None  # type: ignore[assignment]  # equal by value, mutable arrays: unhashable


@dataclass(frozen=True)
class DuhemState:
    """Explicit state of the recursion: the previous voltage [V] and output [um]."""

    v: float = 0.0
    w: float = 0.0


@dataclass(frozen=True)
class DuhemModel:
    """A Duhem hysteresis, whole-curve (ascending is descending) or segmented.

    Parameters
    ----------
    ascending, descending : DuhemBranch
        Parameter sets used on rising (dv >= 0) and falling voltage steps.
    initial : DuhemState
        State the model starts from and returns to on reset.
    fit_range_V : tuple of float or None
        The input range [V] the branches were fitted on: well outside it (past
        POLY_MARGIN of its span) every branch polynomial continues straight from the
        nearer end with that end's slope (``branch_values``), not along its own tail.
        None: the polynomial everywhere.
    continuation : {'straight', 'level'}
        How a branch goes on past ``polynomial_range(fit_range_V)``: straight, with
        the end's slope, or level, at the end's value (bounded: a law fitted on a few
        volts of an amplifier's hundred, whose straight continuation would leave every
        physical bound within the amplifier's range; ``bounded_past_fit``).
    """

    ascending: DuhemBranch
    descending: DuhemBranch
    initial: DuhemState = field(default_factory=DuhemState)
    fit_range_V: tuple | None = None
    continuation: str = "straight"

    def __post_init__(self) -> None:
        if self.continuation not in CONTINUATIONS:
            raise ModelError(f"continuation {self.continuation!r}: one of "
                             f"{', '.join(CONTINUATIONS)}")
        r = self.fit_range_V
        if r is not None:
            lo, hi = (float(x) for x in r)
            if not (np.isfinite(lo) and np.isfinite(hi) and lo < hi):
                raise ModelError(f"fit_range_V {list(r)} must be finite with lo < hi")
            object.__setattr__(self, "fit_range_V", (lo, hi))

    @classmethod
    def whole(cls, alpha: float, f: ArrayLike, g: ArrayLike,
              initial: DuhemState | None = None) -> DuhemModel:
        """A whole-curve model: one (alpha, f, g) for both branches."""
        b = DuhemBranch(alpha, _coeffs(f, "f"), _coeffs(g, "g"))
        return cls(b, b, initial or DuhemState())

    @property
    def structure(self) -> str:
        """'whole' or 'segmented'."""
        return "whole" if self.ascending == self.descending else "segmented"

    def kernel_params(self) -> tuple[np.ndarray, np.ndarray]:
        """(alpha[2], H[2, PREFIX + D]) as the compiled loops take them (computed
        once): each row a branch row (``branch_row``: the compiled ``horner``'s
        layout)."""
        cached = self.__dict__.get("_kp")
        if cached is not None:
            return cached
        ha = self.ascending.h(True)
        hd = self.descending.h(False)
        d = max(ha.size, hd.size)
        H = np.zeros((2, PREFIX + d))
        level = self.continuation == "level"
        H[0, :PREFIX + ha.size] = branch_row(ha, self.fit_range_V, level)
        H[1, :PREFIX + hd.size] = branch_row(hd, self.fit_range_V, level)
        alpha = np.array([self.ascending.alpha, self.descending.alpha])
        object.__setattr__(self, "_kp", (alpha, H))  # frozen: cache through the back door
        return alpha, H

    def simulate(self, v: ArrayLike,
                 state: DuhemState | None = None) -> tuple[np.ndarray, DuhemState]:
        """Batch response to the voltage sequence ``v`` [V].

        Returns
        -------
        w : ndarray, shape (N,)
            Displacement [um] after each sample.
        final : DuhemState
            State after the last sample (feed it back in to continue).
        """
        st = state or self.initial
        v = as_f64(v)
        out = np.empty_like(v)
        alpha, H = self.kernel_params()
        vp, wp = duhem_run(v, float(st.v), float(st.w), alpha, H, out)
        return out, DuhemState(float(vp), float(wp))

    def with_initial(self, state: DuhemState) -> "DuhemModel":
        """The same model starting from another state."""
        return DuhemModel(self.ascending, self.descending, state, self.fit_range_V,
                          self.continuation)

    def with_fit_range(self, lo: float, hi: float) -> "DuhemModel":
        """The same model, fitted on inputs within [lo, hi] V (see ``fit_range_V``)."""
        return DuhemModel(self.ascending, self.descending, self.initial, (lo, hi),
                          self.continuation)

    def with_continuation(self, kind: str) -> "DuhemModel":
        """The same model, its branches going on past their fitted range ``kind``
        ('straight' or 'level')."""
        return DuhemModel(self.ascending, self.descending, self.initial, self.fit_range_V,
                          kind)

    def branch_values(self, ascending_branch: bool, ascending: bool,
                      v: ArrayLike) -> np.ndarray:
        """One branch's polynomial h at ``v`` [V] as the compiled loops evaluate it
        (``branch_values``, with this model's fitted range and continuation)."""
        br = self.ascending if ascending_branch else self.descending
        return branch_values(br.h(ascending), v, self.fit_range_V,
                             self.continuation == "level")


# how a branch goes on past its fitted range (DuhemModel.continuation)
CONTINUATIONS = ("straight", "level")


# Near the data a fitted branch polynomial is still held by it: within this share of the
# fitted span beyond either end the polynomial is kept (our simulated stages' branches
# are polynomials, and a held-out record reaching 148 V against a fit to 133 V was
# predicted to the noise by its tail); past that, the straight continuation.
POLY_MARGIN = 0.15


def polynomial_range(fit_range_V: tuple | None) -> tuple[float, float]:
    """The voltages [V] over which a branch fitted on ``fit_range_V`` is its polynomial
    (the range widened by POLY_MARGIN of its span; everywhere without one)."""
    if fit_range_V is None:
        return -np.inf, np.inf
    lo, hi = fit_range_V
    m = POLY_MARGIN * (hi - lo)
    return lo - m, hi + m


def branch_row(h: ArrayLike, fit_range_V: tuple | None = None,
               level: bool = False) -> np.ndarray:
    """A branch polynomial ``h`` as the compiled ``horner`` takes it: [lo, hi, h(lo),
    slope below lo, h(hi), slope above hi] (``polynomial_range``; each end's slope the
    polynomial's there, never negative; 0 with ``level``), then the coefficients.

    Parameters
    ----------
    h : array_like
        Coefficients [um/V per V**i], lowest power first.
    fit_range_V : tuple of float or None
        The fitted input range; None: the polynomial everywhere.

    Returns
    -------
    ndarray
        The row, PREFIX + len(h) numbers.
    """
    P = np.polynomial.polynomial
    h = np.asarray(h, float)
    lo, hi = polynomial_range(fit_range_V)
    pre = [lo, hi, 0.0, 0.0, 0.0, 0.0]
    if fit_range_V is not None:
        d = P.polyder(h) if h.size > 1 else np.zeros(1)
        keep = 0.0 if level else 1.0
        pre[2:] = [P.polyval(lo, h), keep * max(float(P.polyval(lo, d)), 0.0),
                   P.polyval(hi, h), keep * max(float(P.polyval(hi, d)), 0.0)]
    return np.concatenate([pre, h])


def branch_values(h: ArrayLike, v: ArrayLike,
                  fit_range_V: tuple | None = None, level: bool = False) -> np.ndarray:
    """A branch polynomial ``h`` (lowest power first) at the voltages ``v`` [V] as the
    compiled loops evaluate it: over ``polynomial_range(fit_range_V)`` the polynomial,
    outside it the straight continuation from the nearer end with that end's slope
    (never negative), or with ``level`` the end's value.

    Parameters
    ----------
    h : array_like
        Coefficients [um/V per V**i].
    v : array_like
        Voltages [V].
    fit_range_V : tuple of float or None
        The fitted input range; None: the polynomial everywhere.

    Returns
    -------
    ndarray
        The values h(v) [um/V], the shape of ``v``.
    """
    P = np.polynomial.polynomial
    h = np.asarray(h, float)
    v = np.asarray(v, float)
    with np.errstate(all="ignore"):
        if fit_range_V is None:
            return P.polyval(v, h)
        lo, hi = polynomial_range(fit_range_V)
        d = P.polyder(h) if h.size > 1 else np.zeros(1)
        out = P.polyval(np.clip(v, lo, hi), h)
        keep = 0.0 if level else 1.0
        for end, side in ((hi, v > hi), (lo, v < lo)):
            out = np.where(side, P.polyval(end, h) + keep * max(float(P.polyval(end, d)),
                                                                 0.0) * (v - end), out)
    return out


class DuhemHysteresis:
    """Stateful per-sample Duhem operator (explicit state, ``reset``, ``step``).

    One step is the compiled ``duhem_step`` (the same formula as every batch path),
    called per sample; ``run`` hands a whole array to the compiled loop and keeps the
    state.
    """

    def __init__(self, model: DuhemModel) -> None:
        self.model = model
        self._alpha, self._H = model.kernel_params()
        self.reset()

    def reset(self, state: DuhemState | None = None) -> None:
        """Back to ``state`` (default: the model's initial state)."""
        st = state or self.model.initial
        self.v, self.w = float(st.v), float(st.w)

    @property
    def state(self) -> DuhemState:
        """The current (v, w)."""
        return DuhemState(self.v, self.w)

    def step(self, v: float) -> float:
        """Apply voltage ``v`` [V]; returns the displacement [um]."""
        self.w = duhem_step(self.v, self.w, float(v), self._alpha, self._H)
        self.v = float(v)
        return self.w

    def run(self, v: ArrayLike) -> np.ndarray:
        """Apply a voltage array (the compiled loop); returns the displacements."""
        w, st = self.model.simulate(v, self.state)
        self.v, self.w = st.v, st.w
        return w


AXES = ("x", "y")
OTHER = {"x": "y", "y": "x"}


@dataclass(frozen=True)
class AxisParts:
    """One axis of a stage model as fitted or read: its Duhem ``law``, the coupling
    term from the other axis's voltage into it (None: none) and play operators beside
    the law (None: none). Each kind of fit says its parts (``AxisResult.parts``,
    ``ClassFit.parts``, the gap's candidates); ``StageModel.from_fits`` builds the model."""

    law: "DuhemModel"
    coupling: "DuhemModel | None" = None
    plays: PlayOperators | None = None


@dataclass(frozen=True)
class StageModel:
    """Hysteresis of a 2-axis stage: one Duhem model per axis, optional coupling and
    play operators.

    ``coupling['x']`` is the displacement on x caused by the y voltage (the paper's H_xy),
    itself a Duhem model driven by v_y; ``plays['x']`` (core/model/play.py's PlayOperators,
    optional) adds return-point memory driven by v_x; the axis output is the sum
    w_x = H_xx(v_x) + P_x(v_x) + H_xy(v_y). Axes absent from ``axes`` are not modelled.
    """

    axes: PerAxis[Any]
    coupling: Params = field(default_factory=dict)
    voltage_limits: tuple = (0.0, 150.0)
    plays: Doc = field(default_factory=dict)

    def __post_init__(self) -> None:
        for a in list(self.axes) + list(self.coupling) + list(self.plays):
            if a not in AXES:
                raise ModelError(f"unknown axis {a!r} (axes are x and y)")
        for a, p in self.plays.items():
            if a not in self.axes or not isinstance(p, PlayOperators):
                raise ModelError(f"axis {a}: play operators need the axis's Duhem model "
                                 "and a PlayOperators")
        lo, hi = self.voltage_limits
        if not (np.isfinite(lo) and np.isfinite(hi) and lo < hi):
            raise ModelError(f"voltage limits must be finite with min < max, got {lo}, {hi}")

    def simulate(self, vx: ArrayLike, vy: ArrayLike, states: PerAxis[Any] | None = None,
                 dt_s: float = 0.0) -> tuple[dict[str, np.ndarray], Doc]:
        """Noise-free response [um] of each modelled axis to voltages [V].

        ``states`` maps 'x', 'y', 'cx', 'cy' to DuhemState, 'px', 'py' to the play
        operators' state (an array) and 'qx', 'qy' to a rate-dependent law's rate
        state; ``dt_s`` is the samples' spacing [s] (rate-dependent play operators need
        it). Returns (w dict, states).
        """
        v = {"x": vx, "y": vy}
        states = {k: s.copy() if isinstance(s, np.ndarray) else s
                  for k, s in (states or {}).items()}
        out = {}
        for a in self.axes:
            w, states[a] = self.axis_simulate(a, v[a], states, dt_s)
            c = self.coupling.get(a)
            if c is not None:
                wc, states["c" + a] = c.simulate(v[OTHER[a]], states.get("c" + a))
                w = w + wc
            out[a] = w
        return out, states

    def axis_simulate(self, axis: str, v: ArrayLike, states: PerAxis[Any] | None = None,
                      dt_s: float = 0.0) -> tuple[np.ndarray, DuhemState]:
        """One axis's own response [um] (its Duhem model and play operators, no
        coupling) to ``v`` [V]; ``states`` and ``dt_s`` as for ``simulate`` (the play
        state, when given there, is advanced in place). Returns (w, the Duhem model's
        final state)."""
        states = states if states is not None else {}
        w, final = self.axes[axis].simulate(v, states.get(axis))
        p = self.plays.get(axis)
        if p is not None:
            z = states.setdefault("p" + axis, p.state())
            q = None
            if p.rate_dependent:
                v0 = states[axis].v if states.get(axis) is not None else \
                    self.axes[axis].initial.v
                q = states.setdefault("q" + axis, np.array([float(v0), 0.0]))
            w = w + p.run(as_f64(v), z, dt_s, q)
        return w, final

    @property
    def rate_dependent(self) -> bool:
        """Whether any axis's play operators widen with the input's rate (simulating
        and inverting it then need the samples' spacing)."""
        return any(p.rate_dependent for p in self.plays.values())

    @classmethod
    def from_fits(cls, parts: "dict[str, AxisParts]", voltage_limits: tuple) -> "StageModel":
        """The stage model of each axis's fitted (or read) ``parts`` within
        ``voltage_limits`` [V]: the one place a model is put together (identify, refit,
        the identifier node, the gap's model, a model file)."""
        return cls({a: p.law for a, p in parts.items()},
                   {a: p.coupling for a, p in parts.items() if p.coupling is not None},
                   tuple(voltage_limits),
                   {a: p.plays for a, p in parts.items() if p.plays is not None})

    def replace(self, **changes: object) -> "StageModel":
        """The same model with some fields changed (axes, coupling, voltage_limits,
        plays)."""
        fields: dict[str, Any] = {"axes": self.axes, "coupling": self.coupling,
                                  "voltage_limits": self.voltage_limits, "plays": self.plays}
        fields.update(changes)
        return StageModel(**fields)


DEFAULT_LIMITS_V = (0.0, 150.0)  # the usual piezo amplifier's output


def voltage_limits_for(voltages: Iterable[ArrayLike],
                       amplifier_V: tuple | None = None) -> tuple[float, float]:
    """A model's voltage limits: they belong to the amplifier, not to the record it was
    identified on. ``amplifier_V`` when given (the stage's configuration, ``--limits``),
    and then every voltage must lie within it (DataError otherwise); else 0-150 V
    widened to take the voltages (a bipolar stack's negative side, a higher supply).

    Parameters
    ----------
    voltages : iterable of array_like
        The record's voltages [V], per axis.
    amplifier_V : tuple of float or None
        (lo, hi) the amplifier can drive [V].

    Returns
    -------
    tuple of float
        (lo, hi) [V].
    """
    vs = [np.asarray(v, float) for v in voltages]
    vmin = min((float(v.min()) for v in vs if v.size), default=0.0)
    vmax = max((float(v.max()) for v in vs if v.size), default=0.0)
    if amplifier_V is not None:
        lo, hi = (float(x) for x in amplifier_V)
        if not (np.isfinite(lo) and np.isfinite(hi) and lo < hi):
            raise DataError(f"voltage limits {list(amplifier_V)}: give lo < hi")
        if vmin < lo or vmax > hi:
            raise DataError(f"the record's voltages span {vmin:g}..{vmax:g} V, outside the "
                            f"amplifier's limits {lo:g}..{hi:g} V")
        return lo, hi
    return (min(DEFAULT_LIMITS_V[0], float(np.floor(vmin))),
            max(DEFAULT_LIMITS_V[1], float(np.ceil(vmax))))


def past_fit_range(model: StageModel, v: PerAxis[np.ndarray]) -> list[str]:
    """Where the voltages ``v`` ({axis: array} [V]) go past the range each axis's model
    was fitted on (beyond it the branches continue straight from their ends), one
    phrase an axis: "vx reaches 148 V, 15 V past the 0-133 V it was fitted on"."""
    out = []
    for a, m in model.axes.items():
        if m.fit_range_V is None or a not in v or not np.size(v[a]):
            continue
        lo, hi = m.fit_range_V
        vmin, vmax = float(np.min(v[a])), float(np.max(v[a]))
        tol = 1e-6 * max(1.0, hi - lo)
        if vmax > hi + tol:
            out.append(f"v{a} reaches {vmax:.4g} V, {vmax - hi:.3g} V past the "
                       f"{lo:.4g}..{hi:.4g} V it was fitted on")
        if vmin < lo - tol:
            out.append(f"v{a} reaches {vmin:.4g} V, {lo - vmin:.3g} V below the "
                       f"{lo:.4g}..{hi:.4g} V it was fitted on")
    return out


def stroke_um(model: DuhemModel, limits: tuple[float, float], n: int = 301,
              plays: PlayOperators | None = None) -> float:
    """The displacement one slow full stroke gives: settled on a sweep down to
    ``limits[0]``, then swept up to ``limits[1]`` [um]. Positive for a stage that
    expands with voltage.

    Parameters
    ----------
    model : DuhemModel
        One axis's hysteresis.
    limits : tuple of float
        (lo, hi) voltage range [V].
    n : int
        Samples per sweep.
    plays : PlayOperators or None
        The axis's play operators (their sum is part of the stroke).

    Returns
    -------
    float
        The displacement w(hi) - w(lo) on the ascending sweep [um] (nan if the model
        diverges).
    """
    lo, hi = float(limits[0]), float(limits[1])
    v = np.concatenate([np.linspace(hi, lo, n), np.linspace(lo, hi, n)])
    with np.errstate(all="ignore"):
        w, _ = model.simulate(v, DuhemState(hi, 0.0))
        if plays is not None:
            # (slow: a rate-dependent law's thresholds widen by beta x ~0.5 V/s)
            w = w + plays.run(v, np.full(plays.thresholds_V.size, hi), 1.0)
    return float(w[-1] - w[n - 1])


def check_model_change(new: StageModel, old: StageModel | None = None,
                       span_um: float | None = None, max_ratio: float = 2.0) -> None:
    """Refuse a model that would move the stage wrongly (ModelError, saying why).

    Each axis's full stroke (``stroke_um`` over the new model's voltage limits) must
    be finite and positive (a stage expands with voltage: a model scaled by -1 would
    drive it to the far limit), within ``max_ratio`` of the running model's stroke when
    there is one, else within a factor of 10 of ``span_um`` (the positions the stage is
    asked to reach), when given. A model scaled by 0.001 asks 1000 times the voltage: the
    inverse then saturates and swings between the limits.

    Parameters
    ----------
    new : StageModel
        The model that would replace the running one.
    old : StageModel or None
        The running model (None: none yet).
    span_um : float or None
        The width of the position range the stage serves [um].
    max_ratio : float
        How far the stroke may change from the running model's (either way).
    """
    for a, m in new.axes.items():
        s = stroke_um(m, new.voltage_limits, plays=new.plays.get(a))
        if not np.isfinite(s) or s <= 0:
            raise ModelError(f"axis {a}: a full stroke gives {s:.3g} um; a stage expands "
                             "with voltage (is the model's sign or scale wrong?)")
        if old is not None and a in old.axes:
            s0 = stroke_um(old.axes[a], old.voltage_limits, plays=old.plays.get(a))
            if s0 > 0 and not s0 / max_ratio <= s <= s0 * max_ratio:
                raise ModelError(f"axis {a}: a full stroke gives {s:.4g} um, the running "
                                 f"model {s0:.4g} um (more than x{max_ratio:g} apart)")
        elif span_um:
            if not span_um / 10 <= s <= span_um * 10:
                raise ModelError(f"axis {a}: a full stroke gives {s:.4g} um for a "
                                 f"{span_um:g} um range (more than x10 apart)")
