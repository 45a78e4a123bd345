"""The feedforward node's work per sample, without ROS (nodes/feedforward_node.py is its
shell: parameters, topics, statistics, logs).

Per measured sample k (stamp t_k, position w, voltages applied for it) the feedforward
answers the target ticks t_k + look-ahead: the planner (core/loop/planner.py) gives the
desired position, the previewed reference compensates the model's effects and applies
what learning learned (core/loop/compensation.py, core/loop/learning.py), and the exact inverse
(core/model/inverse.py), synced to the voltages really applied and stepped through the
commands still in flight, turns it into voltages. While the driver does not apply
commands the reference holds where the stage is and the feedforward is the applied
voltage, so enabling is bumpless. A new model replaces the inverse at once; while
armed, the jump between the old model's answer and the new one's is eased out. So is the
jump a backlog leaves (real time, a host stall: the driver held its voltage while the
trajectory went on): the reference rejoins the trajectory from where it was asked last,
at the trajectory's own pace, so the stage moves at most twice as fast as the
trajectory asks, never in one step that a stage's resonance would ring on.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike

from piezo_stage.core.errors import DataError, PiezoStageError
from piezo_stage.core.loop.compensation import EffectCompensator, PreviewedReference
from piezo_stage.core.loop.control import THREAD_PRIORITY
from piezo_stage.core.loop.learning import LearnedFeedforward
from piezo_stage.core.loop.ontarget import PARAMETERS as ON_TARGET
from piezo_stage.core.loop.ontarget import REFUSED, OnTargetJudge, TargetState
from piezo_stage.core.loop.planner import ReferencePlanner
from piezo_stage.core.loop.stamps import Publications, SampleGuard
from piezo_stage.core.metrics import LatencyHistogram
from piezo_stage.core.model.duhem import StageModel, check_model_change, stroke_um
from piezo_stage.core.model.inverse import StageInverse
from piezo_stage.core.params import Param, Schema
from piezo_stage.core.types import Doc, EffectsBlock, Params, PerAxis

HANDOVER_V_PER_TICK = 1.0  # a new model while armed: its jump eased out, 1 V a tick
MAX_FILLED_TICKS = 20  # after a skipped sample, at most this many targets answered
PAST_TRAJECTORY_NS = 1_000_000_000  # a trajectory stamped up to 1 s ago: start now
ON_TARGET_NAMES = tuple(q.name for q in ON_TARGET)
MOVE_SLEW_SHARE = 0.5  # a move's speed: at most this share of the driver's slew limit
REJOIN_MIN_UM_PER_TICK = 0.5  # after a backlog: the reference rejoins at least this fast

# the feedforward node's parameters (core/params.py); effect compensation and the
# learning ones are live
PARAMETERS: Schema = (
    Param("control_rate_hz", 1000.0, "control rate [Hz]", lo=1.0, hi=1e5),
    Param("model_file", "", "initial model YAML ('' = none until one arrives on model)"),
    Param("nominal_um_per_V", 0.5, "gain used before any model [um/V]", lo=0.01, hi=100.0),
    Param("use_coupling", True, "invert the coupling (decoupling)"),
    Param("inverse_feedforward", True,
          "false: hold the feedforward at the voltage applied when enabled (feedback only)"),
    Param("range_um", [-10.0, 90.0], "accepted target range [um]"),
    Param("model_required_after_s", 0.0,
          "lockstep: hold the loop at this trajectory time until a model arrives (0: never)"),
    Param("max_trajectory_points", 200000,
          "longer trajectories are refused (memory, parse time)",
          lo=2, hi=10_000_000),
    Param("wait_for_trajectory", False,
          "answer no sample before a trajectory has arrived (lockstep: the loop waits; real"
          " time: the loop does not close, so the set does not arm)"),
    Param("inputs_once_armed", False,
          "take trajectories, setpoints and moves only once the driver has armed (the "
          "launcher sets it on every real-time set: a set refused for want of capacity "
          "took no input, and one --rate auto runs again at a lower rate lost none); with "
          "wait_for_trajectory the trajectory is taken from the start"),
    Param("approach_speed_um_per_s", 200.0, "approach speed [um/s]", lo=0.1, hi=1e6),
    Param("approach_accel_um_per_s2", 20000.0,
          "approach acceleration [um/s^2]",
          lo=1.0, hi=1e9),
    Param("move_speed_um_per_s", 5000.0, "a move's speed (a move request or a one-point "
          "trajectory) [um/s]", lo=0.1, hi=1e7),
    Param("move_accel_um_per_s2", 5.0e6, "a move's acceleration [um/s^2]", lo=1.0,
          hi=1e12),
    *ON_TARGET,
    Param("max_resonance_inverse_hz", 0.0,
          "a model's resonance above this is taken as its group delay, not inverted (0: no "
          "limit)",
          lo=0.0, hi=1e6),
    Param("compensate_effects", True, "compensate the model's unmodelled effects", live=True),
    Param("learning_period_s", 0.0,
          "learning: the trajectory's period [s] (0: none)",
          lo=0.0, hi=60.0, live=True),
    Param("learning_gain", 1.0,
          "learning: first gain (it falls with the periods learned)",
          lo=0.01, hi=1.0, live=True),
    Param("learning", False, "learn the periodic error into the feedforward", live=True),
    THREAD_PRIORITY,
    Param("min_subscribers", 0, "reference subscribers to wait for"),
)

# the node's counts on /diagnostics, and those reported as rates (key, name, level)
COUNTS = ("trajectories", "rejected_trajectories", "rejected_setpoints", "models",
          "rejected_models", "moves", "rejected_moves", "saturated", "bad_messages",
          "late_dropped", "stray_stamps", "rejoins")
# an input refused -> its count
REFUSED_COUNT = {"model": "rejected_models", "trajectory": "rejected_trajectories",
                 "setpoint": "rejected_setpoints", "move": "rejected_moves"}
RATES = tuple((k, k.replace("_", " "), 0) for k in (
    "rejected_models", "rejected_trajectories", "rejected_setpoints", "rejected_moves",
    "bad_messages", "late_dropped"))


def trajectory_start(stamp_ns: int, now_ns: int) -> int | None:
    """When a trajectory stamped ``stamp_ns`` starts, at ``now_ns`` (the set's clock,
    wall or simulated): None (now) for 0 or a stamp up to PAST_TRAJECTORY_NS ago, the
    stamp when it is in the future. Further in the past: refused (DataError)."""
    if 0 < stamp_ns < now_ns - PAST_TRAJECTORY_NS:
        raise DataError(f"trajectory: stamped {(now_ns - stamp_ns) * 1e-9:.3f} s in the "
                        "past (0: start now; a future stamp: start then)")
    return stamp_ns if stamp_ns > now_ns else None


@dataclass(frozen=True)
class Answer:
    """What the node publishes for one target tick: the reference (``desired`` [um],
    the feedforward ``ff`` [V]) stamped ``target`` [ns]; ``error``, the reason the last
    feedforward was held (logged); ``phase_changed``: the planner's phase changed on
    the way (the node publishes it before this reference); ``enabled``: the driver
    applies commands at ``target``."""

    target: int
    desired: PerAxis[float] | None
    ff: PerAxis[float]
    error: PiezoStageError | None
    phase_changed: bool
    enabled: bool
    late: bool = False  # real time: its tick had passed; no voltage computed, not sent


@dataclass(frozen=True)
class SampleResult:
    """``on_sample``'s verdict on one sample: ``wait`` (lockstep: hold this sample until
    what it waits for is here, ``resume``), ``silent`` (real time, no trajectory yet:
    no answer, so the loop is not closed and nothing arms), or the ``answers`` with the
    voltage ``applied`` [V] they took the stage to be at."""

    answers: tuple[Answer, ...] = ()
    wait: bool = False
    silent: bool = False
    applied: PerAxis[float] | None = None
    on_target: TargetState | None = None  # a move's state, when it changed here
    measured: PerAxis[float] | None = None  # the sample's position [um] they answer


@dataclass(frozen=True)
class PreparedModel:
    """A model ready to be used (``InverseFeedforward.prepare_model``)."""
    model: StageModel
    effects: EffectsBlock | None
    compensator: EffectCompensator | None
    inverse: StageInverse
    gain_um_per_V: float  # the steepest axis's stroke over the voltage range


@dataclass(frozen=True)
class FeedforwardOptions:
    """How an ``InverseFeedforward`` answers, built by keyword.

    Attributes
    ----------
    nominal_um_per_V : float
        The gain used before any model.
    use_coupling : bool
        Invert the model's coupling (decoupling).
    inverse : bool
        False: the feedforward stays at the voltage applied when enabled (feedback only).
    max_resonance_hz : float
        A model's resonance above this is taken as its group delay (0: no limit).
    wait_for_trajectory : bool
        Answer no sample before a trajectory is here (lockstep: hold the sample).
    model_required_after_s : float
        Lockstep: hold the trajectory clock at this many seconds until a model is here
        (0: never).
    move_profile : tuple of float
        A move's speed [um/s] and acceleration [um/s^2] (``move``; capped by the slew
        limit it is given).
    """
    nominal_um_per_V: float = 0.5
    use_coupling: bool = True
    inverse: bool = True
    max_resonance_hz: float = 0.0
    wait_for_trajectory: bool = False
    model_required_after_s: float = 0.0
    move_profile: tuple[float, float] = (5000.0, 5.0e6)


class InverseFeedforward:
    """Desired positions to voltages, sample by sample.

    Parameters
    ----------
    planner : ReferencePlanner
        The desired position's source (trajectory, setpoint, approach, hold).
    dt_ns : int
        The control period [ns].
    options : FeedforwardOptions
        How it answers: the gain before any model, decoupling, the inverse, the
        lockstep waits and a move's profile (by keyword; the defaults by default).
    """

    def __init__(self, planner: ReferencePlanner, dt_ns: int,
                 options: FeedforwardOptions | None = None) -> None:
        o = self.options = options or FeedforwardOptions()
        nominal_um_per_V, use_coupling, inverse = o.nominal_um_per_V, o.use_coupling, o.inverse
        max_resonance_hz, wait_for_trajectory = o.max_resonance_hz, o.wait_for_trajectory
        model_required_after_s, move_profile = o.model_required_after_s, o.move_profile
        self.wait_traj, self.model_after_s = bool(wait_for_trajectory), model_required_after_s
        self.planner, self.dt_ns = planner, int(dt_ns)
        self.stats = dict.fromkeys(COUNTS, 0)  # what it took, refused and dropped
        self.guard = SampleGuard(self.stats)  # what it drops before on_sample, counted
        self.ref = PreviewedReference(planner, self.dt_ns)  # effects compensated
        self.learning = LearnedFeedforward(self.ref, self.dt_ns)
        self.gain, self.use_c, self.use_ff = nominal_um_per_V, use_coupling, inverse
        self.max_res_hz = max_resonance_hz
        self.learn_p = {"learning_period_s": 0.0, "learning_gain": 1.0}
        self.limits = (0.0, 150.0)
        self.inv: StageInverse | None = None
        self.model: StageModel | None = None
        self.handover: PerAxis[float] | None = None
        self.behind = False  # answers were late (a backlog): the next one rejoins
        self.rejoin: PerAxis[float] | None = None  # the reference's offset to the planner's [um]
        self.answered: tuple[int, PerAxis[float]] | None = None  # the planner's last (target, um)
        self.asked: PerAxis[float] | None = None  # the reference last answered [um]
        self.rejoins = 0  # backlogs the reference rejoined the planner's from
        self.effects: EffectsBlock | None = None
        self.comp: EffectCompensator | None = None
        self.started = False  # the inverse has been put where the stage is
        self.ff: dict[str, float] = {"x": 0.0, "y": 0.0}
        self.planned: dict[int, PerAxis[float]] = {}
        self.last_target: int | None = None
        self.traj_text = ""  # which trajectory runs: "trajectory of N points stamped S"
        self.judge = OnTargetJudge(self.dt_ns * 1e-9)  # a move's arrival (ontarget.py)
        self.move_profile = tuple(move_profile)  # a move's speed [um/s], acceleration
        self.model_gain: float | None = None  # the model's steepest mean gain [um/V]
        self.move_text = ""  # what the phase follows in a move ("move M")
        self.last_ns = 0
        # what the node takes in, as the core keeps it: the model's name and the last
        # refusal's reason, the model a new one is checked against (the last prepared),
        # the publications taken (each publication runs once, every publication runs)
        self.model_name, self.last_rejection = "nominal", ""
        self.model_base: StageModel | None = None
        self.publications = Publications()
        self.lag = LatencyHistogram()  # a sample's stamp -> its arrival (real time)
        self.sp_latency = LatencyHistogram()  # a setpoint's arrival -> its target tick
        self.setpoint_arrival: int | None = None
        # lockstep: the sample held until what it waits for is here (``resume``)
        self.held: tuple[int, PerAxis[float], PerAxis[float] | None, int] | None = None
        self.answered_ns = -1  # the last sample answered

    @classmethod
    def from_params(cls, p: Params, dt_ns: int) -> InverseFeedforward:
        """The feedforward the node's parameters (``PARAMETERS``, by name) give, with
        its planner."""
        planner = ReferencePlanner(p["approach_speed_um_per_s"], p["approach_accel_um_per_s2"])
        return cls(planner, dt_ns, FeedforwardOptions(
            nominal_um_per_V=p["nominal_um_per_V"], use_coupling=p["use_coupling"],
            inverse=p["inverse_feedforward"], max_resonance_hz=p["max_resonance_inverse_hz"],
            wait_for_trajectory=p["wait_for_trajectory"],
            model_required_after_s=p["model_required_after_s"],
            move_profile=(p["move_speed_um_per_s"], p["move_accel_um_per_s2"])))

    def set_model(self, model: StageModel, effects: EffectsBlock | None, name: str,
                  driver_limits: tuple | None = None, range_um: float = 100.0,
                  armed: bool = False) -> None:
        """Use ``model`` (and its ``effects``) from the next sample: ``prepare_model``,
        then ``use_model``."""
        self.use_model(self.prepare_model(model, effects, name, driver_limits, range_um),
                       armed)

    def prepare_model(self, model: StageModel, effects: EffectsBlock | None, name: str,
                      driver_limits: tuple | None = None, range_um: float = 100.0,
                      base: StageModel | None = None) -> PreparedModel:
        """A model checked and its inverse built (the compiled kernels warmed), ready
        for ``use_model``; touches nothing the samples use, so it may run off the
        loop's thread. Refused (PiezoStageError) when an axis is missing, its voltage
        limits do not overlap the driver's, or its gain's sign or size is far from
        ``base`` (the running model if None; check_model_change over ``range_um``)."""
        missing = {"x", "y"} - set(model.axes)
        if missing:
            raise PiezoStageError(f"{name} has no model for axis {', '.join(sorted(missing))}")
        if driver_limits:  # never wider than what the driver will apply
            lo = max(model.voltage_limits[0], driver_limits[0])
            hi = min(model.voltage_limits[1], driver_limits[1])
            if not lo < hi:
                raise PiezoStageError(f"{name}: voltage limits {list(model.voltage_limits)} "
                                      f"outside the driver's {driver_limits}")
            model = model.replace(voltage_limits=(lo, hi))
        # gain sign and size against the running model (or the range served): a model
        # scaled by -1 or 0.001 would drive the stage to its limits
        check_model_change(model, self.model if base is None else base, range_um)
        comp = (EffectCompensator(effects, 1e9 / self.dt_ns, tuple(model.axes),
                                  self.max_res_hz) if effects else None)
        inv = StageInverse(model, use_coupling=self.use_c, dt_s=self.dt_ns * 1e-9)
        # the kernels now, not at a sample (compiled at the first tracked one, the
        # look-ahead's stalled the approach long enough to fault a real-time set)
        StageInverse(model, use_coupling=self.use_c, dt_s=self.dt_ns * 1e-9).warm_kernels()
        lo, hi = model.voltage_limits
        gain = max(abs(stroke_um(m, (lo, hi), plays=model.plays.get(a))) / (hi - lo)
                   for a, m in model.axes.items())
        self.model_base = model  # the next one is checked against it
        return PreparedModel(model, effects, comp, inv, gain)

    def use_model(self, prepared: PreparedModel, armed: bool = False) -> None:
        """Switch to a prepared model at the next sample. ``armed``: ease the jump to
        the new model's answer out."""
        inv = prepared.inverse
        if self.planner.desired is not None:
            inv.reset(v=self.ff, w=self.planner.desired)
        self.handover = {} if self.inv is not None and armed else None
        self.inv, self.model = inv, prepared.model
        self.model_gain = prepared.gain_um_per_V
        self.limits = prepared.model.voltage_limits
        self.ref.set_compensator(prepared.compensator)
        self.effects, self.comp = prepared.effects, prepared.compensator
        self.relearn()
        self.started = self.planner.desired is not None  # else: from the first sample

    # -- the node's inputs, taken and counted -----------------------------------------
    def take_model(self, prepared: PreparedModel, name: str,
                   enabled: Callable[[int], bool] = lambda ns: False) -> None:
        """``use_model``, the model called ``name``: counted, the last refusal cleared;
        armed (a bumpless change) where a model runs and the driver applies commands at
        the last sample answered (``enabled``)."""
        self.use_model(prepared, self.inv is not None and enabled(self.answered_ns))
        self.model_name, self.last_rejection = name, ""
        self.stats["models"] += 1

    def refused(self, kind: str, error: BaseException) -> None:
        """An input refused (a model, trajectory, setpoint or move): counted; a model's
        reason is kept for the diagnostics."""
        self.stats[REFUSED_COUNT[kind]] += 1
        if kind == "model":
            self.last_rejection = str(error)

    def take_trajectory(self, t: ArrayLike, w: PerAxis[np.ndarray], stamp_ns: int,
                        start_ns: int | None, now_ns: int,
                        slew_V_per_s: float | None = None) -> str:
        """``set_trajectory`` for a trajectory the node accepted at ``now_ns``: counted;
        returns what was taken, in words."""
        self.stats["trajectories"] += 1
        self.set_trajectory(t, w, stamp_ns, start_ns, slew_V_per_s)
        return f"trajectory of {len(np.asarray(t))} points accepted" + (
            f", stamped {stamp_ns}: starts in {(stamp_ns - now_ns) * 1e-9:.3f} s"
            if stamp_ns > now_ns else "")

    def take_setpoint(self, target: PerAxis[float], now_ns: int) -> None:
        """A streamed setpoint, arrived at ``now_ns`` (its latency is measured to the
        target tick it first reaches)."""
        self.planner.set_setpoint(target)
        self.setpoint_arrival = now_ns

    def move_request(self, move_id: str, target: PerAxis[float],
                     slew_V_per_s: float | None = None) -> TargetState:
        """A move request (``move``): counted, named ``move #N`` when it has no id."""
        self.stats["moves"] += 1
        return self.move(move_id or f"move #{self.stats['moves']}", target,
                         slew_V_per_s=slew_V_per_s)

    def refuse_move(self, move_id: str, reason: str) -> TargetState:
        """A move request that could not be read: counted, its refusal as a state."""
        self.stats["rejected_moves"] += 1
        return TargetState(move_id[:200], REFUSED, {}, None, {}, {}, self.answered_ns,
                           self.answered_ns, reason)

    def take_sample(self, ns: int, w: PerAxis[float], v_applied: PerAxis[float] | None,
                    lookahead_ns: int, enabled: Callable[[int], bool], realtime: bool,
                    now_ns: int = 0, received_ns: int | None = None) -> SampleResult | None:
        """A decoded sample: the guard's verdict on its stamp (None: a duplicate or a
        stray stamp, counted), its arrival lag (``received_ns``), then ``on_sample``;
        lockstep, a sample that must wait is held for ``resume``."""
        if not self.guard.admit(ns):
            return None
        if received_ns is not None:
            self.lag.add((received_ns - ns) * 1e-9)
        return self._answer(ns, w, v_applied, lookahead_ns, enabled, realtime, now_ns)

    def resume(self, enabled: Callable[[int], bool]) -> SampleResult | None:
        """Lockstep: the held sample answered, once what it waited for is here (None:
        none held, or it still waits)."""
        if self.held is None:
            return None
        (ns, w, v_applied, lookahead_ns), self.held = self.held, None
        return self._answer(ns, w, v_applied, lookahead_ns, enabled, False, 0)

    def _answer(self, ns: int, w: PerAxis[float], v_applied: PerAxis[float] | None,
                lookahead_ns: int, enabled: Callable[[int], bool], realtime: bool,
                now_ns: int) -> SampleResult | None:
        r = self.on_sample(ns, w, v_applied, lookahead_ns, enabled, realtime, now_ns)
        if r.wait:
            self.held = (ns, w, v_applied, lookahead_ns)
            return None
        if r.silent:
            return None
        self.answered_ns = ns
        self.stats["bad_messages"] += sum(a.error is not None for a in r.answers)
        self.stats["saturated"], self.stats["rejoins"] = self.saturated, self.rejoins
        return r

    def sendable(self, a: Answer, now_ns: int | None) -> bool:
        """Whether answer ``a`` can still reach the driver in time (real time:
        ``now_ns``; counted when not); a streamed setpoint's latency is taken at the
        first enabled tick it reaches."""
        if self.setpoint_arrival and now_ns is not None and a.enabled:
            # a streamed setpoint cannot be previewed: it starts at this target tick
            self.sp_latency.add((a.target - self.setpoint_arrival) * 1e-9)
            self.setpoint_arrival = None
        return self.guard.on_time(a.target, now_ns, a.late)

    def status(self, lookahead_ns: int) -> tuple[int, str, Doc]:
        """(level, message, values) for /diagnostics."""
        ms = 1e3
        message = f"{self.planner.phase}, model {self.model_name}, {self.ref.describe()}" + (
            f" (last rejected: {self.last_rejection})" if self.last_rejection else "")
        return 0, message, {
            **self.stats, "model": self.model_name, "phase": self.planner.phase,
            "trajectories_taken_already": self.publications.repeated,
            "effects": self.ref.describe(), "learning": self.learning.describe(),
            "lookahead_ms": lookahead_ns * 1e-6,
            "joint_states_lag_median_ms": self.lag.percentile(50) * ms,
            "joint_states_lag_p99_ms": self.lag.percentile(99) * ms,
            "joint_states_lag_max_ms": self.lag.max_s * ms,
            "setpoint_latency_median_ms": self.sp_latency.percentile(50) * ms,
            "setpoint_latency_max_ms": self.sp_latency.max_s * ms}

    def relearn(self, period: float | None = None, gain: float | None = None) -> None:
        """A learner for the present period, gain, model effects and compensation."""
        if period is not None:
            self.learn_p["learning_period_s"] = period
        if gain is not None:
            self.learn_p["learning_gain"] = gain
        self.learning.configure(self.learn_p["learning_period_s"],
                                self.learn_p["learning_gain"], self.effects, self.comp)

    def set_trajectory(self, t: ArrayLike, w: PerAxis[np.ndarray], stamp_ns: int,
                       start_ns: int | None, slew_V_per_s: float | None = None) -> None:
        """Run a new trajectory (t [s], {axis: um}), stamped ``stamp_ns`` by its sender,
        from ``start_ns`` (None: once approached): the learner starts over, and the
        phase names it ("trajectory of N points stamped S")."""
        points = len(t)  # type: ignore[arg-type]
        self.traj_text = f"trajectory of {points} points stamped {stamp_ns}"
        if points == 1:  # a point-to-point move: its profile, judged on target
            self.move(self.traj_text, {a: float(x[0]) for a, x in w.items()}, start_ns,
                      slew_V_per_s)
            return
        self.planner.set_trajectory(t, w, start_ns=start_ns)
        self.learning.reset()

    def move(self, move_id: str, target: PerAxis[float], start_ns: int | None = None,
             slew_V_per_s: float | None = None) -> TargetState:
        """A point-to-point move to ``target`` ({axis: um}; the others held), called
        ``move_id``: the move's profile (``move_profile``), then held; judged on target
        from its first tick (``SampleResult.on_target``). -> its first state (moving).
        The running move asked again (its id and target: an asker that heard no
        answer sends it once more) is the same move: its present state, not a restart."""
        desired = self.planner.desired or {}
        goal = {a: float(target.get(a, desired.get(a, 0.0))) for a in ("x", "y")}
        if move_id and move_id == self.judge.move_id and goal == self.judge.target:
            return self.judge.report(self.last_ns, dict(self.judge.last[1])
                                     if self.judge.last else {})
        self.planner.set_move(goal, *self.profile(slew_V_per_s), start_ns=start_ns)
        self.learning.reset()
        self.judge.begin(move_id, goal, max(self.last_ns + self.dt_ns, start_ns or 0))
        self.move_text = move_id if move_id == self.traj_text else f"move {move_id}"
        return self.judge.report(self.judge.started_ns, {})

    def profile(self, slew_V_per_s: float | None = None) -> tuple[float, float]:
        """A move's (speed [um/s], acceleration [um/s^2]): ``move_profile``, its speed
        kept within MOVE_SLEW_SHARE of the driver's slew limit at the model's steepest
        mean gain (its stroke over its voltage range; the nominal gain before any
        model), so the feedforward never asks faster than the amplifier goes."""
        speed, accel = self.move_profile
        if slew_V_per_s:
            gain = self.model_gain or self.gain
            speed = min(speed, MOVE_SLEW_SHARE * slew_V_per_s * gain)
        return speed, accel

    def set_live_all(self, values: Doc) -> None:
        """``set_live`` for each of ``values`` (name: value)."""
        for name, value in values.items():
            self.set_live(name, value)

    def set_live(self, name: str, value: object) -> None:
        """A parameter that takes effect at once: ``compensate_effects`` (bool),
        ``learning`` (bool), ``learning_period_s`` [s], ``learning_gain``, and the
        on-target tolerance, window and filter (core/loop/ontarget.py)."""
        if name == "compensate_effects":
            self.ref.on = bool(value)
        elif name == "learning":
            self.learning.enable(bool(value))
        elif name in ("learning_period_s", "learning_gain"):
            self.learn_p[name] = float(value)  # type: ignore[arg-type]
            self.relearn()
        elif name in ON_TARGET_NAMES:
            j = self.judge
            now = {"on_target_tol_um": j.tol, "on_target_window_ms": j.window_s * 1e3,
                   "on_target_filter_ms": j.filter_s * 1e3}
            now[name] = float(value)  # type: ignore[arg-type]
            j.configure(now["on_target_tol_um"], now["on_target_window_ms"] * 1e-3,
                        now["on_target_filter_ms"] * 1e-3)
        else:
            raise DataError(f"feedforward: {name} is no live parameter")

    def on_sample(self, ns: int, w: PerAxis[float], v_applied: PerAxis[float] | None,
                  lookahead_ns: int,
                  enabled: Callable[[int], bool], realtime: bool,
                  now_ns: int = 0) -> SampleResult:
        """The sample stamped ``ns``: the stage at ``w`` [um] with ``v_applied`` [V]
        (None: not reported, the last feedforward stands for it). Its answers are for
        ``ns + lookahead_ns`` (and the ticks a skipped sample leaves unanswered);
        ``enabled(target)`` says whether the driver applies commands there. Real time,
        ``now_ns``: an answer for a tick already past (a backlog after a host stall) is
        not computed, only kept track of (``Answer.late``): the loop catches up at the
        cost of the bookkeeping, not of inverses nobody can use."""
        self.learning.measured(ns, w)
        self.last_ns = ns
        on_target = self.judge.sample(ns, w)
        target = ns + lookahead_ns
        clock = self.planner.clock_s(target)
        no_trajectory = self.wait_traj and self.planner.traj is None and \
            self.planner.profile is None  # (a move is what it waits for, too)
        waiting = no_trajectory or (self.inv is None and 0 < self.model_after_s <= (
            clock if clock is not None else -1))
        if waiting and not realtime:
            return SampleResult(wait=True)
        if no_trajectory:
            return SampleResult(silent=True)
        applied = v_applied or self.ff
        self.measured(ns, w, applied)
        answers = []
        for t in self.targets(target):
            phase, on, late = self.planner.phase, enabled(t), realtime and t < now_ns
            desired, error = self.answer(ns, t, w, applied, on, late)
            answers.append(Answer(t, desired, dict(self.ff), error,
                                  self.planner.phase != phase, on, late))
        return SampleResult(tuple(answers), applied=applied, on_target=on_target,
                            measured=w)

    def measured(self, ns: int, w: PerAxis[float], applied: PerAxis[float]) -> None:
        """The sample at ``ns``: the stage at ``w`` with ``applied`` [V]. The inverse
        starts (or restarts, or takes a new model) from where the stage is, not from the
        model's initial state (hysteresis remembers what this node did not see), and is
        synced to the voltages really applied."""
        if self.inv is not None and not self.started:
            self.inv.reset(v=applied, w=w)
            self.started = True
        elif self.inv is not None:
            self.inv.sync(applied["x"], applied["y"])  # the stage's state at t_k

    def targets(self, target: int) -> range:
        """The target ticks to answer for ``target``: one per tick; after a sample the
        driver skipped (a missed tick), also the targets that sample would have
        answered, so no tick goes without a command of its own."""
        gap = (target - self.last_target) // self.dt_ns if self.last_target else 1
        self.last_target = target
        return range(target - (min(gap, MAX_FILLED_TICKS) - 1) * self.dt_ns, target + 1,
                     self.dt_ns)

    def answer(self, ns: int, target: int, w: PerAxis[float], applied: PerAxis[float],
               enabled: bool, late: bool = False
               ) -> tuple[PerAxis[float] | None, PiezoStageError | None]:
        """(desired position [um], the error that held the last feedforward or None) for
        ``target``; the feedforward [V] is ``self.ff``. Not ``enabled`` (the driver does
        not apply commands): hold where the stage is, at the applied voltage. ``late``:
        the reference is planned (its state kept) but no voltage computed."""
        if not enabled:
            self.ref.hold(self.inv.w if self.inv else w, w)
            self.ff, self.planned = dict(applied), {}
            self.behind, self.rejoin, self.answered, self.asked = False, None, None, None
            return self.planner.desired, None
        desired, h = self.ref.sample(target)
        if late:  # planned (the answers after it step through it), not computed
            self.planned[target], self.behind = h, True
            return desired, None
        desired, h = self._rejoined(target, desired, h)
        self.learning.note(target, desired)
        self.planned[target] = h
        if not self.use_ff:
            return desired, None
        try:
            self.ff = self._voltages(ns, target, h)
        except PiezoStageError as e:  # hold the last feedforward, say why, go on
            return desired, e
        return desired, None

    def _rejoined(self, target: int, desired: PerAxis[float],
                  h: PerAxis[float]) -> tuple[PerAxis[float], PerAxis[float]]:
        """The reference for ``target``: the planner's ``desired`` (and its hysteresis
        target ``h``), or, after a backlog, both offset toward where the reference was
        last asked to be (the driver held that meanwhile). The offset shrinks each tick
        by the planner's own change per tick since the last answer (averaged over the
        ticks between), at least REJOIN_MIN_UM_PER_TICK: the first step from the held
        position is the trajectory's pace, the next ones at most twice it, and the
        controller follows the same reference. (Without it a few ticks' host stall
        leaves tens of volts to step in one tick.)"""
        last, self.answered = self.answered, (target, dict(desired))
        if self.behind and self.asked is not None:
            self.rejoin = {a: self.asked[a] - desired[a] for a in desired if a in self.asked}
            self.rejoins += 1
        self.behind = False
        off = self.rejoin
        if off is not None:
            ticks = (target - last[0]) / self.dt_ns if last and target > last[0] else 1.0
            step = {a: max(REJOIN_MIN_UM_PER_TICK, abs(desired[a] - last[1][a]) / ticks)
                    if last else REJOIN_MIN_UM_PER_TICK for a in off}
            off = {a: o - max(-step[a], min(step[a], o)) for a, o in off.items()}  # to 0
            self.rejoin = off if any(off.values()) else None
            desired = {a: x + off.get(a, 0.0) for a, x in desired.items()}
            h = {a: x + off.get(a, 0.0) for a, x in h.items()}
        self.asked = dict(desired)
        return desired, h

    def _voltages(self, ns: int, target: int, desired: PerAxis[float]) -> PerAxis[float]:
        if self.inv is None:
            return {a: min(max(desired[a] / self.gain, self.limits[0]), self.limits[1])
                    for a in ("x", "y")}
        ahead = [self.planned[t] for t in sorted(self.planned) if ns < t < target]
        self.planned = {t: d for t, d in self.planned.items() if t > ns}
        v = self.inv.step_ahead(ahead, desired["x"], desired["y"])
        if self.handover is not None:  # the offset to the old answer shrinks 1 V a tick
            off = self.handover or {a: self.ff[a] - v[a] for a in v}
            h = HANDOVER_V_PER_TICK
            off = {a: o - max(-h, min(h, o)) for a, o in off.items()}  # toward 0 by h
            v = {a: min(max(v[a] + off[a], self.limits[0]), self.limits[1]) for a in v}
            self.handover = off if any(off.values()) else None
        return v

    def phase(self) -> tuple[str, str]:
        """(the planner's phase, what it follows): ("tracking", "trajectory of 1000
        points stamped 1795..."), ("done", ...) once its last point is reached,
        ("tracking", "setpoint"), ("done", "move M") or (phase, "")."""
        what = self.traj_text if self.planner.traj is not None else (
            self.move_text if self.planner.profile is not None else
            "setpoint" if self.planner.setpoint is not None else "")
        return self.planner.phase, what

    @property
    def saturated(self) -> int:
        """Targets the inverse could not reach within the voltage limits, so far."""
        return self.inv.saturated if self.inv is not None else 0
