"""trajectory: publishes a whole desired trajectory (trajectory_msgs/JointTrajectory).

Kinds: sine, variable_sine, steps, triangle, csv, the paper's preset
y(t) = 21 + 24 sin(2 pi f t - pi/2) um (``seed``), and ``raster`` (a microscope's scan:
``frequency_hz`` is its line rate, ``lines``, ``scan_size_um``, ``scan_center_um``,
``corner``, ``slow`` and ``fast_axis`` shape it). ``excite_s`` > 0 prepends a
full-stroke sine of that length (x at 1 Hz, y at ``excite_y_hz``), so the identifier
has loops to learn from, and can tell each axis from its coupling, before the tracking
starts. Published once its consumers listen, again on a parameter change, and again
when the feedforward says it holds with no trajectory a second after the send (it
matched too late for it, or it was restarted): the publisher is latched, but the set's
nodes take trajectories on a volatile subscription and fetch no history from this node
(nodes/_latched.py), so a default-QoS publisher on the graph sees no QoS warning. At
most RESENDS times until the feedforward reports something else. Each publication is
named as a request (``header.frame_id`` ``request:<node>@<start>#<n>``,
core/loop/stamps.py ``request_key``) and a resend is the same request: the feedforward
takes a request once, so a resend that crossed the feedforward's answer (a loaded host
delays either) is dropped there, not run again from its start. It is sent only on the
feedforward's word: it holds with none, it has not answered this request on
trajectory/accepted, and the node itself was not held up (a timer tick that comes
late, on a loaded host, may have messages waiting that say otherwise: it waits one
more tick).
"""

# first, before the heavy imports: stop signals work from here on (see process/signals.py)
import piezo_stage.process.signals  # noqa: F401, I001

# isort: split
import time

import numpy as np
from diagnostic_msgs.msg import KeyValue
from rcl_interfaces.msg import SetParametersResult
from rclpy.node import Node
from rclpy.parameter import Parameter
from trajectory_msgs.msg import JointTrajectory

from piezo_stage.core.errors import PiezoStageError
from piezo_stage.core.loop.planner import HOLD
from piezo_stage.core.loop.stamps import REQUEST_PREFIX
from piezo_stage.core.loop.trajectory import generate
from piezo_stage.core.types import Doc
from piezo_stage.nodes._common import QOS_EVENTS, QOS_LATCHED, steady_timer
from piezo_stage.nodes._executor import LeanNode, run_node
from piezo_stage.nodes._loop import Diagnostics, Gate
from piezo_stage.nodes._params import declare_schema
from piezo_stage.nodes.declared import TRAJECTORY
from piezo_stage_msgs_adapters import phase_from_msg, trajectory_msg

RESENDS, RESEND_AFTER_S, TICK_S = 3, 1.0, 0.25

