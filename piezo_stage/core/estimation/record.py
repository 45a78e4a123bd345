"""A measured or simulated record: time [s], voltages [V], displacements [um].

Records as labs have them are not always on one sample clock: a real-time run's bag
skips the ticks its host serviced late (the stamps stay on the sample clock, with
holes), a hardware logger's time stamps jitter, a file loses samples. Every analysis
(identification, the gap diagnosis, refits) runs its models one sample at a time on
one step, so such a record is put on a uniform grid first (``on_grid``), and says how
in one note:

* the grid's step is the record's median step, refined over the whole record with
  each step's missing samples counted (robust to jitter and to holes);
* a grid point between two samples is interpolated: the displacement linearly, the
  voltage linearly too, except where it is exactly what the actuator got
  (``voltage_exact``, our bags): a driver that skips ticks holds its output over them,
  so the voltage is held (zero-order hold) until the next sample. A skipped tick's
  interpolated displacement is no measurement: marked as a hole's samples are
  (below), it is left out of the fits (a jittered stamp measures its own tick);
* a hole of more than ``HOLE_SAMPLES`` missing samples is not bridged in silence: the
  record is split there into segments, which are fitted together on the one grid.
  Over the hole the voltage is held (or interpolated, as above) so the models' states
  run on across it; the displacement there was never measured, so those samples are
  marked (``measured`` False) and the fits leave them out (``fill_unmeasured``: fitted
  once, the hole filled with that fit's own prediction, fitted again).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import TypeVar

import numpy as np

from piezo_stage.core.errors import DataError
from piezo_stage.core.types import PerAxis

# Relative tolerance on sample spacing: CSV files round time stamps, DAQ clocks do not
# jitter at this level.
UNIFORM_RTOL = 1e-3
# Missing samples in a row that are still interpolated; a longer hole splits the
# record into segments (see the module docstring)
HOLE_SAMPLES = 10
# a grid more than this many times the record's own samples: not one sample clock
MAX_GRID_GROWTH = 4.0


@dataclass
class Record:
    """Columns of one run, all the same length N.

    Attributes
    ----------
    t : ndarray (N,)
        Time [s], strictly increasing; uniform unless said otherwise (``uniform``; the
        analyses take ``on_grid``'s record).
    v : dict axis -> ndarray (N,)
        Applied voltage [V] per axis present.
    w : dict axis -> ndarray (N,)
        Measured displacement [um] per axis present.
    measured : ndarray (N,) of bool, or None
        False where the displacement was not measured (inside a hole ``on_grid``
        kept as one); None: every sample measured.
    notes : list of str
        How the record was made from what was read (``on_grid``'s note).
    """

    t: np.ndarray
    v: PerAxis[np.ndarray] = field(default_factory=dict)
    w: PerAxis[np.ndarray] = field(default_factory=dict)
    source: str = "record"
    # True when v is exactly what the actuator got (the driver's applied voltage, as
    # in our bags); False for a voltage of unknown origin, possibly a noisy measurement
    voltage_exact: bool = False
    measured: np.ndarray | None = None
    notes: list = field(default_factory=list)

    def __post_init__(self) -> None:
        self.t = np.asarray(self.t, float)
        n = self.t.size
        for kind in (self.v, self.w):
            for a, x in list(kind.items()):
                x = np.asarray(x, float)
                if x.shape != (n,):
                    raise DataError(f"{self.source}: column {a} has {x.size} samples, "
                                    f"time has {n}")
                if not np.all(np.isfinite(x)):
                    i = int(np.flatnonzero(~np.isfinite(x))[0])
                    raise DataError(f"{self.source}: non-finite value in column for axis "
                                    f"{a} at sample {i}")
                kind[a] = x
        if self.measured is not None:
            self.measured = np.asarray(self.measured, bool)
            if self.measured.shape != (n,):
                raise DataError(f"{self.source}: the measured mask has "
                                f"{self.measured.size} samples, time has {n}")
            if self.measured.all():
                self.measured = None
        check_increasing(self.t, self.source)
        self._uniform = _is_uniform(self.t)

    @property
    def uniform(self) -> bool:
        """Whether the time base is uniform (within ``UNIFORM_RTOL`` of its step)."""
        return self._uniform

    @property
    def fs_hz(self) -> float:
        """Sample rate [Hz] (from the uniform time base)."""
        return 1.0 / self.dt

    @property
    def dt(self) -> float:
        """Sample period [s]; DataError for a record not on one sample clock (the
        analyses take ``on_grid(record)``)."""
        if not self._uniform:
            check_time(self.t, self.source)  # raises, saying where and what to do
        return float((self.t[-1] - self.t[0]) / (self.t.size - 1))

    def __len__(self) -> int:
        return self.t.size

    def slice(self, start: int, stop: int) -> "Record":
        """The samples start..stop-1 as a new record (time kept)."""
        m = None if self.measured is None else self.measured[start:stop]
        return Record(self.t[start:stop], {a: x[start:stop] for a, x in self.v.items()},
                      {a: x[start:stop] for a, x in self.w.items()}, self.source,
                      self.voltage_exact, m)

    def unmeasured(self) -> int:
        """How many samples hold no measured displacement (interpolated on a grid, or
        inside long holes)."""
        return 0 if self.measured is None else int((~self.measured).sum())


def check_increasing(t: np.ndarray, source: str = "record") -> None:
    """Time must be finite and strictly increasing, with at least 2 samples."""
    t = np.asarray(t, float)
    if t.ndim != 1 or t.size < 2:
        raise DataError(f"{source}: need at least 2 samples")
    if not np.all(np.isfinite(t)):
        raise DataError(f"{source}: time has NaN or inf")
    d = np.diff(t)
    if np.any(d <= 0):
        i = int(np.flatnonzero(d <= 0)[0])
        raise DataError(f"{source}: time is not increasing at sample {i + 1}")


def _is_uniform(t: np.ndarray) -> bool:
    d = np.diff(t)
    dt = (t[-1] - t[0]) / (t.size - 1)
    return bool(np.max(np.abs(d - dt)) <= UNIFORM_RTOL * dt)


def check_time(t: np.ndarray, source: str = "record") -> float:
    """Time must be finite, strictly increasing and uniformly sampled (what a command
    that plays or inverts a waveform needs: one rate). -> the step [s]."""
    t = np.asarray(t, float)
    check_increasing(t, source)
    d = np.diff(t)
    dt = (t[-1] - t[0]) / (t.size - 1)
    if np.max(np.abs(d - dt)) > UNIFORM_RTOL * dt:
        i = int(np.argmax(np.abs(d - dt)))
        raise DataError(f"{source}: time is not uniformly sampled (step {d[i]:.6g} s at "
                        f"sample {i + 1}, mean {dt:.6g} s); this needs one rate: resample "
                        "it (identify, gap and refit take such records as they are)")
    return dt


def on_grid(rec: Record, hole_samples: int = HOLE_SAMPLES) -> Record:
    """``rec`` on a uniform grid (itself when it is on one already): see the module
    docstring. The returned record's ``notes`` end with one line saying how (the step,
    how many samples were interpolated, the holes that split it), ``measured`` marks
    the samples inside holes longer than ``hole_samples``.

    Parameters
    ----------
    rec : Record
        Any record with increasing time.
    hole_samples : int
        Missing samples in a row still interpolated.

    Returns
    -------
    Record
        On a uniform grid from ``rec.t[0]`` to (about) ``rec.t[-1]``.
    """
    if rec.uniform:
        return rec
    t = rec.t
    d = np.diff(t)
    t0, dt, j = sample_clock(t, rec.source)
    grid = t0 + np.arange(int(j[-1]) + 1) * dt
    # the sample on or before each grid point's tick, and whether the point is a sample
    k = np.searchsorted(j, np.arange(grid.size), side="right") - 1
    on = np.zeros(grid.size, bool)
    on[j[np.abs(t - grid[j]) <= UNIFORM_RTOL * dt]] = True
    interpolated = int(grid.size - on.sum())
    w = {a: np.interp(grid, t, x) for a, x in rec.w.items()}
    if rec.voltage_exact:  # the driver held it over the ticks it skipped
        v = {a: x[k] for a, x in rec.v.items()}
    else:
        v = {a: np.interp(grid, t, x) for a, x in rec.v.items()}
    missing = np.diff(j) - 1
    holes = np.flatnonzero(missing > hole_samples)
    # only the ticks with a sample are measured: a skipped tick's interpolated
    # displacement is no measurement (the stage moved on its own path meanwhile: on a
    # real-time bag such ticks carried 5 x the fit error of the samples), so it is left
    # out of the fits as a hole's samples are
    measured = np.zeros(grid.size, bool)
    measured[j] = True  # a tick with its sample (a jittered stamp is near its tick)
    for i in holes:
        measured[j[i] + 1:j[i + 1]] = False
    if rec.measured is not None:  # a hole marked before stays one
        measured &= np.interp(grid, t, rec.measured.astype(float)) >= 1.0
    how = ("the voltage held over skipped ticks as the driver held it, the displacement "
           "interpolated linearly") if rec.voltage_exact else "interpolated linearly"
    note = (f"{rec.source}: time is not uniformly sampled (steps {d.min() * 1e3:.4g}-"
            f"{d.max() * 1e3:.4g} ms): put on a uniform {dt * 1e3:.4g} ms grid "
            f"({1 / dt:.6g} Hz), {how}; {interpolated} of {grid.size} samples "
            f"interpolated" + (f", {int(np.sum(missing))} of them skipped ticks (their "
                                "displacement left out of the fits)" if missing.any() else ""))
    if holes.size:
        longest = float(d[holes].max())
        note += (f"; {holes.size} hole(s) of more than {hole_samples} samples (the "
                 f"longest {longest:.3g} s) split it into {holes.size + 1} segments, "
                 f"fitted together: the displacement in the holes "
                 f"({int((~measured).sum())} samples) is not measured and left out of "
                 "the fits")
    return Record(grid, v, w, rec.source, rec.voltage_exact, measured,
                  list(rec.notes) + [note])


def sample_clock(t: np.ndarray, source: str = "record") -> tuple[float, float, np.ndarray]:
    """The sample clock behind increasing time stamps ``t`` [s] that jitter about it
    (by under half a step) and skip some of its ticks: (t0 [s], step [s], each
    stamp's tick index from 0). The step starts as the median step and is refined by
    least squares of the stamps on their ticks over a doubling stretch of the record:
    each stamp's tick is counted from the clock fitted so far (not from the previous
    stamp, whose own jitter would double the error), so a jitter of +-30 % of a step and
    lost samples are told apart. DataError when two stamps fall on one tick."""
    dt = float(np.median(np.diff(t)))
    t0, n = float(t[0]), min(t.size, 64)
    while True:
        j = np.round((t[:n] - t0) / dt)
        if n > 2 and np.ptp(j) > 0:
            dt, t0 = (float(c) for c in np.polyfit(j, t[:n], 1))
        if n == t.size:
            break
        n = min(t.size, 2 * n)
    j = np.round((t - t0) / dt).astype(np.int64)
    j -= j[0]
    t0 = float(np.mean(t - j * dt))
    if np.any(np.diff(j) < 1) or j[-1] + 1 > MAX_GRID_GROWTH * t.size + 10:
        d = np.diff(t)
        raise DataError(f"{source}: time steps from {d.min():.3g} to {d.max():.3g} s "
                        f"(median {np.median(d):.3g} s) are not one sample clock with "
                        "jitter under half a step: resample it")
    return t0, dt, j


def fill_unmeasured(rec: Record, pred: PerAxis[np.ndarray]) -> Record:
    """``rec`` with the displacement inside its holes (``measured`` False) replaced by
    ``pred`` ({axis: [um] over the record}, a model's output); every sample counts as
    measured in the result."""
    gone = ~rec.measured if rec.measured is not None else np.zeros(len(rec), bool)
    w = {a: np.where(gone, np.asarray(pred[a], float), x) if a in pred else x
         for a, x in rec.w.items()}
    return Record(rec.t, dict(rec.v), w, rec.source, rec.voltage_exact, None,
                  list(rec.notes))


T = TypeVar("T")


def fitted_together(rec: Record, fit: Callable[[Record], T],
                    predict: Callable[[T, Record], PerAxis[np.ndarray]]) -> T:
    """``fit(rec)`` with the samples of its holes left out of the cost: where some
    displacement was not measured (``measured``), fitted once on the record as it is
    (the holes interpolated), the holes then filled with that fit's own prediction
    (``predict(fitted, rec)`` -> {axis: [um]}) and fitted again, so they add (nearly)
    nothing to the least-squares cost: one step of the EM iteration for missing data.
    The segments either side of a hole are fitted together, with one set of
    parameters, and the models' states run on across the hole on the voltage it
    held."""
    if rec.measured is None:
        return fit(rec)
    first = fit(fill_unmeasured(rec, {}))
    return fit(fill_unmeasured(rec, predict(first, rec)))
