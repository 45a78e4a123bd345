"""On target: whether a move has arrived, judged on the sensor the way a controller's
``ONT?`` is, but honest about the sensor's noise.

Per axis the measured error to the move's target is averaged over ``filter_s`` (longer
where the tolerance is near the sensor's noise: long enough that the noise's guard
leaves half the tolerance). The guard band has two parts: the noise left in the
average, from the sensor's noise as the measurements at rest show it (the median of
the successive differences while no move runs or the last is on target), and the
motion the average hides (a ring it averages out shows as variance
beyond the noise). An axis is on target once its averaged error has stayed within
``tol_um`` less the guard for a whole settling window (``window_s``); the move is on
target when every axis is, and that is latched: it stays on target until an axis's
averaged error leaves the band (then it is moving again, with the same move id, and is
judged again). The settle time is from the move's start to the start of the window
that declared it.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass, field
from typing import Any

from piezo_stage.core.errors import ConfigError
from piezo_stage.core.params import Param, Schema
from piezo_stage.core.types import PerAxis

MOVING, ON_TARGET, REFUSED = "moving", "on_target", "refused"
GUARD_SIGMAS = 3.0  # the guard band: this many standard deviations of the filtered noise
NOISE_SAMPLES = 200  # successive differences the noise estimate is taken over
NOISE_EVERY = 25  # ... and taken again every this many samples
MAX_FILTER_S = 1.0  # the longest average a tolerance near the noise may ask for [s]

# the feedforward's on-target parameters (core/params.py), live
PARAMETERS: Schema = (
    Param("on_target_tol_um", 0.3, "on target: tolerance on each axis [um]", lo=1e-4,
          hi=100.0, live=True),
    Param("on_target_window_ms", 5.0, "on target: the settling window the error stays "
          "within the tolerance for [ms]", lo=0.0, hi=10_000.0, live=True),
    Param("on_target_filter_ms", 5.0, "on target: the sensor's moving average [ms] (0: "
          "one sample)", lo=0.0, hi=1000.0, live=True),
)


@dataclass(frozen=True)
class TargetState:
    """What the judge says of a move: its ``move_id``, ``state`` per axis and for the
    move (``moving`` or ``on_target``; ``refused``, with the ``reason``, for a request
    the stage did not take), the ``settle_s`` (None until on target), the filtered
    ``error_um`` per axis at the last sample, the ``target_um``, the ``stamp_ns`` of
    the sample it is judged at and the ``started_ns`` of the move's first."""

    move_id: str
    state: str
    axes: PerAxis[Any]
    settle_s: float | None
    error_um: PerAxis[float]
    target_um: PerAxis[float]
    stamp_ns: int
    started_ns: int
    reason: str = ""


