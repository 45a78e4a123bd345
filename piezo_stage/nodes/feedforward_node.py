
"""feedforward: the inverse Duhem model turns desired positions into voltages.

Clocked by joint_states: sample k (stamp t_k) is answered by ``reference`` (desired
position, feedforward voltage, the measurement and the voltage applied) stamped t_k plus
the driver's look-ahead. The work is core/loop/feedforward.py's; this node decodes, calls
it and publishes. A model on ``model`` replaces the inverse without a restart.
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
from sensor_msgs.msg import JointState
from std_msgs.msg import String
from trajectory_msgs.msg import JointTrajectory

import piezo_stage_msgs_adapters as msgs
from piezo_stage.core.errors import PiezoStageError
from piezo_stage.core.loop import feedforward as core_ff
from piezo_stage.core.loop.planner import HOLD
from piezo_stage.core.loop.stamps import publication_key, request_key
from piezo_stage.core.model.duhem import StageModel
from piezo_stage.core.types import EffectsBlock, PerAxis
from piezo_stage.nodes._common import QOS_DATA, QOS_EVENTS, QOS_INPUTS, QOS_LATCHED, MessageInfo
from piezo_stage.nodes._executor import LeanNode, hot_subscription, run_node
from piezo_stage.nodes._intake import Input, Inputs, warm_up
from piezo_stage.nodes._latched import LatchedFetch
from piezo_stage.nodes._loop import Diagnostics, DriverState, Gate
from piezo_stage.nodes._params import declare_schema
from piezo_stage_msgs_adapters import TrajectoryRefused

# a trajectory taken: (t [s], w {axis: um}, stamp, start, now [ns])
Decoded = tuple[np.ndarray, PerAxis[np.ndarray], int, int | None, int]


class Feedforward(LeanNode, Node):
    USES_KERNELS = True  # the model's inverse (LeanNode)

    def __init__(self, **node_options: Any) -> None:
        # node_options: a node of a composed loop gets its own arguments (loop_container)
        super().__init__("feedforward", **node_options)
        live = tuple(q for q in core_ff.PARAMETERS if q.live)
        p = self.p = declare_schema(self, tuple(q for q in core_ff.PARAMETERS if not q.live))
        self.max_points = p["max_trajectory_points"]
        # the per-sample work (core/loop/feedforward.py): reference, learning, inverse
        self.core = core_ff.InverseFeedforward.from_params(
            p, int(round(1e9 / p["control_rate_hz"])))
        # the live ones once the core is there (a start-up override calls them at once):
        # effect compensation and learning feedforward (core/loop/learning.py)
        p.update(declare_schema(self, live, {q.name: lambda v, name=q.name: self.core.set_live(
            name, v) for q in live}))
        self.core.set_live_all({q.name: p[q.name] for q in live})
        # an input: decoded and checked, then taken, or refused (``take``); in real time
        # taken apart on the intake's thread
        self.inputs = Inputs({
            "trajectory": Input(self.decode_trajectory, self.take_trajectory,
                                self.reject_trajectory),
            "model": Input(self.prepare_model, self.use_model, self.reject_model)},
            (PiezoStageError,))
        warm_up(lambda data: msgs.trajectory_from_cdr(data, self.p["range_um"],
                                                      self.max_points), (PiezoStageError,))
        # the driver's announcements: taken before the data in each lean-loop pass
        # in real time: heap for taking the largest trajectory it admits (no page fault)
        self.take_bytes = msgs.trajectory_take_bytes(self.max_points)  # (once, not per sample)
        self.driver = DriverState(self, self.core.dt_ns, p["thread_priority"],
                                  heap_bytes=self.take_bytes)
        if p["model_file"]:
            from piezo_stage.io.model_file import load_model
            self.use_model(self.prepare_model((*load_model(p["model_file"]), p["model_file"])))
        self._make_publishers(p["min_subscribers"])
        hot_subscription(self, JointState, "joint_states", self.on_state, QOS_DATA, raw=True,
                         with_info=True)
        # the inputs from outside the loop: at once, or (inputs_once_armed) once the
        # driver has armed, its capacity judged (the launcher's real-time sets): a set
        # refused took nothing, and one --rate auto runs again at a lower rate lost nothing
        self.inputs_waiting = p["inputs_once_armed"] and not p["wait_for_trajectory"]
        if not self.inputs_waiting:
            self.take_inputs()
        self.create_subscription(String, "model", self.on_model, QOS_LATCHED)
        self.diag = Diagnostics(self, lambda: self.core.status(self.driver.lookahead_ns),
                                "inverse feedforward", rates=core_ff.RATES)

    def _make_publishers(self, min_subscribers: int) -> None:
        """The node's publishers (the reference gated on ``min_subscribers`` readers)."""
        publisher = self.create_publisher
        self.pub = publisher(JointState, "reference", QOS_DATA)
        self.phase_pub = publisher(KeyValue, "feedforward/phase", QOS_EVENTS)
        self.phase_pub.publish(msgs.phase_msg(HOLD))
        # what the stage runs, byte for byte as it came, latched: the recorder takes it
        # from here whenever its own match with the sender came late or not at all
        self.accepted_pub = publisher(JointTrajectory, "trajectory/accepted", QOS_LATCHED)
        # a move's state, judged on the sensor (core/loop/ontarget.py), latched
        self.on_target_pub = publisher(DiagnosticArray, "on_target", QOS_LATCHED)
        # a trajectory refused, said to its sender (its frame_id and stamp, the reason)
        self.refused_pub = publisher(DiagnosticArray, "trajectory/refused", QOS_EVENTS)
        self.gate = Gate(self, [(self.pub, min_subscribers)])

    def take_inputs(self) -> None:
        """Subscribe to the trajectories, setpoints and moves of other nodes."""
        self.inputs_waiting = False
        # volatile: every publisher matches, none warns; a latched publisher's trajectory
        # sent before we matched (a restarted feedforward) comes by a brief
        # transient-local fetch (_latched.py); one publication delivered twice is taken
        # once (raw: checked for size, then decoded straight from the bytes, so a long
        # trajectory does not stall the loop in per-point message objects)
        # (a callback of two arguments gets the message info, the publication's
        # identity: rclpy's annotation names the one-argument form only)
        self.create_subscription(JointTrajectory, "trajectory",
                                 self.on_trajectory, QOS_INPUTS, raw=True)  # type: ignore[arg-type]
        self.latched = LatchedFetch(self, JointTrajectory, "trajectory", self.on_trajectory)
        self.create_subscription(PointStamped, "setpoint", self.on_setpoint, QOS_INPUTS)
        # a move is taken at once (with the samples), not at the base executor's turn
        hot_subscription(self, PointStamped, "move", self.on_move, QOS_INPUTS)

    def final_report(self) -> None:
        self.diag.final()  # (LeanNode) the final counts, before the recorder stops

    # -- models ---------------------------------------------------------------------------
    def prepare_model(self, item: str | tuple[StageModel, EffectsBlock | None, str]
                      ) -> tuple[core_ff.PreparedModel, str]:
        """(model, effects, name) or a model message's text -> (prepared, name), checked
        against the last model prepared. Any thread."""
        if isinstance(item, str):
            name = f"model message #{self.core.stats['models'] + 1}"
            model, effects = msgs.model_from_msg(String(data=item))
        else:
            model, effects, name = item
        return self.core.prepare_model(
            model, effects, name, self.driver.limits,
            self.p["range_um"][1] - self.p["range_um"][0], base=self.core.model_base), name

    def use_model(self, prepared_name: tuple[core_ff.PreparedModel, str]) -> None:
        self.core.take_model(*prepared_name, enabled=self.driver.enabled)
        self.get_logger().info(f"using model {prepared_name[1]}")
        self.resume()

    def reject_model(self, e: BaseException) -> None:
        self.core.refused("model", e)
        self.get_logger().error(f"model rejected, keeping {self.core.model_name}: {e}")
        self.resume()

    def on_model(self, msg: String) -> None:
        self.take("model", msg.data)  # a model refused: the old one stays

    # -- trajectories, setpoints, moves ---------------------------------------------------
    def on_trajectory(self, msg: bytes, info: MessageInfo) -> None:
        """A trajectory's bytes and its publication (rclpy's message info)."""
        self.take("trajectory", (bytes(msg), publication_key(info)))

    def take(self, kind: str, item: Any) -> None:
        """An input: inline in lockstep, decoded on the intake's thread in real time."""
        self.inputs.take(kind, item, inline=not self.driver.realtime)

    def decode_trajectory(self, item: tuple[bytes, tuple | None]) -> Decoded | None:
        """(bytes, publication) -> (t, w, stamp, start, now) of a trajectory accepted
        and republished as accepted, else None (taken already). Any thread."""
        # taken already: a publication delivered again (volatile and latched), or a
        # request sent again (``request_key``: a resend that crossed the answer)
        msg, key = item
        if not self.core.publications.admit(key, request_key(msgs.trajectory_header(msg)[0])):
            return None
        try:  # (its size checked before anything is decoded)
            t, w = msgs.trajectory_from_cdr(msg, self.p["range_um"], self.max_points)
            stamp, now = msgs.trajectory_stamp_ns(msg), self.get_clock().now().nanoseconds
            start = core_ff.trajectory_start(stamp, now)  # (the clock: wall or simulated)
        except PiezoStageError as e:  # what its sender names it by, with the reason
            raise TrajectoryRefused(str(e), msg) from None
        self.accepted_pub.publish(msg)  # only what the stage will run
        return t, w, stamp, start, now

    def take_trajectory(self, decoded: Decoded | None) -> None:
        if decoded is not None:
            self.get_logger().info(self.core.take_trajectory(*decoded, self.driver.slew_V_per_s))
            self.publish_phase()
        self.resume()

    def reject_trajectory(self, e: BaseException) -> None:
        self.core.refused("trajectory", e)
        self.get_logger().warning(f"trajectory rejected: {e}")
        self.refused_pub.publish(msgs.trajectory_refusal_msg(
            self.get_clock().now().nanoseconds, e))
        self.resume()

    def publish_phase(self) -> None:
        """The planner's phase and what it follows (the driver relays it on state)."""
        self.phase_pub.publish(msgs.phase_msg(*self.core.phase()))

    def on_setpoint(self, msg: PointStamped) -> None:
        try:
            self.core.take_setpoint(msgs.setpoint_from_msg(msg, self.p["range_um"]),
                                    time.time_ns())
        except PiezoStageError as e:
            self.core.refused("setpoint", e)
            self.get_logger().warning(f"setpoint rejected: {e}")

    def on_move(self, msg: PointStamped) -> None:
        """A move request: the move's profile to its target, judged on target."""
        try:
            state = self.core.move_request(*msgs.move_from_msg(msg, self.p["range_um"]),
                                           self.driver.slew_V_per_s)
        except PiezoStageError as e:  # said on on_target too: the asker waits no more
            self.get_logger().warning(f"move rejected: {e}")
            state = self.core.refuse_move(msg.header.frame_id, str(e))
        self.on_target_pub.publish(msgs.on_target_msg(state))
        self.publish_phase()
        self.resume()

    # -- the samples ----------------------------------------------------------------------
    def on_state(self, msg: bytes, info: MessageInfo | None = None) -> None:
        if self.inputs_waiting and self.driver.armed_once:
            self.take_inputs()
            self.get_logger().info("armed: taking trajectories, setpoints and moves")
        # (heap: twice, the running trajectory and its latched copy live on meanwhile)
        self.inputs.apply_ready(self.driver.realtime, 2 * self.take_bytes)
        try:
            ns, w, v_applied = msgs.joint_state_to_um(msg, with_effort=True)
        except PiezoStageError:
            self.core.guard.malformed()
            return
        rt = self.driver.realtime
        # the per-sample work, one call: stamp guard, reference, learning, inverse
        self.publish(self.core.take_sample(
            ns, w, v_applied, self.driver.lookahead_ns, self.driver.enabled, rt,
            time.time_ns() if rt else 0, info["received_timestamp"] if rt and info else None))

    def resume(self) -> None:
        """Lockstep: answer the sample the loop was held at, once what it waited for is here."""
        self.publish(self.core.resume(self.driver.enabled))

    def publish(self, r: core_ff.SampleResult | None) -> None:
        """A sample's answers (and a move's state, and the phase where it changed)."""
        if r is None:
            return
        if r.on_target is not None:
            self.on_target_pub.publish(msgs.on_target_msg(r.on_target))
        now = time.time_ns() if self.driver.realtime else None
        for a in r.answers:
            if a.error is not None:
                self.get_logger().error(f"feedforward for {a.desired}: {a.error}",
                                        throttle_duration_sec=1.0)
            if a.phase_changed:
                self.publish_phase()
            if self.core.sendable(a, now):  # else it could only reach the driver too late
                assert a.desired is not None and r.applied is not None and r.measured is not None
                self.gate.publish(self.pub, msgs.reference_cdr(a.target, a.desired, a.ff,
                                                               r.measured, r.applied))


def main(args: list[str] | None = None) -> int:
    """Run the feedforward (the Jazzy form)."""
    return run_node(Feedforward, args)


if __name__ == "__main__":
    from piezo_stage.process.stopping import exit_now
    exit_now(main())  # flushed, at-exit work done, no finalization (stopping.py)
