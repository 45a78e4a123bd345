"""stage_driver: the stage (sim, NI-DAQ, PI, NV200 or replay) on topics; the last line of
defence. The sample loop itself (the sample clock, the command schedule, the arming
supervisor, the voltage and slew clamp) is core/sample_loop.py; this node gives it its
parameters and topics: commands in, joint_states (and the simulated stage's true
position) out, the latched ``state`` topic and /diagnostics; ``arm`` (std_srvs/SetBool)
arms and disarms; ``estop`` (std_srvs/Trigger). In real time the executor calls
``on_lean_tick`` at each tick (the DAQ's read blocks until its clock).
"""

# first, before the heavy imports: stop signals work from here on (see _signals)
import piezo_stage.nodes._signals  # noqa: F401, I001

# isort: split

import time

import rclpy
from diagnostic_msgs.msg import DiagnosticArray, KeyValue
from geometry_msgs.msg import PointStamped, Vector3Stamped
from rclpy.duration import Duration
from rclpy.node import Node
from rosgraph_msgs.msg import Clock
from sensor_msgs.msg import JointState
from std_srvs.srv import SetBool, Trigger

from piezo_stage.core.arming import ENABLED, ArmingParams
from piezo_stage.core.arming import PARAMETERS as ARMING
from piezo_stage.core.errors import BackendFault, DataError
from piezo_stage.core.sample_loop import PARAMETERS, RATES, SampleLoop, check_mode
from piezo_stage.drivers import BACKEND_PARAMS, done_line, make_backend
from piezo_stage.nodes._common import QOS_DATA, QOS_EVENTS, steady_timer
from piezo_stage.nodes._executor import hot_subscription, run_node
from piezo_stage.nodes._loop import Diagnostics, Gate, missing_links, set_realtime_priority
from piezo_stage.nodes._params import declare
from piezo_stage.nodes._signals import STATE as STOP_STATE
from piezo_stage.nodes._signals import watch as watch_stop
from piezo_stage_msgs_adapters import (
    arming_state_msg,
    clock_msg,
    joint_state_cdr,
    phase_from_msg,
    point_cdr,
    voltage_from_msg,
)


