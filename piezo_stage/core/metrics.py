"""Figures of merit on records: errors, noise floor, hysteresis loop shape."""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike

from piezo_stage.core.types import Doc


def rms(x: ArrayLike) -> float:
    """Root mean square of ``x`` (0 for an empty array)."""
    x = np.asarray(x, float)
    return float(np.sqrt(np.mean(x * x))) if x.size else float("nan")


def error_figures(w_meas: ArrayLike, w_model: ArrayLike) -> Doc:
    """RMS and max error [um], and RMS as % of the measured displacement range."""
    e = np.asarray(w_model, float) - np.asarray(w_meas, float)
    span = float(np.ptp(w_meas)) if np.size(w_meas) else 0.0
    r = rms(e)
    return {"rms_um": r, "max_err_um": float(np.max(np.abs(e))) if e.size else float("nan"),
            "rms_pct": 100.0 * r / span if span > 0 else float("nan"), "range_um": span}


def noise_floor(w: ArrayLike) -> float:
    """White-noise RMS [um] estimated from the data alone.

    Third differences of a smooth signal sampled finely are tiny, while those of white
    noise of variance s^2 have variance 20 s^2. A median-based scale (MAD) ignores the
    few samples at turning points and steps. Valid when the signal's own content is
    well below the sampling rate (true for hysteresis records at kHz rates).
    """
    w = np.asarray(w, float)
    if w.size < 8:
        return float("nan")
    d3 = np.diff(w, 3)
    mad = np.median(np.abs(d3 - np.median(d3)))
    return float(1.4826 * mad / np.sqrt(20.0))


def loop_figures(v: ArrayLike, w: ArrayLike) -> Doc:
    """Shape of one periodic hysteresis loop (pass exactly one cycle).

    Returns range, the widest vertical opening between the branches (and as % of the
    range), and the opening at mid-voltage.
    """
    v = np.asarray(v, float)
    w = np.asarray(w, float)
    dv = np.diff(v, prepend=v[0])
    up = dv > 0
    down = dv < 0
    if up.sum() < 3 or down.sum() < 3:
        return {"range_um": float(np.ptp(w)), "max_width_um": float("nan"),
                "max_width_pct": float("nan"), "mid_width_um": float("nan")}
    lo, hi = v.min(), v.max()
    grid = np.linspace(lo + 0.02 * (hi - lo), hi - 0.02 * (hi - lo), 201)

    def branch(mask: np.ndarray) -> np.ndarray:
        o = np.argsort(v[mask])
        return np.interp(grid, v[mask][o], w[mask][o])

    width = branch(down) - branch(up)
    span = float(np.ptp(w))
    i = int(np.argmax(np.abs(width)))
    return {"range_um": span, "max_width_um": float(width[i]),
            "max_width_pct": 100.0 * float(width[i]) / span if span else float("nan"),
            "max_width_at_V": float(grid[i]), "mid_width_um": float(width[100])}


class LatencyHistogram:
    """Whole-run percentiles of a latency at fixed cost: 10 us bins up to ``top_s``
    (beyond it, the last bin), one integer increment per sample, bounded memory."""

    def __init__(self, bin_s: float = 1e-5, top_s: float = 0.1) -> None:
        self.bin = float(bin_s)
        self.counts = [0] * (int(top_s / bin_s) + 1)
        self.n, self.max_s = 0, 0.0

    def add(self, x_s: float) -> None:
        """Count one latency ``x_s`` [s] (negative counts as 0)."""
        k = int(x_s / self.bin) if x_s > 0 else 0
        self.counts[min(k, len(self.counts) - 1)] += 1
        self.n += 1
        if x_s > self.max_s:
            self.max_s = x_s

    def percentile(self, q: float) -> float:
        """The q-th percentile [s] (upper edge of its bin); 0 when empty."""
        if not self.n:
            return 0.0
        want, run = q / 100.0 * self.n, 0
        for k, c in enumerate(self.counts):
            run += c
            if run >= want:
                return (k + 1) * self.bin
        return self.max_s
