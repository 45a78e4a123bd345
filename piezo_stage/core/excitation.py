"""Diagnostic excitation for the sim-to-real gap (``piezo-stage excite --protocol gap``).

Per axis, the other held at its lower limit: sines over a range of frequencies (rate
and dynamics effects), steps with multi-second holds up and down (creep follows the
step's sign, drift does not), variable amplitudes (minor loops); then the other axis
alone (coupling shows on the idle axis). Voltages in [lo, hi]; the seed varies the
amplitudes and step levels so FIT and HOLDOUT can be two different records.

``chirp_s`` > 0 (``excite --chirp 2``) adds, per axis, a small linear chirp about
mid-stroke from 20 Hz to 0.4 x the sample rate: the slow blocks cannot tell a
resonance above the control rate from a pure delay (both only lag the slow motion),
the chirp passes through the resonance and shows its peak (the gap diagnosis seeds
its resonance search there).
"""

from __future__ import annotations

import numpy as np

SINES = ((1.0, 2, 1.0), (5.0, 5, 0.7), (20.0, 10, 0.5), (80.0, 16, 0.25))  # Hz, cycles, amp


def gap_protocol(fs_hz: float = 5000.0, lo: float = 0.0, hi: float = 150.0, seed: int = 0,
                 hold_s: float = 3.0, chirp_s: float = 0.0,
                 chirp_frac: float = 0.015) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Returns (t [s], vx [V], vy [V]); about 35 s at the defaults (plus 2 x (chirp_s
    + 0.2 s) with a chirp of +-chirp_frac of the span)."""
    rng = np.random.default_rng(seed)
    span = hi - lo
    dt = 1.0 / fs_hz

    def ramp_to(a, b, s=0.1):
        n = max(2, int(s * fs_hz))
        return a + (b - a) * (1 - np.cos(np.linspace(0, np.pi, n))) / 2

    def axis_block():
        parts = []
        for f, cyc, amp in SINES:
            a = amp * rng.uniform(0.85, 1.0)
            t = np.arange(int(cyc * fs_hz / f)) * dt
            parts.append(lo + span * a / 2 * (1 - np.cos(2 * np.pi * f * t)))
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
            parts.append(ramp_to(cur, L, 0.02))
            parts.append(np.full(int(hold_s * fs_hz), L))
            cur = L
        return np.concatenate(parts)

    bx = axis_block()
    by = axis_block()
    vx = np.concatenate([bx, np.full(by.size, lo)])
    vy = np.concatenate([np.full(bx.size, lo), by])
    t = np.arange(vx.size) * dt
    return t, vx, vy
