"""The feedforward's reference planner and the smooth approach: what the stage is asked
to be at a target time, given the driver's state (hold where it is while disabled; once
enabled, a speed- and acceleration-limited straight approach to the goal, then track the
trajectory or hold the setpoint). Times are integers in ns; positions in um.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike

from piezo_stage.core.errors import ConfigError
from piezo_stage.core.types import Doc, PerAxis

# -- approach -----------------------------------------------------------------------

@dataclass(frozen=True)
class Approach:
    """A straight move from ``start`` to ``end`` (um per axis) with a trapezoidal speed
    profile: speed <= ``speed_um_s`` and acceleration <= ``accel_um_s2`` along the path,
    all axes arriving together. ``at(tau)`` gives the position tau seconds in."""

    start: Doc
    end: Doc
    speed_um_s: float
    accel_um_s2: float
    duration_s: float = field(init=False)
    _t_acc: float = field(init=False)
    _dist: float = field(init=False)

    def __post_init__(self) -> None:
        if not (self.speed_um_s > 0 and self.accel_um_s2 > 0):
            raise ConfigError("approach speed and acceleration must be > 0")
        d = math.sqrt(sum((self.end[a] - self.start[a]) ** 2 for a in self.start))
        vmax, amax = self.speed_um_s, self.accel_um_s2
        t_acc = vmax / amax
        if amax * t_acc ** 2 >= d:  # triangular: never reaches vmax
            t_acc = math.sqrt(d / amax)
            dur = 2 * t_acc
        else:
            dur = 2 * t_acc + (d - amax * t_acc ** 2) / vmax
        object.__setattr__(self, "_t_acc", t_acc)
        object.__setattr__(self, "_dist", d)
        object.__setattr__(self, "duration_s", dur)

    def fraction(self, tau: float) -> float:
        """Share of the path covered after tau seconds (0..1)."""
        if self._dist == 0.0 or tau >= self.duration_s:
            return 1.0
        if tau <= 0.0:
            return 0.0
        a, ta, T = self.accel_um_s2, self._t_acc, self.duration_s
        if tau < ta:
            s = 0.5 * a * tau ** 2
        elif tau > T - ta:
            s = self._dist - 0.5 * a * (T - tau) ** 2
        else:
            s = 0.5 * a * ta ** 2 + a * ta * (tau - ta)
        return min(max(s / self._dist, 0.0), 1.0)

    def at(self, tau: float) -> Doc:
        """The position [um] ``tau`` seconds into the approach."""
        f = self.fraction(tau)
        return {a: self.start[a] + f * (self.end[a] - self.start[a]) for a in self.start}


# -- the feedforward's reference planner -------------------------------------------------

HOLD, APPROACH, TRACK, DONE = "holding", "approaching", "tracking", "done"


class ReferencePlanner:
    """What the stage is asked to be at a target time, given the driver's state.

    Disabled (the driver holds its safe voltage): *holding* where the stage is.
    Enabled: an approach from the held position to the goal (the trajectory's first
    point, or a streamed setpoint), then *tracking*: the trajectory clock starts when
    the approach ends, or at the trajectory's start time if that is later (its first
    point held until then); past its last point the phase is *done* and the last point
    is held. A new trajectory or setpoint while enabled is approached from the
    present desired position; a re-enable after a fault restarts the trajectory from
    its beginning, through the approach. Pure and deterministic: times are the target
    stamps [ns] the caller asks for.
    """

    def __init__(self, speed_um_s: float = 200.0, accel_um_s2: float = 20000.0) -> None:
        Approach({"x": 0.0}, {"x": 0.0}, speed_um_s, accel_um_s2)  # validates
        self.speed, self.accel = float(speed_um_s), float(accel_um_s2)
        self.traj: tuple[np.ndarray, dict[str, np.ndarray]] | None = None  # (t [s], {axis: um})
        self.setpoint: dict[str, float] | None = None  # {axis: um}
        self.phase = HOLD
        self.desired: dict[str, float] | None = None  # {axis: um}: last position asked for
        self._approach: tuple[Approach, int] | None = None  # (Approach, start ns)
        self._track_ns: int | None = None  # trajectory clock origin [ns]
        self.start_ns: int | None = None  # the trajectory's own start time, if it asked
        self.profile: tuple[float, float] | None = None  # a move's (speed, accel)

    def set_trajectory(self, t: ArrayLike, w: PerAxis[np.ndarray],
                       start_ns: int | None = None) -> None:
        """A new trajectory (t [s], {axis: um}): approached from where the stage is
        asked to be; its clock starts when the approach ends, or at ``start_ns`` if
        that is later."""
        self.traj, self.setpoint = (np.asarray(t, float), {a: np.asarray(x, float)
                                                          for a, x in w.items()}), None
        self.start_ns = None if start_ns is None else int(start_ns)
        self.profile = None
        self._restart()

    def set_setpoint(self, w: PerAxis[float]) -> None:
        """A new streamed setpoint {axis: um}: approached, then held."""
        self.setpoint, self.traj, self.profile = dict(w), None, None
        self._restart()

    def set_move(self, w: PerAxis[float], speed_um_s: float, accel_um_s2: float,
                 start_ns: int | None = None) -> None:
        """A point-to-point move to {axis: um}: the same straight path as an approach,
        with the move's own speed and acceleration, then held (phase *done* once
        there); from ``start_ns`` when given (a one-point trajectory's start)."""
        Approach({"x": 0.0}, {"x": 0.0}, speed_um_s, accel_um_s2)  # validates
        self.setpoint, self.traj = dict(w), None
        self.start_ns = None if start_ns is None else int(start_ns)
        self.profile = (float(speed_um_s), float(accel_um_s2))
        self._restart()

    def _restart(self) -> None:
        if self.phase != HOLD:
            self.phase, self._approach, self._track_ns = APPROACH, None, None

    def hold(self, w_now: Doc) -> None:
        """Disabled: ask for where the stage is; the next enable starts over."""
        self.phase, self._approach, self._track_ns = HOLD, None, None
        self.desired = dict(w_now)

    def clock_s(self, target_ns: int) -> float | None:
        """Seconds the trajectory clock will have run at target_ns (None: not running)."""
        if self.phase not in (TRACK, DONE) or self._track_ns is None:
            return None
        return (target_ns - self._track_ns) * 1e-9

    def _goal(self, desired: dict[str, float]) -> Doc:
        if self.traj is not None:
            t, w = self.traj
            return {a: float(w[a][0]) if a in w else desired[a] for a in desired}
        if self.setpoint is not None:
            return {a: self.setpoint.get(a, desired[a]) for a in desired}
        return dict(desired)

    def sample(self, target_ns: int) -> PerAxis[float]:
        """The desired position [um] for ``target_ns`` while enabled."""
        desired = self.desired
        if desired is None:
            raise ConfigError("planner: hold() must give the start position first")
        if self.phase == HOLD:
            self.phase = APPROACH
        if self.phase == APPROACH:
            if self._approach is None:
                if self.profile is not None and (self.start_ns or 0) > target_ns:
                    return dict(desired)  # a move held until its start
                speed, accel = self.profile or (self.speed, self.accel)
                self._approach = (Approach(dict(desired), self._goal(desired), speed,
                                           accel), int(target_ns))
            ap, t0 = self._approach
            tau = (target_ns - t0) * 1e-9
            if tau < ap.duration_s:
                self.desired = ap.at(tau)
                return dict(self.desired)
            self.phase, self._track_ns = TRACK, max(t0 + int(round(ap.duration_s * 1e9)),
                                                    self.start_ns or 0)
        if self.traj is not None:
            t, w = self.traj
            tau = (target_ns - (self._track_ns or 0)) * 1e-9
            desired = interp_axes(tau, t, w, desired)
            if tau > t[-1]:
                self.phase = DONE  # the last point, held
        elif self.setpoint is not None:
            desired = {a: self.setpoint.get(a, desired[a]) for a in desired}
            if self.profile is not None:
                self.phase = DONE  # a move: arrived on its path (on target is judged)
        self.desired = desired
        return dict(desired)


def interp_axes(tau: float, t: np.ndarray, w: PerAxis[np.ndarray],
                held: PerAxis[float]) -> PerAxis[float]:
    """Each axis of ``w`` ({axis: array over ``t``}) at ``tau`` [s], linearly
    interpolated and held past the ends (``np.interp``'s rule), the others as in
    ``held``: one search a sample for every axis (np.interp per axis and sample cost
    the real-time loop a tenth of its time)."""
    n = t.size
    k = int(t.searchsorted(tau, side="right"))  # (the method: no dispatch wrapper)
    if k <= 0 or k >= n:
        i = 0 if k <= 0 else n - 1
        return {a: float(w[a][i]) if a in w else held[a] for a in held}
    t0, t1 = float(t[k - 1]), float(t[k])
    f = (tau - t0) / (t1 - t0) if t1 > t0 else 0.0
    out = {}
    for a in held:
        if a in w:
            x = w[a]
            x0 = float(x[k - 1])
            out[a] = x0 + f * (float(x[k]) - x0)
        else:
            out[a] = held[a]
    return out
