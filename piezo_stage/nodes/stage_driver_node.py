"""stage_driver: the stage (sim, NI-DAQ or replay) on topics; the last line of defence.

Samples sit on the stage's own sample clock, ``t0 + j * dt``: in lockstep t0 = 0 and
one step is taken per command stamped for the next sample; in real time t0 is the ROS
time of the first tick, the sim is paced by the wall clock (a tick serviced more than a
period late skips the missed samples: the plant holds its voltage over them and the
stamps show the gap) and the DAQ by its hardware clock. Commands are applied at the tick
they are stamped for; late ones are counted and the last command is held. The arming
supervisor (core/arming.py) decides what is applied: the safe voltage until the loop is
proven closed, then commands, and a ramp to the safe voltage on a fault (stale
commands), an e-stop (latched until disarm) or shutdown. Everything is clamped to the
voltage limits and the slew limit. State: latched ``state`` topic and /diagnostics;
``arm`` (std_srvs/SetBool) arms and disarms; ``estop`` (std_srvs/Trigger).
"""

# first, before the heavy imports: stop signals work from here on (see _signals)
import piezo_stage.nodes._signals  # noqa: F401, I001

# isort: split

import os
import socket
import time
from collections import deque

import rclpy
from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import PointStamped, Vector3Stamped
from rclpy.duration import Duration
from rclpy.node import Node
from rosgraph_msgs.msg import Clock
from sensor_msgs.msg import JointState
from std_msgs.msg import String
from std_srvs.srv import SetBool, Trigger

from piezo_stage.core.arming import (
    ENABLED,
    ArmingParams,
    ArmingSupervisor,
    CommandSchedule,
    SampleClock,
)
from piezo_stage.core.arming import PARAMETERS as ARMING
from piezo_stage.core.control import clamp_slew
from piezo_stage.core.errors import BackendFault, DataError
from piezo_stage.drivers import BACKEND_PARAMS, make_backend, step_period_summary
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
    point_cdr,
    voltage_from_msg,
)

PARAMS = (  # name (one name: the parameter's), default, description, limits
    ("backend", "sim", "stage backend", {"choices": ("sim", "daq", "pi", "nv200",
                                                  "replay")}),
    ("mode", "lockstep", "lockstep (sim, replay) | realtime",
     {"choices": ("lockstep", "realtime")}),
    ("control_rate_hz", 1000.0, "sample rate [Hz]", {"lo": 1.0, "hi": 1e5}),
    ("lookahead_s", 0.005, "real time: commands are computed this far ahead of the "
     "sample they answer [s]", {"lo": 0.0, "hi": 1.0}),
    ("max_steps", 0, "stop after this many samples (0: never)", {"lo": 0, "hi": 2**31 - 1}),
    ("exit_after_max_steps", False, "exit (code 0) after max_steps", {}),
    ("min_subscribers", 0, "lockstep: joint_states subscribers to wait for",
     {"lo": 0, "hi": 100}),
    ("min_record_subscribers", 0, "lockstep: true_position subscribers to wait for "
     "(recorders)", {"lo": 0, "hi": 100}),
    ("clock_period_s", 0.01, "lockstep: publish /clock (simulated time for nodes on "
     "use_sim_time) every this much sample time [s]; 0: not at all", {"lo": 0.0, "hi": 10.0}),
    ("thread_priority", 50, "real time: SCHED_FIFO priority of the sample loop (0: leave "
     "the scheduler alone)", {"lo": 0, "hi": 99}),
)


# real time: a command stamped further than this from its arrival is no command of this
# loop (the look-ahead is milliseconds); taking it would poison the schedule
COMMAND_WINDOW_NS = 1_000_000_000

