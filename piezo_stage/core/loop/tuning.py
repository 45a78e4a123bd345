"""PID gains from an identified model: discrete loop shaping with stated margins.

Method. Per axis the loop from an error sample to the measured position is

    L(z) = C(z) z^-L k P_fx(z),   C(z) = kp + ki T z / (z - 1)   (the controller's PID,
                                                                   backward-Euler integral)

with L the loop's latency in periods (lockstep: a command computed from sample k is
applied over the next period, L = 1), k the hysteresis model's largest incremental
gain dw/dv over its voltage range (the plant is steepest there, so margins that hold
for it hold everywhere along the branches), and P_fx the model's unmodelled effects at
the control rate (creep, dynamics with the delay's fraction, the delay's whole periods),
exactly as core/loop/compensation.py inverts them. Among PI gains on a log grid the largest
crossover frequency is chosen whose loop has at least the asked phase and gain margins
on both axes (the phase margin at every unity-gain crossing, the gain margin at every
-180 deg crossing: with a stable plant the closed loop is then stable); kd stays
0 (a derivative on a 0.1 um-noise sensor buys little at these bandwidths). The expected
closed-loop bandwidth is the -3 dB frequency of L / (1 + L).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from piezo_stage.core.errors import ModelError
from piezo_stage.core.loop.compensation import CREEP_TAUS_S, DynamicsInverse
from piezo_stage.core.model.duhem import StageModel
from piezo_stage.core.model.effects import effects_on
from piezo_stage.core.types import Doc, EffectsBlock, PerAxis


def model_gain(model: StageModel, axis: str, n: int = 2001) -> tuple[float, float]:
    """(largest, median) incremental gain dw/dv [um/V] of ``axis`` over a full
    up-and-down sweep of the voltage range (coupling input held at the low limit)."""
    lo, hi = model.voltage_limits
    up = np.linspace(lo, hi, n)
    v = np.concatenate([up, up[::-1][1:], up[1:]])
    other = np.full_like(v, lo)
    # (a slow sweep: 1 s between samples, a rate-dependent law barely widens)
    w, _ = model.simulate(v, other, dt_s=1.0) if axis == "x" else \
        model.simulate(other, v, dt_s=1.0)
    dw, dv = np.diff(w[axis]), np.diff(v)
    slope = dw / dv
    if not np.all(np.isfinite(slope)):
        raise ModelError(f"axis {axis}: the model gives non-finite displacements over "
                         f"{lo:g}..{hi:g} V")
    return float(np.max(slope)), float(np.median(slope))


def effects_response(effects: EffectsBlock, axis: str, rate_hz: float,
                     z: np.ndarray) -> tuple[np.ndarray, int]:
    """The unmodelled effects' frequency response at z = e^(j w T) for ``axis``, and
    the whole periods of its delay."""
    T = 1.0 / rate_hz
    H = np.ones_like(z)
    lead = 0
    eff = effects_on(effects, axis)
    delay = float(eff.get("delay", {}).get("delay_s", 0.0))
    lead = int(math.floor(delay / T + 1e-9))
    if "creep" in eff:
        g = float(eff["creep"]["gamma"])
        p = np.exp(-T / np.asarray(eff["creep"].get("tau_s", CREEP_TAUS_S), float))
        slow = np.mean([(1 - pi) / (1 - pi / z) for pi in p], axis=0)
        H = H * (1 - g + g * slow)
    if "dynamics" in eff:
        d = {k: v for k, v in eff["dynamics"].items() if k not in ("enabled", "axes")}
        m = DynamicsInverse(rate_hz, delta_s=delay - lead * T, **d)
        n = m.Ad.shape[0]
        Hd = np.array([m.Ds + m.Cs @ np.linalg.solve(zi * np.eye(n) - m.Ad, m.Bd.ravel())
                       for zi in z])
        H = H * Hd
    return H * z ** (-lead), lead


@dataclass
class Tuning:
    """Gains from ``tune`` with the loop's figures and the method used."""
    kp: float
    ki: float
    kd: float
    crossover_hz: float
    bandwidth_hz: float
    phase_margin_deg: float
    gain_margin_db: float
    noise_gain: float
    gains_um_per_V: Doc = field(default_factory=dict)
    method: str = ""
    source: str = ""
    notes: str = ""

    def summary(self) -> str:
        """The gains, crossover, bandwidth and margins as printed lines."""
        g = ", ".join(f"{a} {hi:.3f}" + (f" (median {md:.3f})" if md != hi else "")
                      for a, (hi, md) in self.gains_um_per_V.items())
        what = "model gain dw/dv" if self.source == "model" else "measured loop gain"
        return ((self.notes + "\n" if self.notes else "") +
                f"method: {self.method}\n{what} [um/V]: {g}\n"
                f"gains: kp {self.kp:.4g} V/um, ki {self.ki:.4g} V/(um s), kd {self.kd:g}\n"
                f"crossover {self.crossover_hz:.1f} Hz, expected closed-loop bandwidth "
                f"{self.bandwidth_hz:.1f} Hz (-3 dB), phase margin "
                f"{self.phase_margin_deg:.1f} deg, gain margin {self.gain_margin_db:.1f} dB "
                + ("(worst axis, at the steepest point of the branches)"
                   if self.source == "model" else "(worst axis, at the measured gain)")
                + "; sensor noise "
                f"passed to the true position: {self.noise_gain:.2f} x its RMS")

    def params_yaml(self) -> str:
        """A node parameter file with the gains (doubles), for ``launch --params``."""
        return (f"# PID gains from `piezo-stage tune` ({self.source})\n# {self.method}\n"
                f"# crossover {self.crossover_hz:.1f} Hz, bandwidth {self.bandwidth_hz:.1f} "
                f"Hz, PM {self.phase_margin_deg:.1f} deg, GM {self.gain_margin_db:.1f} dB\n"
                f"/**/controller:\n  ros__parameters:\n    kp: {_double(self.kp)}\n"
                f"    ki: {_double(self.ki)}\n    kd: {_double(self.kd)}\n")


