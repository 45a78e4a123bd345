"""What the control loop's nodes share: real-time priority and memory, the driver's announcements
(DriverState), which link of the loop is missing, start-up gating (Gate), and
/diagnostics."""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from typing import TYPE_CHECKING, Any

from piezo_stage.core.errors import PiezoStageError
from piezo_stage.core.loop.arming import ARMED
from piezo_stage.nodes._common import QOS_DIAG, QOS_EVENTS, Status, steady_timer
from piezo_stage.nodes._executor import hot_subscription, local_readers, subscriber_count
from piezo_stage_msgs_adapters import diagnostic_array

if TYPE_CHECKING:
    from diagnostic_msgs.msg import DiagnosticArray
    from rclpy.node import Node
    from rclpy.publisher import Publisher


def set_realtime_priority(prio: int, logger: Any, main_thread: bool = True) -> int:
    """SCHED_FIFO at ``prio`` for every thread of this process (the loop's and the
    middleware's, so a publish never waits on a starved middleware thread: priority
    inversion), as ros2_control does for its control thread. Where the OS does not
    permit it, say so and go on at normal priority. Real time only: a lockstep loop is
    CPU-bound and would starve everything else. ``main_thread=False``: only the
    middleware's threads (a recorder receives and acknowledges promptly, while its own
    batch writing and compression stay at normal priority)."""
    import os
    if prio <= 0:
        return 0
    try:
        for tid in os.listdir("/proc/self/task"):
            if int(tid) == os.getpid() and not main_thread:
                continue
            below = _polls_a_mutex(tid)
            if below and (prio <= 1 or not main_thread):
                continue  # nothing lower to give it than normal priority: leave it there
            want = prio - 1 if below else prio
            if os.sched_getscheduler(int(tid)) == os.SCHED_FIFO and \
                    os.sched_getparam(int(tid)).sched_priority >= want:
                continue  # composed nodes: the highest asked for stands (the driver's)
            os.sched_setscheduler(int(tid), os.SCHED_FIFO, os.sched_param(want))
        return prio
    except (PermissionError, OSError, AttributeError, ValueError) as e:
        logger.warning(f"thread_priority {prio}: not permitted here ({e}); running at "
                       "normal priority, so expect more missed ticks and late commands")
        return 0


PAGE, HEAP_CAP = 4096, 512 * 2**20
M_TRIM_THRESHOLD, M_MMAP_MAX = -1, -4  # glibc's mallopt parameters (malloc.h)


def reserve_heap(nbytes: int, logger: Any) -> int:
    """The real-time memory recipe (as the PREEMPT_RT wiki and ros2_realtime give it):
    no allocation of its own mmap, the heap never trimmed, and ``nbytes`` of it touched
    now, so later allocations up to that size reuse pages already faulted in. rclpy
    takes a message with the GIL held, copying it twice (the middleware's buffer, then
    Python's bytes); on fresh pages a 11.2 MB trajectory took 20-25 ms of the loop's
    thread here (page faults in this VM: ~1 ms per MB), on faulted ones 1-2 ms. At
    most HEAP_CAP (a lab that raises a node's message limits far pays the faults beyond
    it). glibc only; elsewhere say so and go on. Returns the bytes reserved (0: none)."""
    import ctypes
    import ctypes.util
    nbytes = min(int(nbytes), HEAP_CAP)
    if nbytes <= 0:
        return 0
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
        if not (libc.mallopt(M_MMAP_MAX, 0) and libc.mallopt(M_TRIM_THRESHOLD, -1)):
            raise OSError("mallopt refused")
    except (OSError, AttributeError) as e:
        logger.warning(f"heap reserve: not available here ({e}); a large message's "
                       "first take may stall the loop by ~1 ms per MB")
        return 0
    block = bytearray(nbytes)
    block[::PAGE] = b"\1" * len(range(0, nbytes, PAGE))  # touch every page
    del block  # back to the heap, which keeps it
    return nbytes


def _polls_a_mutex(tid: int | str) -> bool:
    """Whether a thread is one of Fast DDS's asynchronous writer threads (``dds.asyn.*``),
    which poll a writer's mutex in a loop while another thread holds it (rmw_fastrtps
    issue 666). At the holder's own SCHED_FIFO priority two of them filled both cores of
    a 2-core host and the holder never ran again (a controller at 188 % CPU for half an
    hour, deaf to signals). So they go one level below every thread that may hold that
    mutex, and where one of those stays at normal priority (the recorder's main thread),
    they stay there too: the holder then always preempts them."""
    try:
        with open(f"/proc/self/task/{tid}/comm") as fh:
            return fh.read().startswith("dds.asyn")
    except OSError:
        return False


