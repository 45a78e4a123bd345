"""Diagnostic excitation for the sim-to-real gap (``piezo-stage excite --protocol gap``).

Per axis, the other held at its lower limit: sines over a range of frequencies (rate
and dynamics effects), steps with multi-second holds up and down (creep follows the
step's sign, drift does not), variable amplitudes (minor loops); then the other axis
alone (coupling shows on the idle axis). Voltages in [lo, hi]; the seed varies the
amplitudes and step levels so FIT and HOLDOUT can be two different records.

The protocol ends each axis's sines with a small linear chirp about mid-stroke, from
20 Hz to 0.4 x the sample rate, ``chirp_s`` long (CHIRP_S by default; 0 leaves it out:
``excite --chirp 0``): the slow blocks cannot tell a resonance above the control rate
from a pure delay (both only lag the slow motion), the chirp passes through the
resonance and shows its peak (the gap diagnosis seeds its resonance search there).

``nested=True`` (``excite --nested``) adds, after the sines, the minor loops that show
a hysteresis's memory: 1 Hz sines from the lower limit at 100, 66 and 33 % of the span
(the paper's 60/40/20 um experiment), then loops inside the major one on its falling
branch (between 90 and 50 %) and on its rising branch (between 20 and 60 %); about
11 s more per axis. A law with return-point memory closes each of them where it
began; our Duhem law does not.
"""

from __future__ import annotations

import numpy as np

SINES = ((1.0, 2, 1.0), (5.0, 5, 0.7), (20.0, 10, 0.5), (80.0, 16, 0.25))  # Hz, cycles, amp
CHIRP_S = 2.0  # s per axis: enough to resolve a resonance's peak (0.8 kHz, zeta 0.05)


def gap_protocol(fs_hz: float = 5000.0, lo: float = 0.0, hi: float = 150.0, seed: int = 0,
                 hold_s: float = 3.0, chirp_s: float = CHIRP_S,
                 chirp_frac: float = 0.015,
                 nested: bool = False) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Returns (t [s], vx [V], vy [V]); about 36 s at the defaults (31.6 s, plus
    2 x (chirp_s + 0.2 s) for the chirps of +-chirp_frac of the span; ``nested``: 22 s
    more, see the module docstring)."""
    rng = np.random.default_rng(seed)
    span = hi - lo
    dt = 1.0 / fs_hz

    def ramp_to(a: float, b: float, s: float = 0.1) -> np.ndarray:
        n = max(2, int(s * fs_hz))
        return a + (b - a) * (1 - np.cos(np.linspace(0, np.pi, n))) / 2

    def axis_block() -> np.ndarray:
        parts = []
        for f, cyc, amp in SINES:
            a = amp * rng.uniform(0.85, 1.0)
            t = np.arange(int(cyc * fs_hz / f)) * dt
            parts.append(lo + span * a / 2 * (1 - np.cos(2 * np.pi * f * t)))
        if nested:
            t = np.arange(int(2 * fs_hz)) * dt  # two cycles at 1 Hz each
            for frac in (1.0, 0.66, 0.33):
                a = frac * rng.uniform(0.9, 1.0)
                parts.append(lo + span * a / 2 * (1 - np.cos(2 * np.pi * t)))
            for top, bottom, start in ((0.9, 0.5, "top"), (0.6, 0.2, "bottom")):
                hi_v, lo_v = lo + span * top, lo + span * bottom
                first = hi_v if start == "top" else lo_v
                parts.append(ramp_to(parts[-1][-1], first, 0.5))
                mid, half = (hi_v + lo_v) / 2, (hi_v - lo_v) / 2
                sign = 1.0 if start == "top" else -1.0
                parts.append(mid + sign * half * np.cos(2 * np.pi * t))
            parts.append(ramp_to(parts[-1][-1], lo, 0.5))
        if chirp_s > 0:
            mid = lo + span / 2
            parts.append(ramp_to(lo, mid, 0.1))
            t = np.arange(int(chirp_s * fs_hz)) * dt
            f0, f1 = 20.0, 0.4 * fs_hz
            ph = 2 * np.pi * (f0 * t + (f1 - f0) * t * t / (2 * chirp_s))
            taper = np.minimum(1.0, np.minimum(t, chirp_s - t) / 0.05)
            parts.append(mid + span * chirp_frac * rng.uniform(0.85, 1.0) * taper * np.sin(ph))
            parts.append(ramp_to(mid, lo, 0.1))
        levels = lo + span * np.array([rng.uniform(0.55, 0.75), rng.uniform(0.15, 0.3),
                                       rng.uniform(0.8, 0.95), 0.0])
        cur = lo
        for L in levels:
            # 50 ms edges: a full-stroke step asks ~5 kV/s at most, under the 80 Hz
            # sine's 9 kV/s (20 ms asked 12 kV/s: a command step of 10.5 V per 1 ms
            # sample, which a 1e5 V/s amplifier spreads over two of its own steps, and
            # the hysteresis path with it: a shape the sampled model cannot follow)
            parts.append(ramp_to(cur, L, 0.05))
            parts.append(np.full(int(hold_s * fs_hz), L))
            cur = L
        return np.concatenate(parts)

    bx = axis_block()
    by = axis_block()
    vx = np.concatenate([bx, np.full(by.size, lo)])
    vy = np.concatenate([np.full(bx.size, lo), by])
    t = np.arange(vx.size) * dt
    return t, vx, vy
