
"""feedforward: the inverse Duhem model turns desired positions into voltages.

Clocked by joint_states: sample k (stamp t_k) is answered by the internal ``reference``
(sensor_msgs/JointState: desired position [m] and feedforward [V] for x, y, plus the
measurement of t_k and the voltage applied for it) stamped t_k + lookahead, the
driver's look-ahead (one period in lockstep; in real time the loop's latency budget,
announced on the driver's ``state``), so a command reaches the driver before the tick
it is for. The planner (core/loop/planner.py) decides the desired position: while the driver
does not apply commands it holds where the stage is (feedforward = the applied voltage,
so enabling is bumpless); enabled, it approaches the goal and then runs the trajectory
clock. The inverse is synced to the voltages really applied and steps through the
commands still in flight before computing the next. A new model on ``model`` replaces
the inverse without a restart. Without any model the feedforward is a nominal gain.
"""

# first, before the heavy imports: stop signals work from here on (see process/signals.py)
import piezo_stage.process.signals  # noqa: F401, I001

# isort: split
import time
from typing import Any

import numpy as np
from diagnostic_msgs.msg import DiagnosticArray, KeyValue
from geometry_msgs.msg import PointStamped
from rclpy.node import Node
from rclpy.qos import QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import JointState
from std_msgs.msg import String
from trajectory_msgs.msg import JointTrajectory

from piezo_stage.core.errors import PiezoStageError
from piezo_stage.core.loop import feedforward as core_ff
from piezo_stage.core.loop.ontarget import REFUSED, TargetState
from piezo_stage.core.loop.planner import HOLD, ReferencePlanner
from piezo_stage.core.loop.stamps import (
    Publications,
    publication_key,
    request_key,
)
from piezo_stage.core.metrics import LatencyHistogram
from piezo_stage.core.model.duhem import StageModel
from piezo_stage.core.types import EffectsBlock, Params, PerAxis
from piezo_stage.nodes._common import QOS_DATA, QOS_EVENTS, QOS_LATCHED, MessageInfo
from piezo_stage.nodes._executor import LeanNode, hot_subscription, run_node
from piezo_stage.nodes._intake import Intake, warm_up
from piezo_stage.nodes._latched import LatchedFetch
from piezo_stage.nodes._loop import Diagnostics, DriverState, Gate
from piezo_stage.nodes._params import declare_schema
from piezo_stage_msgs_adapters import (
    check_trajectory_size,
    joint_state_to_um,
    model_from_msg,
    move_from_msg,
    on_target_msg,
    phase_msg,
    reference_cdr,
    refusal_msg,
    setpoint_from_msg,
    trajectory_from_cdr,
    trajectory_header,
    trajectory_stamp_ns,
    trajectory_take_bytes,
)


class Refused(PiezoStageError):
    """A trajectory refused: the reason, and its header's frame_id and stamp [ns]."""

    def __init__(self, reason: str, frame_id: str, stamp_ns: int) -> None:
        super().__init__(reason)
        self.frame_id, self.stamp_ns = frame_id, stamp_ns


# a trajectory taken: (t [s], w {axis: um}, stamp, start, now [ns])
Decoded = tuple[np.ndarray, PerAxis[np.ndarray], int, int | None, int]