def _double(x: float) -> str:
    """A YAML float that stays a float (ROS parameters are typed: ``0`` would be an
    integer, which a double parameter refuses)."""
    return repr(float(f"{x:.6g}"))


def _margins(Lw: np.ndarray, w: np.ndarray) -> tuple[float, float, float] | None:
    """(phase margin deg, gain margin dB, crossover rad/sample) of a loop response on
    the grid w (ascending): the phase margin at every unity-gain crossing, the gain
    margin at every -180 deg crossing (so a resonance peak that crosses again counts);
    None when |L| never falls through 1."""
    mag = np.abs(Lw)
    ph = np.unwrap(np.angle(Lw))
    cross = np.nonzero((mag[:-1] >= 1) & (mag[1:] < 1))[0]
    if cross.size == 0:
        return None
    up = np.nonzero((mag[:-1] < 1) & (mag[1:] >= 1))[0]
    pm = min(math.degrees(math.remainder(ph[i] + math.pi, 2 * math.pi))
             for i in np.concatenate([cross, up]))
    k: list[int] = list(np.nonzero(np.diff(np.floor((ph + math.pi) / (2 * math.pi))) != 0)[0])
    if abs(math.remainder(ph[-1] + math.pi, 2 * math.pi)) < 1e-6:
        k.append(len(w) - 1)  # real and negative at Nyquist: a -180 deg point too
    gm = min((-20 * math.log10(max(mag[j], 1e-12)) for j in k), default=math.inf)
    return pm, gm, w[cross[0]]


def tune(model: StageModel, effects: EffectsBlock | None = None, rate_hz: float = 1000.0,
         phase_margin_deg: float = 60.0, gain_margin_db: float = 10.0,
         latency_periods: float = 1.0, max_noise_gain: float = 0.3,
         source: str = "model") -> Tuning:
    """See the module docstring. ModelError when the model cannot be tuned from."""
    if not (rate_hz > 0 and 0 < phase_margin_deg < 90 and gain_margin_db > 0
            and latency_periods >= 0):
        raise ModelError("tune: rate > 0, 0 < phase margin < 90 deg, gain margin > 0 dB "
                         "and latency >= 0 periods")
    T = 1.0 / rate_hz
    w = np.concatenate([np.geomspace(1e-4, math.pi * 0.999, 1500), [math.pi]])
    z = np.exp(1j * w)
    L = int(math.ceil(latency_periods - 1e-9))
    plants: PerAxis[np.ndarray] = {}
    gains: PerAxis[tuple[float, float]] = {}
    for a in ("x", "y"):
        if a not in model.axes:
            continue
        hi, md = model_gain(model, a)
        if not (hi > 0 and md > 0):
            raise ModelError(f"axis {a}: the model's gain dw/dv is not positive over the "
                             "voltage range (largest "
                             f"{hi:.3g}, median {md:.3g} um/V): not enough data to tune from")
        gains[a] = (hi, md)
        H, _ = effects_response(effects or {}, a, rate_hz, z)
        plants[a] = hi * H * z ** (-L)
    if not plants:
        raise ModelError("tune: the model has no axes")
    method = (f"PI on the steepest model gain, {L} period(s) of latency, the model's "
              f"effects at {rate_hz:g} Hz")
    return _shape(plants, w, T, phase_margin_deg, gain_margin_db, max_noise_gain, gains,
                  method, source)