class Trajectory(LeanNode, Node):
    def __init__(self) -> None:
        super().__init__("trajectory")
        # live: a set builds and publishes the new trajectory (or is refused with why)
        self.p = declare_schema(self, TRAJECTORY)
        wait_for = self.p.pop("min_subscribers")  # (of the publisher, not the trajectory)
        self.pub = self.create_publisher(JointTrajectory, "trajectory", QOS_LATCHED)
        self.gate = Gate(self, [(self.pub, wait_for)])
        self.published, self.resent, self.last = 0, 0, None
        self.ff_phase: tuple[str, str] | None = None
        self.sent_at, self.budget = 0.0, RESENDS  # (last: None)
        self.accepted, self.ticked_at = False, time.monotonic()  # (this publication's)
        # this node's requests: its name and start, so a restarted node's are new ones
        self.request = f"{REQUEST_PREFIX}{self.get_fully_qualified_name()}@{time.time_ns():x}"
        self.add_on_set_parameters_callback(self.on_set)
        self.publish(self.build(self.p))
        self.create_subscription(KeyValue, "feedforward/phase", self.on_phase, QOS_EVENTS)
        self.create_subscription(JointTrajectory, "trajectory/accepted", self.on_accepted,
                                 QOS_EVENTS)
        steady_timer(self, TICK_S, self.resend_if_held)
        self.diag = Diagnostics(self, lambda: (
            0, f"{self.published} trajectories published (last: {self.p.get('kind')})",
            {"published": self.published, "resent": self.resent, **self.p}), "trajectory")

    def final_report(self) -> None:
        self.diag.final()  # (LeanNode) the final counts, before the recorder stops

    def build(self, p: Doc) -> JointTrajectory:
        table = None
        if p["kind"] == "csv":
            from piezo_stage.io.csv_table import read_table
            table = read_table(p["csv_path"], ["t", "wx", "wy"])
        scan = {"lines": p["lines"], "size_um": list(p["scan_size_um"]),
                "center_um": list(p["scan_center_um"]), "corner": p["corner"],
                "slow": p["slow"], "fast_axis": p["fast_axis"]}
        t, w = generate(p["kind"], p["duration_s"], p["dt_s"], p["frequency_hz"],
                        p["center_um"], p["amplitude_um"], table=table, scan=scan)
        if p["excite_s"] > 0:
            te, we = generate("sine", p["excite_s"], p["dt_s"], 1.0, p["excite_center_um"],
                              p["excite_amplitude_um"])
            we["y"] = generate("sine", p["excite_s"], p["dt_s"], p["excite_y_hz"],
                               p["excite_center_um"], p["excite_amplitude_um"])[1]["y"]
            # blend into the tracking start over 0.2 s so no step is asked for
            tb = np.arange(1, int(0.2 / p["dt_s"]) + 1) * p["dt_s"]
            wb = {a: we[a][-1] + (w[a][0] - we[a][-1]) * (1 - np.cos(np.pi * tb / 0.2)) / 2
                  for a in w}
            t = np.concatenate([te, te[-1] + tb, te[-1] + tb[-1] + p["dt_s"] + t])
            w = {a: np.concatenate([we[a], wb[a], w[a]]) for a in w}
        return trajectory_msg(t, w)

    def publish(self, msg: JointTrajectory) -> None:
        msg.header.frame_id = f"{self.request}#{self.published + 1}"
        self.gate.publish(self.pub, msg)
        self.published += 1
        self.last, self.sent_at, self.budget = msg, time.monotonic(), RESENDS
        self.accepted = False

    def on_accepted(self, msg: JointTrajectory) -> None:
        if self.last is not None and msg.header.frame_id == self.last.header.frame_id:
            # the feedforward took this request (its name: the bytes of a resend crossed)
            self.accepted = True

    def on_phase(self, msg: KeyValue) -> None:
        was, self.ff_phase = self.ff_phase, phase_from_msg(msg)
        if self.ff_phase != (HOLD, ""):
            self.budget = RESENDS  # it has one: a later restart may ask again
        elif was is not None and was != (HOLD, ""):
            self.accepted = False  # it had one and holds with none: restarted

    def resend_if_held(self) -> None:
        """The last trajectory again when the feedforward still holds with none a
        second after it went out (a message the gate held goes out when it opens)."""
        now, ticked = time.monotonic(), self.ticked_at
        self.ticked_at = now
        if now - ticked > 2 * TICK_S:  # held up: what waits may say otherwise
            return
        sent = max(self.sent_at, self.gate.opened_at)
        if (self.ff_phase == (HOLD, "") and not self.accepted and self.gate.open
                and self.last is not None and self.budget > 0
                and now - sent > RESEND_AFTER_S):
            self.pub.publish(self.last)
            self.resent += 1
            self.budget -= 1
            self.sent_at = time.monotonic()

    def on_set(self, params: list[Parameter]) -> SetParametersResult:
        p = dict(self.p)
        p.update({x.name: x.value for x in params if x.name in p})
        try:
            msg = self.build(p)
        except PiezoStageError as e:
            return SetParametersResult(successful=False, reason=str(e))
        self.p = p
        self.publish(msg)
        return SetParametersResult(successful=True)


def main(args: list[str] | None = None) -> int:
    """Run the trajectory node (the Jazzy form)."""
    return run_node(Trajectory, args)


if __name__ == "__main__":
    from piezo_stage.process.stopping import exit_now
    exit_now(main())  # flushed, at-exit work done, no finalization (stopping.py)
