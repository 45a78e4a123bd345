"""controller: composite law, feedforward + PID on the measured error (the paper's eq. 17-19).

Each reference, stamped for the target sample, carries the desired position and the
feedforward for it, and the measurement of the sample t_k it answers with the voltage
applied for t_k. The controller computes v = v_ff + PID(asked(t_k) - measured(t_k)) per
axis (the error of the sample just measured against what was asked for it), clamps to
the voltage limits and publishes ``command`` (geometry_msgs/Vector3Stamped, volts)
stamped for the target sample.

The feedback acts only while the driver applies commands (its ``state``, by stamp); the
integral holds while our command for t_k did not come back as the voltage applied at
t_k (the loop is not closed), while the output is clamped, and it restarts after a gap
in the references (a stall). In real time a reference whose target has already passed
is dropped: its command could only arrive late. A non-finite result is never sent.
kp, ki, kd and feedback take effect at run time (feedback switches bumplessly).
With ``relay_amplitude_V`` > 0 the feedback is a relay instead of the PID (core.control
Relay: the autotuning experiment of ``piezo-stage tune --relay``), under the same
arming, clamping and staleness rules.
"""

# first, before the heavy imports: stop signals work from here on (see _signals)
import piezo_stage.nodes._signals  # noqa: F401, I001

# isort: split

import math
import time

from geometry_msgs.msg import Vector3Stamped
from rcl_interfaces.msg import SetParametersResult
from rclpy.node import Node
from sensor_msgs.msg import JointState

from piezo_stage.core.control import LIVE, PARAMETERS, PID, CompositeAxis, PIDGains, Relay
from piezo_stage.core.errors import PiezoStageError
from piezo_stage.core.stamps import StampGuard
from piezo_stage.nodes._common import QOS_DATA
from piezo_stage.nodes._executor import hot_subscription, run_node
from piezo_stage.nodes._loop import Diagnostics, DriverState, Gate
from piezo_stage.nodes._params import declare
from piezo_stage_msgs_adapters import reference_from_msg, voltage_cdr

GAINS = ("kp", "ki", "kd")


class Controller(Node):
    def __init__(self):
        super().__init__("controller")
        p = {name: declare(self, name, default, desc, live=True if name in LIVE else None,
                           **kw) for name, default, desc, kw in PARAMETERS}
        rate = p["control_rate_hz"]
        self.dt_ns = int(round(1e9 / rate))
        self.gains = PIDGains(kp=p["kp"], ki=p["ki"], kd=p["kd"],
                              i_limit_V=p["integral_limit_V"])
        self.limits = tuple(p["voltage_limits_V"])
        self.axes = {a: CompositeAxis(PID(self.gains, 1.0 / rate), self.limits,
                                      p["feedback"]) for a in ("x", "y")}
        relay_V, relay_eps = p["relay_amplitude_V"], p["relay_hysteresis_um"]
        self.relays = {a: Relay(relay_V, relay_eps, 1.0 / rate) for a in self.axes} \
            if relay_V > 0 else {}
        # the driver's announcements: taken before the data in each lean-loop pass
        self.driver = DriverState(self, self.dt_ns, p["thread_priority"])
        self.sent = {}     # target stamp -> (desired um, command V): for t_k's check
        self.last_ns = -1
        self.stamps = StampGuard()  # a stray stamp from the graph never poisons the loop
        self.stats = {"commands": 0, "clamped": 0, "bad_messages": 0, "late_dropped": 0,
                      "not_closed": 0, "non_finite": 0, "restarts": 0, "stray_stamps": 0}
        self.pub = self.create_publisher(Vector3Stamped, "command", QOS_DATA)
        self.gate = Gate(self, [(self.pub, p["min_subscribers"])])
        hot_subscription(self, JointState, "reference", self.on_reference, QOS_DATA, raw=True)
        self.add_on_set_parameters_callback(self.on_set)
        Diagnostics(self, lambda: (0, ("relay experiment" if self.relays else
                                       "composite (feedback on)" if self.axes["x"].feedback
                                       else "feedforward only (feedback off)") +
                                   ", kp {kp:g} ki {ki:g} kd {kd:g}".format(**vars(self.gains)),
                                   {**self.stats, "feedback": self.axes["x"].feedback,
                                    **vars(self.gains)}), "feedback control",
                    rates=[(k, k.replace("_", " "), 0) for k in (
                        "bad_messages", "late_dropped", "non_finite", "clamped")])

    def on_set(self, params):
        g = dict(vars(self.gains))
        g.update({p.name: float(p.value) for p in params if p.name in GAINS})
        try:
            gains = PIDGains(**g)
        except PiezoStageError as e:
            return SetParametersResult(successful=False, reason=str(e))
        for k in GAINS:  # one gains object shared by both axes' PIDs
            setattr(self.gains, k, getattr(gains, k))
        for p in params:
            if p.name == "feedback":
                for ax in self.axes.values():
                    ax.set_feedback(bool(p.value))
        return SetParametersResult(successful=True)

    def on_reference(self, msg):
        try:
            ns, desired, ff, w, applied = reference_from_msg(msg)
        except PiezoStageError:
            self.stats["bad_messages"] += 1
            return
        if not self.stamps.accept(ns):
            self.stats["stray_stamps"] = self.stamps.dropped
            return  # a duplicate changes nothing; a stray stamp is counted
        if self.driver.realtime and ns < time.time_ns():
            self.stats["late_dropped"] += 1  # its command would arrive after its tick
            return
        t_k = ns - self.driver.lookahead_ns
        if self.last_ns >= 0 and ns - self.last_ns > 10 * self.dt_ns:
            self.restart()  # a stall: what the integral knew is stale
        self.last_ns = ns
        enabled = self.driver.enabled(t_k) and self.driver.enabled(ns)
        if not enabled:
            self.restart(count=False)
        asked, sent = self.sent.pop(t_k, (w, None))
        closed = sent is not None and all(abs(sent[a] - applied[a]) < 1e-6 for a in sent)
        self.stats["not_closed"] += enabled and not closed
        v = {}
        lo, hi = self.limits
        for a, ax in self.axes.items():
            if self.relays and enabled:
                u = ff[a] + self.relays[a].update(asked[a] - w[a])
                v[a], clamped = min(max(u, lo), hi), (u > hi or u < lo)
            else:
                v[a], clamped = ax.update(ff[a], asked[a] - w[a], enabled, hold=not closed)
            self.stats["clamped"] += clamped
        if not all(math.isfinite(x) for x in v.values()):
            self.stats["non_finite"] += 1
            self.restart(count=False)
            return
        self.sent = {t: s for t, s in self.sent.items() if t > t_k}
        self.sent[ns] = (desired, v)
        self.stats["commands"] += 1
        self.gate.publish(self.pub, voltage_cdr(ns, v))

    def restart(self, count=True):
        self.stats["restarts"] += count
        for ax in (*self.axes.values(), *self.relays.values()):
            ax.reset()


def main(args=None):
    """Run the controller (the Jazzy form)."""
    return run_node(Controller, args)


if __name__ == "__main__":
    raise SystemExit(main())