def missing_links(node: Node) -> str:
    """Which link of the control loop has no node, in words ('' when none is missing):
    for an arm request's refusal and the driver's diagnostics."""
    ns = node.get_namespace().rstrip("/")
    missing = [f"no {who}: nothing {verb} {ns}/{topic}" for who, verb, topic, n in (
        ("controller", "publishes", "command", node.count_publishers(f"{ns}/command")),
        ("feedforward", "subscribes to", "joint_states",  # (composed with it: linked)
         node.count_subscribers(f"{ns}/joint_states") + local_readers(f"{ns}/joint_states")),
        ("feedforward", "publishes", "reference", node.count_publishers(f"{ns}/reference")),
    ) if n == 0]
    return "; ".join(missing)


class DriverState:
    """What a loop node knows of the driver, from its announcements on ``state``
    (taken by LeanExecutor before the node's data, so lockstep stays deterministic):
    the state by sample stamp (``timeline``), the look-ahead, whether the set runs in
    real time (the node then takes its real-time priority ``prio`` and reserves
    ``heap_bytes`` of heap: ``reserve_heap``), the driver's voltage and slew limits. ``bad``
    counts malformed announcements."""

    def __init__(self, node: Node, dt_ns: int, prio: int, heap_bytes: int = 0) -> None:
        from diagnostic_msgs.msg import DiagnosticArray

        from piezo_stage.core.loop.arming import StateTimeline
        self.node, self.prio, self.heap_bytes = node, prio, int(heap_bytes)
        self.timeline, self.lookahead_ns, self.dt_ns = StateTimeline(), dt_ns, dt_ns
        self.realtime, self.bad = False, 0
        self.armed_once = False  # the driver has announced armed (its capacity held)
        self.limits: tuple | None = None  # the driver's voltage limits, once announced
        self.slew_V_per_s: float | None = None  # its slew limit (the slowest axis's)
        hot_subscription(node, DiagnosticArray, "state", self.on_state, QOS_EVENTS)

    def on_state(self, msg: DiagnosticArray) -> None:
        from piezo_stage_msgs_adapters import announcement_from_msg
        try:
            a = announcement_from_msg(msg)
        except PiezoStageError:
            self.bad += 1
            return
        self.lookahead_ns = int(round(a.lookahead_s * 1e9)) or self.dt_ns
        if a.mode == "realtime" and not self.realtime:
            # the heap first, at normal priority: touching it holds a core for a while,
            # which at SCHED_FIFO another set's loop on this host could not preempt
            reserved = reserve_heap(self.heap_bytes, self.node.get_logger())
            if reserved:
                self.node.get_logger().info(
                    f"heap: {reserved / 2**20:.0f} MB reserved and touched (the "
                    "largest message this node takes then costs no page faults)")
            self.heap_bytes = 0  # once
            set_realtime_priority(self.prio, self.node.get_logger())
        self.realtime = a.mode == "realtime"
        self.limits = a.limits or self.limits
        try:
            self.slew_V_per_s = float(a.values["slew_V_per_s"])
        except (KeyError, ValueError):
            pass
        self.timeline.add(a.since_ns, a.state)
        self.armed_once = self.armed_once or a.state == ARMED

    def enabled(self, ns: int) -> bool:
        return self.timeline.enabled(ns)


class Gate:
    """Holds outgoing messages until every listed publisher has its number of matched
    subscriptions, then sends them in order. In lockstep nothing is published before
    every consumer (the recorder included) listens, so a run loses nothing and is
    reproducible. ``needs``: list of (publisher, n)."""

    def __init__(self, node: Node, needs: Sequence[tuple[Publisher, int]]) -> None:
        self._node = node
        self.needs = [(p, int(n)) for p, n in needs]
        self.queue: list = []
        self.open = all(n <= 0 for _, n in self.needs)
        self.opened_at = time.monotonic()  # when what it held went out (steady clock)
        if not self.open:
            self._timer = steady_timer(node, 0.01, self.poll)

    def poll(self) -> None:
        """Open the gate where every publisher has its subscriptions now (its timer's
        callback; a node whose own clock ticks may call it at each tick)."""
        if not self.open and all(subscriber_count(p) >= n for p, n in self.needs):
            self.open, self.opened_at = True, time.monotonic()
            self._timer.cancel()
            self._node.destroy_timer(self._timer)  # out of the executor's wait set
            for pub, m in self.queue:
                pub.publish(m)
            self.queue.clear()

    def holding(self) -> bool:
        """Still closed, polled now: a node whose own clock ticks looks at each tick,
        not only when the gate's timer is served (its executor serves one callback each
        SLOW_PERIOD_S among the others ready: subscribers were seen late, in steps of
        it)."""
        if not self.open:
            self.poll()
        return not self.open

    def publish(self, pub: Publisher, msg: Any) -> None:
        if self.open:
            pub.publish(msg)
        else:  # the timer polls the graph: a graph query per message costs the loop
            self.queue.append((pub, msg))


