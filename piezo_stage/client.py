"""A Python client for a running node set: for acquisition scripts and notebooks.

No launch file and no node of ours to write: ``Stage`` is an rclpy node in its own
context, so it lives in a Jupyter cell beside anything else::

    from piezo_stage.client import Stage

    with Stage() as stage:                       # the set at /stage, ROS_DOMAIN_ID's
        print(stage.position())                  # (x, y) [um], the last sample
        done = stage.move_to(40.0, 20.0, tol_um=0.3)
        print(done.settle_s, done.error_um)      # judged on target by the stage
        with stage.record("scan_bag"):           # an MCAP bag of what follows
            stage.run(t, {"x": wx, "y": wy})     # a trajectory, waited for to its end

A move is the stage's own: the feedforward runs it on its profile and judges it on
target on the sensor (core/loop/ontarget.py); the client only asks and waits for the
answer on ``on_target``. Errors are ``NoStage`` (nothing answers at the namespace),
``StageFault`` (the driver faulted or is disarmed), ``MoveRefused`` (a target outside
the stage's range) and ``MoveTimeout``.
"""

from __future__ import annotations

import itertools
import os
import signal
import subprocess
import sys
import time
from collections import deque
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from typing import TYPE_CHECKING

from piezo_stage.core.errors import PiezoStageError
from piezo_stage.core.loop.motion import MotionTimeModel
from piezo_stage.core.loop.ontarget import ON_TARGET, REFUSED, TargetState
from piezo_stage.core.types import PerAxis
from piezo_stage_msgs_adapters.wire import Announcement

if TYPE_CHECKING:
    import numpy as np

RESEND_S = 1.0  # a move unanswered this long is sent again
SETTLE_IN_S = 0.3  # after the first answers: the rest of the latched history
# no node of the set on the graph this long after the start: no set. Fast DDS announces a
# participant in a burst at its start, then every 3 s: a busy host that missed the burst
# (a set in lockstep takes every core it gets) sees the set by the next announcement
DISCOVERY_S = 6.0
SAMPLES_KEPT = 200_000  # the samples a client keeps for its dwells (minutes at 1 kHz)


class StageError(PiezoStageError):
    """What the client could not do (one line, as every error of ours)."""


class NoStage(StageError):
    """Nothing answers at the namespace: no set launched there, or another domain."""


class StageFault(StageError):
    """The driver faulted, or does not apply commands (disarmed): nothing moves."""


class MoveTimeout(StageError, TimeoutError):
    """The move was not on target in time."""


class MoveRefused(StageError):
    """The stage refused the move (a target outside its range)."""


class TrajectoryRefused(StageError):
    """The stage refused the trajectory (a point outside its range, stamped in the
    past, too long, malformed): the feedforward's reason."""


@dataclass(frozen=True)
class Dwell:
    """The stage at rest: the ``samples`` measured from ``t0_ns`` to ``t1_ns`` (the
    set's own stamps), their ``mean_um`` and ``std_um`` per axis."""

    samples: int
    t0_ns: int
    t1_ns: int
    mean_um: PerAxis[float]
    std_um: PerAxis[float]


@dataclass(frozen=True)
class MoveDone:
    """A move judged on target by the stage: its ``move_id``, the ``settle_s`` (from
    the move's start until the stage stayed within the tolerance), the filtered
    ``error_um`` per axis when declared, the ``elapsed_s`` the client waited, and the
    ``target_um``."""

    move_id: str
    settle_s: float
    error_um: PerAxis[float]
    elapsed_s: float
    target_um: PerAxis[float]
    stamp_ns: int = 0  # the sample it was declared at (the set's clock)


