"""Point-to-point moves closed around the simulated stage without ROS: the feedforward's
and the controller's own per-sample work (core/loop/feedforward.py, core/loop/control.py)
in lockstep with the plant (core/model/plant.py), one sample of look-ahead as the node
set runs it, the driver's clamp and slew in between. Each move is judged on target by
the feedforward's judge on the measured position, and checked against the true one:
how long the stage really took to settle, whether a declared on-target ever had the
stage outside the tolerance, whether a settled stage went undeclared. `piezo-stage
bench settle` and the motion-time model are built on it.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from piezo_stage.core.loop.control import PARAMETERS as CONTROL_PARAMETERS
from piezo_stage.core.loop.control import CompositeController, clamp_slew
from piezo_stage.core.loop.feedforward import FeedforwardOptions, InverseFeedforward
from piezo_stage.core.loop.ontarget import ON_TARGET, TargetState
from piezo_stage.core.loop.planner import ReferencePlanner
from piezo_stage.core.model.plant import Plant
from piezo_stage.core.params import defaults
from piezo_stage.core.types import Doc, PerAxis


@dataclass(frozen=True)
class MoveResult:
    """One move: its ``step_um`` (the distance), the ``declared_s`` settle time the
    judge gave (None: never on target within the timeout), the ``true_settle_s``
    (from the move's start until the true position entered the tolerance for good,
    over the move and its dwell), ``false_samples`` (samples declared on target with
    the true position outside the tolerance), ``missed`` (the true position stayed
    inside for a whole window and the move was never declared), the largest true
    error from the declaring window on, the final measured error, and the
    ``elapsed_s`` the move took (to its declaration and dwell, or its timeout)."""

    step_um: float
    declared_s: float | None
    true_settle_s: float | None
    false_samples: int
    missed: bool
    after_declared_um: float
    final_error_um: float
    elapsed_s: float


@dataclass(frozen=True)
class MoveSetup:
    """How the moves run: ``composite`` (the inverse feedforward and the PID; False:
    the PID alone), the control rate, the tolerance [um], window [s] and filter [s] of
    the judge, the move's speed and acceleration, the dwell after on target [s], the
    timeout of a move [s], and the controller's gains."""

    composite: bool = True
    rate_hz: float = 1000.0
    tol_um: float = 0.3
    window_s: float = 0.005
    filter_s: float = 0.005
    speed_um_s: float = 5000.0
    accel_um_s2: float = 5.0e6
    dwell_s: float = 0.02
    timeout_s: float = 0.5
    kp: float = 0.2
    ki: float = 150.0
    integral_limit_V: float | None = None  # None: 30 V composite, the span PID alone


class _Loop:
    """The closed loop, one sample at a time: the feedforward's answer, the
    controller's command, the driver's clamp and slew, the plant."""

    def __init__(self, plant: Plant, model, effects, setup: MoveSetup):
        self.plant, self.dt_ns = plant, int(round(1e9 / setup.rate_hz))
        self.ff = InverseFeedforward(ReferencePlanner(), self.dt_ns, FeedforwardOptions(
            inverse=setup.composite, move_profile=(setup.speed_um_s, setup.accel_um_s2)))
        self.slew_V_per_s = plant.config.slew_V_per_s  # (the driver announces its own)
        self.ff.judge.configure(setup.tol_um, setup.window_s, setup.filter_s)
        self.limits = model.voltage_limits
        lo, hi = self.limits
        self.ff.set_model(model, effects or None, "model", driver_limits=(lo, hi))
        i_limit = setup.integral_limit_V if setup.integral_limit_V is not None else (
            30.0 if setup.composite else hi - lo)
        self.ctl = CompositeController(defaults(CONTROL_PARAMETERS) | {
            "control_rate_hz": setup.rate_hz, "kp": setup.kp, "ki": setup.ki,
            "voltage_limits_V": [lo, hi], "integral_limit_V": i_limit})
        self.max_step = plant.config.slew_V_per_s / setup.rate_hz
        self.v = {"x": 0.0, "y": 0.0}
        wx, wy = plant.step(0.0, 0.0)
        self.w, self.true, self.ns = {"x": wx, "y": wy}, _true(plant), 0

    def tick(self, enabled: bool = True) -> TargetState | None:
        """One sample; the move's state when it changed."""
        r = self.ff.on_sample(self.ns, self.w, self.v, self.dt_ns, lambda t: enabled, False)
        cmd = self.v
        for a in r.answers:
            c = self.ctl.on_sample(a.target, self.ns, a.desired or self.w, a.ff, self.w,
                                   self.v, a.enabled)
            cmd = c if c is not None else cmd
        self.v, _ = clamp_slew(cmd, self.v, self.limits, self.max_step)
        wx, wy = self.plant.step(self.v["x"], self.v["y"])
        self.w, self.true, self.ns = {"x": wx, "y": wy}, _true(self.plant), \
            self.ns + self.dt_ns
        return r.on_target