class Diagnostics:
    """/diagnostics at 1 Hz (steady cadence, stamped on the node's clock), the
    diagnostic_msgs way: status name ``"<namespace>/<node>: <task>"`` (two stages never
    collide), ``hardware_id`` naming the device (the driver's own; the other nodes
    learn it from the driver's ``state``), and a message that says why the level is
    what it is.

    ``status()`` -> (level, message, values) gives the node's own state. ``rates``:
    (counter key, what it counts, WARN above this many per second, averaged over the
    last ``window_s``): levels come from what happened recently, so a warning clears
    once its cause stops; the cumulative counters stay in the values."""

    def __init__(self, node: Node, status: Callable[[], Status], task: str,
                 hardware_id: str | Callable[[], str] | None = None,
                 rates: Sequence[tuple[str, str, float]] = (), window_s: float = 5.0) -> None:
        from diagnostic_msgs.msg import DiagnosticArray
        self.node, self.status, self.task, self.rates = node, status, task, tuple(rates)
        self.hw: str | Callable[[], str] = hardware_id or ""
        self.window_s = window_s
        self.history: list = []
        self.pub = node.create_publisher(DiagnosticArray, "/diagnostics", QOS_DIAG)
        if hardware_id is None:  # the device is the driver's: from its announcements
            self.hw = f"stage {node.get_namespace()}"
            node.create_subscription(DiagnosticArray, "state", self._on_driver_state,
                                     QOS_EVENTS)
        steady_timer(node, 1.0, self.publish)

    def _on_driver_state(self, msg: DiagnosticArray) -> None:
        if msg.status and msg.status[0].hardware_id:
            self.hw = msg.status[0].hardware_id

    def learn_from_state(self, data: bytes) -> None:
        """The driver's ``state`` as the recorder takes it, bytes: the recorder's own
        subscription to it is served only now and then by its executor, and in a short
        lockstep run its last report once went out still naming "stage /stage"."""
        from piezo_stage.io.bag import deserialize
        try:
            self._on_driver_state(deserialize(data, "diagnostic_msgs/msg/DiagnosticArray"))
        except Exception:  # noqa: BLE001 - not the driver's announcement: nothing learnt
            pass

    @property
    def name(self) -> str:
        return f"{self.node.get_namespace().rstrip('/')}/{self.node.get_name()}: {self.task}"

    def evaluate(self, now_s: float | None = None) -> Status:
        """(level, message, values) with the recent-rate checks applied."""
        level, message, values = self.status()
        now_s = time.monotonic() if now_s is None else now_s
        self.history.append((now_s, {k: values.get(k, 0) for k, _, _ in self.rates}))
        while len(self.history) > 1 and now_s - self.history[0][0] > self.window_s:
            self.history.pop(0)
        t0, old = self.history[0]
        span = now_s - t0
        why = []
        for key, what, per_s in self.rates:
            n = float(values.get(key, 0)) - float(old.get(key, 0))
            if span > 0 and n > 0 and n / span > per_s:
                why.append(f"{n:g} {what} in the last {span:.0f} s")
        if why:
            level = max(level, 1)
            message = f"{message}; " + "; ".join(why)
        return level, message, values

    def final(self, timeout_s: float = 1.0) -> None:
        """The last report, with the final counts, delivered before the node goes (the
        driver's end_run, a lone node's close: the recorder stops after the nodes that
        publish). A run shorter than the 1 s cadence, or whose node's report was due
        after the run's end (composed nodes share one executor), still has every node's
        report in its bag."""
        from rclpy.duration import Duration
        try:
            self.publish()
            self.pub.wait_for_all_acked(Duration(seconds=timeout_s))
        except Exception:  # noqa: BLE001 - the context already shut down: nothing to tell
            pass

    def report(self) -> tuple[int, DiagnosticArray]:
        """(stamp [ns], the report now as a DiagnosticArray)."""
        level, message, values = self.evaluate()
        ns = self.node.get_clock().now().nanoseconds
        return ns, diagnostic_array(ns, self.name, level, message, values,
                                    self.hw() if callable(self.hw) else self.hw)

    def publish(self) -> None:
        self.pub.publish(self.report()[1])
