
"""stage_driver: the stage (sim, NI-DAQ, PI, NV200 or replay) on topics; the last line of
defence. The sample loop itself (the sample clock, the command schedule, the arming
supervisor, the voltage and slew clamp) is core/loop/sample_loop.py, and what a fault
escalates to is core/loop/lifecycle.py's table; this node gives them its parameters and
topics: commands in, joint_states (and the simulated stage's true position) out, the
latched ``state`` topic and /diagnostics; ``arm`` (std_srvs/SetBool) arms and disarms;
``estop`` (std_srvs/Trigger). In real time the executor calls ``on_lean_tick`` at each
tick (the DAQ's read blocks until its clock).

A managed (lifecycle) node (docs/realtime.md#lifecycle-the-driver-as-a-managed-node);
with ``managed: false`` (the launcher's default) it configures and activates itself.
"""

# first, before the heavy imports: stop signals work from here on (see process/signals.py)
import piezo_stage.process.signals  # noqa: F401, I001

# isort: split

import time
from collections.abc import Callable
from typing import Any

import rclpy
from diagnostic_msgs.msg import DiagnosticArray, KeyValue
from geometry_msgs.msg import PointStamped, Vector3Stamped
from rclpy.clock import ROSClock
from rclpy.duration import Duration
from rclpy.lifecycle import LifecycleNode, LifecycleState, TransitionCallbackReturn
from rosgraph_msgs.msg import Clock
from sensor_msgs.msg import JointState
from std_msgs.msg import Header
from std_srvs.srv import SetBool, Trigger

# the simulated stage (the default backend) with the node's imports, before the start
# gate: its backend would import them as it configured, after the node had joined
import piezo_stage.core.model.plant  # noqa: F401
import piezo_stage.io.plant_file  # noqa: F401
import piezo_stage_msgs_adapters as msgs
from piezo_stage.core.errors import BackendFault, ConfigError, DataError
from piezo_stage.core.loop import lifecycle as lc
from piezo_stage.core.loop import sample_loop as sl
from piezo_stage.core.loop.arming import PARAMETERS as ARMING
from piezo_stage.core.loop.arming import ArmingParams
from piezo_stage.core.loop.driver import DriverCore, fixable
from piezo_stage.core.loop.hold import LockstepHold
from piezo_stage.drivers import BACKEND_PARAMS, done_line, make_backend
from piezo_stage.io.capacity_file import write_refusal
from piezo_stage.nodes._common import QOS_DATA, QOS_EVENTS, MessageInfo, Status, steady_timer
from piezo_stage.nodes._executor import LeanNode, end_run, hot_subscription, run_node
from piezo_stage.nodes._loop import Diagnostics, Gate, missing_links, set_realtime_priority
from piezo_stage.nodes._params import declare_schema
from piezo_stage.process.signals import STATE as STOP_STATE
from piezo_stage.process.signals import watch as watch_stop

STATE_ACK_S = 1.0  # lockstep: the longest wait for the state's readers (see _announce)

SUCCESS, ERROR = TransitionCallbackReturn.SUCCESS, TransitionCallbackReturn.ERROR


