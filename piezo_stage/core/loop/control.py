"""Control laws: discrete PID and the composite law (feedforward + feedback).

Units: errors in um, voltages in V, so gains are V/um (P), V/(um s) (I), V s/um (D).
The composite law follows the paper's eq. 17-19: the inverse-model feedforward voltage
plus a PID correction of the measured error. Cross-coupling is compensated in the
feedforward by the joint inverse of the 2-axis model (StageInverse), which is the
exact form of the paper's decoupler (eqs. 15-16) when the model holds the coupling.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

from piezo_stage.core.errors import ConfigError
from piezo_stage.core.loop.stamps import SampleGuard
from piezo_stage.core.params import Param, Schema
from piezo_stage.core.types import Params, PerAxis

# the real-time priority of a loop node that answers samples (the controller's and the
# feedforward's: the driver's own sample loop runs above them)
THREAD_PRIORITY = Param("thread_priority", 45, "real time: SCHED_FIFO priority (0: leave the "
                        "scheduler alone; lockstep never changes it)", lo=0, hi=99)

# the controller node's parameters (core/params.py: the node declares them from here,
# the launcher checks a parameter file against them); the gains and ``feedback`` are
# live (they take effect at run time)
PARAMETERS: Schema = (
    Param("control_rate_hz", 1000.0, "control rate [Hz]", lo=1.0, hi=1e5),
    Param("kp", 0.2, "proportional gain [V/um]", lo=0.0, hi=100.0, live=True),
    Param("ki", 150.0, "integral gain [V/(um s)]", lo=0.0, hi=1e5, live=True),
    Param("kd", 0.0, "derivative gain [V s/um]", lo=0.0, hi=10.0, live=True),
    Param("integral_limit_V", 30.0,
          "|integral contribution| <= this [V] (feedback only: the whole voltage span)",
          lo=0.0, hi=1000.0),
    Param("feedback", True,
          "PID on (false: feedforward only); switches bumplessly",
          live=True),
    Param("voltage_limits_V", [0.0, 150.0], "clamp [V]"),
    Param("relay_amplitude_V", 0.0,
          "relay experiment (tune --relay): the feedback is a relay of this amplitude [V]; "
          "0: PID",
          lo=0.0, hi=75.0),
    Param("relay_hysteresis_um", 0.0,
          "relay experiment: its hysteresis band [um] (0 unless noise makes it chatter)",
          lo=0.0, hi=50.0),
    THREAD_PRIORITY,
    Param("min_subscribers", 0, "command subscribers to wait for"),
)


@dataclass
class PIDGains:
    """PID gains and the derivative filter and integral limit."""
    kp: float = 0.2        # V/um
    ki: float = 150.0      # V/(um s)
    kd: float = 0.0        # V s/um
    d_filter_hz: float = 200.0  # first-order filter on the derivative term
    i_limit_V: float = 30.0     # anti-windup: |integral contribution| <= this

    def __post_init__(self) -> None:
        for k in ("kp", "ki", "kd", "i_limit_V"):
            if getattr(self, k) < 0:
                raise ConfigError(f"PID {k} must be >= 0")
        if self.d_filter_hz <= 0:
            raise ConfigError("PID d_filter_hz must be > 0")


class PID:
    """Discrete PID on the error (backward Euler integral, filtered derivative,
    clamped integral). Explicit state; ``reset`` clears it."""

    def __init__(self, gains: PIDGains, dt: float) -> None:
        if not dt > 0:
            raise ConfigError("PID dt must be > 0")
        self.g = gains
        self.dt = float(dt)
        self.reset()

    def reset(self) -> None:
        """Forget the integral and the derivative's memory."""
        self.integral = 0.0
        self.prev_e: float | None = None
        self.d = 0.0

    def update(self, e: float, hold_integral: bool = False) -> float:
        """The PID output [V] for error ``e`` [um]; the integral holds when asked."""
        g = self.g
        if not hold_integral:
            self.integral += g.ki * e * self.dt
            self.integral = max(-g.i_limit_V, min(g.i_limit_V, self.integral))
        if self.prev_e is not None and g.kd > 0:
            raw = (e - self.prev_e) / self.dt
            a = self.dt / (self.dt + 1.0 / (2 * 3.141592653589793 * g.d_filter_hz))
            self.d += a * (raw - self.d)
        self.prev_e = e
        return g.kp * e + self.integral + g.kd * self.d


