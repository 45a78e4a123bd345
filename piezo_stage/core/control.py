"""Control laws: discrete PID and the composite law (feedforward + feedback).

Units: errors in um, voltages in V, so gains are V/um (P), V/(um s) (I), V s/um (D).
The composite law follows the seed's eq. 17-19: the inverse-model feedforward voltage
plus a PID correction of the measured error. Cross-coupling is compensated in the
feedforward by the joint inverse of the 2-axis model (StageInverse), which is the
exact form of the seed's decoupler (eqs. 15-16) when the model holds the coupling.
"""

from __future__ import annotations

from dataclasses import dataclass

from piezo_stage.core.errors import ConfigError


@dataclass
class PIDGains:
    kp: float = 0.2        # V/um
    ki: float = 150.0      # V/(um s)
    kd: float = 0.0        # V s/um
    d_filter_hz: float = 200.0  # first-order filter on the derivative term
    i_limit_V: float = 30.0     # anti-windup: |integral contribution| <= this

    def __post_init__(self):
        for k in ("kp", "ki", "kd", "i_limit_V"):
            if getattr(self, k) < 0:
                raise ConfigError(f"PID {k} must be >= 0")
        if self.d_filter_hz <= 0:
            raise ConfigError("PID d_filter_hz must be > 0")


class PID:
    """Discrete PID on the error (backward Euler integral, filtered derivative,
    clamped integral). Explicit state; ``reset`` clears it."""

    def __init__(self, gains: PIDGains, dt: float):
        if not dt > 0:
            raise ConfigError("PID dt must be > 0")
        self.g = gains
        self.dt = float(dt)
        self.reset()

    def reset(self):
        self.integral = 0.0
        self.prev_e = None
        self.d = 0.0

    def update(self, e: float, hold_integral: bool = False) -> float:
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


def composite(v_ff: float, e_um: float, pid: PID, limits=(0.0, 150.0)) -> tuple[float, bool]:
    """v = v_ff + PID(e), clamped to the limits; the integral holds while saturated
    in the direction of the error (conditional integration). Returns (v, clamped)."""
    lo, hi = limits
    u = v_ff + pid.g.kp * e_um + pid.integral
    pushing_out = (u >= hi and e_um > 0) or (u <= lo and e_um < 0)
    v = v_ff + pid.update(e_um, hold_integral=pushing_out)
    clamped = v > hi or v < lo
    return min(max(v, lo), hi), clamped