class StageDriver(LeanNode, LifecycleNode):
    TICKS = True  # real time: the sample clock is its tick (LeanNode)
    USES_KERNELS = True  # the simulated stage's (LeanNode)

    def __init__(self, **node_options: Any) -> None:
        # node_options: a node of a composed loop gets its own arguments (loop_container)
        super().__init__("stage_driver", **node_options)
        STOP_STATE.watch_s = 12.0  # its stop ramps and closes the backend (see below)
        p = self.p = declare_schema(self, sl.PARAMETERS)
        sl.check_mode(p["backend"], p["mode"], self.get_parameter("use_sim_time").value)
        arm = declare_schema(self, ARMING)
        arm_params = ArmingParams(**{q.field: arm[q.name] for q in ARMING})
        bp = declare_schema(self, BACKEND_PARAMS)
        # what the driver holds across its lifecycle: the backend and the sample loop
        # over it (from configure to cleanup), its fault, its last announcement
        self.d = DriverCore(p, arm_params, lambda: make_backend(
            p["backend"], p["control_rate_hz"], bp, arm_params.safe_V), self._announce)
        self.managed = bool(p["managed"])
        self.rt_priority = 0
        self._exit_timer: Any = None  # lockstep, all steps done: the timer that ends it
        self.lock = p["mode"] == "lockstep"
        self.transition_error: Exception | None = None
        self.jpub = self.create_publisher(JointState, "joint_states", QOS_DATA)
        self.tpub = self.create_publisher(PointStamped, "sim/true_position", QOS_DATA)
        self.spub = self.create_publisher(DiagnosticArray, "state", QOS_EVENTS)
        # lockstep: the sample clock is the set's clock (a bag then has one time base)
        self.clock_pub = self.create_publisher(Clock, "/clock", 10) \
            if self.lock and p["clock_period_s"] > 0 else None
        hot_subscription(self, Vector3Stamped, "command", self.on_command, QOS_DATA,
                         raw=True, with_info=True)
        # taken with the samples: at the base executor's turn (one callback each slow
        # period) a phase waited, and the state said "approaching" after the move's
        # on-target verdict
        hot_subscription(self, KeyValue, "feedforward/phase", self.on_phase, QOS_EVENTS)
        # lockstep: the gap node's live watch holds the set at a window's last sample
        # while it diagnoses it (docs/watch.md); the command answering that sample waits
        self.hold = LockstepHold()
        self.hold_sub = self.create_subscription(
            Header, "watch/hold", self.on_hold, QOS_EVENTS) if self.lock else None
        self.create_service(SetBool, "arm", self.on_arm)
        self.create_service(Trigger, "estop", self.on_estop)
        steady_timer(self, 0.5, self.check_links)
        self.diag = Diagnostics(self, self.status, "sample loop", self.d.hardware_id,
                                rates=sl.RATES)
        self.lean_deadline: float | None = None  # real time: no tick until configured
        if not self.lock:
            self.lean_take_at_tick = True  # commands are due at a later tick: no wake each
            self.rt_priority = set_realtime_priority(p["thread_priority"], self.get_logger())
        if not self.managed:  # the launcher's way: configured and active from the start
            for step in (self.trigger_configure, self.trigger_activate):
                if step() != SUCCESS:
                    raise self.transition_error or RuntimeError(f"{step.__name__} failed")

    # -- lifecycle transitions ----------------------------------------------------------
    def _transition(self, name: str, body: Callable[[], object]) -> TransitionCallbackReturn:
        """Run a transition's ``body``: SUCCESS, or FAILURE with the reason logged (a
        backend that cannot open, bad limits), ERROR for anything else; rclpy's own
        wrapper would turn an exception into ERROR without a word."""
        self.transition_error = None
        try:
            body()
            return SUCCESS
        except Exception as e:  # noqa: BLE001 - said, then the state machine decides
            self.transition_error = e
            self.get_logger().error(f"{name} failed: {e}")
            return TransitionCallbackReturn.FAILURE if fixable(e) else ERROR

    def on_configure(self, state: LifecycleState) -> TransitionCallbackReturn:
        """Open the backend and start the sample loop, disarmed at the safe voltage."""
        return self._transition("configure", self._configure)

    def on_activate(self, state: LifecycleState) -> TransitionCallbackReturn:
        """Arm once the loop is closed (managed, or ``auto_arm``), then the approach."""
        return self._transition("activate", lambda: self.d.took(
            self.d.running.activate(self.managed or self.d.arm_params.auto_arm)))

    def on_deactivate(self, state: LifecycleState) -> TransitionCallbackReturn:
        """Disarm: ramp to the safe voltage, still publishing. A fault's own deactivate
        (``why_error``) is an error: the error transition follows."""
        if self.d.why_error:
            return ERROR
        return self._transition("deactivate", lambda: self.d.took(self.d.running.deactivate()))

    def on_cleanup(self, state: LifecycleState) -> TransitionCallbackReturn:
        """Close the backend (ramping to safe) and stop the sample loop."""
        return self._transition("cleanup", lambda: self._close("cleaned up"))

    def on_shutdown(self, state: LifecycleState) -> TransitionCallbackReturn:
        """Ramp to safe and close (real time: over the next ticks), then exit 0."""
        return self._transition("shutdown", self._shutdown)

    def on_error(self, state: LifecycleState) -> TransitionCallbackReturn:
        """After a fault (at the safe voltage by then) or a failed transition: close the
        backend; unconfigured, from where configure can be tried again."""
        reason = self.d.error_reason(state.label, self.transition_error)
        self.get_logger().warning(f"error transition: {reason}; unconfigured, the "
                                  "backend closed: configure and activate to go on")
        self._close(f"error: {reason}")
        return SUCCESS

    def _configure(self) -> None:
        self.d.configure(self._start)  # arming: activate's (or the arm service's)

    def _start(self, loop: sl.SampleLoop) -> None:
        # lockstep: nothing is published before every consumer listens; real time: the
        # sample clock starts then (the first publishes to new readers are slow)
        p = self.p
        self.gate = Gate(self, [(self.jpub, p["min_subscribers"]), (
            self.tpub, p["min_record_subscribers"] * (p["backend"] == "sim"))])
        if self.lock:
            self.follow(loop.on_start())  # the first sample: at rest
        else:
            self.lean_deadline = 0.0  # the first real-time tick: now

    def _shutdown(self) -> None:
        self.get_logger().info("shutdown: ramping to the safe voltage, then exiting")
        if self.d.loop is None or self.lock:
            self._close("shut down")
            self._exit_timer = steady_timer(self, 0.2, rclpy.try_shutdown)
        else:
            self.request_shutdown()

    def _close(self, why: str) -> None:
        """The backend ramps to the safe voltage and closes; no tick until configured
        again; ``state`` says so (disarmed, the last values, unconfigured)."""
        self.lean_deadline = None
        error = self.d.close(why)
        if error:
            self.get_logger().error(f"{why}: the backend's close failed: {error}")

    def escalate(self, event: str, why: str) -> str:
        """Take the step lifecycle.py's table gives ``event`` here (a transition, or none)."""
        step = self.d.escalate(event, self.managed, self.lifecycle_label(), why)
        if step in (lc.DEACTIVATE, lc.CLEANUP):
            (self.trigger_deactivate if step == lc.DEACTIVATE else self.trigger_cleanup)()
        return step

    # -- the sample loop ----------------------------------------------------------------
    def on_lean_tick(self) -> None:
        """Real time: the sample clock's tick."""
        loop = self.d.loop
        if loop is None:
            self.lean_deadline = None
            return
        if not self.gate.open and loop.shutdown_requested:  # stopped before any sample
            rclpy.try_shutdown()                              # went out: no ramp
            return
        if self.gate.holding():  # consumers still matching
            self.lean_deadline = time.monotonic() + 0.01
            return
        out = loop.on_tick(time.monotonic(), self.ros_now_ns, self.d.link)
        self.follow(out)
        if self.d.loop is not None:  # (a hardware fault may have closed it)
            self.lean_deadline = out.deadline

    def ros_now_ns(self) -> int:
        """The node's ROS time [ns]: the system clock's, read directly (rclpy's ``now()``
        builds a Time: 4.5 us here, a tick's), unless simulated time is active."""
        clock = self.get_clock()
        if isinstance(clock, ROSClock) and clock.ros_time_is_active:
            return clock.now().nanoseconds
        return time.time_ns()

    def on_command(self, msg: bytes, info: MessageInfo) -> None:
        loop = self.d.loop
        if loop is None:  # unconfigured: no sample to answer
            return
        try:
            ns, v = msgs.voltage_from_msg(msg)
        except DataError:  # NaN/inf or malformed: never counts as a fresh command
            loop.reject_command()
            return
        # a command is stamped for the tick it applies at: the one for the tick after
        # the window's last sample waits (core/loop/hold.py)
        last = self.hold.last_ns
        if last is not None:  # (lockstep only)
            was = self.hold.waiting
            if not self.hold.take(ns, v):
                if was is None:
                    self.get_logger().info(f"waiting after {last / 1e9:.3f} s "
                                           "for the watch's diagnosis of the window ending "
                                           "there")
                return
        recv = 0 if self.lock else (info.get("received_timestamp") or self.ros_now_ns())
        self.follow(loop.on_command(ns, v, recv, self.d.link))

    def on_hold(self, msg: Header) -> None:
        """Lockstep: the watch's hold (the last sample before the wait), or go on."""
        try:
            last = msgs.hold_from_msg(msg)
        except DataError as e:
            self.get_logger().warning(f"{e}: ignored", throttle_duration_sec=10.0)
            return
        self.go_on(self.hold.hold(last), "the diagnosis is decided")

    def go_on(self, waited: tuple[int, Any] | None, why: str) -> None:
        """The command that waited at the hold taken: the set goes on."""
        if waited is None:
            return
        ns, v = waited
        self.get_logger().info(f"going on at {ns / 1e9:.3f} s: {why}")
        if self.d.loop is not None:
            self.follow(self.d.loop.on_command(ns, v, 0, self.d.link))

    def follow(self, out: sl.Outcome) -> None:
        """What the sample loop decided (core/loop/sample_loop.py Outcome): publish the
        sample taken, then its next action."""
        if out.stop_began_s is not None:  # max_steps (real time): ramping to safe
            watch_stop(max(STOP_STATE.watch_s, out.stop_began_s))
        if out.next is sl.Next.DONE:
            return self.done()
        if out.next is sl.Next.FAULT:
            return self.hardware_failed(out.error)
        if out.next is sl.Next.REFUSE:  # the host cannot hold the rate: said once, it ends
            write_refusal(self.d.running.refusal_figures())  # for ``launch --rate auto``
            raise ConfigError(out.reason)
        s = out.sample
        if s is not None:
            self.gate.publish(self.jpub, msgs.joint_state_cdr(s.ns, s.w, s.applied))
            if s.true is not None:
                self.gate.publish(self.tpub, msgs.point_cdr(s.ns, s.true))
            if self.clock_pub is not None and out.clock_due:
                self.gate.publish(self.clock_pub, msgs.clock_msg(s.ns))
        if out.next is sl.Next.SHUT_DOWN:
            end_run(self)  # at the safe voltage (or out of time): exit
        elif out.next is sl.Next.FAULTED_AT_SAFE:
            self.escalate(lc.FAULTED_AT_SAFE, out.reason)
        return None

    def hardware_failed(self, error: BaseException | None) -> None:
        """A lost link or a controller error: faulted, said on state and diagnostics, no
        sample after it; then the table's step (unmanaged: exit 1 with the reason)."""
        # the backend's close ramps to safe where the link still allows it
        if self.d.hardware_fault(error):
            self.get_logger().error(f"faulted: hardware: {error}")
            self.final_report()
            self.spub.wait_for_all_acked(Duration(seconds=1))
        if self.escalate(lc.HARDWARE_FAULT, f"faulted: hardware: {error}") == lc.EXIT:
            raise error if error is not None else BackendFault("hardware: unknown")

    def done(self) -> None:
        if self.lock:
            if self.p["exit_after_max_steps"] and self._exit_timer is None:
                self._exit_timer = steady_timer(self, 0.2, self.finish)
        elif not self.d.running.shutdown_requested:
            self.request_shutdown()

    def finish(self) -> None:
        """Lockstep, all steps done: make sure every subscriber has them, then exit."""
        t0 = time.monotonic()
        if self.gate.open and all(pub.wait_for_all_acked(Duration(seconds=5))
                                  for pub in (self.jpub, self.tpub)):
            self.get_logger().info(done_line(self.d.running, time.monotonic() - t0))
            end_run(self)

    def final_report(self) -> None:
        """Last diagnostics with the final counts, delivered before exiting."""
        self.diag.final()

    @property
    def shutdown_requested(self) -> bool:
        """A stop is under way (the executor's StopsInOrder hook)."""
        return self.d.shutdown_requested

    def request_shutdown(self) -> None:
        """SIGINT/SIGTERM or max_steps: ramp to the safe voltage, still publishing, then
        exit; lockstep and an unconfigured driver (nothing open) exit at once."""
        ramp_s = self.d.ramp_down(realtime=not self.lock)
        if ramp_s is None:
            end_run(self)
        else:  # the ramp, then the backend's close (which may ramp again), the teardown
            watch_stop(max(STOP_STATE.watch_s, ramp_s))

    # -- arming ---------------------------------------------------------------------------

    def _announce(self, state: str, reason: str, log: bool = True) -> None:
        """The state topic: the arming state, the driver's values and its lifecycle
        state, announced a few samples ahead of when it applies."""
        # before the next sample is published: the loop nodes take `state` before their
        # data in every pass, so in lockstep each has it before the sample it must act
        # on (reruns identical)
        name = f"{self.get_namespace().rstrip('/')}/{self.get_name()}: arming"
        self.spub.publish(msgs.arming_state_msg(
            self.d.state_since, name, state, reason,
            self.d.announcement(self.lifecycle_label()), self.d.hardware_id()))
        # lockstep, a change announced ahead of the sample it applies at (the enable):
        # no sample goes out before every reader holds it. Sent first is not received
        # first: a state lost on the way (a full shared-memory queue on a busy host) is
        # repaired only after the next heartbeat, and a loop node that took its samples
        # meanwhile started the approach a tick late, and reruns were no longer
        # identical. A change that applies at once (a disarm, a fault) cannot
        # be known ahead by anyone, and a lockstep run has none it did not ask for.
        if self.lock and self.d.ahead() and not self.spub.wait_for_all_acked(
                Duration(seconds=STATE_ACK_S)):
            self.get_logger().warning(f"{state}: a reader of state did not acknowledge it "
                                      f"within {STATE_ACK_S:g} s; going on",
                                      throttle_duration_sec=10.0)
        if log and state == "faulted":  # (one call site per severity: rclpy's rule)
            self.get_logger().warning(f"{state}: {reason}")
        elif log:
            self.get_logger().info(f"{state}: {reason}")

    def check_links(self) -> None:
        """Graph queries cost the loop thread ~1 ms: only while not armed, where a
        refusal or the arming reason needs them."""
        if self.d.needs_links():
            self.d.links(missing_links(self))
        if self.hold.held and self.hold_sub is not None and \
                self.count_publishers(self.hold_sub.topic_name) == 0:
            self.go_on(self.hold.go_on(), "the watch that held the set is gone")

    def on_phase(self, msg: KeyValue) -> None:
        """The feedforward's phase and what it follows: the arming state follows it,
        and /stage/state relays it."""
        if self.d.loop is not None and self.d.loop.feedforward_phase(
                *msgs.phase_from_msg(msg)):
            self.d.restate()

    def on_arm(self, request: SetBool.Request, response: SetBool.Response
               ) -> SetBool.Response:
        """Arm or disarm within active (the lifecycle's activate and deactivate do the
        same and move its state; this service is the finer switch a set without a
        manager has always had)."""
        self.check_links()
        response.success, response.message = self.d.arm(request.data, self.lifecycle_label())
        return response

    def on_estop(self, request: Trigger.Request, response: Trigger.Response
                 ) -> Trigger.Response:
        response.success, response.message = True, self.d.estop()
        return response

    def lifecycle_label(self) -> str:
        """The lifecycle state's label (unconfigured, inactive, active, finalized; a
        transition's own label while it runs, such as deactivating)."""
        return self._state_machine.current_state[1]

    def status(self) -> Status:
        return self.d.status(self.lifecycle_label(), self.rt_priority)

    def stop_summary(self) -> str:
        """What a stop left the stage at (run_node prints it)."""
        return self.d.summary(self.lifecycle_label())

    def close(self) -> None:
        """The backend ramps to the safe voltage and closes before the node goes
        (run_node calls this, then destroys the node)."""
        self.d.close_backend()


def main(args: list[str] | None = None) -> int:
    """Run the stage driver (the Jazzy form). SIGINT or SIGTERM first ramps the stage to its
    safe voltage; a second one stops at once."""
    return run_node(StageDriver, args)


if __name__ == "__main__":
    from piezo_stage.process.stopping import exit_now
    exit_now(main())  # flushed, at-exit work done, no finalization (stopping.py)
