"""Desired trajectories [um] as sampled (t, wx, wy) arrays.

Kinds: sine, variable-amplitude sine (the seed's 60/40/20 um cycles), steps, triangle,
from CSV (t,wx,wy), and the seed's preset y(t) = 21 + 24 sin(2 pi f t - pi/2) um on
both axes (seed section 4.3, f = 10 Hz by default).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from piezo_stage.core.errors import ConfigError

KINDS = ("sine", "variable_sine", "steps", "triangle", "seed", "csv")


MAX_POINTS = 200_000  # the feedforward's max_trajectory_points default


def generate(kind: str = "seed", duration_s: float = 1.0, dt_s: float = 1e-3,
             frequency_hz: float = 10.0, center_um: float = 21.0, amplitude_um: float = 24.0,
             axes: Sequence[str] = ("x", "y"),
             step_levels_um: Sequence[float] = (10.0, 40.0, 25.0, 55.0),
             table: dict | None = None) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """Returns (t [s], {axis: w [um]}) sampled every dt_s over duration_s. Kind ``csv``
    takes ``table``: {"t", "wx", "wy"} arrays, as the caller read them (io.csv_table)."""
    if kind not in KINDS:
        raise ConfigError(f"unknown trajectory kind {kind!r}; use one of {', '.join(KINDS)}")
    if kind == "csv":
        if table is None:
            raise ConfigError("trajectory kind csv needs a table (t, wx, wy)")
        t = np.asarray(table["t"], float)
        return t - t[0], {"x": np.asarray(table["wx"], float),
                          "y": np.asarray(table["wy"], float)}
    if not (duration_s > 0 and dt_s > 0 and frequency_hz > 0):
        raise ConfigError("duration_s, dt_s and frequency_hz must be > 0")
    # what a sampled loop can follow: two points a period at least, and a trajectory
    # the feedforward takes (its max_trajectory_points default)
    if frequency_hz * dt_s > 0.5:
        raise ConfigError(f"frequency_hz {frequency_hz:g} is above the point rate's "
                          f"Nyquist frequency {0.5 / dt_s:g} Hz (dt_s {dt_s:g} s)")
    if duration_s / dt_s > MAX_POINTS:
        raise ConfigError(f"{duration_s:g} s at dt_s {dt_s:g} s is "
                          f"{duration_s / dt_s:.0f} points, more than {MAX_POINTS}")
    t = np.arange(int(round(duration_s / dt_s)) + 1) * dt_s
    ph = 2 * np.pi * frequency_hz * t
    if kind == "seed":
        w = 21.0 + 24.0 * np.sin(ph - np.pi / 2)
    elif kind == "sine":
        w = center_um + amplitude_um * np.sin(ph - np.pi / 2)
    elif kind == "variable_sine":
        # seed section 4.3: cycles peaking at 60, 40, 20 um (from 0), repeating
        peaks = np.array([60.0, 40.0, 20.0]) * amplitude_um / 24.0 * 0.5
        cyc = np.floor(frequency_hz * t).astype(int) % 3
        w = peaks[cyc] * (1 - np.cos(ph))
    elif kind == "triangle":
        frac = (frequency_hz * t) % 1.0
        w = center_um - amplitude_um + 2 * amplitude_um * (1 - np.abs(2 * frac - 1))
    else:  # steps, one level per period
        lv = np.asarray(step_levels_um, float)
        w = lv[np.floor(frequency_hz * t).astype(int) % lv.size]
    return t, {a: w.copy() for a in axes}
