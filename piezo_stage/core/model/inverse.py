"""Inverse Duhem model: the voltage that makes the model produce a desired displacement.

Exact inverse
    Per sample, from the model's current state (v_{k-1}, w_{k-1}), solve the forward
    step of the paper's eq. 6 for v_k::

        w_{k-1} + dv H_b(v_{k-1} + dv) - (1 + alpha_b |dv|) w*_k = 0

    on the branch given by the sign of w*_k - w_{k-1} (ascending branch for a rise);
    of the roots we take the one nearest to v_{k-1} (a scan for the first sign change,
    then bracketed regula falsi to machine precision). Forward(inverse(w*)) is then
    w* to rounding wherever w* is reachable. A target no voltage within the limits can
    reach saturates at the limit and is flagged; the state then follows what the
    model really does at that voltage.

    With play operators (a model's ``plays``: return-point memory, core/model/play.py) the
    target is the Duhem step plus the operators' sum P(v_k) from their state; P is
    continuous and piecewise linear in v_k, so the same scan and regula falsi find the
    nearest root, and forward(inverse(w*)) is w* again.

Seed eq. 12 (for comparison)
    The explicit first-order inverse v_k = v_{k-1} + dw_k / S_b(v_{k-1}, w_k), with
    the branch slope S from eq. 6 (dw/dv = H_asc(v) - alpha w rising,
    H_desc(v) + alpha w falling). The paper prints the falling case with the signs of
    the rising one, which contradicts its own eq. 6; we implement the form consistent
    with eq. 6. It is exact only in the limit of small steps.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import ArrayLike

from piezo_stage.core._jit import as_f64
from piezo_stage.core.errors import DataError, ModelError
from piezo_stage.core.model._kernels import (
    duhem_inverse_run,
    stage_inverse_ahead,
    stage_inverse_step,
    stage_sync,
)
from piezo_stage.core.model.duhem import (
    AXES,
    OTHER,
    DuhemModel,
    DuhemState,
    StageModel,
    branch_values,
)
from piezo_stage.core.model.play import PlayOperators
from piezo_stage.core.types import PerAxis

# Scan resolution for the first root: the voltage span is split into this many
# intervals; a branch would need two roots within span/64 (> 2 V) to fool it.
N_SCAN = 64


@dataclass
class InverseResult:
    """Voltages [V], the displacement the model then produces [um], saturation flags."""

    v: np.ndarray
    w: np.ndarray
    saturated: np.ndarray
    final: DuhemState

    @property
    def n_saturated(self) -> int:
        """Samples whose target was out of reach (saturated at a voltage limit)."""
        return int(np.count_nonzero(self.saturated))


_NO_PLAYS = (np.zeros((3, 0)), np.zeros(0))


def invert(model: DuhemModel, w_target: ArrayLike, v_limits: tuple[float, float] = (0.0, 150.0),
           state: DuhemState | None = None, plays: PlayOperators | None = None,
           play_state: np.ndarray | None = None, dt_s: float = 0.0,
           rate_state: np.ndarray | None = None) -> InverseResult:
    """Exact inverse of one axis's Duhem model (plus its play operators, when given:
    ``play_state`` their state, advanced in place; default their initial state) over a
    target sequence [um]. Rate-dependent operators need the targets' spacing ``dt_s``
    [s] and take ``rate_state`` ([voltage before, low-passed rate], updated in place;
    None: at rest)."""
    wt = as_f64(w_target)
    if not np.all(np.isfinite(wt)):
        raise DataError("target displacement has NaN or inf")
    st = state or model.initial
    alpha, H = model.kernel_params()
    r, p = (plays.table, plays.weights_um_per_V) if plays is not None else _NO_PLAYS
    z = play_state if play_state is not None else (
        plays.state() if plays is not None else np.zeros(0))
    q = plays.widening(dt_s, rate_state) if plays is not None else np.zeros(3)
    n = wt.size
    v, w, sat = np.empty(n), np.empty(n), np.zeros(n, dtype=np.int8)
    vp, wp = duhem_inverse_run(wt, float(st.v), float(st.w), alpha, H,
                               float(v_limits[0]), float(v_limits[1]), N_SCAN, r, p, z, q,
                               v, w, sat)
    if rate_state is not None and plays is not None and plays.rate_dependent:
        rate_state[0], rate_state[1] = vp, q[2] / plays.rate_widening_s
    return InverseResult(v, w, sat.astype(bool), DuhemState(float(vp), float(wp)))


def invert_seed_eq12(model: DuhemModel, w_target: ArrayLike,
                     v_limits: tuple[float, float] = (0.0, 150.0),
                     state: DuhemState | None = None) -> InverseResult:
    """Seed eq. 12 (explicit slope inverse, signs made consistent with eq. 6)."""
    wt = as_f64(w_target)
    st = state or model.initial
    alpha, _ = model.kernel_params()
    ha, hd = model.ascending.h(True), model.descending.h(False)
    fr, level = model.fit_range_V, model.continuation == "level"
    h = lambda c, x: float(branch_values(c, x, fr, level))  # noqa: E731 - as the kernels do
    lo, hi = v_limits
    vp, wp = float(st.v), float(st.w)
    n = wt.size
    v, w, sat = np.empty(n), np.empty(n), np.zeros(n, dtype=bool)
    for k in range(n):
        dw = wt[k] - wp
        if dw >= 0:
            slope = h(ha, vp) - alpha[0] * wt[k]
        else:
            slope = h(hd, vp) + alpha[1] * wt[k]
        vk = vp + dw / slope if slope > 0 else vp
        if vk > hi or vk < lo or slope <= 0:
            sat[k] = True
            vk = min(max(vk, lo), hi)
        d = vk - vp
        b = 0 if d >= 0 else 1
        wp = (wp + d * h(ha if b == 0 else hd, vk)) / (1 + alpha[b] * abs(d))
        vp = vk
        v[k], w[k] = vk, wp
    return InverseResult(v, w, sat, DuhemState(vp, wp))


def invert_stage(model: StageModel, wx: ArrayLike, wy: ArrayLike,
                 states: PerAxis[Any] | None = None,
                 tol_V: float = 1e-10, max_iter: int = 50,
                 dt_s: float = 0.0, held_V: Mapping[str, ArrayLike] | None = None
                 ) -> PerAxis[InverseResult]:
    """Joint inverse of a 2-axis model with coupling.

    w_x = H_xx(v_x) + P_x(v_x) + H_xy(v_y) and likewise for y: Gauss-Seidel on whole
    sequences (v_x from w_x minus the coupling of the current v_y, then v_y likewise),
    which converges because the coupling is small against the direct gain. ``dt_s``:
    the targets' spacing [s] (rate-dependent play operators need it). ``held_V``
    ({axis: voltages [V]}): axes driven with these voltages, not inverted (their
    target is ignored; the others' inverse takes their coupling in).

    Returns dict axis -> InverseResult (w is the model's total output on that axis).
    """
    targets = {"x": as_f64(wx), "y": as_f64(wy)}
    lo_hi = model.voltage_limits
    states = dict(states or {})
    held = {a: as_f64(x) for a, x in (held_V or {}).items()}
    n = targets["x"].size
    v = {a: held[a] if a in held else np.full(n, lo_hi[0]) for a in AXES}
    res = {}
    for _ in range(max_iter):
        change = 0.0
        for a in AXES:
            if a not in model.axes or a in held:
                continue
            c = model.coupling.get(a)
            wc = c.simulate(v[OTHER[a]], states.get("c" + a))[0] if c else 0.0
            p = model.plays.get(a)
            z = states["p" + a].copy() if "p" + a in states else None
            q = states["q" + a].copy() if "q" + a in states else None
            r = invert(model.axes[a], targets[a] - wc, lo_hi, states.get(a), p, z, dt_s, q)
            change = max(change, float(np.max(np.abs(r.v - v[a]), initial=0.0)))
            v[a] = r.v
            res[a] = r
        if change < tol_V or not model.coupling:
            break
    w, _ = model.simulate(v["x"], v["y"], states, dt_s=dt_s)
    for a in res:
        res[a].w = w[a]
    return res


class StageInverse:
    """Stateful per-sample exact inverse of a 2-axis model (the feedforward's core).

    ``step(wx, wy)`` returns the voltages [V] that make the model reach the targets
    [um] from its current state, coupling included (Gauss-Seidel sweeps per sample,
    one compiled call), and advances the model state. ``sync(vx, vy)`` advances the
    state with the voltages really applied instead. ``saturated`` counts unreachable
    targets. An axis absent from the model is held at the lower voltage limit.
    ``dt_s``: the samples' spacing [s] (rate-dependent play operators need it).
    """

    def __init__(self, model: StageModel, use_coupling: bool = True, sweeps: int = 4,
                 dt_s: float = 0.0) -> None:
        self.model = model
        self.dt_s = float(dt_s)
        self.use_coupling = bool(use_coupling and model.coupling)
        self.sweeps = sweeps if self.use_coupling else 1
        lo, hi = model.voltage_limits
        self.limits = (float(lo), float(hi))
        none = DuhemModel.whole(1.0, [0.0], [0.0])  # no model: output stays at 0
        axes = [model.axes.get(a) for a in AXES]
        self.present = np.array([m is not None for m in axes])
        kp = [(m or none).kernel_params() for m in axes]
        ckp = [model.coupling.get(a, none).kernel_params() for a in AXES]
        D = max(k[1].shape[1] for k in kp)
        Dc = max(k[1].shape[1] for k in ckp)
        self._alpha = np.array([k[0] for k in kp])
        self._H = np.zeros((2, 2, D))
        for i, k in enumerate(kp):
            self._H[i, :, :k[1].shape[1]] = k[1]
        self._calpha = np.array([k[0] for k in ckp])
        self._cH = np.zeros((2, 2, Dc))
        for i, k in enumerate(ckp):
            self._cH[i, :, :k[1].shape[1]] = k[1]
        # play operators per axis (their tables, weights), padded with zero weights to
        # one length
        P = max([p.thresholds_V.size for p in model.plays.values()] or [0])
        self._pr, self._pp = np.zeros((2, 3, P)), np.zeros((2, P))
        for i, a in enumerate(AXES):
            if a in model.plays:
                k = model.plays[a].thresholds_V.size
                self._pr[i, :, :k] = model.plays[a].table
                self._pp[i, :k] = model.plays[a].weights_um_per_V
        self.pz = np.zeros((2, P))
        self.pq = np.zeros((2, 3))  # the rate widening per axis (zeros: none)
        self._out = np.zeros((4, 2))
        self._target = np.zeros(2)
        self._present = tuple(bool(p) for p in self.present)
        self._present_f = np.array([1.0 if p else 0.0 for p in self._present])
        self.saturated = 0
        self.reset()

    def reset(self, v: PerAxis[float] | None = None, w: PerAxis[float] | None = None) -> None:
        """Back to the model's initial states, or to voltages v / outputs w (dicts)."""
        init = [self.model.axes[a].initial if a in self.model.axes else DuhemState(
            self.limits[0], 0.0) for a in AXES]
        self.vp = np.array([s.v for s in init], float)
        self.wp = np.array([s.w for s in init], float)
        cinit = [self.model.coupling[a].initial if a in self.model.coupling else DuhemState()
                 for a in AXES]
        self.cvp = np.array([s.v for s in cinit], float)
        self.cwp = np.array([s.w for s in cinit], float)
        self.pz[:] = 0.0
        for i, a in enumerate(AXES):
            if a in self.model.plays:
                p = self.model.plays[a]
                self.pz[i, :p.thresholds_V.size] = p.initial_V
                self.pq[i] = p.widening(self.dt_s)
        if v:
            self.vp = np.array([float(v.get(a, 0.0)) for a in AXES])
            self.pz[:] = self.vp[:, None]  # the operators at rest at v
            self.wp = np.array([float((w or {}).get(a, 0.0)) for a in AXES]) - self._play_w()
            self.cvp = self.vp[::-1].copy()
            self.cwp = np.zeros(2)

    def _play_w(self) -> np.ndarray:
        """The play operators' sum per axis [um] in the present state."""
        return np.einsum("ij,ij->i", self._pp,
                         np.clip(self.pz, self._pr[:, 1], self._pr[:, 2]))

    @property
    def v(self) -> dict[str, float]:
        """The voltages [V] of the inverse's current state, per axis."""
        return {"x": float(self.vp[0]), "y": float(self.vp[1])}

    @property
    def w(self) -> dict[str, float]:
        """The model's present output [um] per axis (main term plus the coupling the
        inverse compensates)."""
        w = self.wp + self._play_w()
        w = w + self.cwp if self.use_coupling else w
        return {"x": float(w[0]), "y": float(w[1])}

    def snapshot(self) -> tuple[np.ndarray, ...]:
        """A copy of the hysteresis state (for stepping ahead and coming back)."""
        return (self.vp.copy(), self.wp.copy(), self.cvp.copy(), self.cwp.copy(),
                self.pz.copy(), self.pq.copy())

    def restore(self, snap: tuple[np.ndarray, ...]) -> None:
        """Go back to a state taken with ``snapshot``."""
        self.vp[:], self.wp[:], self.cvp[:], self.cwp[:], self.pz[:], self.pq[:] = snap

    def step_ahead(self, in_flight: Sequence[dict[str, float]], wx: float,
                   wy: float) -> dict[str, float]:
        """Voltages for the target (wx, wy) [um] reached after the targets still in
        flight (a list of {axis: um}, oldest first: commands computed but not yet
        applied), from the present (synced) state, which is left as it was. Raises
        ModelError when the inverse is not finite."""
        if not in_flight:
            vx, vy, _ = self.step(wx, wy, commit=False)
        else:  # every step in one compiled call, on a copy of the state
            ahead = np.array([(d["x"], d["y"]) for d in in_flight], float)
            t = self._target
            t[0], t[1] = wx, wy
            o = stage_inverse_ahead(ahead, t, self.vp, self.wp, self._alpha, self._H,
                                    self.cvp, self.cwp, self._calpha, self._cH, self._pr,
                                    self._pp, self.pz, self.pq, self._present_f,
                                    self.use_coupling, self.limits[0], self.limits[1],
                                    self.sweeps, N_SCAN, self._out)
            vx = float(o[0, 0]) if self._present[0] else self.limits[0]
            vy = float(o[0, 1]) if self._present[1] else self.limits[0]
            self.saturated += int(o[3, 0] + o[3, 1])
        if not (np.isfinite(vx) and np.isfinite(vy)):
            raise ModelError("the inverse gave a non-finite voltage")
        return {"x": vx, "y": vy}

    def sync(self, vx: float, vy: float) -> None:
        """Advance the model with the voltages really applied (feedforward plus
        feedback, after the driver's limits), so the next inverse starts from the
        state the stage is actually in rather than from the feedforward's own output."""
        stage_sync(float(vx), float(vy), self.vp, self.wp, self._alpha, self._H, self.cvp,
                   self.cwp, self._calpha, self._cH, self._pr, self._pp, self.pz, self.pq)

    def warm_kernels(self) -> None:
        """Call each compiled kernel the per-sample path calls (``sync``, ``step``,
        ``step_ahead`` with commands in flight), in the types it calls them with, so that
        none is compiled or loaded from numba's cache at a sample: loaded at the first
        tracked sample, the look-ahead's alone would hold a real-time loop's thread
        for many ticks. Moves this inverse's state: warm a
        throwaway one."""
        self.sync(*self.limits)
        self.step(0.0, 0.0)
        self.step_ahead([{"x": 0.0, "y": 0.0}], 0.0, 0.0)

    def step(self, wx: float, wy: float,
             commit: bool = True) -> tuple[float, float, dict[str, bool]]:
        """Voltages for the targets; ``commit=False`` leaves the state for ``sync``."""
        t = self._target
        t[0], t[1] = wx, wy
        o = stage_inverse_step(t, self.vp, self.wp, self._alpha, self._H, self.cvp,
                               self.cwp, self._calpha, self._cH, self._pr, self._pp,
                               self.pz, self.pq, self.use_coupling,
                               self.limits[0], self.limits[1], self.sweeps, N_SCAN,
                               self._out)
        vx, vy, sx, sy = o[0, 0], o[0, 1], o[3, 0], o[3, 1]
        px, py = self._present
        vx, vy = float(vx) if px else self.limits[0], float(vy) if py else self.limits[0]
        sat = {"x": bool(sx) and px, "y": bool(sy) and py}
        self.saturated += sat["x"] + sat["y"]
        if commit:
            self.sync(vx, vy)
        return vx, vy, sat