def run_moves(plant: Plant, model, effects, targets, setup: MoveSetup = MoveSetup(),
              start=None) -> list[MoveResult]:
    """Move the simulated ``plant`` to each of ``targets`` ({axis: um}) in turn, the
    feedforward on ``model`` (and its ``effects``); ``start``: a first target reached
    (and settled) before the moves judged. Returns one MoveResult per target."""
    loop = _Loop(plant, model, effects, setup)
    loop.tick(enabled=False)  # the planner holds where the stage is, then enabled
    if start is not None:
        _one(loop, "start", start, replace(setup, timeout_s=max(setup.timeout_s, 1.0)))
    return [_one(loop, f"move {k}", t, setup) for k, t in enumerate(targets)]


def _true(plant: Plant) -> Doc:
    return {a: float(x[-1]) for a, x in plant.last_true.items()}


def _one(loop: _Loop, move_id: str, target: PerAxis[float], setup: MoveSetup) -> MoveResult:
    """One move: run until declared and dwelt, or the timeout; judged on the truth."""
    ff = loop.ff
    here = dict(ff.planner.desired or loop.w)
    goal = {a: float(target.get(a, here[a])) for a in ("x", "y")}
    ff.move(move_id, goal, slew_V_per_s=loop.slew_V_per_s)
    n_max = int(round(setup.timeout_s * setup.rate_hz))
    n_dwell = int(round(setup.dwell_s * setup.rate_hz))
    true_err, declared = [], []
    declared_at: float | None = None
    end: int | None = None
    for k in range(n_max):
        change = loop.tick()
        if change is not None and change.state == ON_TARGET and declared_at is None:
            declared_at, end = change.settle_s, k + n_dwell
        declared.append(ff.judge.state == ON_TARGET)
        true_err.append(max(abs(loop.true[a] - goal[a]) for a in goal))
        if end is not None and k >= end:
            break
    e, on = np.asarray(true_err), np.asarray(declared)
    if declared_at is not None:  # the window that declared it counts as declared
        first = max(0, int(round(declared_at / (loop.dt_ns * 1e-9))) - 1)
        on[first:] |= np.arange(on.size - first) < int(np.argmax(on[first:]) + 1)
    outside = np.flatnonzero(e > setup.tol_um)
    # true_err[k] is the sample judged at the move's tick k + 1 (stamped k + 1
    # periods after its first): the first inside for good is outside[-1] + 1
    true_settle: float | None = (int(outside[-1]) + 2) * loop.dt_ns * 1e-9 \
        if outside.size else 0.0
    if outside.size and outside[-1] == e.size - 1:
        true_settle = None  # still outside at the end
    window = max(1, int(round(setup.window_s * setup.rate_hz)))
    missed = declared_at is None and _longest_run(e <= setup.tol_um) >= window + int(
        round(setup.filter_s * setup.rate_hz))
    after = float(e[on].max()) if on.any() else float("nan")
    final = max(abs(loop.w[a] - goal[a]) for a in goal)
    return MoveResult(float(np.hypot(goal["x"] - here["x"], goal["y"] - here["y"])),
                      declared_at, true_settle, int(np.count_nonzero(on & (e > setup.tol_um))),
                      bool(missed), after, float(final), e.size * loop.dt_ns * 1e-9)


def _longest_run(mask: np.ndarray) -> int:
    """The longest run of True in ``mask``."""
    best = run = 0
    for x in mask:
        run = run + 1 if x else 0
        best = max(best, run)
    return best