@dataclass
class _Axis:
    """One axis's filter, noise estimate and run of samples inside the band."""
    n_filter: int
    window: deque = field(default_factory=deque)  # the last errors, for the average
    total: float = 0.0
    total2: float = 0.0  # the sum of the squared errors in the window
    diffs: deque = field(default_factory=lambda: deque(maxlen=NOISE_SAMPLES))
    sigma: float = 0.0  # the sensor's noise [um], from the successive differences
    count: int = 0
    was_quiet: bool = False
    last_raw: float | None = None
    inside_since: int | None = None  # stamp of the first sample of the run inside
    on: bool = False

    def measured(self, w: float, quiet: bool) -> None:
        """A measurement [um]; ``quiet``: the stage rests (no move, or one on target):
        the noise estimate takes it (kept over moves: it is the sensor's; a move's own
        motion, a ring above all, would pass for noise)."""
        if self.last_raw is not None and quiet and self.was_quiet:
            self.diffs.append(abs(w - self.last_raw))
            self.count += 1
            if self.count < NOISE_EVERY or self.count % NOISE_EVERY == 0:
                # the median of |differences|: a step's few large ones do not count
                n = len(self.diffs)
                self.sigma = sorted(self.diffs)[n // 2] / (0.6745 * math.sqrt(2.0))
        self.last_raw, self.was_quiet = w, quiet

    def restart(self) -> None:
        """A new move: its filter and its run inside the band start over."""
        self.window.clear()
        self.total, self.total2, self.inside_since, self.on = 0.0, 0.0, None, False

    def filtered(self, e: float) -> float:
        """The moving average of the error, with ``e`` the newest sample."""
        self.window.append(e)
        self.total += e
        self.total2 += e * e
        while len(self.window) > self.n_filter:
            old = self.window.popleft()
            self.total -= old
            self.total2 -= old * old
        return self.total / len(self.window)

    def guard(self) -> tuple[float, float]:
        """The guard band's two parts [um]: the filtered noise, and the motion the
        average hides (a ring or a drift shows as variance beyond the sensor's noise:
        what exceeds the noise's own spread, as a sinusoid's amplitude; a drift's
        is about the average's lag behind its newest sample)."""
        n = len(self.window) or 1
        noise = GUARD_SIGMAS * self.sigma / math.sqrt(n)
        if n < 3:
            return noise, 0.0
        mean = self.total / n
        var = max(self.total2 / n - mean * mean, 0.0) * n / (n - 1)
        excess = var - self.sigma ** 2 * (1.0 + 2.0 * math.sqrt(2.0 / (n - 1)))
        return noise, (math.sqrt(2.0 * excess) if excess > 0 else 0.0)


class OnTargetJudge:
    """Judges each move, sample by sample (see the module's docstring).

    Parameters
    ----------
    dt_s : float
        The sample period [s].
    tol_um, window_s, filter_s : float
        The tolerance on each axis [um], the settling window [s] and the sensor's
        moving average [s].
    """

    def __init__(self, dt_s: float, tol_um: float = 0.3, window_s: float = 0.005,
                 filter_s: float = 0.005) -> None:
        if not dt_s > 0:
            raise ConfigError("on target: the sample period must be > 0")
        self.dt_s = float(dt_s)
        self.move_id: str | None = None
        self.target: PerAxis[float] = {}
        self.started_ns = 0
        self.axes: dict[str, _Axis] = {}
        self.settle_s: float | None = None
        self.state = MOVING
        self.last: tuple[int, PerAxis[float]] | None = None  # the running move's last errors
        self.configure(tol_um, window_s, filter_s)

    def configure(self, tol_um: float, window_s: float, filter_s: float) -> None:
        """New tolerance [um], window [s] and filter [s] (checked; the running move is
        judged with them from its next sample)."""
        if not (tol_um > 0 and window_s >= 0 and filter_s >= 0):
            raise ConfigError("on target: tolerance > 0, window and filter >= 0")
        self.tol, self.window_s, self.filter_s = float(tol_um), float(window_s), \
            float(filter_s)
        self.n_filter = max(1, int(round(filter_s / self.dt_s)))
        self.max_filter = max(self.n_filter, int(round(MAX_FILTER_S / self.dt_s)))
        for ax in self.axes.values():
            ax.n_filter = self.n_filter

    def begin(self, move_id: str, target_um: PerAxis[float], started_ns: int) -> None:
        """A new move to ``target_um`` ({axis: um}) from the sample stamped
        ``started_ns``: moving until judged on target."""
        self.move_id, self.target = str(move_id), dict(target_um)
        self.started_ns, self.settle_s, self.state = int(started_ns), None, MOVING
        self.last = None
        for a in self.target:
            self._axis(a).restart()

    def _axis(self, a: str) -> _Axis:
        """Axis ``a``'s state, made on first use (not one made and dropped a sample)."""
        ax = self.axes.get(a)
        if ax is None:
            ax = self.axes[a] = _Axis(self.n_filter)
        return ax

    def sample(self, ns: int, w: PerAxis[float]) -> TargetState | None:
        """The measured sample ``w`` ({axis: um}) stamped ``ns``: the move's state when
        it changed (on target, or moving again), else None. No move: None."""
        quiet = self.move_id is None or self.state == ON_TARGET
        for a in w:
            self._axis(a).measured(w[a], quiet)
        if self.move_id is None or ns < self.started_ns:
            return None
        errors = {}
        need = self.window_s - 1e-9
        for a in self.target:
            ax = self.axes[a]
            # the average long enough for the guard to leave half the tolerance (a
            # tolerance near the sensor's noise needs more samples), within a second
            ax.n_filter = min(max(self.n_filter, math.ceil(
                (2 * GUARD_SIGMAS * ax.sigma / self.tol) ** 2)), self.max_filter)
            e = ax.filtered(w[a] - self.target[a])
            errors[a] = e
            noise, motion = ax.guard()
            band = self.tol - noise - motion
            if ax.on:  # latched: out when it may have left the tolerance (half the
                if abs(e) > self.tol - 0.5 * noise - motion:  # noise's guard: no chatter)
                    ax.on, ax.inside_since = False, None
                continue
            if abs(e) <= band and len(ax.window) >= ax.n_filter:
                if ax.inside_since is None:
                    ax.inside_since = ns
                ax.on = (ns - ax.inside_since) * 1e-9 >= need
            else:
                ax.inside_since = None
        self.last = (ns, errors)
        on = all(self.axes[a].on for a in self.target)
        state = ON_TARGET if on else MOVING
        if state == self.state:
            return None
        self.state = state
        if on:
            since = max(self.axes[a].inside_since or ns for a in self.target)
            self.settle_s = (since - self.started_ns) * 1e-9
        return self.report(ns, errors)

    def report(self, ns: int, errors: PerAxis[float]) -> TargetState:
        """The move's state at ``ns`` (the filtered ``errors``)."""
        return TargetState(self.move_id or "", self.state,
                           {a: ON_TARGET if self.axes[a].on else MOVING
                            for a in self.target},
                           self.settle_s, dict(errors), dict(self.target), int(ns),
                           self.started_ns)