class CompositeAxis:
    """One axis of the composite law with the safeguards a running stage needs.

    ``update(v_ff, e_um, active)`` returns (v, clamped). The feedback acts only while
    ``active`` (the driver applies our commands and they come back as applied, and the
    reference is fresh); otherwise the output is the feedforward alone and the
    integral holds. Conditional integration stops windup while the output is clamped.
    Switching feedback off (``set_feedback(False)``) fades its last contribution out
    with time constant ``fade_s`` instead of dropping it; switching it on starts the
    integral so that the output does not jump (bumpless transfer both ways).
    """

    def __init__(self, pid: PID, limits: tuple[float, float] = (0.0, 150.0),
                 feedback: bool = True, fade_s: float = 0.05) -> None:
        self.pid, self.limits = pid, tuple(limits)
        self.feedback = bool(feedback)
        self.fade = math.exp(-pid.dt / fade_s) if fade_s > 0 else 0.0
        self.carry = 0.0        # feedback output being faded out after a switch-off
        self.last_fb = 0.0      # the feedback contribution of the last update [V]
        self._bump_e: bool | None = None  # switch-on: take the first error without a step

    def set_feedback(self, on: bool) -> None:
        """Switch the feedback on or off, bumplessly."""
        on = bool(on)
        if on and not self.feedback:
            self.pid.reset()
            self._bump_e = True
        elif not on and self.feedback:
            self.carry += self.last_fb
            self.last_fb = 0.0
        self.feedback = on

    def reset(self) -> None:
        """Loop opened (disarmed, faulted, stale): forget the integral and the fade."""
        self.pid.reset()
        self.carry = self.last_fb = 0.0

    def update(self, v_ff: float, e_um: float, active: bool,
               hold: bool = False) -> tuple[float, bool]:
        """``active``: feedback acts; ``hold``: the integral holds (the loop is not
        closed: our last command did not come back as applied)."""
        lo, hi = self.limits
        self.carry *= self.fade
        if not (self.feedback and active):
            u = v_ff + self.carry
            return min(max(u, lo), hi), (u > hi or u < lo)
        if self._bump_e:  # switch-on: the integral absorbs the proportional step
            self._bump_e = None
            self.pid.integral = -self.pid.g.kp * e_um + self.carry
            self.carry = 0.0
        u_try = v_ff + self.carry + self.pid.g.kp * e_um + self.pid.integral
        pushing_out = (u_try >= hi and e_um > 0) or (u_try <= lo and e_um < 0)
        self.last_fb = self.pid.update(e_um, hold_integral=pushing_out or hold)
        u = v_ff + self.carry + self.last_fb
        return min(max(u, lo), hi), (u > hi or u < lo)


