"""A hysteresis that is not our model class: a Prandtl-Ishlinskii law (play operators)
with a non-polynomial output envelope, for the simulated stage's ``hysteresis`` option.

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

from dataclasses import dataclass

import numpy as np

from piezo_stage.core._jit import play_run
from piezo_stage.core.errors import ConfigError

KEYS = ("kind", "axes", "operators", "max_threshold_V", "weight_um_per_V", "decay_V",
        "envelope")


@dataclass
class PlayHysteresis:
    """The law with its parameters (see the module docstring); ``z`` is its state."""

    thresholds_V: np.ndarray
    weights_um_per_V: np.ndarray
    scale_um: float
    width_um: float
    centre_um: float

    @classmethod
    def from_params(cls, params: dict, where: str = "hysteresis") -> PlayHysteresis:
        """From a plant file's ``hysteresis`` block; ConfigError naming the key."""
        unknown = set(params) - set(KEYS)
        if unknown:
            raise ConfigError(f"{where}: unknown key(s) {sorted(unknown)}")
        if params.get("kind", "prandtl-ishlinskii") != "prandtl-ishlinskii":
            raise ConfigError(f"{where}.kind: only 'prandtl-ishlinskii' is known")

        def num(d, key, default, lo, hi, w=where):
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
        r = np.linspace(0.0, top, n)
        return cls(r, w0 * np.exp(-r / decay), a, b, c)

    def rest(self, v0: float = 0.0) -> np.ndarray:
        """The operators' state at rest at ``v0`` [V]."""
        return np.full(self.thresholds_V.size, float(v0))

    def run(self, v: np.ndarray, z: np.ndarray) -> np.ndarray:
        """Displacement [um] over ``v`` [V] from state ``z`` (updated in place)."""
        x = np.empty(v.size)
        play_run(np.ascontiguousarray(v, dtype=float), self.thresholds_V,
                 self.weights_um_per_V, z, x)
        return self.envelope(x)

    def envelope(self, x: np.ndarray) -> np.ndarray:
        """The static output bend [um] of the operators' sum ``x`` [um]."""
        return x + self.scale_um * np.tanh((x - self.centre_um) / self.width_um)
