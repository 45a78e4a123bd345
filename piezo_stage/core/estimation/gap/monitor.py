"""The live sim-to-real residual: a model's exact twin beside the stage, on the same
voltages (the gap node's core).

Each sample's measured displacement minus the twin's, with the real sensor's zero (the
mean residual of the first ``ZERO_SAMPLES`` samples) taken out, and the rolling RMS of
the last ``window`` residuals per axis.
"""

from __future__ import annotations

from collections import deque

import numpy as np

from piezo_stage.core.model.duhem import AXES, StageModel
from piezo_stage.core.model.plant import Plant
from piezo_stage.core.types import EffectsBlock

ZERO_SAMPLES = 100  # the sensor's zero: averaged over this many first samples


class ResidualMonitor:
    """The residual of a stage against the exact twin of ``model`` (with its
    ``effects``, as its file lists them) driven at ``rate_hz``."""

    def __init__(self, model: StageModel, effects: EffectsBlock | None, rate_hz: float,
                 window: int) -> None:
        self.twin = Plant.of_model(model, effects, rate_hz)
        self.rate_hz = float(rate_hz)
        self.res: dict[str, deque[float]] = {a: deque(maxlen=int(window)) for a in AXES}
        self.offset = dict.fromkeys(AXES, 0.0)
        self.n = 0

    def sample(self, w: dict[str, float], v: dict[str, float]) -> dict[str, float]:
        """One sample: the stage at ``w`` [um] with ``v`` [V] applied -> the residual
        [um] per axis (measured - twin, less the sensor's zero)."""
        twin = self.twin.step(v["x"], v["y"])
        r = {a: w[a] - twin[i] for i, a in enumerate(AXES)}
        self.n += 1
        if self.n <= ZERO_SAMPLES:  # noise averages out of the zero
            for a in r:
                self.offset[a] += (r[a] - self.offset[a]) / self.n
        r = {a: r[a] - self.offset[a] for a in r}
        for a in r:
            self.res[a].append(r[a])
        return r

    def rms_um(self) -> dict[str, float]:
        """The rolling RMS of the residual per axis [um] (NaN before any sample)."""
        return {a: float(np.sqrt(np.mean(np.square(x)))) if x else float("nan")
                for a, x in self.res.items()}

    def switch(self, model: StageModel, effects: EffectsBlock | None,
               history: np.ndarray, settle: int = 0) -> None:
        """The twin of another model from now on (a model handed on), brought to now by
        running it over ``history`` ((n, 4): vx, vy, wx, wy from the sample its initial
        state is that of, to the last one taken): its sensor zero is the mean residual
        there after the first ``settle`` samples (the twin's start from its initial
        state: the one constant a written model's held-out figure removes)."""
        twin = Plant.of_model(model, effects, self.rate_hz)
        out = twin.run(history[:, 0], history[:, 1])
        k = settle if len(history) > settle else 0
        for i, a in enumerate(AXES):
            self.offset[a] = float(np.mean(history[k:, 2 + i] - out[a][k:])) \
                if len(history) else 0.0
        self.twin = twin