class Relay:
    """Relay feedback for an autotuning experiment (Astrom and Hagglund): the output is
    ``bias + amplitude`` while the error is above ``+hysteresis`` and ``bias -
    amplitude`` below ``-hysteresis`` (it keeps its side in between, so sensor noise
    does not chatter it). A loop closed through it oscillates where its phase is -180
    deg (less asin(hysteresis / error amplitude)): the ultimate point.

    The bias adapts, so the oscillation straddles the asked position however far off
    the feedforward's hold voltage is: it integrates the error slowly (``bias_gain``
    [V/(um s)]: centres the oscillation) plus the relay's own side (``bias_rate`` [1/s]:
    moves by bias_rate x amplitude V/s towards the side the relay dwells on). The error
    term alone approaches zero error from one side without ever crossing it (the
    relay would never switch) and can rest inside the hysteresis band; the side term
    keeps moving until the relay switches, as long as bias_gain x hysteresis <
    bias_rate x amplitude. Both act over many oscillation periods, so they barely move
    the point measured."""

    def __init__(self, amplitude_V: float, hysteresis_um: float, dt: float,
                 bias_gain: float = 20.0, bias_rate: float = 5.0,
                 bias_limit_V: float = 150.0) -> None:
        if not (amplitude_V > 0 and hysteresis_um >= 0 and dt > 0 and bias_gain >= 0
                and bias_rate > 0):
            raise ConfigError("relay: amplitude > 0 V, hysteresis >= 0 um, dt > 0, "
                              "bias gain >= 0, bias rate > 0")
        self.d, self.eps, self.dt = float(amplitude_V), float(hysteresis_um), float(dt)
        self.bias_gain, self.bias_rate = float(bias_gain), float(bias_rate)
        self.bias_limit = float(bias_limit_V)
        self.reset()

    def reset(self) -> None:
        """Start again on the upper side with no bias."""
        self.side = 1.0
        self.bias = 0.0

    def update(self, e_um: float) -> float:
        """The relay's output [V] (added to the feedforward) for error ``e_um``."""
        if e_um > self.eps:
            self.side = 1.0
        elif e_um < -self.eps:
            self.side = -1.0
        self.bias += (self.bias_gain * e_um + self.bias_rate * self.side * self.d) * self.dt
        self.bias = max(-self.bias_limit, min(self.bias_limit, self.bias))
        return self.bias + self.side * self.d


def clamp_slew(v: PerAxis[float], prev: PerAxis[float],
               limits: tuple[float, float] | PerAxis[tuple[float, float]],
               max_step: float | PerAxis[float]) -> tuple[PerAxis[float], bool]:
    """Clamp each axis's voltage to ``limits`` (V: (lo, hi), or per axis {axis: (lo,
    hi)}), then move it from ``prev`` by at most ``max_step`` (V, or per axis).
    Returns (voltages, whether anything was limited). The driver's last line of
    defence, and the supervisor's ramp to the safe voltage."""
    amplifier_step = _AMPLIFIER_STEP or _amplifier_step()
    out, hit = {}, False
    for a, x in v.items():
        lo, hi = limits[a] if isinstance(limits, dict) else limits
        step = max_step[a] if isinstance(max_step, dict) else max_step
        out[a], h = amplifier_step(float(x), float(prev[a]), float(lo), float(hi),
                                   float(step))
        hit |= bool(h)
    return out, hit


_AMPLIFIER_STEP: Callable[..., tuple[float, bool]] | None = None


def _amplifier_step() -> Callable[..., tuple[float, bool]]:
    """The one clamp-and-slew formula (the plant's amplifier kernel), imported once:
    an import statement in ``clamp_slew`` cost most of its time (2.0 against 1.3 us a
    call here), and the driver calls it every sample. Imported on first use:
    the controller alone needs no compiled kernels."""
    global _AMPLIFIER_STEP
    from piezo_stage.core.model._kernels import amplifier_step
    _AMPLIFIER_STEP = amplifier_step
    return amplifier_step


STALL_TICKS = 10  # references further apart than this: a stall, the integral restarts
COUNTS = ("commands", "clamped", "bad_messages", "late_dropped", "not_closed",
          "non_finite", "restarts", "stray_stamps")