class Feedforward(LeanNode, Node):
    USES_KERNELS = True  # the model's inverse (LeanNode)

    def _core(self, p: Params) -> tuple[ReferencePlanner, core_ff.InverseFeedforward]:
        """The planner and the per-sample core of the node's parameters ``p``."""
        planner = ReferencePlanner(p["approach_speed_um_per_s"],
                                   p["approach_accel_um_per_s2"])
        # the per-sample work (core/loop/feedforward.py): reference, learning, inverse
        opts = core_ff.FeedforwardOptions(
            nominal_um_per_V=p["nominal_um_per_V"], use_coupling=p["use_coupling"],
            inverse=p["inverse_feedforward"], max_resonance_hz=p["max_resonance_inverse_hz"],
            wait_for_trajectory=p["wait_for_trajectory"],
            model_required_after_s=p["model_required_after_s"],
            move_profile=(p["move_speed_um_per_s"], p["move_accel_um_per_s2"]))
        return planner, core_ff.InverseFeedforward(planner, self.dt_ns, opts)

    def _make_publishers(self, min_subscribers: int) -> None:
        """The node's publishers (the reference gated on ``min_subscribers`` readers)."""
        self.pub = self.create_publisher(JointState, "reference", QOS_DATA)
        self.phase_pub = self.create_publisher(KeyValue, "feedforward/phase", QOS_EVENTS)
        self.phase_pub.publish(phase_msg(HOLD))
        # what the stage runs, byte for byte as it came, latched: the recorder takes it
        # from here whenever its own match with the sender came late or not at all
        self.accepted_pub = self.create_publisher(JointTrajectory, "trajectory/accepted",
                                                  QOS_LATCHED)
        # a move's state, judged on the sensor (core/loop/ontarget.py), latched
        self.on_target_pub = self.create_publisher(DiagnosticArray, "on_target",
                                                   QOS_LATCHED)
        # a trajectory refused, said to its sender (its frame_id and stamp, the reason)
        self.refused_pub = self.create_publisher(DiagnosticArray, "trajectory/refused",
                                                 QOS_EVENTS)
        self.gate = Gate(self, [(self.pub, min_subscribers)])

    def __init__(self, **node_options: Any) -> None:
        # node_options: a node of a composed loop gets its own arguments (loop_container)
        super().__init__("feedforward", **node_options)
        live = tuple(q for q in core_ff.PARAMETERS if q.live)
        p = self.p = declare_schema(self, tuple(q for q in core_ff.PARAMETERS if not q.live))
        self.dt_ns = int(round(1e9 / p["control_rate_hz"]))
        self.max_points = p["max_trajectory_points"]
        self.planner, self.core = self._core(p)
        self.ref, self.learning = self.core.ref, self.core.learning
        # the live ones once the core is there (a start-up override calls them at once):
        # effect compensation and learning feedforward (core/loop/learning.py)
        p.update(declare_schema(self, live, {q.name: lambda v, name=q.name: self.core.set_live(
            name, v) for q in live}))
        for q in live:
            self.core.set_live(q.name, p[q.name])
        self.model_name = "nominal"
        self.pending: bytes | None = None  # lockstep: the sample the loop waits at
        # a trajectory is its publication: the same bytes sent again run again, one
        # publication delivered twice (volatile and the latched fetch) runs once
        self.publications = Publications()
        # real time: trajectories and models are taken apart on the intake's thread
        self.intake = Intake({"trajectory": self.decode_trajectory,
                              "model": self.prepare_model}, (PiezoStageError,))
        self.model_base: StageModel | None = None  # the model the next one is checked against
        warm_up(lambda data: trajectory_from_cdr(data, self.p["range_um"], self.max_points),
                (PiezoStageError,))
        # the driver's announcements: taken before the data in each lean-loop pass
        # in real time: heap for taking the largest trajectory it admits (no page fault)
        self.driver = DriverState(self, self.dt_ns, p["thread_priority"],
                                  heap_bytes=trajectory_take_bytes(self.max_points))
        self.last_ns, self.last_rejection = -1, ""
        # a stray stamp from the graph never poisons the loop
        # the core's counters and its guard (stamps, late answers)
        self.stats, self.guard = self.core.stats, self.core.guard
        if p["model_file"]:
            from piezo_stage.io.model_file import load_model
            self.set_model(*load_model(p["model_file"]), p["model_file"])
        self._make_publishers(p["min_subscribers"])
        hot_subscription(self, JointState, "joint_states", self.on_state, QOS_DATA, raw=True,
                         with_info=True)
        self.lag = LatencyHistogram()  # sample stamp -> its arrival here
        self.sp_latency = LatencyHistogram()
        self.setpoint_arrival: int | None = None
        # the inputs from outside the loop: at once, or (inputs_once_armed) once the
        # driver has armed, its capacity judged: what a refused attempt took would be lost
        # with it, when the launcher's --rate auto runs the set again at a lower rate
        self.inputs_waiting = p["inputs_once_armed"] and not p["wait_for_trajectory"]
        if not self.inputs_waiting:
            self.take_inputs()
        self.create_subscription(String, "model", self.on_model, QOS_LATCHED)
        self.diag = Diagnostics(self, lambda: (
            0, f"{self.planner.phase}, model {self.model_name}, {self.ref.describe()}" + (
            f" (last rejected: {self.last_rejection})" if self.last_rejection else ""), {
            **self.stats, "model": self.model_name, "phase": self.planner.phase,
            "trajectories_taken_already": self.publications.repeated,
            "effects": self.ref.describe(), "learning": self.learning.describe(),
            "lookahead_ms": self.driver.lookahead_ns * 1e-6,
            "joint_states_lag_median_ms": self.lag.percentile(50) * 1e3,
            "joint_states_lag_p99_ms": self.lag.percentile(99) * 1e3,
            "joint_states_lag_max_ms": self.lag.max_s * 1e3,
            "setpoint_latency_median_ms": self.sp_latency.percentile(50) * 1e3,
            "setpoint_latency_max_ms": self.sp_latency.max_s * 1e3}), "inverse feedforward",
            rates=core_ff.RATES)

    def take_inputs(self) -> None:
        """Subscribe to the trajectories, setpoints and moves of other nodes."""
        self.inputs_waiting = False
        reliable = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE)
        # volatile: every publisher matches, none warns; a latched publisher's trajectory
        # sent before we matched (a restarted feedforward) comes by a brief
        # transient-local fetch (_latched.py); one publication delivered twice is taken
        # once (raw: checked for size, then decoded straight from the bytes, so a long
        # trajectory does not stall the loop in per-point message objects)
        # (a callback of two arguments gets the message info, the publication's
        # identity: rclpy's annotation names the one-argument form only)
        self.create_subscription(JointTrajectory, "trajectory",
                                 self.on_trajectory, reliable, raw=True)  # type: ignore[arg-type]
        self.latched = LatchedFetch(self, JointTrajectory, "trajectory", self.on_trajectory)
        self.create_subscription(PointStamped, "setpoint", self.on_setpoint, reliable)
        # a move is taken at once (with the samples), not at the base executor's turn
        hot_subscription(self, PointStamped, "move", self.on_move, reliable)

    def final_report(self) -> None:
        self.diag.final()  # (LeanNode) the final counts, before the recorder stops

    def set_model(self, model: StageModel, effects: EffectsBlock | None, name: str) -> None:
        self.use_model(self.prepare_model((model, effects, name)))

    def prepare_model(self, item: str | tuple[StageModel, EffectsBlock | None, str]
                      ) -> tuple[core_ff.PreparedModel, str]:
        """(model, effects, name) or a model message's text -> (prepared, name), checked
        against the last model prepared. Any thread."""
        if isinstance(item, str):
            name = f"model message #{self.stats['models'] + 1}"
            model, effects = model_from_msg(String(data=item))
        else:
            model, effects, name = item
        prepared = self.core.prepare_model(
            model, effects, name, self.driver.limits,
            self.p["range_um"][1] - self.p["range_um"][0], base=self.model_base)
        self.model_base = prepared.model
        return prepared, name

    def use_model(self, prepared_name: tuple[core_ff.PreparedModel, str]) -> None:
        prepared, name = prepared_name
        self.core.use_model(prepared, armed=self.core.inv is not None and
                            self.driver.enabled(self.last_ns))
        self.model_name = name
        self.stats["models"] += 1
        self.last_rejection = ""  # the warning clears with a good model
        self.get_logger().info(f"using model {name}")
        self.resume()

    def reject_model(self, e: BaseException) -> None:
        self.stats["rejected_models"] += 1
        self.last_rejection = str(e)
        self.get_logger().error(f"model rejected, keeping {self.model_name}: {e}")
        self.resume()

    def on_model(self, msg: String) -> None:
        """A model message: parsed, checked and its inverse built inline in lockstep,
        on the intake's thread in real time."""
        if self.driver.realtime:
            self.intake.submit("model", msg.data)
            return
        try:
            self.use_model(self.prepare_model(msg.data))
        except PiezoStageError as e:  # the old model stays
            self.reject_model(e)

    def resume(self) -> None:
        """Lockstep: answer the sample the loop was held at, once what it waited for is here."""
        if self.pending is not None:
            msg, self.pending = self.pending, None
            self.on_state(msg, resumed=True)

    def on_trajectory(self, msg: bytes, info: MessageInfo) -> None:
        """A trajectory's bytes and its publication (rclpy's message info): checked,
        decoded and republished as accepted inline in lockstep, on the intake's thread
        in real time (``_intake.py``)."""
        item = (bytes(msg), publication_key(info))
        if self.driver.realtime:
            self.intake.submit("trajectory", item)
            return
        try:
            self.take_trajectory(self.decode_trajectory(item))
        except PiezoStageError as e:
            self.reject_trajectory(e)

    def decode_trajectory(self, item: tuple[bytes, tuple | None]) -> Decoded | None:
        """(bytes, publication) -> (t, w, stamp, start, now) of a trajectory that is
        accepted (every check passed, its stamp's too), republished as accepted; None
        for a publication taken already, delivered again (volatile and latched), and for
        a request taken already, sent again (``request_key``: a resend that crossed the
        answer). Any thread (one at a time)."""
        msg, key = item
        request = request_key(trajectory_header(msg)[0])
        if not self.publications.admit(key, request):
            return None
        try:
            check_trajectory_size(msg, self.max_points)  # before anything else
            t, w = trajectory_from_cdr(msg, self.p["range_um"], self.max_points)
            stamp, now = trajectory_stamp_ns(msg), self.get_clock().now().nanoseconds
            start = core_ff.trajectory_start(stamp, now)  # (the clock: wall or simulated)
        except PiezoStageError as e:  # what its sender names it by, with the reason
            raise Refused(str(e), *trajectory_header(msg)) from None
        self.accepted_pub.publish(msg)  # only what the stage will run
        return t, w, stamp, start, now

    def take_trajectory(self, decoded: Decoded | None) -> None:
        if decoded is not None:
            t, w, stamp, start, now = decoded
            self.stats["trajectories"] += 1
            self.core.set_trajectory(t, w, stamp, start, self.driver.slew_V_per_s)
            self.get_logger().info(f"trajectory of {len(t)} points accepted" + (
                f", stamped {stamp}: starts in {(stamp - now) * 1e-9:.3f} s"
                if stamp > now else ""))
            self.publish_phase()
        self.resume()

    def reject_trajectory(self, e: BaseException) -> None:
        self.stats["rejected_trajectories"] += 1
        self.get_logger().warning(f"trajectory rejected: {e}")
        frame_id, stamp = (e.frame_id, e.stamp_ns) if isinstance(e, Refused) else ("", 0)
        self.refused_pub.publish(refusal_msg(self.get_clock().now().nanoseconds,
                                             frame_id, stamp, str(e)))
        self.resume()

    def publish_phase(self) -> None:
        """The planner's phase and what it follows, as data (core: ``phase``); the driver
        relays it on /stage/state, so an outside node can wait for the end."""
        self.phase_pub.publish(phase_msg(*self.core.phase()))

    def on_setpoint(self, msg: PointStamped) -> None:
        try:
            self.planner.set_setpoint(setpoint_from_msg(msg, self.p["range_um"]))
            self.setpoint_arrival = time.time_ns()  # for its arrival-to-applied latency
        except PiezoStageError as e:
            self.stats["rejected_setpoints"] += 1
            self.get_logger().warning(f"setpoint rejected: {e}")

    def on_move(self, msg: PointStamped) -> None:
        """A move request: the move's profile to its target, judged on target."""
        try:
            move_id, target = move_from_msg(msg, self.p["range_um"])
        except PiezoStageError as e:  # said on on_target too: the asker waits no more
            self.stats["rejected_moves"] += 1
            self.get_logger().warning(f"move rejected: {e}")
            self.on_target_pub.publish(on_target_msg(TargetState(
                msg.header.frame_id[:200], REFUSED, {}, None, {}, {}, self.last_ns,
                self.last_ns, str(e))))
            return
        self.stats["moves"] += 1
        self.on_target_pub.publish(on_target_msg(self.core.move(
            move_id or f"move #{self.stats['moves']}", target,
            slew_V_per_s=self.driver.slew_V_per_s)))
        self.publish_phase()
        self.resume()

    def on_state(self, msg: bytes, info: MessageInfo | None = None,
                 resumed: bool = False) -> None:
        if self.inputs_waiting and self.driver.armed_once:
            self.take_inputs()
            self.get_logger().info("armed: taking trajectories, setpoints and moves")
        if self.driver.realtime and self.intake.thread is None:
            # twice: the running trajectory and its latched copy live on meanwhile
            self.intake.start(2 * trajectory_take_bytes(self.max_points))
        for kind, done in self.intake.ready():  # real time: what the intake finished
            if isinstance(done, PiezoStageError):
                (self.reject_trajectory if kind == "trajectory" else self.reject_model)(done)
            else:
                (self.take_trajectory if kind == "trajectory" else self.use_model)(done)
        try:
            ns, w, v_applied = joint_state_to_um(msg, with_effort=True)
        except PiezoStageError:
            self.guard.malformed()
            return
        if not resumed and not self.guard.admit(ns):
            return  # a duplicate changes nothing; a stray stamp is counted
        if self.driver.realtime and info:
            self.lag.add((info["received_timestamp"] - ns) * 1e-9)
        # the per-sample work, one call: reference, learning, inverse (core/loop)
        r = self.core.on_sample(ns, w, v_applied, self.driver.lookahead_ns,
                                self.driver.enabled, self.driver.realtime,
                                time.time_ns() if self.driver.realtime else 0)
        if r.wait:
            self.pending = msg  # lockstep: the loop waits here
            return
        if r.silent:
            return
        self.last_ns = ns
        if r.on_target is not None:
            self.on_target_pub.publish(on_target_msg(r.on_target))
        for a in r.answers:
            self.publish_answer(a, w, r.applied)
        self.stats["saturated"], self.stats["rejoins"] = self.core.saturated, self.core.rejoins

    def publish_answer(self, a: core_ff.Answer, w: PerAxis[float],
                       applied: PerAxis[float] | None) -> None:
        """One target's reference (and the phase first, when it changed)."""
        if a.error is not None:
            self.stats["bad_messages"] += 1
            self.get_logger().error(f"feedforward for {a.desired}: {a.error}",
                                    throttle_duration_sec=1.0)
        if a.phase_changed:
            self.publish_phase()
        if self.setpoint_arrival and self.driver.realtime and a.enabled:
            # a streamed setpoint cannot be previewed: it starts at this target tick
            self.sp_latency.add((a.target - self.setpoint_arrival) * 1e-9)
            self.setpoint_arrival = None
        if not self.guard.on_time(a.target, time.time_ns() if self.driver.realtime else None,
                                  a.late):
            return  # it could only reach the driver too late (counted)
        assert a.desired is not None and applied is not None  # (an answer has both)
        self.gate.publish(self.pub, reference_cdr(a.target, a.desired, a.ff, w, applied))


def main(args: list[str] | None = None) -> int:
    """Run the feedforward (the Jazzy form)."""
    return run_node(Feedforward, args)


if __name__ == "__main__":
    from piezo_stage.process.stopping import exit_now
    exit_now(main())  # flushed, at-exit work done, no finalization (stopping.py)