class StageDriver(Node):
    def __init__(self):
        super().__init__("stage_driver")
        STOP_STATE.watch_s = 12.0  # its stop ramps and closes the backend (see below)
        d = lambda *a, **k: declare(self, *a, **k)  # noqa: E731
        p = self.p = {name: d(name, default, desc, **kw) for name, default, desc, kw in PARAMS}
        if p["backend"] in ("daq", "pi", "nv200") and p["mode"] != "realtime":
            raise DataError(f"backend {p['backend']} runs in real time only (mode: "
                            "realtime)")
        if p["mode"] == "realtime" and self.get_parameter("use_sim_time").value:
            raise DataError("use_sim_time is for lockstep (the driver's samples are the "
                            "clock); in real time the nodes run on the system clock")
        defaults = ArmingParams()
        arm = ArmingParams(**{field: d(name, getattr(defaults, field), desc, **(
            {"lo": r[0], "hi": r[1]} if r else {})) for name, field, desc, r in ARMING})
        bp = {k: d(k, default, desc) for k, default, desc in BACKEND_PARAMS}
        self.backend = make_backend(p["backend"], p["control_rate_hz"], bp, arm.safe_V)
        self.lock = p["mode"] == "lockstep"
        self.dt_ns = int(round(1e9 / p["control_rate_hz"]))
        self.lookahead_ns = self.dt_ns if self.lock else max(
            self.dt_ns, int(round(p["lookahead_s"] * 1e9)))
        self.max_step = {a: s / p["control_rate_hz"] for a, s in self.backend.slew_V_per_s.items()}
        self.v = {"x": arm.safe_V, "y": arm.safe_V}
        self.j, self.t0_ns = -1, 0
        self.stats = {"samples": 0, "rejected": 0, "limit_hits": 0, "unexpected_stamp": 0,
                      "missed_ticks": 0, "late_commands": 0}
        self.step_times = deque(maxlen=1_000_000)     # lockstep: the loop's pace
        self.link, self.shutdown_requested, self.shutdown_by = "", False, None
        self.ff_phase = ""  # what the feedforward last said (relayed on state)
        self.failed = None  # the hardware's fault (BackendFault), once it failed
        self.jpub = self.create_publisher(JointState, "joint_states", QOS_DATA)
        self.tpub = self.create_publisher(PointStamped, "sim/true_position", QOS_DATA)
        self.spub = self.create_publisher(DiagnosticArray, "state", QOS_EVENTS)
        # lockstep: the sample clock is the set's clock (a bag then has one time base)
        self.clock_pub = self.create_publisher(Clock, "/clock", 10) \
            if self.lock and p["clock_period_s"] > 0 else None
        self.clock_every = (max(1, int(round(p["clock_period_s"] * p["control_rate_hz"])))
                            if p["clock_period_s"] else 0)
        self.sup = ArmingSupervisor(arm, self.v, 1.0 / p["control_rate_hz"],
                                    3 * self.dt_ns if self.lock else max(
                                        3 * self.dt_ns, 20_000_000), self.on_state_change)
        self.sched = CommandSchedule(0, self.dt_ns, self.lookahead_ns)
        self.clock = SampleClock(self.dt_ns * 1e-9, self.backend.paced)
        # lockstep: nothing is published before every consumer listens; real time: the
        # sample clock starts then (the first publishes to new readers are slow)
        self.gate = Gate(self, [(self.jpub, p["min_subscribers"]),
                                (self.tpub,
                                 p["min_record_subscribers"] * (p["backend"] == "sim"))])
        hot_subscription(self, Vector3Stamped, "command", self.on_command, QOS_DATA,
                         raw=True, with_info=True)
        self.create_subscription(String, "feedforward/phase", self.on_phase, QOS_EVENTS)
        self.create_service(SetBool, "arm", self.on_arm)
        self.create_service(Trigger, "estop", self.on_estop)
        steady_timer(self, 0.5, self.check_links)
        self.diag = Diagnostics(self, self.status, "sample loop", self.backend.hardware_id,
                                rates=(("missed_ticks", "missed ticks", 0),
                                       ("late_commands", "late commands", 0),
                                       ("rejected", "malformed commands", 0),
                                       ("limit_hits", "voltage or slew limit hits", 0)))
        self.on_state_change(self.sup.state, self.sup.reason, 0)
        if self.lock:
            self.tick(0, None, False)  # sample 0: the stage at rest
        else:
            self.lean_deadline = 0.0   # the first real-time tick: now
            self.lean_take_at_tick = True  # commands are due at a later tick: no wake each
            self.rt_priority = set_realtime_priority(p["thread_priority"], self.get_logger())

    # -- time -------------------------------------------------------------------------
    def stamp(self, j):
        return self.t0_ns + j * self.dt_ns

    def on_lean_tick(self):
        """Real time: the sample clock's tick (the DAQ's read blocks until its clock)."""
        if not self.gate.open:
            self.lean_deadline = time.monotonic() + 0.01  # consumers still matching
            return
        if self.clock.mono0 is None:  # map the sample clock to ROS time once
            self.backend.start()  # the hardware clock starts now, not when built
            self.t0_ns = self.sched.t0 = self.get_clock().now().nanoseconds
        j = self.clock.tick(time.monotonic(), self.j)
        cmd, on_time = self.sched.due(j, count_held=self.sup.state in ENABLED)
        self.tick(j, cmd, on_time, missed=j - self.j - 1)
        self.lean_deadline = self.clock.deadline(self.j + 1)

    # -- commands -----------------------------------------------------------------------
    def on_command(self, msg, info):
        try:
            ns, v = voltage_from_msg(msg)
        except DataError:  # NaN/inf or malformed: never counts as a fresh command
            self.stats["rejected"] += 1
            return
        if self.lock:
            if ns != self.stamp(self.j + 1):
                self.stats["unexpected_stamp"] += 1
                return
            self.sup.note_command(ns)
            self.tick(self.j + 1, v, True)
            return
        recv = info.get("received_timestamp") or self.get_clock().now().nanoseconds
        if abs(ns - recv) > COMMAND_WINDOW_NS:  # a stray stamp: never scheduled
            self.stats["unexpected_stamp"] += 1
            return
        self.sup.note_command(recv)
        self.sched.add(ns, v, recv, self.j)
        self.stats["late_commands"] = self.sched.late

    # -- one sample -----------------------------------------------------------------------
    def tick(self, j, cmd, on_time, missed=0):
        if getattr(self.backend, "exhausted", False) or (
                self.lock and self.p["max_steps"] and j > self.p["max_steps"]):
            return self.done()
        if self.p["max_steps"] and j > self.p["max_steps"] and not self.shutdown_requested:
            self.request_shutdown()  # real time: ramp to the safe voltage, then exit
        now = self.stamp(j) if self.lock else self.get_clock().now().nanoseconds
        target = self.sup.tick(self.stamp(j), now, cmd, on_time, self.link, missed + 1)
        v, hit = clamp_slew(target, self.v, self.backend.limits,
                            {a: s * (missed + 1) for a, s in self.max_step.items()})
        self.stats["limit_hits"] += hit and self.sup.state in ENABLED
        try:
            for _ in range(missed):  # the plant held the last voltage over the missed ticks
                self.backend.step(self.v["x"], self.v["y"])
            w, true, applied, hw_j = self.backend.step(v["x"], v["y"])
        except BackendFault as e:
            return self.hardware_failed(e)
        if hw_j is not None:  # the DAQ's own sample count: its misses show in the stamps
            missed, j = missed + hw_j - j, hw_j
        self.stats["missed_ticks"] += missed
        self.v, self.j = dict(applied), j
        self.sup.applied(applied)
        ns = self.stamp(j)
        self.gate.publish(self.jpub, joint_state_cdr(ns, w, applied))
        if true is not None:
            self.gate.publish(self.tpub, point_cdr(ns, true))
        if self.clock_pub is not None and j % self.clock_every == 0:
            self.gate.publish(self.clock_pub, clock_msg(ns))
        self.stats["samples"] += 1
        if self.lock:
            self.step_times.append(time.perf_counter())
        if self.shutdown_requested and (self.sup.state not in ENABLED and all(
                abs(x - self.sup.p.safe_V) < 1e-9 for x in self.v.values())
                or time.monotonic() > self.shutdown_by):
            self.final_report()
            rclpy.try_shutdown()  # at the safe voltage (or out of time): exit

    def hardware_failed(self, error):
        """A lost link or a controller error: faulted, said on state and diagnostics,
        then the node exits 1 with the reason (the backend's close ramps to safe where
        the link still allows it). No sample is taken after it."""
        if self.failed is None:
            self.failed = error
            self.sup.fault(f"hardware: {error}", self.stamp(self.j))
            self.get_logger().error(f"faulted: hardware: {error}")
            self.final_report()
            self.spub.wait_for_all_acked(Duration(seconds=1))
        raise error

    def done(self):
        if self.lock:
            if self.p["exit_after_max_steps"] and not hasattr(self, "_exit_timer"):
                self._exit_timer = steady_timer(self, 0.2, self.finish)
        elif not self.shutdown_requested:
            self.request_shutdown()

    def finish(self):
        """Lockstep, all steps done: make sure every subscriber has them, then exit."""
        if self.gate.open and all(pub.wait_for_all_acked(Duration(seconds=5))
                                  for pub in (self.jpub, self.tpub)):
            self.get_logger().info(f"done after {self.j + 1} samples: "
                                   f"{step_period_summary(list(self.step_times)[1:])}")
            self.final_report()
            rclpy.try_shutdown()

    def final_report(self):
        """Last diagnostics with the final counts, delivered before exiting."""
        self.diag.publish()
        self.diag.pub.wait_for_all_acked(Duration(seconds=1))

    def request_shutdown(self):
        """SIGINT/SIGTERM or max_steps: ramp to the safe voltage, still publishing, then
        exit. Lockstep (a simulation waiting for commands) exits at once."""
        self.shutdown_requested = True
        if self.lock:
            rclpy.try_shutdown()
            return
        self.sup.request_disarm(self.stamp(self.j))
        self.sup.reason = "shutting down"
        span = max(abs(x - self.sup.p.safe_V) for x in self.v.values())
        self.shutdown_by = time.monotonic() + span / self.sup.p.ramp_V_per_s + 1.0
        # the ramp, then the backend's close (which may ramp again) and the teardown
        watch_stop(max(STOP_STATE.watch_s, 2 * span / self.sup.p.ramp_V_per_s + 6.0))

    # -- arming ---------------------------------------------------------------------------
    def on_state_change(self, state, reason, since_ns, log=True):
        self.state_since = since_ns
        lim = self.backend.limits
        values = {"lookahead_s": self.lookahead_ns * 1e-9,
                  "control_rate_hz": self.p["control_rate_hz"],
                  "mode": self.p["mode"], "voltage_limits_V": [
                      max(lo for lo, _ in lim.values()), min(hi for _, hi in lim.values())],
                  # whose set this is (a second launch on this namespace names it)
                  "host": socket.gethostname(),
                  "pid": str(os.getppid()),  # the launcher (or shell) that started it
                  "feedforward": self.ff_phase}  # which trajectory runs, or it is done
        # announced a few samples ahead of when it applies, and before the next sample
        # is published: the loop nodes take `state` before their data in every pass, so
        # in lockstep each has it before the sample it must act on (reruns identical)
        self.spub.publish(arming_state_msg(since_ns, self.status_name("arming"), state,
                                           reason, values, self.backend.hardware_id))
        if not log:
            return
        if state == "faulted":
            self.get_logger().warning(f"{state}: {reason}")
        else:
            self.get_logger().info(f"{state}: {reason}")

    def status_name(self, task):
        return f"{self.get_namespace().rstrip('/')}/{self.get_name()}: {task}"

    def check_links(self):
        """Graph queries cost the loop thread ~1 ms: only while not armed, where a
        refusal or the arming reason needs them."""
        if self.sup.state not in ENABLED:
            self.link = missing_links(self)

    def on_phase(self, msg):
        """The feedforward's phase ("tracking: trajectory of N points stamped S", "done:
        ..."): the arming state follows it, and /stage/state relays it."""
        self.sup.set_tracking(msg.data.split(":")[0] in ("tracking", "done"),
                              self.stamp(self.j))
        if msg.data != self.ff_phase:
            self.ff_phase = msg.data
            self.on_state_change(self.sup.state, self.sup.reason, self.state_since,
                                 log=False)  # the same state, from the same sample

    def on_arm(self, request, response):
        self.check_links()
        now = self.stamp(self.j)
        if request.data:
            response.success, response.message = self.sup.request_arm(now)
            if self.link and not response.success:
                response.message += f" ({self.link})"
        else:
            response.success, response.message = self.sup.request_disarm(now)
        return response

    def on_estop(self, request, response):
        self.sup.trigger_estop(self.stamp(self.j))
        response.success = True
        response.message = "driving to the safe voltage; latched until disarm and re-arm"
        return response

    def status(self):
        lag, late, ms = self.sched.arrival_lag, self.clock.late, 1e3
        s, st = self.stats, self.sup.state
        level = 2 if st == "faulted" else 0  # disarmed is a state asked for, not a fault
        values = {**s, "state": st, "reason": self.sup.reason, "backend": self.p["backend"],
                  "mode": self.p["mode"], "v_x_V": self.v["x"], "v_y_V": self.v["y"],
                  "tick_late_median_ms": late.percentile(50) * ms,
                  "tick_late_p99_ms": late.percentile(99) * ms,
                  "tick_late_max_ms": late.max_s * ms,
                  "command_lag_median_ms": lag.percentile(50) * ms,
                  "command_lag_p99_ms": lag.percentile(99) * ms,
                  "command_lag_max_ms": lag.max_s * ms,
                  "late_commands": self.sched.late, "commands": self.sched.received,
                  "held_ticks": self.sched.held_ticks,
                  "lookahead_ms": self.lookahead_ns * 1e-6,
                  "thread_priority": getattr(self, "rt_priority", 0), **self.sup.counts}
        return level, f"{st}: {self.sup.reason}", values

    def stop_summary(self) -> str:
        """What a stop left the stage at (run_node prints it)."""
        return (f"{self.sup.state}, x {self.v['x']:.3f} V, y {self.v['y']:.3f} V (safe "
                f"{self.sup.p.safe_V:g} V) after {self.stats['samples']} samples; the "
                "backend then ramps to safe and closes")

    def destroy_node(self):
        """The backend ramps to the safe voltage and closes, then the node goes."""
        self.backend.close(self.sup.p.safe_V, self.sup.p.ramp_V_per_s)
        super().destroy_node()


def main(args=None):
    """Run the stage driver (the Jazzy form). SIGINT or SIGTERM first ramps the stage to its
    safe voltage; a second one stops at once."""
    return run_node(StageDriver, args)


if __name__ == "__main__":
    raise SystemExit(main())
