"""A measured or simulated record: time [s], voltages [V], displacements [um]."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from piezo_stage.core.errors import DataError

# Relative tolerance on sample spacing: CSV files round time stamps, DAQ clocks do not
# jitter at this level.
UNIFORM_RTOL = 1e-3


@dataclass
class Record:
    """Columns of one run, all the same length N.

    Attributes
    ----------
    t : ndarray (N,)
        Time [s], strictly increasing and uniform.
    v : dict axis -> ndarray (N,)
        Applied voltage [V] per axis present.
    w : dict axis -> ndarray (N,)
        Measured displacement [um] per axis present.
    """

    t: np.ndarray
    v: dict = field(default_factory=dict)
    w: dict = field(default_factory=dict)
    source: str = "record"
    # True when v is exactly what the actuator got (the driver's applied voltage, as
    # in our bags); False for a voltage of unknown origin, possibly a noisy measurement
    voltage_exact: bool = False

    def __post_init__(self):
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
        check_time(self.t, self.source)

    @property
    def fs_hz(self) -> float:
        """Sample rate [Hz] (from the uniform time base)."""
        return 1.0 / self.dt

    @property
    def dt(self) -> float:
        """Sample period [s]."""
        return float((self.t[-1] - self.t[0]) / (self.t.size - 1))

    def __len__(self):
        return self.t.size

    def slice(self, start: int, stop: int) -> "Record":
        """The samples start..stop-1 as a new record (time kept)."""
        return Record(self.t[start:stop], {a: x[start:stop] for a, x in self.v.items()},
                      {a: x[start:stop] for a, x in self.w.items()}, self.source,
                      self.voltage_exact)


def check_time(t: np.ndarray, source: str = "record") -> float:
    """Time must be finite, strictly increasing and uniformly sampled."""
    t = np.asarray(t, float)
    if t.ndim != 1 or t.size < 2:
        raise DataError(f"{source}: need at least 2 samples")
    if not np.all(np.isfinite(t)):
        raise DataError(f"{source}: time has NaN or inf")
    d = np.diff(t)
    if np.any(d <= 0):
        i = int(np.flatnonzero(d <= 0)[0])
        raise DataError(f"{source}: time is not increasing at sample {i + 1}")
    dt = (t[-1] - t[0]) / (t.size - 1)
    if np.max(np.abs(d - dt)) > UNIFORM_RTOL * dt:
        i = int(np.argmax(np.abs(d - dt)))
        raise DataError(f"{source}: time is not uniformly sampled (step {d[i]:.6g} s at "
                        f"sample {i + 1}, mean {dt:.6g} s)")
    return dt
