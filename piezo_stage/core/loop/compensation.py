"""Effect compensation: the exact inverse of the unmodelled effects at the control rate.

The plant acts on each axis's hysteresis output h (what the Duhem model gives for the
applied voltage) with creep, then linear dynamics, then drift, then a transport delay
(``core/model/plant.py``). A command is held over one control period, so at the control rate
these operators are discrete and exactly invertible:

* delay d = n T + delta: n whole periods are taken by previewing the known trajectory
  n periods ahead; the fraction delta only moves the instant within the period at
  which the dynamics' output is sampled (it is part of the dynamics' discrete model);
* dynamics (resonance or lag) with the held input: x_m = Ad x_(m-1) + Bd u_m, sampled
  y_m = C' x_(m-1) + D' u_m with C' = C Phi(T - delta), D' = C Gamma(T - delta); the
  inverse u_m = (y_m - C' x_(m-1)) / D' is used when its own poles
  (eig(Ad - Bd C' / D')) are inside the unit circle, i.e. the sampled plant is minimum
  phase at this rate (checked); otherwise (a resonance near or above the Nyquist rate)
  its stable noncausal inverse, which previews the known trajectory a few more periods
  (``PreviewDynamicsInverse``);
* creep, y = h - gamma (h - mean_i LP_i(h)) with first-order low-passes LP_i, is
  solved for h sample by sample (its direct term is 1 - gamma + gamma mean(1 - p_i));
* drift ignores the input: no feedforward can remove it (feedback does).

A streamed setpoint cannot be previewed and steps: only creep is compensated for it
(inverting the dynamics of a step would ask for an impulse).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import TYPE_CHECKING, Protocol

import numpy as np

from piezo_stage.core.errors import ConfigError
from piezo_stage.core.model.effects import effects_on
from piezo_stage.core.types import Doc, EffectsBlock, Params, PerAxis

if TYPE_CHECKING:
    from piezo_stage.core.loop.planner import ReferencePlanner

CREEP_TAUS_S = (0.05, 0.5, 5.0, 50.0)


def _phi_gamma(A: np.ndarray, B: np.ndarray, tau: float) -> tuple[np.ndarray, np.ndarray]:
    """Phi(tau) = e^(A tau) and Gamma(tau) = int_0^tau e^(A s) ds B (one matrix exponential)."""
    from scipy.linalg import expm  # (at first use: a node without effects starts sooner)
    n = A.shape[0]
    M = np.zeros((n + 1, n + 1))
    M[:n, :n], M[:n, n:] = A * tau, B * tau
    E = expm(M)
    return E[:n, :n], E[:n, n:]


class CreepInverse:
    """The exact inverse of core.effects.Creep: h_k from the wanted creep output y_k."""

    def __init__(self, rate_hz: float, gamma: float,
                 tau_s: Sequence[float] = CREEP_TAUS_S) -> None:
        self.gamma = float(gamma)
        if not 0 <= self.gamma < 1:
            raise ConfigError(f"creep gamma must be in [0, 1), got {gamma}")
        self.p = np.exp(-1.0 / (rate_hz * np.asarray(tau_s, float)))
        self.direct = 1 - self.gamma + self.gamma * float(np.mean(1 - self.p))
        self.lp = np.zeros_like(self.p)

    def reset(self, h0: float) -> None:
        """At rest at ``h0``."""
        self.lp[:] = h0

    def step(self, y: float) -> float:
        """The hysteresis output that makes the creep output ``y``."""
        h = (y - self.gamma * float(np.mean(self.p * self.lp))) / self.direct
        self.lp = self.p * self.lp + (1 - self.p) * h
        return h


class DynamicsInverse:
    """The inverse of unit-DC dynamics at the control rate: u_m from the wanted sampled
    output y_m, the output sampled ``delta_s`` before the end of the period the input
    is held in."""

    def __init__(self, rate_hz: float, kind: str = "resonance", fn_hz: float = 800.0,
                 zeta: float = 0.05, tau_s: float = 0.5e-3, delta_s: float = 0.0) -> None:
        T = 1.0 / rate_hz
        if kind == "resonance":
            wn = 2 * math.pi * float(fn_hz)
            A = np.array([[0.0, 1.0], [-wn * wn, -2 * float(zeta) * wn]])
            B = np.array([[0.0], [wn * wn]])
        elif kind == "lag":
            A, B = np.array([[-1.0 / tau_s]]), np.array([[1.0 / tau_s]])
        else:
            raise ConfigError(f"dynamics kind must be 'resonance' or 'lag', got {kind!r}")
        C = np.zeros((1, A.shape[0]))
        C[0, 0] = 1.0
        self.Ad, self.Bd = _phi_gamma(A, B, T)
        P, G = _phi_gamma(A, B, T - delta_s)
        self.Cs, self.Ds = (C @ P).ravel(), float((C @ G)[0, 0])
        self.ok = abs(self.Ds) > 1e-9
        if self.ok:
            inv_poles = np.linalg.eigvals(self.Ad - np.outer(self.Bd.ravel(), self.Cs) / self.Ds)
            self.ok = bool(np.max(np.abs(inv_poles)) < 0.999)
        self._steady = -np.linalg.solve(A, B).ravel()  # state per unit constant input
        self.x = np.zeros(A.shape[0])

    def reset(self, u0: float) -> None:
        """At rest with input and output at ``u0``."""
        self.x = self._steady * u0

    def step(self, y: float) -> float:
        """The input that makes the sampled output ``y``."""
        u = (y - float(self.Cs @ self.x)) / self.Ds
        self.x = self.Ad @ self.x + self.Bd.ravel() * u
        return u


class PreviewDynamicsInverse:
    """The stable inverse of sampled dynamics that are not minimum phase, with preview
    (stable inversion in the manner of Devasia, Chen and Paden, in discrete time).

    The sampled model ``G(z) = Cs (zI - Ad)^-1 Bd + Ds`` (DynamicsInverse's) is
    num(z) / den(z); its zeros outside the unit circle (z_u, from sampling a resonance
    near or above the Nyquist rate) make the causal inverse den / num unstable. Split
    num = K num_s num_u (zeros inside / outside) and invert each part the way it is
    stable:

    * 1 / num_u(z) = prod(-1 / z_u) / prod(1 - z / z_u) is expanded in powers of z, that
      is in future samples: a noncausal FIR whose taps decay as |1 / z_u|^k, truncated
      where they fall below ``tol`` of the first (``taps`` samples of preview);
    * den(z) / (K num_s(z)) is causal and stable once advanced by r = deg num_u samples
      (its poles are num_s's zeros, inside the circle).

    So u_m needs y_m .. y_(m + preview) with preview = taps - 1 + r: ``step`` is fed the
    wanted output ``preview`` samples ahead and returns u_m for the oldest. The result
    makes the sampled output follow y at the samples (the truncation leaves an error
    of ``tol``); between samples a mode above the Nyquist rate can still move, which
    no command held for a whole period can prevent.
    """

    def __init__(self, inv: DynamicsInverse, tol: float = 1e-6, max_taps: int = 2000) -> None:
        # here, not at the top: scipy.signal's import would lengthen every node's start-up
        from scipy.signal import lfilter, lfilter_zi, ss2tf
        self._lfilter = lfilter
        num, den = ss2tf(inv.Ad, inv.Bd, inv.Cs[None, :], np.array([[inv.Ds]]))
        num, den = np.trim_zeros(np.real(num[0]), "f"), np.real(den)
        zeros = np.roots(num)
        inside, outside = zeros[np.abs(zeros) < 1.0], zeros[np.abs(zeros) >= 1.0]
        if np.any(np.abs(np.abs(outside) - 1.0) < 1e-6):
            raise ConfigError("the sampled dynamics have a zero on the unit circle: no "
                              "stable inverse")
        k_gain = num[0]
        r = outside.size
        # the noncausal part: prod(-1/z_u) * series of 1 / prod(1 - p_i z), p_i = 1/z_u
        p = 1.0 / outside
        rho = float(np.max(np.abs(p))) if r else 0.0
        taps = 1 if r == 0 else min(max_taps, int(np.ceil(np.log(tol) / np.log(rho))) + 1)
        if r and rho ** (taps - 1) > 10 * tol:
            raise ConfigError(f"the sampled dynamics' zero at |z| = {1 / rho:.4f} needs "
                              f"more than {max_taps} samples of preview")
        series = np.zeros(taps)
        series[0] = 1.0
        series = lfilter([1.0], np.real(np.poly(p)), series) if r else series
        self.fir = np.real(np.prod(-p) * series) if r else series
        # the causal part den / (K num_s), in powers of z^-1
        self.b = den / k_gain
        self.a = np.real(np.poly(inside)) if inside.size else np.ones(1)
        self.preview = taps - 1 + r
        self.r = r
        self._zi_unit = lfilter_zi(self.b, self.a) if max(self.a.size, self.b.size) > 1 \
            else np.zeros(0)
        self._dc_fir = float(np.sum(self.fir))
        self.window = np.zeros(taps + r)
        self.zi = np.zeros(max(self.a.size, self.b.size) - 1)

    def reset(self, u0: float) -> None:
        """At rest with input and output at ``u0`` (unit DC gain)."""
        self.window[:] = u0
        w0 = u0 * self._dc_fir
        self.zi = self._zi_unit * w0

    def step(self, y_ahead: float) -> float:
        """Feed the wanted output ``preview`` samples ahead; the input for the sample
        ``preview`` before it."""
        self.window[:-1] = self.window[1:]
        self.window[-1] = y_ahead
        # w_(m + r) from y_(m + r) .. y_(m + r + taps - 1): the window's last taps
        w = float(self.fir @ self.window[self.r:])
        u, self.zi = self._lfilter(self.b, self.a, [w], zi=self.zi)
        return float(u[0])


class EffectCompensator:
    """Per axis, the hysteresis target that makes the effects chain give the desired
    position: ``lead_ticks`` say how far ahead the desired position must be asked for
    (the whole periods of the delay), ``step`` turns it into hysteresis targets.

    ``effects`` is a model file's ``effects`` block ({name: {params..., axes: [...]}},
    or a list of such per set of axes, as ``gap --out-model`` writes it; read per axis
    by ``effects_on``: ``enabled: false`` entries are skipped). A
    resonance above ``max_resonance_hz`` (None or 0: no limit) is not inverted: its
    group delay joins the delay."""

    def __init__(self, effects: EffectsBlock, rate_hz: float, axes: Sequence[str] = ("x", "y"),
                 max_resonance_hz: float | None = None) -> None:
        self.rate_hz = float(rate_hz)
        T = 1.0 / self.rate_hz
        max_fn = float(max_resonance_hz) if max_resonance_hz else math.inf
        self.creep: Params = {}
        self.dynamics: dict[str, DynamicsInverse | PreviewDynamicsInverse] = {}
        self.lead_ticks = {a: 0 for a in axes}
        # of lead_ticks, the samples a stable inverse previews (not a time advance)
        self.preview_ticks = {a: 0 for a in axes}
        self.compensated: set[str] = set()
        self.uncompensated: dict[str, str] = {}
        self.notes: dict[str, str] = {}
        for a in axes:  # each axis's own parameter sets (effects_on)
            eff = effects_on(effects, a)
            unknown = sorted(set(eff) - {"delay", "creep", "dynamics", "drift"})
            if unknown:
                raise ConfigError(f"unknown effect {unknown[0]!r} in the model's effects")
            d = float(eff["delay"]["delay_s"]) if "delay" in eff else 0.0
            if "delay" in eff:
                self.lead_ticks[a] = int(math.floor(d / T + 1e-9))
                self.compensated.add("delay")
            if "creep" in eff:
                c = eff["creep"]
                self.creep[a] = CreepInverse(self.rate_hz, c["gamma"],
                                             c.get("tau_s", CREEP_TAUS_S))
                self.compensated.add("creep")
            if "drift" in eff:
                self.uncompensated["drift"] = "ignores the input (left to the feedback)"
            if "dynamics" in eff:
                self._dynamics(a, dict(eff["dynamics"]), d, max_fn)
        self.axes = tuple(axes)

    def _dynamics(self, a: str, dyn: Params, d: float, max_fn: float) -> None:
        """Axis ``a``'s dynamics inverted (read at the fraction of its delay ``d`` [s]
        past the whole periods), with preview where the sampled plant is not minimum
        phase, or taken as a group delay above ``max_fn`` [Hz]."""
        T = 1.0 / self.rate_hz
        fn = float(dyn.get("fn_hz", 0.0))
        if dyn.get("kind", "resonance") == "resonance" and fn > max_fn:
            # a resonance the user does not trust enough to invert (inverting one
            # whose parameters are off amplifies their error, where its group delay
            # alone errs far less): its
            # low-frequency part, the group delay 2 zeta / wn, joins the delay
            gd = 2.0 * float(dyn.get("zeta", 0.0)) / (2 * math.pi * fn)
            self.lead_ticks[a] = int(math.floor((d + gd) / T + 1e-9))
            self.uncompensated["dynamics"] = (
                f"resonance at {fn:.0f} Hz, above {max_fn:.0f} Hz: taken as its group "
                f"delay of {gd * 1e6:.0f} us")
            return
        inv = DynamicsInverse(self.rate_hz, delta_s=d - self.lead_ticks[a] * T, **dyn)
        if inv.ok:
            self.dynamics[a] = inv
            self.compensated.add("dynamics")
            return
        # not minimum phase at this rate: the stable inverse with preview
        try:
            pinv = PreviewDynamicsInverse(inv)
        except ConfigError as e:
            self.uncompensated["dynamics"] = (
                f"not minimum phase when sampled at {self.rate_hz:g} Hz: {e}")
            return
        self.dynamics[a] = pinv
        self.compensated.add("dynamics")
        self.preview_ticks[a] = pinv.preview
        self.lead_ticks[a] += pinv.preview
        self.notes["dynamics"] = (
            f"not minimum phase at {self.rate_hz:g} Hz: inverted with "
            f"{pinv.preview} samples of preview")

    @property
    def max_lead_ticks(self) -> int:
        """The longest preview any axis needs [periods]."""
        return max(self.lead_ticks.values(), default=0)

    def reset(self, w0: PerAxis[float]) -> None:
        """At rest at w0 [um] (everything settled)."""
        for a, c in self.creep.items():
            c.reset(w0[a])
        for a, d in self.dynamics.items():
            d.reset(w0[a])

    def step(self, wanted: PerAxis[float], preview: bool = True) -> PerAxis[float]:
        """Hysteresis targets [um] for one period from the wanted positions (each
        asked ``lead_ticks`` ahead). Without preview (a streamed setpoint) the dynamics
        are not inverted."""
        out = {}
        for a in self.axes:
            y = wanted[a]
            d = self.dynamics.get(a)
            if d is not None:
                if preview:
                    y = d.step(y)
                else:
                    d.reset(y)
            c = self.creep.get(a)
            out[a] = c.step(y) if c is not None else y
        return out

    def describe(self) -> str:
        """One line: which effects are compensated, which not and why."""
        done = ", ".join(f"{k} ({self.notes[k]})" if k in self.notes else k
                         for k in sorted(self.compensated)) or "none"
        left = "; ".join(f"{k}: {v}" for k, v in sorted(self.uncompensated.items()))
        return f"effects compensated: {done}" + (f" (not: {left})" if left else "")


class LearnedOffsets(Protocol):
    """What the reference needs of a learner (core.learning.PeriodicLearner)."""

    def offset(self, k: int, axes: tuple | None = None) -> PerAxis[float]:
        """The correction {axis: um} at trajectory sample ``k``, given to ``axes``
        (default: every axis)."""


class PreviewedReference:
    """The reference planner with the model's effects compensated: what the stage should
    be at each target tick, and the hysteresis target to command for it.

    With a compensator the planner runs the delay's whole periods ahead (the trajectory
    is known), its samples are kept until their own tick comes (that is where the stage
    should be then), and the wanted positions go through ``EffectCompensator.step``.
    Without one (or switched off) it is the planner itself. ``hold`` is the disabled
    path: the planner holds, the lead samples are dropped, the compensator rests at the
    measured position.
    """

    def __init__(self, planner: ReferencePlanner, dt_ns: int) -> None:
        self.planner, self.dt_ns = planner, int(dt_ns)
        self.comp: EffectCompensator | None = None
        self.on = True
        self.ahead: dict[int, PerAxis[float]] = {}
        self.learner: LearnedOffsets | None = None  # a core.learning.PeriodicLearner

    def set_compensator(self, comp: EffectCompensator | None) -> None:
        """A new model's compensator (None: no effects)."""
        self.comp, self.ahead = comp, {}

    def set_learner(self, learner: LearnedOffsets | None) -> None:
        """Learning feedforward: ``learner.offset(k)`` is added to the wanted position
        of trajectory sample ``k`` (before the effects are compensated); None: off."""
        self.learner = learner

    def sample_index(self, stamp_ns: int) -> int | None:
        """The trajectory sample (at this reference's period) a stamp falls on while the
        trajectory runs; None outside it."""
        clock = self.planner.clock_s(stamp_ns)
        if clock is None or clock < 0 or self.planner.traj is None or \
                clock > self.planner.traj[0][-1]:
            return None
        return int(round(clock * 1e9 / self.dt_ns))

    def _learned(self, wanted: PerAxis[float], stamps: Doc) -> PerAxis[float]:
        """``wanted`` with the learned correction of each axis's stamp added."""
        if self.learner is None:
            return wanted
        out = dict(wanted)
        for a, ts in stamps.items():
            k = self.sample_index(ts)
            if k is not None:
                out[a] = wanted[a] + self.learner.offset(k, (a,)).get(a, 0.0)
        return out

    def describe(self) -> str:
        """The diagnostics' line: what is compensated, or that nothing is."""
        if self.comp is None:
            return "no effects in the model"
        return self.comp.describe() + ("" if self.on else " (switched off)")

    def hold(self, w_hold: PerAxis[float], w_measured: PerAxis[float]) -> None:
        """Disabled: the planner holds ``w_hold``; the compensator rests at the stage."""
        self.planner.hold(w_hold)
        self.ahead = {}
        if self.comp is not None:
            self.comp.reset(w_measured)

    def sample(self, target_ns: int) -> tuple[PerAxis[float], PerAxis[float]]:
        """(where the stage should be at target_ns, the hysteresis target for it)."""
        comp = self.comp if self.on else None
        if comp is None:
            d = self.planner.sample(target_ns)
            return d, self._learned(d, {a: target_ns for a in d})
        preview = self.planner.traj is not None
        held: PerAxis[float] = dict(self.planner.desired or {})
        lead = comp.max_lead_ticks if preview else 0
        t_lead = target_ns + lead * self.dt_ns
        self.ahead[t_lead] = self.planner.sample(t_lead)
        stamps = {a: target_ns + comp.lead_ticks[a] * self.dt_ns if preview else target_ns
                  for a in held}
        wanted = self._learned({a: self.ahead.get(stamps[a], held)[a] for a in held}, stamps)
        desired = self.ahead.get(target_ns, held)
        self.ahead = {t: d for t, d in self.ahead.items() if t >= target_ns}
        return desired, comp.step(wanted, preview)