def _shape(plants: PerAxis[np.ndarray], w: np.ndarray, T: float, phase_margin_deg: float,
           gain_margin_db: float, max_noise_gain: float,
           gains: PerAxis[tuple[float, float]], method: str,
           source: str, notes: str = "") -> Tuning:
    """The PI search both tunings share: on a log grid of (kp, ki), the largest
    crossover whose loop meets the margins and the noise bound on every axis's plant
    response ``plants[axis]`` (at z = e^(j w)); ``method`` says what the plants are."""
    z = np.exp(1j * w)
    integ = T * z / (z - 1)
    best = None
    for ki in np.geomspace(1.0, 1e5, 161):
        for kp in np.concatenate([[0.0], np.geomspace(1e-3, 5.0, 56)]):
            C = kp + ki * integ
            got = [_margins(C * P, w) for P in plants.values()]
            ms = [m for m in got if m is not None]
            if len(ms) < len(got):
                continue
            worst = tuple(min(m[i] for m in ms) for i in range(3))
            if worst[0] < phase_margin_deg or worst[1] < gain_margin_db:
                continue
            if max(_noise_gain(C * P, w) for P in plants.values()) > max_noise_gain:
                continue
            if best is None or worst[2] > best[2][2]:
                best = (kp, ki, worst)
    method = (f"discrete loop shaping: the largest crossover with phase margin >= "
              f"{phase_margin_deg:g} deg and gain margin >= {gain_margin_db:g} dB on both "
              f"axes, white sensor noise passed to the true position at most "
              f"{max_noise_gain:g} x its RMS; {method}")
    if best is None:
        raise ModelError("tune: no PI gains meet the margins on this "
                         f"{'model' if source == 'model' else 'loop'}")
    kp, ki, (pm, gm, wc) = best
    C = kp + ki * integ
    bw = min(_bandwidth(C * P, w) for P in plants.values())
    noise = max(_noise_gain(C * P, w) for P in plants.values())
    return Tuning(float(kp), float(ki), 0.0, wc / (2 * math.pi * T), bw / (2 * math.pi * T),
                  pm, gm, noise, gains, method, source, notes)


@dataclass
class RelayPoint:
    """One axis's ultimate point from a relay experiment: the loop's response where
    it oscillates (from the controller's command to the measured position, the loop's
    latency included), as measured."""
    freq_hz: float             # oscillation frequency
    gain_um_per_V: float       # |G| there (1 / the ultimate gain)
    phase_deg: float           # arg G there, unwrapped (-180, or -180 - n x 360)
    amplitude_um: float        # first-harmonic amplitude of the measured position
    cycles: int                # whole cycles the figures come from
    latency_periods: int       # command-to-application latency included in G

    @property
    def ultimate_gain(self) -> float:
        """Ku [V/um]."""
        return 1.0 / self.gain_um_per_V

    @property
    def ultimate_period_s(self) -> float:
        """Tu [s]."""
        return 1.0 / self.freq_hz