class CompositeController:
    """The controller node's per-sample work (the paper's eq. 17-19): for each
    reference, stamped for a target sample ``ns`` and answering the sample ``t_k`` just
    measured, v = v_ff + PID(asked(t_k) - measured(t_k)) per axis, clamped to the
    voltage limits. The feedback acts only while the driver applies commands
    (``enabled``); the integral holds while the command sent for t_k did not come back
    as the voltage applied at t_k (the loop is not closed) and while the output is
    clamped; it restarts after a gap in the references (a stall). With a relay
    amplitude > 0 the feedback is a relay (core.control.Relay) under the same rules.
    ``on_sample`` is the one entry; ``stats`` its counts."""

    def __init__(self, p: Params) -> None:
        rate = p["control_rate_hz"]
        self.dt_ns = int(round(1e9 / rate))
        self.gains = PIDGains(kp=p["kp"], ki=p["ki"], kd=p["kd"],
                              i_limit_V=p["integral_limit_V"])
        self.limits = tuple(p["voltage_limits_V"])
        self.axes = {a: CompositeAxis(PID(self.gains, 1.0 / rate), self.limits,
                                      p["feedback"]) for a in ("x", "y")}
        relay_V, relay_eps = p["relay_amplitude_V"], p["relay_hysteresis_um"]
        self.relays = {a: Relay(relay_V, relay_eps, 1.0 / rate) for a in self.axes} \
            if relay_V > 0 else {}
        # target stamp -> (desired um, command V): for t_k's check
        self.sent: dict[int, tuple[PerAxis[float], PerAxis[float] | None]] = {}
        self.last_ns = -1
        self.stats = dict.fromkeys(COUNTS, 0)
        self.guard = SampleGuard(self.stats)  # what it drops before on_sample, counted

    @property
    def feedback(self) -> bool:
        """Whether the feedback acts (both axes switch together)."""
        return self.axes["x"].feedback

    def describe(self) -> str:
        """The law and its gains, for the node's diagnostics."""
        return (("relay experiment" if self.relays else "composite (feedback on)"
                 if self.feedback else "feedforward only (feedback off)")
                + ", kp {kp:g} ki {ki:g} kd {kd:g}".format(**vars(self.gains)))

    def set_gains(self, **gains: float) -> None:
        """New kp, ki or kd (PiezoStageError, nothing changed, when refused)."""
        g = dict(vars(self.gains))
        g.update({k: float(v) for k, v in gains.items()})
        new = PIDGains(**g)
        for k in ("kp", "ki", "kd"):  # one gains object shared by both axes' PIDs
            setattr(self.gains, k, getattr(new, k))

    def set_feedback(self, on: bool) -> None:
        """Feedback on or off, bumplessly."""
        for ax in self.axes.values():
            ax.set_feedback(bool(on))

    def on_sample(self, ns: int, t_k: int, desired: PerAxis[float], ff: PerAxis[float],
                  w: PerAxis[float],
                  applied: PerAxis[float], enabled: bool) -> PerAxis[float] | None:
        """The command {axis: V} for target ``ns``, from the reference (``desired``
        for ns, feedforward ``ff``, measured ``w`` and ``applied`` at t_k); None when
        the result is not finite (never sent)."""
        if self.last_ns >= 0 and ns - self.last_ns > STALL_TICKS * self.dt_ns:
            self.restart()  # a stall: what the integral knew is stale
        self.last_ns = ns
        if not enabled:
            self.restart(count=False)
        asked, sent = self.sent.pop(t_k, (w, None))
        closed = sent is not None and all(abs(sent[a] - applied[a]) < 1e-6 for a in sent)
        self.stats["not_closed"] += enabled and not closed
        v = {}
        lo, hi = self.limits
        for a, ax in self.axes.items():
            if self.relays and enabled:
                u = ff[a] + self.relays[a].update(asked[a] - w[a])
                v[a], clamped = min(max(u, lo), hi), (u > hi or u < lo)
            else:
                v[a], clamped = ax.update(ff[a], asked[a] - w[a], enabled, hold=not closed)
            self.stats["clamped"] += clamped
        if not all(math.isfinite(x) for x in v.values()):
            self.stats["non_finite"] += 1
            self.restart(count=False)
            return None
        self.sent = {t: s for t, s in self.sent.items() if t > t_k}
        self.sent[ns] = (desired, v)
        self.stats["commands"] += 1
        return v

    def restart(self, count: bool = True) -> None:
        """Forget the integral and the relays' state (``count``: as a restart)."""
        self.stats["restarts"] += count
        for ax in self.axes.values():
            ax.reset()
        for relay in self.relays.values():
            relay.reset()
