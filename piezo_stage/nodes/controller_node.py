"""controller: composite law, feedforward + PID on the measured error (the paper's eq. 17-19).

Each reference, stamped for the target sample, carries the desired position and the
feedforward for it, and the measurement of the sample t_k it answers with the voltage
applied for t_k. The law is the core's (core/loop/control.py ``CompositeController``, one
``on_sample`` call per reference); this node decodes the reference, drops a stray stamp
and, in real time, a reference whose target has already passed (its command could only
arrive late), and publishes ``command`` (geometry_msgs/Vector3Stamped, volts) stamped
for the target sample. kp, ki, kd and feedback take effect at run time (feedback
switches bumplessly). With ``relay_amplitude_V`` > 0 the feedback is a relay (the
autotuning experiment of ``piezo-stage tune --relay``).
"""

# first, before the heavy imports: stop signals work from here on (see process/signals.py)
import piezo_stage.process.signals  # noqa: F401, I001

# isort: split
import time
from typing import Any

from geometry_msgs.msg import Vector3Stamped
from rcl_interfaces.msg import SetParametersResult
from rclpy.node import Node
from rclpy.parameter import Parameter
from sensor_msgs.msg import JointState

from piezo_stage.core.errors import PiezoStageError
from piezo_stage.core.loop.control import PARAMETERS, CompositeController
from piezo_stage.nodes._common import QOS_DATA
from piezo_stage.nodes._executor import LeanNode, hot_subscription, run_node
from piezo_stage.nodes._loop import Diagnostics, DriverState, Gate
from piezo_stage.nodes._params import declare_schema
from piezo_stage_msgs_adapters import reference_from_msg, voltage_cdr

GAINS = ("kp", "ki", "kd")


class Controller(LeanNode, Node):
    def __init__(self, **node_options: Any) -> None:
        # node_options: a node of a composed loop gets its own arguments (loop_container)
        super().__init__("controller", **node_options)
        p = declare_schema(self, PARAMETERS)  # the gains live through on_set
        self.core = CompositeController(p)  # the control law (core/loop/control.py)
        self.stats = self.core.stats
        # the driver's announcements: taken before the data in each lean-loop pass
        self.driver = DriverState(self, self.core.dt_ns, p["thread_priority"])
        self.guard = self.core.guard  # the stamp and late checks, counted in the core
        self.pub = self.create_publisher(Vector3Stamped, "command", QOS_DATA)
        self.gate = Gate(self, [(self.pub, p["min_subscribers"])])
        hot_subscription(self, JointState, "reference", self.on_reference, QOS_DATA, raw=True)
        self.add_on_set_parameters_callback(self.on_set)
        self.diag = Diagnostics(self, lambda: (0, self.core.describe(), {
            **self.stats, "feedback": self.core.feedback, **vars(self.core.gains)}),
            "feedback control", rates=[(k, k.replace("_", " "), 0) for k in (
                "bad_messages", "late_dropped", "non_finite", "clamped")])

    def final_report(self) -> None:
        self.diag.final()  # (LeanNode) the final counts, before the recorder stops

    def on_set(self, params: list[Parameter]) -> SetParametersResult:
        try:
            self.core.set_gains(**{p.name: p.value for p in params if p.name in GAINS})
        except PiezoStageError as e:
            return SetParametersResult(successful=False, reason=str(e))
        for p in params:
            if p.name == "feedback":
                self.core.set_feedback(bool(p.value))
        return SetParametersResult(successful=True)

    def on_reference(self, msg: bytes) -> None:
        """One reference: decoded, its stamp checked, then the core's one call."""
        try:
            r = reference_from_msg(msg)
        except PiezoStageError:
            self.guard.malformed()
            return
        ns = r.ns
        # a duplicate changes nothing; a stray stamp, or in real time a reference whose
        # command would arrive after its tick, is dropped and counted
        if not self.guard.admit(ns, time.time_ns() if self.driver.realtime else None):
            return
        t_k = ns - self.driver.lookahead_ns
        v = self.core.on_sample(ns, t_k, r.desired_um, r.ff_V, r.measured_um, r.applied_V,
                                self.driver.enabled(t_k) and self.driver.enabled(ns))
        if v is not None:
            self.gate.publish(self.pub, voltage_cdr(ns, v))


def main(args: list[str] | None = None) -> int:
    """Run the controller (the Jazzy form)."""
    return run_node(Controller, args)


if __name__ == "__main__":
    from piezo_stage.process.stopping import exit_now
    exit_now(main())  # flushed, at-exit work done, no finalization (stopping.py)
