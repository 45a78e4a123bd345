"""Desired trajectories [um] as sampled (t, wx, wy) arrays.

Kinds: sine, variable-amplitude sine (the paper's 60/40/20 um cycles), steps, triangle,
from CSV (t,wx,wy), the paper's preset y(t) = 21 + 24 sin(2 pi f t - pi/2) um on both
axes (the paper's section 4.3, f = 10 Hz by default), and ``raster``: the scan of a
microscope, a fast-axis triangle with rounded turnarounds and a slow-axis staircase or
ramp (:func:`raster`).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from piezo_stage.core.errors import ConfigError
from piezo_stage.core.types import Doc

KINDS = ("sine", "variable_sine", "steps", "triangle", "seed", "csv", "raster")


MAX_POINTS = 200_000  # the feedforward's max_trajectory_points default


def generate(kind: str = "seed", duration_s: float = 1.0, dt_s: float = 1e-3,
             frequency_hz: float = 10.0, center_um: float = 21.0, amplitude_um: float = 24.0,
             axes: Sequence[str] = ("x", "y"),
             step_levels_um: Sequence[float] = (10.0, 40.0, 25.0, 55.0),
             table: Doc | None = None,
             scan: Doc | None = None) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """Returns (t [s], {axis: w [um]}) sampled every dt_s over duration_s. Kind ``csv``
    takes ``table``: {"t", "wx", "wy"} arrays, as the caller read them (io.csv_table).
    Kind ``raster`` takes ``scan``: :func:`raster`'s keyword arguments (its line rate is
    ``frequency_hz``; its length is set by its lines, not by ``duration_s``)."""
    if kind not in KINDS:
        raise ConfigError(f"unknown trajectory kind {kind!r}; use one of {', '.join(KINDS)}")
    if kind == "csv":
        if table is None:
            raise ConfigError("trajectory kind csv needs a table (t, wx, wy)")
        t = np.asarray(table["t"], float)
        return t - t[0], {"x": np.asarray(table["wx"], float),
                          "y": np.asarray(table["wy"], float)}
    if kind == "raster":
        return raster(line_rate_hz=frequency_hz, dt_s=dt_s, **(scan or {}))
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
        # the paper's section 4.3: cycles peaking at 60, 40, 20 um (from 0), repeating
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


def rounded_triangle(phase: np.ndarray, corner: float) -> np.ndarray:
    """A triangle from 0 up to 1 and back over each unit of ``phase`` (0 at whole
    numbers), its turnarounds rounded: over the fraction ``corner`` of each line (the
    half period) around a turnaround the velocity turns over linearly, so the position
    there is a parabola and the velocity has no jump; in between it is exactly linear.

    Parameters
    ----------
    phase : numpy.ndarray
        Time in periods.
    corner : float
        The share of each line spent turning, in [0, 0.5].

    Returns
    -------
    numpy.ndarray
        The position, 0 at the lower and 1 at the upper turnaround.
    """
    if not 0.0 <= corner <= 0.5:
        raise ConfigError(f"corner {corner:g} must be in [0, 0.5] (a share of the line)")
    p = np.mod(np.asarray(phase, float), 1.0)
    p = np.where(p > 0.5, 1.0 - p, p)  # the retrace mirrors the trace
    h = corner * 0.25  # half the turning width, in periods
    c0 = 1.0 / (0.5 - h)  # the linear part's slope: the ends reach 0 and 1 exactly
    if h == 0.0:
        return c0 * p
    return np.where(p < h, c0 * p ** 2 / (2 * h),
                    np.where(p <= 0.5 - h, c0 * (p - h / 2),
                             1.0 - c0 * (0.5 - p) ** 2 / (2 * h)))


def raster(line_rate_hz: float = 20.0, lines: int = 16, size_um: Sequence[float] = (40.0, 40.0),
           center_um: Sequence[float] = (40.0, 40.0), corner: float = 0.1,
           slow: str = "steps", fast_axis: str = "x", dt_s: float = 1e-3
           ) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """A raster scan: the fast axis sweeps a triangle with rounded turnarounds (one trace
    and one retrace per line period, 1 / ``line_rate_hz``), the slow axis moves to the
    next line once per period, at the fast axis's lower turnaround (``slow="steps"``: a
    staircase whose steps are raised-cosine blends inside that turnaround, so the slow
    axis stands still while the fast one sweeps), or all the time (``"ramp"``).

    Parameters
    ----------
    line_rate_hz : float
        Line periods (trace and retrace) per second.
    lines : int
        Line periods in the scan, at least 2.
    size_um : sequence of float
        Scan size [fast, slow] [um].
    center_um : sequence of float
        Scan centre [fast, slow] [um].
    corner : float
        The share of each line spent turning around, in [0, 0.5].
    slow : str
        ``"steps"`` or ``"ramp"``.
    fast_axis : str
        ``"x"`` or ``"y"``.
    dt_s : float
        Point spacing [s].

    Returns
    -------
    tuple of (numpy.ndarray, dict)
        Time [s] from 0 and {axis: position [um]}, ``lines`` whole periods and the
        point that closes the last one.
    """
    if fast_axis not in ("x", "y") or slow not in ("steps", "ramp"):
        raise ConfigError("raster: fast_axis is x or y, slow is steps or ramp")
    if not (line_rate_hz > 0 and dt_s > 0 and int(lines) == lines and lines >= 2):
        raise ConfigError("raster: line_rate_hz and dt_s must be > 0, lines an integer >= 2")
    if line_rate_hz * dt_s > 0.5:
        raise ConfigError(f"raster: line rate {line_rate_hz:g} Hz is above the point "
                          f"rate's Nyquist frequency {0.5 / dt_s:g} Hz (dt_s {dt_s:g} s)")
    size, center = [float(x) for x in size_um], [float(x) for x in center_um]
    if len(size) != 2 or len(center) != 2 or min(size) < 0:
        raise ConfigError("raster: size_um and center_um are [fast, slow], sizes >= 0")
    n = int(round(lines / line_rate_hz / dt_s))
    if n + 1 > MAX_POINTS:
        raise ConfigError(f"raster: {lines} lines at {line_rate_hz:g} Hz and dt_s {dt_s:g} s "
                          f"is {n + 1} points, more than {MAX_POINTS}")
    t = np.arange(n + 1) * dt_s
    phase = line_rate_hz * t
    fast = center[0] - size[0] / 2 + size[0] * rounded_triangle(phase, corner)
    if slow == "ramp":
        level = np.minimum(phase / lines, 1.0)
    else:
        # the k-th step is taken inside the lower turnaround that ends line k:
        # a raised-cosine blend over the turning width, centred on phase k
        h = max(corner * 0.25, 0.5 * dt_s * line_rate_hz)
        k = np.floor(phase + h)
        into = np.clip((phase - (k - h)) / (2 * h), 0.0, 1.0)
        step = np.where(k >= 1, (1 - np.cos(np.pi * into)) / 2, 0.0)
        level = np.minimum((np.maximum(k - 1, 0) + step) / (lines - 1), 1.0)
    slow_w = center[1] - size[1] / 2 + size[1] * level
    other = "y" if fast_axis == "x" else "x"
    return t, {fast_axis: fast, other: slow_w}
