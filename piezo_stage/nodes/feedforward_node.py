"""feedforward: the inverse Duhem model turns desired positions into voltages.

Clocked by joint_states: on sample k it samples the desired trajectory (or the last
streamed setpoint) at t_{k+1}, inverts the 2-axis model exactly (coupling included)
and publishes the internal ``reference`` (sensor_msgs/JointState: desired position
[m] and feedforward [V] for x, y, plus the measurement of t_k) stamped t_{k+1}. A new model on ``model`` replaces the
inverse without a restart, continuing from the current voltage and position.
Without any model the feedforward is a linear nominal gain.
"""

import numpy as np
from geometry_msgs.msg import PointStamped
from sensor_msgs.msg import JointState
from std_msgs.msg import String
from trajectory_msgs.msg import JointTrajectory

from piezo_stage.core.errors import PiezoStageError
from piezo_stage.core.inverse import StageInverse
from piezo_stage.nodes._common import (QOS_DATA, QOS_LATCHED, Diagnostics, Gate, declare,
                                       hot_subscription, run)
from piezo_stage_msgs_adapters import (joint_state_to_um, model_from_msg, reference_cdr,
                                       setpoint_from_msg, trajectory_from_msg)
from rclpy.node import Node
from rclpy.qos import QoSProfile, ReliabilityPolicy


class Feedforward(Node):
    def __init__(self):
        super().__init__("feedforward")
        self.dt_ns = int(round(1e9 / declare(self, "control_rate_hz", 1000.0, "control "
                                             "rate [Hz]", read_only=True, lo=1.0, hi=1e5)))
        model_file = declare(self, "model_file", "", "initial model YAML ('' = none until "
                             "one arrives on model)")
        self.gain = declare(self, "nominal_um_per_V", 0.5, "gain used before any model "
                            "[um/V]", lo=0.01, hi=100.0)
        self.use_c = declare(self, "use_coupling", True, "invert the coupling (decoupling)")
        self.range = declare(self, "range_um", [-10.0, 90.0], "accepted target range [um]")
        self.hold_s = declare(self, "model_required_after_s", 0.0, "lockstep: hold the "
                              "loop at this trajectory time until a model arrives (0: never)")
        self.pending = None
        self.limits = (0.0, 150.0)
        self.inv, self.model_name, self.traj, self.t_start = None, "nominal", None, None
        self.desired, self.last_ns, self.ff = None, -1, {"x": 0.0, "y": 0.0}
        self.stats = {"rejected_trajectories": 0, "rejected_setpoints": 0, "models": 0,
                      "saturated": 0, "bad_messages": 0}
        if model_file:
            from piezo_stage.io.model_file import load_model
            self.set_model(load_model(model_file)[0], model_file)
        self.pub = self.create_publisher(JointState, "reference", QOS_DATA)
        self.gate = Gate(self, [(self.pub, declare(self, "min_subscribers", 0,
                                                   "reference subscribers to wait for"))])
        hot_subscription(self, JointState, "joint_states", self.on_state, QOS_DATA, raw=True)
        reliable = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE)
        self.create_subscription(JointTrajectory, "trajectory", self.on_trajectory, reliable)
        self.create_subscription(PointStamped, "setpoint", self.on_setpoint, reliable)
        self.create_subscription(String, "model", self.on_model, QOS_LATCHED)
        Diagnostics(self, lambda: (0, "ok", {**self.stats, "model": self.model_name}))

    def set_model(self, model, name):
        inv = StageInverse(model, use_coupling=self.use_c)
        if self.desired is not None:
            inv.reset(v=self.ff, w=self.desired)
        self.inv, self.model_name, self.limits = inv, name, model.voltage_limits
        self.stats["models"] += 1
        self.get_logger().info(f"using model {name}")

    def on_model(self, msg):
        try:
            self.set_model(model_from_msg(msg)[0], f"model message #{self.stats['models'] + 1}")
        except PiezoStageError as e:
            self.get_logger().error(f"model rejected: {e}")
        if self.pending is not None and self.inv is not None:
            msg, self.pending = self.pending, None
            self.on_state(msg)

    def on_trajectory(self, msg):
        try:
            self.traj = trajectory_from_msg(msg, self.range)
            self.t_start = None
            self.get_logger().info(f"trajectory of {len(self.traj[0])} points accepted")
        except PiezoStageError as e:
            self.stats["rejected_trajectories"] += 1
            self.get_logger().warning(f"trajectory rejected: {e}")

    def on_setpoint(self, msg):
        try:
            self.desired, self.traj = setpoint_from_msg(msg, self.range), None
        except PiezoStageError as e:
            self.stats["rejected_setpoints"] += 1
            self.get_logger().warning(f"setpoint rejected: {e}")

    def on_state(self, msg):
        try:
            ns, w, v_applied = joint_state_to_um(msg, with_effort=True)
        except PiezoStageError:
            self.stats["bad_messages"] += 1
            return
        if ns <= self.last_ns:
            return  # duplicates change nothing
        self.last_ns, t_next = ns, ns + self.dt_ns
        if self.desired is None:
            self.desired = dict(w)
        if self.traj is not None:
            if self.t_start is None:
                self.t_start = t_next
            t, traj = self.traj
            tau = (t_next - self.t_start) * 1e-9
            if self.inv is None and 0 < self.hold_s <= tau:
                self.pending, self.last_ns = msg, ns - 1  # resume on the model
                return
            self.desired = {a: float(np.interp(tau, t, traj[a])) if a in traj
                            else self.desired[a] for a in ("x", "y")}
        if self.inv is not None:
            if v_applied is not None:  # follow what the stage really got
                self.inv.sync(v_applied["x"], v_applied["y"])
            vx, vy, sat = self.inv.step(self.desired["x"], self.desired["y"],
                                        commit=v_applied is None)
            self.stats["saturated"] = self.inv.saturated
            self.ff = {"x": vx, "y": vy}
        else:
            self.ff = {a: min(max(self.desired[a] / self.gain, self.limits[0]), self.limits[1])
                       for a in ("x", "y")}
        self.gate.publish(self.pub, reference_cdr(t_next, self.desired, self.ff, w))


def main(args=None):
    return run(Feedforward, args)


if __name__ == "__main__":
    raise SystemExit(main())