class StageDriver(Node):
    def __init__(self):
        super().__init__("stage_driver")
        STOP_STATE.watch_s = 12.0  # its stop ramps and closes the backend (see below)
        d = lambda *a, **k: declare(self, *a, **k)  # noqa: E731
        p = self.p = {name: d(name, default, desc, **kw)
                      for name, default, desc, kw in PARAMETERS}
        check_mode(p["backend"], p["mode"], self.get_parameter("use_sim_time").value)
        defaults = ArmingParams()
        arm = ArmingParams(**{field: d(name, getattr(defaults, field), desc, **(
            {"lo": r[0], "hi": r[1]} if r else {})) for name, field, desc, r in ARMING})
        bp = {k: d(k, default, desc) for k, default, desc in BACKEND_PARAMS}
        self.backend = make_backend(p["backend"], p["control_rate_hz"], bp, arm.safe_V)
        self.lock = p["mode"] == "lockstep"
        self.link, self.failed = "", None  # the missing links; the hardware's fault
        self.jpub = self.create_publisher(JointState, "joint_states", QOS_DATA)
        self.tpub = self.create_publisher(PointStamped, "sim/true_position", QOS_DATA)
        self.spub = self.create_publisher(DiagnosticArray, "state", QOS_EVENTS)
        # lockstep: the sample clock is the set's clock (a bag then has one time base)
        self.clock_pub = self.create_publisher(Clock, "/clock", 10) \
            if self.lock and p["clock_period_s"] > 0 else None
        self.loop = SampleLoop(self.backend, arm, p["control_rate_hz"], self.lock,
                               p["lookahead_s"], p["max_steps"], self.on_state_change,
                               p["clock_period_s"], p["max_steps_from_arming"])
        self.sup = self.loop.sup
        # lockstep: nothing is published before every consumer listens; real time: the
        # sample clock starts then (the first publishes to new readers are slow)
        self.gate = Gate(self, [(self.jpub, p["min_subscribers"]),
                                (self.tpub,
                                 p["min_record_subscribers"] * (p["backend"] == "sim"))])
        hot_subscription(self, Vector3Stamped, "command", self.on_command, QOS_DATA,
                         raw=True, with_info=True)
        self.create_subscription(KeyValue, "feedforward/phase", self.on_phase, QOS_EVENTS)
        self.create_service(SetBool, "arm", self.on_arm)
        self.create_service(Trigger, "estop", self.on_estop)
        steady_timer(self, 0.5, self.check_links)
        self.diag = Diagnostics(self, self.status, "sample loop", self.backend.hardware_id,
                                rates=RATES)
        self.on_state_change(self.sup.state, self.sup.reason, 0)
        if self.lock:
            self.tick(0, None, False)  # sample 0: the stage at rest
        else:
            self.lean_deadline = 0.0   # the first real-time tick: now
            self.lean_take_at_tick = True  # commands are due at a later tick: no wake each
            self.rt_priority = set_realtime_priority(p["thread_priority"], self.get_logger())

    def on_lean_tick(self):
        """Real time: the sample clock's tick."""
        if not self.gate.open:
            self.lean_deadline = time.monotonic() + 0.01  # consumers still matching
            return
        j, cmd, on_time, missed = self.loop.next_tick(
            time.monotonic(), lambda: self.get_clock().now().nanoseconds)
        self.tick(j, cmd, on_time, missed)
        self.lean_deadline = self.loop.clock.deadline(self.loop.j + 1)

    def on_command(self, msg, info):
        try:
            ns, v = voltage_from_msg(msg)
        except DataError:  # NaN/inf or malformed: never counts as a fresh command
            self.loop.stats["rejected"] += 1
            return
        recv = 0 if self.lock else (info.get("received_timestamp")
                                    or self.get_clock().now().nanoseconds)
        if self.loop.command(ns, v, recv):  # lockstep: the next sample's command
            self.tick(self.loop.j + 1, v, True)

    def tick(self, j, cmd, on_time, missed=0):
        """Take sample ``j`` and publish it; exit once a stop has ramped down."""
        if self.loop.ended(j):
            return self.done()
        if self.loop.past_max_steps(j):
            self.request_shutdown()  # real time: ramp to the safe voltage, then exit
        now = self.loop.stamp(j) if self.lock else self.get_clock().now().nanoseconds
        try:
            s = self.loop.step(j, cmd, on_time, now, self.link, missed)
        except BackendFault as e:
            return self.hardware_failed(e)
        self.gate.publish(self.jpub, joint_state_cdr(s.ns, s.w, s.applied))
        if s.true is not None:
            self.gate.publish(self.tpub, point_cdr(s.ns, s.true))
        if self.clock_pub is not None and self.loop.clock_due:
            self.gate.publish(self.clock_pub, clock_msg(s.ns))
        if self.loop.shut_down:
            self.final_report()
            rclpy.try_shutdown()  # at the safe voltage (or out of time): exit

    def hardware_failed(self, error):
        """A lost link or a controller error: faulted, said on state and diagnostics,
        then the node exits 1 with the reason (the backend's close ramps to safe where
        the link still allows it). No sample is taken after it."""
        if self.failed is None:
            self.failed = error
            self.sup.fault(f"hardware: {error}", self.loop.stamp(self.loop.j))
            self.get_logger().error(f"faulted: hardware: {error}")
            self.final_report()
            self.spub.wait_for_all_acked(Duration(seconds=1))
        raise error

    def done(self):
        if self.lock:
            if self.p["exit_after_max_steps"] and not hasattr(self, "_exit_timer"):
                self._exit_timer = steady_timer(self, 0.2, self.finish)
        elif not self.loop.shutdown_requested:
            self.request_shutdown()

    def finish(self):
        """Lockstep, all steps done: make sure every subscriber has them, then exit."""
        t0 = time.monotonic()
        if self.gate.open and all(pub.wait_for_all_acked(Duration(seconds=5))
                                  for pub in (self.jpub, self.tpub)):
            self.get_logger().info(done_line(self.loop, time.monotonic() - t0))
            self.final_report()
            rclpy.try_shutdown()

    def final_report(self):
        """Last diagnostics with the final counts, delivered before exiting."""
        self.diag.publish()
        self.diag.pub.wait_for_all_acked(Duration(seconds=1))

    @property
    def shutdown_requested(self) -> bool:
        """A stop is under way (the executor's StopsInOrder hook)."""
        return self.loop.shutdown_requested

    def request_shutdown(self) -> None:
        """SIGINT/SIGTERM or max_steps: ramp to the safe voltage, still publishing, then
        exit. Lockstep (a simulation waiting for commands) exits at once."""
        if self.lock:
            self.loop.shutdown_requested = True
            rclpy.try_shutdown()
            return
        # the ramp, then the backend's close (which may ramp again) and the teardown
        watch_stop(max(STOP_STATE.watch_s, self.loop.begin_shutdown()))

    # -- arming ---------------------------------------------------------------------------
    def on_state_change(self, state, reason, since_ns, log=True):
        self.state_since = since_ns
        values = {**self.loop.announced(), "mode": self.p["mode"]}
        # announced a few samples ahead of when it applies, and before the next sample
        # is published: the loop nodes take `state` before their data in every pass, so
        # in lockstep each has it before the sample it must act on (reruns identical)
        name = f"{self.get_namespace().rstrip('/')}/{self.get_name()}: arming"
        self.spub.publish(arming_state_msg(since_ns, name, state, reason, values,
                                           self.backend.hardware_id))
        if log and state == "faulted":  # (one call site per severity: rclpy's rule)
            self.get_logger().warning(f"{state}: {reason}")
        elif log:
            self.get_logger().info(f"{state}: {reason}")

    def check_links(self):
        """Graph queries cost the loop thread ~1 ms: only while not armed, where a
        refusal or the arming reason needs them."""
        if self.sup.state not in ENABLED:
            self.link = missing_links(self)

    def on_phase(self, msg):
        """The feedforward's phase and what it follows: the arming state follows it,
        and /stage/state relays it."""
        if self.loop.feedforward_phase(*phase_from_msg(msg)):
            self.on_state_change(self.sup.state, self.sup.reason, self.state_since,
                                 log=False)  # the same state, from the same sample

    def on_arm(self, request, response):
        self.check_links()
        response.success, response.message = self.loop.arm(request.data, self.link)
        return response

    def on_estop(self, request, response):
        response.success, response.message = True, self.loop.estop()
        return response

    def status(self):
        level, message, values = self.loop.status()
        values.update(backend=self.p["backend"], mode=self.p["mode"],
                      thread_priority=getattr(self, "rt_priority", 0))
        return level, message, values

    def stop_summary(self) -> str:
        """What a stop left the stage at (run_node prints it)."""
        return f"{self.loop.summary()}; the backend then ramps to safe and closes"

    def close(self):
        """The backend ramps to the safe voltage and closes before the node goes
        (run_node calls this, then destroys the node)."""
        self.backend.close(self.sup.p.safe_V, self.sup.p.ramp_V_per_s)


def main(args=None):
    """Run the stage driver (the Jazzy form). SIGINT or SIGTERM first ramps the stage to its
    safe voltage; a second one stops at once."""
    return run_node(StageDriver, args)


if __name__ == "__main__":
    raise SystemExit(main())