class Stage:
    """A running set at ``namespace`` (see the module's docstring).

    Parameters
    ----------
    namespace : str
        The set's namespace (``launch --namespace``).
    domain_id : int or None
        The ROS domain (None: ``ROS_DOMAIN_ID``, else 0).
    timeout : float
        Seconds to wait for the set to answer (``NoStage`` after).
    motion_model : MotionTimeModel or None
        What ``predict`` answers with (``bench settle`` fits one).
    """

    _ids = itertools.count(1)

    def __init__(self, namespace: str = "/stage", domain_id: int | None = None,
                 timeout: float = 10.0, motion_model: MotionTimeModel | None = None):
        import rclpy
        from diagnostic_msgs.msg import DiagnosticArray, KeyValue
        from geometry_msgs.msg import PointStamped
        from rclpy.context import Context
        from rclpy.experimental.events_executor import EventsExecutor
        from rclpy.qos import QoSProfile, ReliabilityPolicy
        from sensor_msgs.msg import JointState
        from trajectory_msgs.msg import JointTrajectory

        from piezo_stage.nodes._common import QOS_DATA, QOS_EVENTS, QOS_LATCHED
        self.ns = "/" + namespace.strip("/")
        if domain_id is None:
            domain_id = int(os.environ.get("ROS_DOMAIN_ID", "0") or 0)
        self.ctx = Context()
        rclpy.init(context=self.ctx, domain_id=int(domain_id))
        self.node = rclpy.create_node(f"client_{os.getpid()}", context=self.ctx)
        # the events executor: a set's every sample (1 kHz and more in lockstep) costs
        # it a tenth of what the wait-set executors pay per callback (DESIGN.md)
        self.ex = EventsExecutor(context=self.ctx)
        self.ex.add_node(self.node)
        self.motion_model = motion_model
        self.driver: Announcement | None = None  # the driver's last state
        self.w: PerAxis[float] | None = None
        self.targets: dict[str, TargetState] = {}  # move id -> its last state
        self.phases: list[tuple[str, str]] = []
        self.accepted = 0
        self.last_frame = ""  # the header.frame_id of the last trajectory accepted
        n = self.node
        n.create_subscription(DiagnosticArray, f"{self.ns}/state", self._on_state,
                              QOS_EVENTS)
        # every sample (a dwell's statistics take them all), the last SAMPLES_KEPT kept
        self.samples: deque[tuple[int, float, float]] = deque(maxlen=SAMPLES_KEPT)
        n.create_subscription(JointState, f"{self.ns}/joint_states", self._on_sample,
                              QOS_DATA)
        n.create_subscription(DiagnosticArray, f"{self.ns}/on_target", self._on_target,
                              QOS_LATCHED)
        n.create_subscription(KeyValue, f"{self.ns}/feedforward/phase", self._on_phase,
                              QOS_EVENTS)
        n.create_subscription(JointTrajectory, f"{self.ns}/trajectory/accepted",
                              self._on_accepted, QOS_LATCHED)
        self.refused: dict[str, str] = {}  # a refused trajectory's frame_id -> why
        n.create_subscription(DiagnosticArray, f"{self.ns}/trajectory/refused",
                              self._on_refused, QOS_EVENTS)
        reliable = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE)
        self.move_pub = n.create_publisher(PointStamped, f"{self.ns}/move", reliable)
        self.traj_pub = n.create_publisher(JointTrajectory, f"{self.ns}/trajectory", reliable)
        self.params: dict[str, float] = {}
        try:
            def answered():
                return (self.driver is not None and self.w is not None
                        and self.move_pub.get_subscription_count() > 0)
            # a set's nodes announce themselves twice a second: none on the graph after
            # DISCOVERY_S is no set (said then, not after the whole timeout); one that
            # is there but not yet answering (starting, arming) gets the timeout
            if not self._wait(lambda: answered() or self._set_on_graph(),
                              min(timeout, DISCOVERY_S)) or not self._wait(answered,
                                                                           timeout):
                raise NoStage(f"no stage at {self.ns} in domain {domain_id} "
                              f"(is the set launched there?)")
            # the latched history (the driver's earlier states, the phases) comes in
            # order on matching: the last of it is the present
            self._wait(lambda: False, SETTLE_IN_S)
        except BaseException:
            self.close()
            raise

    def _set_on_graph(self) -> bool:
        """Whether a node of the set's namespace (its driver's state publisher, or any
        node there) is on the graph."""
        n = self.node
        if n.count_publishers(f"{self.ns}/state") > 0:
            return True
        ns = "/" + self.ns.strip("/")
        return any(node_ns == ns for _, node_ns in n.get_node_names_and_namespaces())

    # -- what comes in ----------------------------------------------------------------
    def _on_state(self, msg) -> None:
        from piezo_stage_msgs_adapters import announcement_from_msg
        try:
            self.driver = announcement_from_msg(msg)
        except PiezoStageError:
            pass

    def _on_sample(self, msg) -> None:
        from piezo_stage_msgs_adapters import joint_state_to_um
        try:
            ns, self.w = joint_state_to_um(msg)
        except PiezoStageError:
            return
        self.samples.append((ns, self.w["x"], self.w["y"]))

    def _on_target(self, msg) -> None:
        from piezo_stage_msgs_adapters import on_target_from_msg
        try:
            s = on_target_from_msg(msg)
        except PiezoStageError:
            return
        self.targets[s.move_id] = s

    def _on_phase(self, msg) -> None:
        from piezo_stage_msgs_adapters import phase_from_msg
        self.phases.append(phase_from_msg(msg))

    def _on_refused(self, msg) -> None:
        from piezo_stage_msgs_adapters import refusal_from_msg
        try:
            frame_id, _, reason = refusal_from_msg(msg)
        except PiezoStageError:
            return
        self.refused[frame_id] = reason

    def _on_accepted(self, msg) -> None:
        self.accepted += 1
        self.last_frame = msg.header.frame_id

    def _wait(self, cond, timeout: float) -> bool:
        t_end = time.monotonic() + timeout
        while not cond():
            left = t_end - time.monotonic()
            if left <= 0:
                return False
            self.ex.spin_once(timeout_sec=min(0.01, left))
        return True

    def _resend(self, pub, msg, answered, t_end: float) -> None:
        """``msg`` (published once already) sent again each RESEND_S until ``answered()``
        or ``t_end`` (monotonic [s]): a reader that had not yet matched this writer
        dropped what came before it. For a move only: the stage takes a move asked again
        under its id as the same move (a trajectory sent again is another one)."""
        while not self._wait(answered, min(RESEND_S, max(0.0, t_end - time.monotonic()))):
            if time.monotonic() >= t_end:
                return
            pub.publish(msg)

    def _check_driver(self) -> None:
        """StageFault when the driver faulted or applies no commands."""
        for _ in range(10):  # what came in meanwhile
            self.ex.spin_once(timeout_sec=0.0)
        d = self.driver
        if d is not None and d.state == "faulted":
            raise StageFault(f"{self.ns}: faulted: {d.reason}")
        if d is not None and d.state == "disarmed":
            raise StageFault(f"{self.ns}: disarmed ({d.reason}): arm it first (its arm "
                             "service, or activate a managed set)")

    # -- what a script asks ---------------------------------------------------------
    def position(self) -> tuple[float, float]:
        """The stage's last measured position (x, y) [um]."""
        self.ex.spin_once(timeout_sec=0.0)
        assert self.w is not None
        return self.w["x"], self.w["y"]

    def state(self) -> str:
        """The driver's arming state (armed, approaching, arming, disarmed, faulted)."""
        self.ex.spin_once(timeout_sec=0.0)
        return self.driver.state if self.driver is not None else ""

    def wait_state(self, name: str = "armed", timeout: float = 30.0) -> None:
        """Wait until the driver's state is ``name`` (MoveTimeout after ``timeout``;
        StageFault if it faults meanwhile, unless that is the state asked for)."""
        def there():
            d = self.driver
            return d is not None and (d.state == name or d.state == "faulted")
        if not self._wait(there, timeout):
            raise MoveTimeout(f"{self.ns}: not {name} within {timeout:g} s (it is "
                              f"{self.state() or 'silent'})")
        d = self.driver
        if d is not None and d.state == "faulted" and name != "faulted":
            raise StageFault(f"{self.ns}: faulted: {d.reason}")

    def predict(self, x: float, y: float) -> float:
        """The settle time [s] a move from here to (x, y) takes, by the motion-time
        model (StageError when the client has none)."""
        if self.motion_model is None:
            raise StageError("no motion-time model: `piezo-stage bench settle --out "
                             "FILE` fits one; Stage(motion_model=...) takes it")
        wx, wy = self.position()
        return self.motion_model.predict(((x - wx) ** 2 + (y - wy) ** 2) ** 0.5)

    def configure(self, tol_um: float | None = None, settle_ms: float | None = None) -> None:
        """The stage's on-target tolerance [um] and settling window [ms] (the
        feedforward's live parameters), set where they differ from the last set."""
        want = {k: float(v) for k, v in (("on_target_tol_um", tol_um),
                                         ("on_target_window_ms", settle_ms))
                if v is not None and self.params.get(k) != float(v)}
        if not want:
            return
        from rclpy.parameter import Parameter
        from rclpy.parameter_client import AsyncParameterClient
        cli = AsyncParameterClient(self.node, f"{self.ns}/feedforward")
        if not cli.wait_for_services(10.0):
            raise NoStage(f"{self.ns}/feedforward: no parameter service")
        fut = cli.set_parameters([Parameter(k, value=v) for k, v in want.items()])
        if not self._wait(fut.done, 10.0):
            raise StageError(f"{self.ns}/feedforward: no answer setting {', '.join(want)}")
        for (k, v), r in zip(want.items(), fut.result().results):
            if not r.successful:
                raise StageError(f"{k} {v:g} refused: {r.reason}")
            self.params[k] = v

    def move_to(self, x: float, y: float, tol_um: float | None = None,
                settle_ms: float | None = None, timeout: float = 10.0) -> MoveDone:
        """Move to (x, y) [um] and wait until the stage says it is on target (within
        ``tol_um`` for ``settle_ms``: the stage's own when None). Raises StageFault,
        MoveRefused, MoveTimeout."""
        from piezo_stage_msgs_adapters import move_msg
        self._check_driver()
        self.configure(tol_um, settle_ms)
        move_id = f"{self.node.get_name()}-{next(self._ids)}"
        t0 = time.monotonic()
        t_end = t0 + timeout
        msg = move_msg(move_id, {"x": x, "y": y})
        self.move_pub.publish(msg)
        # the stage's verdict, or a fault, or the timeout
        def over():
            s = self.targets.get(move_id)
            d = self.driver
            return (s is not None and s.state in (ON_TARGET, REFUSED)) or (
                d is not None and d.state == "faulted")
        self._resend(self.move_pub, msg, lambda: over() or move_id in self.targets, t_end)
        arrived = self._wait(over, max(0.0, t_end - time.monotonic()))
        self._check_driver()
        s = self.targets.get(move_id)
        if s is not None and s.state == REFUSED:
            raise MoveRefused(f"move to ({x:g}, {y:g}) um refused by the stage: {s.reason}")
        if not arrived or s is None:
            w = self.w or {}
            last = (f"; {s.state}, at " + ", ".join(
                f"{a} {w[a] - s.target_um[a]:+.3f} um" for a in s.target_um if a in w)
                + " from the target") if s else "; the stage never answered it"
            raise MoveTimeout(f"move to ({x:g}, {y:g}) um not on target within "
                              f"{timeout:g} s{last}")
        return MoveDone(move_id, float(s.settle_s or 0.0), dict(s.error_um),
                        time.monotonic() - t0, dict(s.target_um), s.stamp_ns)

    def dwell(self, seconds: float, since_ns: int | None = None,
              timeout: float | None = None) -> Dwell:
        """Wait ``seconds`` of the set's time from ``since_ns`` (a move's declaration,
        ``MoveDone.stamp_ns``; None: the last sample) and return the position measured
        meanwhile: its mean and spread per axis, as a detector integrating there sees
        it. Raises StageFault, MoveTimeout (``timeout``: 10 s beyond ``seconds``)."""
        import numpy as np
        self.ex.spin_once(timeout_sec=0.0)
        t0 = since_ns if since_ns is not None else (self.samples[-1][0] if self.samples
                                                     else 0)
        t1 = t0 + int(round(seconds * 1e9))
        limit = seconds + 10.0 if timeout is None else timeout
        if not self._wait(lambda: bool(self.samples) and self.samples[-1][0] >= t1 or (
                self.driver is not None and self.driver.state == "faulted"), limit):
            raise MoveTimeout(f"a {seconds:g} s dwell: the set's samples did not reach it "
                              f"within {limit:g} s")
        self._check_driver()
        got = [s for s in self.samples if t0 <= s[0] <= t1]
        if not got:
            raise StageError(f"a {seconds:g} s dwell: no sample kept from it")
        w = np.array([(x, y) for _, x, y in got])
        return Dwell(len(got), got[0][0], got[-1][0],
                     {"x": float(w[:, 0].mean()), "y": float(w[:, 1].mean())},
                     {"x": float(w[:, 0].std()), "y": float(w[:, 1].std())})

    def run(self, t_s, w_um: PerAxis[np.ndarray], timeout: float | None = None) -> float:
        """Run a trajectory (t [s], {axis: um}) and wait for its end (the
        feedforward's phase done) -> the seconds waited, from its publication to its
        end (a float). Raises TrajectoryRefused (with the stage's reason), StageFault
        and MoveTimeout (``timeout``: the trajectory's length plus 30 s when None)."""
        from piezo_stage_msgs_adapters import trajectory_msg
        self._check_driver()
        msg = trajectory_msg(t_s, w_um)
        # its name: the acceptance that carries it is this run's
        msg.header.frame_id = f"{self.node.get_name()}-{next(self._ids)}"
        n_acc = self.accepted
        limit = timeout if timeout is not None else float(t_s[-1]) + 30.0
        # its phases: from here on, and naming it (the feedforward's phase follows
        # "trajectory of N points stamped S"). Counted from acceptance, a short one's
        # "done" was missed now and then in lockstep, where it can come in before the
        # acceptance is read (two topics, no order between them), and the client waited
        # out its timeout for a trajectory that had ended
        n_phase = len(self.phases)
        st = msg.header.stamp
        follows = (f"trajectory of {len(msg.points)} points stamped "
                   f"{st.sec * 1_000_000_000 + st.nanosec}")
        t0 = time.monotonic()
        t_end = t0 + min(limit, 30.0)
        self._wait(lambda: self.traj_pub.get_subscription_count() > 0, min(limit, 30.0))
        self.traj_pub.publish(msg)
        # sent once, reliably, and kept until every matched reader has it: sent again it
        # would be another publication, which the stage runs again
        from rclpy.duration import Duration
        self.traj_pub.wait_for_all_acked(Duration(seconds=max(0.0, t_end - time.monotonic())))

        def accepted():
            return self.accepted > n_acc and self.last_frame == msg.header.frame_id
        self._wait(lambda: accepted() or msg.header.frame_id in self.refused,
                   max(0.0, t_end - time.monotonic()))
        if msg.header.frame_id in self.refused:
            raise TrajectoryRefused(f"{self.ns}: the trajectory was refused: "
                                    f"{self.refused[msg.header.frame_id]}")
        if not accepted():
            raise StageError(f"{self.ns}: the trajectory was not accepted (see the "
                             "feedforward's log)")
        def ended():
            d = self.driver
            return any(p == "done" and f == follows for p, f in self.phases[n_phase:]) or (
                d is not None and d.state == "faulted")
        if not self._wait(ended, limit):
            raise MoveTimeout(f"the trajectory did not end within {limit:g} s")
        self._check_driver()
        return time.monotonic() - t0

    @contextmanager
    def record(self, path: str) -> Iterator[str]:
        """Record every topic of the set to an MCAP bag at ``path`` while the block
        runs (our recorder, as a process of its own; stopped and the bag finished at
        the block's end)."""
        if os.path.exists(path):
            raise StageError(f"{path}: exists (a bag is never overwritten)")
        sim = self.node.count_publishers("/clock") > 0
        out = os.path.abspath(path)
        cmd = [sys.executable, "-m", "piezo_stage.nodes.recorder_node", "--ros-args",
               "-r", f"__ns:={self.ns}", "-p", f"output:={out}",
               "-p", f"log_time:={'stamp' if sim else 'receive'}",
               "-p", f"use_sim_time:={'true' if sim else 'false'}"]
        env = dict(os.environ, ROS_DOMAIN_ID=str(self.ctx.get_domain_id()))
        # its diagnostics say when the set's samples reach it (discovery of a new
        # process takes up to a second or so; what comes before would be lost)
        from diagnostic_msgs.msg import DiagnosticArray

        from piezo_stage.nodes._common import QOS_DIAG
        seen = {"n": 0}

        def on_diag(msg):
            for st in msg.status:
                kv = {v.key: v.value for v in st.values}
                if kv.get("bag") == out:
                    seen["n"] = int(kv.get(f"{self.ns}/joint_states", "0") or 0)
        sub = self.node.create_subscription(DiagnosticArray, "/diagnostics", on_diag,
                                            QOS_DIAG)
        import tempfile
        log = tempfile.TemporaryFile(mode="w+")  # (a pipe left unread would block it)
        proc = subprocess.Popen(cmd, env=env, stdout=subprocess.DEVNULL, stderr=log,
                                text=True)
        try:
            if not self._wait(lambda: proc.poll() is not None or seen["n"] > 0, 30.0) \
                    or proc.poll() is not None:
                raise StageError(f"the recorder did not start: {_tail(proc, log)}")
            self.node.destroy_subscription(sub)
            yield path
        finally:
            if proc.poll() is None:
                proc.send_signal(signal.SIGINT)
                try:
                    proc.wait(30)
                except subprocess.TimeoutExpired:
                    proc.kill()
                    proc.wait()
            log.close()

    def close(self) -> None:
        """Leave the set (the node and its context end; in a ``piezo-stage`` command
        that talks to a set, at the command's end, bounded: process/teardown.py)."""
        import rclpy

        from piezo_stage.process import teardown
        ex, node, ctx = self.ex, self.node, self.ctx

        def leave() -> None:
            try:
                ex.shutdown()  # the executor lets go of the node's entities first
                node.destroy_node()
            finally:
                rclpy.try_shutdown(context=ctx)
        teardown.leave(leave)

    def __enter__(self) -> Stage:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def _tail(proc: subprocess.Popen, log) -> str:
    """The recorder's last line of stderr (or its exit code)."""
    if proc.poll() is None:
        return "still starting"
    log.seek(0)
    lines = log.read().strip().splitlines()
    return lines[-1] if lines else f"exit {proc.returncode}"
