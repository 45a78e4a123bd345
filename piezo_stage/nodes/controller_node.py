"""controller: composite law, feedforward + PID on the measured error (seed eq. 17-19).

Each reference stamped t_{k+1} carries the desired position and the feedforward for
t_{k+1} and the measurement of t_k they were computed from; the controller computes
v = v_ff + PID(asked - measured) per axis (the error of the sample just measured
against what was asked for it), clamps to the voltage limits and publishes ``command``
(geometry_msgs/Vector3Stamped, volts) stamped t_{k+1}. Decoupling lives in the
feedforward's joint inverse (see core/control.py).
"""

from geometry_msgs.msg import Vector3Stamped
from sensor_msgs.msg import JointState

from piezo_stage.core.control import PID, PIDGains, composite
from piezo_stage.core.errors import PiezoStageError
from piezo_stage.nodes._common import (QOS_DATA, Diagnostics, Gate, declare,
                                       hot_subscription, run)
from piezo_stage_msgs_adapters import reference_from_msg, voltage_cdr
from rclpy.node import Node


class Controller(Node):
    def __init__(self):
        super().__init__("controller")
        rate = declare(self, "control_rate_hz", 1000.0, "control rate [Hz]", read_only=True,
                       lo=1.0, hi=1e5)
        self.dt_ns = int(round(1e9 / rate))
        g = PIDGains(kp=declare(self, "kp", 0.2, "proportional gain [V/um]", lo=0.0, hi=100.0),
                     ki=declare(self, "ki", 150.0, "integral gain [V/(um s)]", lo=0.0, hi=1e5),
                     kd=declare(self, "kd", 0.0, "derivative gain [V s/um]", lo=0.0, hi=10.0))
        self.feedback = declare(self, "feedback", True, "PID on (false: feedforward only)")
        self.limits = tuple(declare(self, "voltage_limits_V", [0.0, 150.0], "clamp [V]"))
        self.pid = {a: PID(g, 1.0 / rate) for a in ("x", "y")}
        self.asked, self.last_ns = None, -1
        self.stats = {"commands": 0, "clamped": 0, "bad_messages": 0}
        self.pub = self.create_publisher(Vector3Stamped, "command", QOS_DATA)
        self.gate = Gate(self, [(self.pub, declare(self, "min_subscribers", 0,
                                                   "command subscribers to wait for"))])
        hot_subscription(self, JointState, "reference", self.on_reference, QOS_DATA, raw=True)
        Diagnostics(self, lambda: (0, "ok", {**self.stats, "feedback": self.feedback}))

    def on_reference(self, msg):
        try:
            ns, desired, ff, w = reference_from_msg(msg)
        except PiezoStageError:
            self.stats["bad_messages"] += 1
            return
        if ns <= self.last_ns:
            return  # a duplicate changes nothing
        self.last_ns = ns
        # the error of the sample just measured (t_k) against what was asked for t_k;
        # desired(t_{k+1}) - w(t_k) would mistake the trajectory's own motion for error
        asked = self.asked if self.asked is not None else w
        self.asked = desired
        v = {}
        for a in ("x", "y"):
            if self.feedback:
                v[a], clamped = composite(ff[a], asked[a] - w[a], self.pid[a], self.limits)
                self.stats["clamped"] += clamped
            else:
                v[a] = min(max(ff[a], self.limits[0]), self.limits[1])
        self.stats["commands"] += 1
        self.gate.publish(self.pub, voltage_cdr(ns, v))


def main(args=None):
    return run(Controller, args)


if __name__ == "__main__":
    raise SystemExit(main())