def relay_point(u_V: np.ndarray, y_um: np.ndarray, rate_hz: float, amplitude_V: float,
                latency_periods: int = 1, min_cycles: int = 5) -> RelayPoint:
    """The ultimate point of one axis from a relay experiment's samples: ``u_V`` the
    voltage applied at each sample, ``y_um`` the position measured at it (uniformly
    sampled at ``rate_hz``, the oscillation settled), ``amplitude_V`` the relay's.
    The period is the mean spacing of the relay's upward switches; G = Y1 / U1, the
    ratio of the first harmonics over the whole cycles between the first and the last
    upward switch, times the latency's e^(-j w L T) (a command is computed L periods
    before it applies; the phase is kept unwrapped). ModelError when there is no
    sustained oscillation."""
    u, y = np.asarray(u_V, float), np.asarray(y_um, float)
    if u.shape != y.shape or u.ndim != 1 or not np.all(np.isfinite(u) & np.isfinite(y)):
        raise ModelError("relay: voltage and position must be finite, one sample each")
    up = np.nonzero(np.diff(u) > amplitude_V)[0] + 1   # a switch moves by 2 x amplitude
    if up.size < min_cycles + 1:
        raise ModelError(f"relay: {max(up.size - 1, 0)} oscillation cycle(s), need "
                         f"{min_cycles}: no sustained oscillation (relay amplitude too "
                         "small for the sensor noise, or the loop is not closed)")
    n = int(up[-1] - up[0])
    m = int(up.size - 1)
    k = np.arange(n)
    omega = 2 * math.pi * m / n                       # rad per sample
    basis = np.exp(-1j * omega * k)
    U1 = np.dot(u[up[0]:up[-1]] - u[up[0]:up[-1]].mean(), basis)
    Y1 = np.dot(y[up[0]:up[-1]] - y[up[0]:up[-1]].mean(), basis)
    if abs(U1) == 0 or abs(Y1) == 0:
        raise ModelError("relay: no first harmonic in the oscillation")
    G = Y1 / U1  # the stage's own response, applied voltage to measured position
    # the loop's phase: the stage's (a lag within a turn) and the latency's, unwrapped:
    # with a latency of L periods the relay can also settle in an odd harmonic mode
    # (period 2L / (2n + 1)), where the loop's phase is -180 - n x 360 deg
    phase = math.degrees(math.atan2(G.imag, G.real)) - math.degrees(omega * latency_periods)
    return RelayPoint(omega * rate_hz / (2 * math.pi), float(abs(G)), phase,
                      float(2 * abs(Y1) / n), m, int(latency_periods))


def tune_relay(points: Doc, rate_hz: float = 1000.0, phase_margin_deg: float = 60.0,
               gain_margin_db: float = 10.0, max_noise_gain: float = 0.3,
               source: str = "relay experiment") -> Tuning:
    """PI gains from relay experiments (``points``: axis -> RelayPoint). Each axis's
    loop is modelled as a gain with a pure delay, |G| e^(-j w tau), through its
    measured ultimate point (tau = -arg G / w_u), then tuned by the same discrete loop
    shaping as ``tune``. The gain is the small-signal gain at the experiment's
    operating point; the gain margin covers branches steeper than that."""
    if not points:
        raise ModelError("tune: no relay point")
    if not (rate_hz > 0 and 0 < phase_margin_deg < 90 and gain_margin_db > 0):
        raise ModelError("tune: rate > 0, 0 < phase margin < 90 deg and gain margin > 0 dB")
    T = 1.0 / rate_hz
    w = np.concatenate([np.geomspace(1e-4, math.pi * 0.999, 1500), [math.pi]])
    plants, gains, lines = {}, {}, []
    for a, p in sorted(points.items()):
        wu = 2 * math.pi * p.freq_hz * T
        tau = -math.radians(p.phase_deg) / wu        # periods
        plants[a] = p.gain_um_per_V * np.exp(-1j * w * tau)
        gains[a] = (p.gain_um_per_V, p.gain_um_per_V)
        lines.append(f"relay {a}: oscillation {p.freq_hz:.1f} Hz (Tu {1e3 / p.freq_hz:.2f} "
                     f"ms) over {p.cycles} cycles, amplitude {p.amplitude_um:.3f} um, "
                     f"Ku {p.ultimate_gain:.3f} V/um, loop phase {p.phase_deg:.1f} deg "
                     f"with {p.latency_periods} period(s) of latency: modelled as "
                     f"{p.gain_um_per_V:.3f} um/V with a {tau:.2f}-period delay")
    method = ("PI on a relay experiment (Astrom-Hagglund ultimate point per axis, the "
              "loop modelled as gain + delay through it)")
    return _shape(plants, w, T, phase_margin_deg, gain_margin_db, max_noise_gain, gains,
                  method, source, "\n".join(lines))


def _noise_gain(Lw: np.ndarray, w: np.ndarray) -> float:
    """RMS of the white sensor noise the loop passes to the true position, per unit
    noise RMS: sqrt(mean |T|^2) over (0, pi) (the grid is log-spaced, so weighted)."""
    T2 = np.abs(Lw / (1 + Lw)) ** 2
    return math.sqrt(float(np.trapezoid(T2, w)) / math.pi)


def _bandwidth(Lw: np.ndarray, w: np.ndarray) -> float:
    Tw = np.abs(Lw / (1 + Lw))
    below = np.nonzero(Tw < 1 / math.sqrt(2))[0]
    return w[below[0]] if below.size else w[-1]
