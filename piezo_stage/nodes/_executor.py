"""LeanExecutor: the executor every node spins on (per-sample subscriptions taken
directly, a real-time tick, everything else through rclpy's executor), and the pieces
of a node's Jazzy ``main()``.

rclpy's executors rebuild a wait set and dispatch through tasks for every callback:
about 0.3-0.5 ms of CPU per callback here, too much for a 1 kHz loop through four
processes. ``LeanExecutor`` subclasses ``rclpy.executors.Executor`` the way
ros2/examples writes custom executors: its ``spin_once`` waits on a wait set of the
node's per-sample subscriptions only (the ``LeanLoop`` callback group, which the base
class never executes), takes and dispatches what arrived, calls the node's real-time
tick when it is due, and gives the base class's machinery (timers, services,
parameters, other topics) one callback every ``SLOW_PERIOD_S`` (every ready one, up to
``IDLE_SLOW_MAX``, in a pass that carried no sample).

Composed nodes (several spun by one executor) pass their per-sample messages to each
other in the process (``LocalLinks``: rclcpp's intra-process communication, which
rclpy lacks); the middleware still carries them to every other process.
"""

from __future__ import annotations

import gc
import os
import signal
import sys
import time
import weakref
from collections import deque
from collections.abc import Callable, Sequence
from contextlib import ExitStack
from typing import TYPE_CHECKING, Any, ClassVar, Protocol, cast, runtime_checkable

import rclpy
from rclpy.callback_groups import CallbackGroup
from rclpy.executors import (
    ConditionReachedException,
    Executor,
    ExternalShutdownException,
    ShutdownException,
    TimeoutException,
)
from rclpy.signals import SignalHandlerOptions

import piezo_stage.process.signals as signals
from piezo_stage.core.errors import ConfigError, DataError
from piezo_stage.nodes._params import check_overrides

if TYPE_CHECKING:
    from rclpy.context import Context
    from rclpy.node import Node
    from rclpy.publisher import Publisher
    from rclpy.qos import QoSProfile
    from rclpy.subscription import Subscription

SLOW_PERIOD_S = 0.05  # the base executor's turn (timers, services, other topics)
IDLE_SLOW_MAX = 16    # callbacks the base executor may serve in a pass nothing came in
IDLE_WAKE_S = 0.02    # with nothing arriving, a node still wakes this often (its stops)
TAKE_LIMIT = 256      # messages per subscription per pass
# composed: while the composed nodes pass a sample along, the middleware's readers are
# asked at least this often (what other processes send: moves, phases), and at once
# after a composed node published where another composed node reads the middleware
MIDDLEWARE_POLL_S = 0.0005
LOCAL_HOPS = 3        # hops handed over in one pass (the loop's three)
HOP_TIMES_ENV = "PIEZO_STAGE_HOP_TIMES"  # a file: a composed process's per-hop costs


class LeanLoop(CallbackGroup):
    """Callback group of one per-sample subscription, served by ``LeanExecutor`` and
    never by the base executor (``can_execute`` is False), so its slow path neither
    builds it into its wait set nor dispatches it. ``with_info``: the callback also
    takes the middleware's message info."""

    def __init__(self, with_info: bool = False) -> None:
        super().__init__()
        self.with_info = bool(with_info)

    def can_execute(self, entity: Any) -> bool:
        return False

    def beginning_execution(self, entity: Any) -> bool:
        return False

    def ending_execution(self, entity: Any) -> None:
        pass


def hot_subscription(node: Node, msg_type: type, topic: str, callback: Callable[..., None],
                     qos: QoSProfile, raw: bool = False, with_info: bool = False) -> Subscription:
    """A per-sample subscription (loop inputs, the recorder's topics), dispatched by
    ``LeanExecutor``. With ``raw`` the callback gets the CDR bytes; with ``with_info``
    it also gets the middleware's message info (``received_timestamp`` [ns], ...)."""
    return node.create_subscription(msg_type, topic, callback, qos,
                                    callback_group=LeanLoop(with_info), raw=raw)


class LocalLinks:
    """The per-sample topics between composed nodes, delivered in the process (rclcpp's
    intra-process communication, which rclpy does not have).

    A per-sample subscription (``hot_subscription``) of one composed node whose topic
    another composed node publishes (same name and type, compatible QoS, volatile: a
    latched topic keeps the middleware, which replays it to a late reader) is taken off
    the middleware and linked to that publisher: each message the publisher sends
    still goes to the middleware's readers (the recorder, other processes) and is also
    queued here, and the executor hands it to the subscriber's callback in publish
    order, as the bytes or the message object that was published (converted where the
    subscriber asked for the other form). On the middleware a message between two
    nodes of one process is a write into the reader's history, a wake of the wait set
    and a take; here it is a call. A pass hands over up to ``LOCAL_HOPS`` hops (what a
    callback publishes is handed over after the callbacks before it), and asks the
    middleware between them at least every ``MIDDLEWARE_POLL_S`` and at once after a
    composed node published where another composed node reads the middleware (a
    latched topic: the driver's state comes before the data that follows it). Asking
    each subscription at every hop cost a sixth of a lockstep loop's time.

    What a linked subscriber no longer hears is another process publishing on its
    topic: the loop's links (joint_states, reference, command) have one publisher each
    in a set, and a set whose node is replaced from outside is not composed (the
    launcher composes only where every node of the composition is its own).
    ``subscriber_count`` and ``local_readers`` count a linked subscriber where the
    middleware's counts no longer do (gates, the driver's missing-link check)."""

    def __init__(self) -> None:
        self.queue: deque = deque()  # (reader, message) in publish order
        self._flagged: weakref.WeakSet = weakref.WeakSet()
        path = os.environ.get(HOP_TIMES_ENV)
        self.times = HopTimes(path) if path else None
        # a composed node published on a topic that another composed node takes from
        # the middleware (a latched one: the driver's state): take it before going on
        self.sent_on_middleware = False

    def link(self, nodes: Sequence[Node]) -> int:
        """Link every per-sample subscription of ``nodes`` that another of them
        publishes; the number linked."""
        from rclpy.qos import DurabilityPolicy, QoSCompatibility, qos_check_compatible
        pubs = [(n, p) for n in nodes for p in n.publishers]
        linked = 0
        for node in nodes:
            for sub in list(node.subscriptions):
                if not isinstance(sub.callback_group, LeanLoop) or \
                        sub.qos_profile.durability != DurabilityPolicy.VOLATILE:
                    continue
                peers = [p for n, p in pubs if n is not node
                         and p.topic_name == sub.topic_name and p.msg_type is sub.msg_type
                         and qos_check_compatible(p.qos_profile, sub.qos_profile)[0]
                         != QoSCompatibility.ERROR]
                if not peers:
                    continue
                reader = LocalReader(sub)
                if self.times is not None:
                    reader.callback = self.times.timed("callback", sub.topic_name,
                                                       reader.callback)
                for p in peers:
                    self._attach(p, reader)
                node.destroy_subscription(sub)
                linked += 1
        for node in nodes:  # per-sample topics that stay on the middleware
            for sub in node.subscriptions:
                if isinstance(sub.callback_group, LeanLoop):
                    for n, p in pubs:
                        if n is not node and p.topic_name == sub.topic_name and \
                                p not in self._flagged:
                            self._flag(p)
        if self.times is not None:  # every publish of the composed nodes, timed
            for _, p in pubs:
                p.publish = self.times.timed(  # type: ignore[method-assign]
                    "publish", p.topic_name, p.publish)
        return linked

    def _flag(self, pub: Publisher) -> None:
        """``pub``'s messages reach a composed node through the middleware: after each,
        the executor's next pass asks the middleware first (publish order kept)."""
        send = pub.publish
        self._flagged.add(pub)

        def publish(msg: Any) -> None:
            send(msg)
            self.sent_on_middleware = True
        pub.publish = publish  # type: ignore[method-assign]

    def _attach(self, pub: Publisher, reader: LocalReader) -> None:
        readers = LOCAL_READERS.setdefault(pub, [])
        if not readers:  # the publisher's own publish, then the queue
            send, queue = pub.publish, self.queue

            def publish(msg: Any) -> None:
                send(msg)
                for r in readers:
                    queue.append((r, msg))
            pub.publish = publish  # type: ignore[method-assign]
        readers.append(reader)

    def deliver(self) -> int:
        """Hand over what was queued before this call (what those callbacks publish
        waits for the next call: the executor asks the middleware first where a
        composed node published to it, ``sent_on_middleware``); the number handed
        over."""
        n = len(self.queue)
        for _ in range(n):
            reader, msg = self.queue.popleft()
            reader.take(msg)
        return n


class HopTimes:
    """The composed nodes' per-hop costs, for ``bench loop`` (``HOP_TIMES_ENV`` names
    the file the process writes them to at its end): each linked callback's time (the
    node's work and its own publishes) and each publish's (the middleware's send, and
    the queue for a linked reader), per topic: the count and the seconds in all."""

    def __init__(self, path: str) -> None:
        self.path = path
        self.acc: dict[str, list] = {}  # "callback /stage/reference" -> [count, seconds]

    def timed(self, kind: str, topic: str, fn: Callable[..., None]) -> Callable[..., None]:
        acc = self.acc.setdefault(f"{kind} {topic}", [0, 0.0])
        clock = time.perf_counter

        def call(*args: Any) -> None:
            t = clock()
            fn(*args)
            acc[1] += clock() - t
            acc[0] += 1
        return call

    def write(self) -> None:
        """The figures as JSON ({"callback TOPIC": [count, seconds], ...}), written whole."""
        import json
        tmp = f"{self.path}.tmp"
        with open(tmp, "w") as fh:
            json.dump(self.acc, fh)
        os.replace(tmp, self.path)


class LocalReader:
    """A linked subscription's callback and the form it takes its messages in."""

    def __init__(self, sub: Subscription) -> None:
        from rclpy.serialization import deserialize_message, serialize_message
        self.topic_name = sub.topic_name
        self.msg_type, self.raw, self.callback = sub.msg_type, sub.raw, sub.callback
        self.with_info = cast(LeanLoop, sub.callback_group).with_info
        self._from_cdr, self._to_cdr = deserialize_message, serialize_message

    def take(self, msg: Any) -> None:
        if isinstance(msg, (bytes, bytearray, memoryview)):
            msg = bytes(msg) if self.raw else self._from_cdr(bytes(msg), self.msg_type)
        elif self.raw:
            msg = self._to_cdr(msg)
        if self.with_info:
            now = time.time_ns()  # the middleware's stamps are the system clock's
            self.callback(msg, {"source_timestamp": now, "received_timestamp": now})
        else:
            self.callback(msg)


# publisher -> the composed subscribers linked to it (LocalLinks)
LOCAL_READERS: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()


def subscriber_count(pub: Publisher) -> int:
    """The publisher's matched subscriptions, its linked ones in the process too."""
    return pub.get_subscription_count() + len(LOCAL_READERS.get(pub, ()))


def local_readers(topic_name: str) -> int:
    """Linked subscriptions of this process on a topic (its fully qualified name)."""
    return sum(r.topic_name == topic_name for rs in LOCAL_READERS.values() for r in rs)


class LeanNode:
    """What ``LeanExecutor`` and ``run_nodes`` ask of a node, with the answers of a node
    that asks for nothing. Every node of the package derives from it, first of its bases
    (``class Recorder(LeanNode, Node)``); a plain rclpy node runs with these defaults.

    - ``TICKS``: the node has a real-time tick: ``on_lean_tick()`` is called once
      ``lean_deadline`` (the monotonic time [s] of the next tick; 0.0 for a tick paced
      by the hardware, which blocks in it; None: no tick now, as in lockstep) has
      passed, right after what arrived was taken; the base executor has its turn right
      after a tick, where the period's slack is.
    - ``lean_take_at_tick``: True while a tick is scheduled: the executor does not wake
      for each per-sample message but sleeps to the deadline and takes what arrived
      just before the tick (the driver in real time: commands are stamped for a later
      tick, so one wake per sample instead of two; their middleware reception time is
      still in the message info).
    - ``lean_batch_s``: a node off the loop's critical path (the recorder, the live view)
      waits that long between passes and takes what arrived in one go.
    - ``USES_KERNELS``: building the node loads compiled kernels (the simulated
      stage, the model's inverse): numba's set-up is done before the start gate.
    - ``DEFERS_STOPS``: the node is built whole though a stop comes meanwhile (the
      recorder: its bag open and its readers acknowledging); the stop ends its first pass.
    - ``close()``: the node's own teardown (the bag, the hardware), before it is
      destroyed; ``final_report()``: its last /diagnostics, before the process's run
      ends (``end_run``); ``stop_summary()``: what a stop leaves behind, for its exit
      line."""

    TICKS: ClassVar[bool] = False
    DEFERS_STOPS: ClassVar[bool] = False
    USES_KERNELS: ClassVar[bool] = False
    lean_deadline: float | None = None
    lean_take_at_tick: bool = False
    lean_batch_s: float = 0.0

    def on_lean_tick(self) -> None:
        """One real-time tick (a node with ``TICKS``)."""

    def close(self) -> None:
        """Close what the node holds open (nothing, unless it says otherwise); by
        default its final report (a lone node; composed, ``end_run`` gave it)."""
        self.final_report()

    def final_report(self) -> None:
        """The node's last report, while its context still holds (``end_run``; none
        unless it says otherwise)."""

    def stop_summary(self) -> str | None:
        """What a stop leaves behind, in words (None: nothing worth a line)."""
        return None


NO_HOOKS = LeanNode()  # the hooks of a plain rclpy node: none asked for


def hooks(node: object) -> LeanNode:
    """The node's hooks: itself where it is a LeanNode, else the defaults."""
    return node if isinstance(node, LeanNode) else NO_HOOKS


@runtime_checkable
class StopsInOrder(Protocol):
    """A node that a stop signal asks to stop in its own order (the stage driver): it
    says whether a stop is under way, and starts one."""

    @property
    def shutdown_requested(self) -> bool: ...

    def request_shutdown(self) -> None: ...


class LeanExecutor(Executor):
    """Spins one node, or the loop's nodes composed in one process (see the module
    docstring and ``loop_container``).

    What a node asks of it is its ``LeanNode`` hooks (a tick, waking at the tick only,
    batching).

    Subscriptions a node creates while it spins (the recorder's discovery) join at the
    base executor's next turn (listing them every pass cost 3-6 % of a loop node's
    time). While the node is spun, everything that exists is frozen out of the
    cyclic garbage collector's scans, so a full collection is not a multi-ms loop
    stall.

    Several nodes (a list; the first that ticks is the clock): their per-sample
    subscriptions share one wait set, and the topics between them are linked in the
    process (``LocalLinks``), so a sample the driver publishes is handed to the
    feedforward in the same thread, its reference to the controller, its command to
    the driver, with no process woken and no middleware between them. Each pass takes
    what the middleware brought, each node's subscriptions in the order it made them
    (its driver's ``state`` before its data, as alone), then what the composed nodes
    sent each other (``LocalLinks``: the middleware is asked between hops only now and
    then, and whenever a composed node published to it). A composed set wakes for every message
    (``lean_take_at_tick`` is a lone driver's) and batches nothing (``lean_batch_s``
    nodes run alone)."""

    def __init__(self, node: Node | Sequence[Node], *, context: Context | None = None) -> None:
        nodes: list[Node] = list(node) if isinstance(node, (list, tuple)) else [node]  # type: ignore[list-item]
        super().__init__(context=context or nodes[0].context)
        for n in nodes:
            self.add_node(n)
        self.nodes = nodes
        # the first that ticks is the clock (its hooks: the node itself)
        self.node = next((h for h in map(hooks, nodes) if h.TICKS), hooks(nodes[0]))
        self.ticking = self.node.TICKS
        self.alone = len(nodes) == 1
        self.local = LocalLinks()
        if not self.alone:
            self.local.link(nodes)
        self._n_subs = -1
        self._hot: list = []
        self._stack = ExitStack()
        self._ws = None
        self._last_slow = 0.0
        self._last_take = 0.0

    # -- the base executor's turn -----------------------------------------------------
    def _slow_once(self, timeout_sec: float = 0.0) -> bool:
        """One ready callback of the node's other entities, through the base class;
        whether there was one."""
        try:
            handler, _, _ = self.wait_for_ready_callbacks(timeout_sec)
        except (ShutdownException, TimeoutException, ConditionReachedException):
            return False
        handler()
        if handler.exception() is not None:
            raise handler.exception()
        return True

    # -- the per-sample subscriptions -------------------------------------------------
    def _subscriptions(self) -> list:
        """Every subscription of the spun nodes, node by node, each in its order."""
        return [s for n in self.nodes for s in n.subscriptions]

    def _rebuild(self, subs: list) -> None:
        from rclpy.impl.implementation_singleton import rclpy_implementation as _rclpy
        self._n_subs = len(subs)
        self._stack.close()
        self._hot = [(s.handle, s.msg_type, s.raw, s.callback, s.callback_group.with_info)
                     for s in subs if isinstance(s.callback_group, LeanLoop)]
        for h, *_ in self._hot:
            self._stack.enter_context(h)
        self._ws = (_rclpy.WaitSet(len(self._hot), 0, 0, 0, 0, 0, self.context.handle)
                    if self._hot else None)

    def take_all(self, limit: int | None = TAKE_LIMIT) -> int:
        """Dispatch what has arrived, at most ``limit`` messages per subscription (None:
        all): a node that falls behind its input still gives the base executor
        (services, parameters, timers) and its tick their turn. The number taken."""
        total = 0
        for h, msg_type, raw, callback, info in self._hot:
            n = 0
            taken = h.take_message(msg_type, raw)
            while taken is not None:
                if info:
                    callback(taken[0], taken[1])
                else:
                    callback(taken[0])
                n += 1
                if limit is not None and n >= limit:
                    break
                taken = h.take_message(msg_type, raw)
            total += n
        return total

    # -- Executor API ------------------------------------------------------------------
    def spin_once(self, timeout_sec: float | None = None) -> None:
        """One pass: wait for per-sample messages or the tick's deadline (at most
        ``timeout_sec``, ``IDLE_WAKE_S`` if None), dispatch, tick when due, and give the
        base executor its turn when it is due."""
        node = self.node
        if self._n_subs < 0:  # first pass; later changes are seen at the slow turn
            self._rebuild(self._subscriptions())
        if not self._hot and not self.ticking:
            self._slow_once(SLOW_PERIOD_S if timeout_sec is None else timeout_sec)
            self._n_subs = -1  # not on the loop: look again next pass
            return
        timeout = IDLE_WAKE_S if timeout_sec is None else timeout_sec
        deadline = node.lean_deadline if self.ticking else None
        if deadline is not None:
            timeout = min(timeout, max(0.0, deadline - time.monotonic()))
        if self.local.queue:
            pass  # what the composed nodes sent each other is due now: no wait
        elif deadline is not None and self.alone and node.lean_take_at_tick:
            if timeout > 0:
                time.sleep(timeout)
        elif self._ws is not None:
            self._ws.clear_entities()
            for h, *_ in self._hot:
                self._ws.add_subscription(h)
            self._ws.wait(int(timeout * 1e9))
        elif timeout > 0:
            time.sleep(timeout)
        local = self.local
        if local.queue and not local.sent_on_middleware and \
                time.monotonic() - self._last_take < MIDDLEWARE_POLL_S:
            busy = 0  # the composed nodes' hops first; the middleware shortly
        else:
            local.sent_on_middleware = False
            self._last_take = time.monotonic()
            busy = self.take_all()
        for _ in range(LOCAL_HOPS if local.queue else 0):
            busy += local.deliver()
            if not local.queue or local.sent_on_middleware:
                break
        now = time.monotonic()
        ticked = deadline is not None and now >= deadline
        if ticked:
            node.on_lean_tick()
        if now - self._last_slow > SLOW_PERIOD_S and (ticked or deadline is None) or \
                not (busy or ticked or self.local.queue):
            # a pass with no sample in it (start-up, a lockstep set waiting) serves
            # every callback ready, up to IDLE_SLOW_MAX: one a pass, the start gates of
            # composed nodes (a timer each) opened one slow period after another
            self._last_slow = now
            for _ in range(1 if busy or ticked else IDLE_SLOW_MAX):
                if not self._slow_once(0.0):
                    break
            subs = self._subscriptions()  # created or destroyed since (discovery)
            if len(subs) != self._n_subs:
                self._rebuild(subs)
        batch = node.lean_batch_s if self.alone else 0.0
        if batch:
            t_end = now + batch
            while self.context.ok() and not signals.count() and time.monotonic() < t_end:
                time.sleep(min(batch, 0.02))

    def spin(self) -> None:
        """Spin until the context shuts down (SIGINT, or the node itself); what had
        already arrived is still handed over (the recorder's last few milliseconds).
        Raises ExternalShutdownException then, as rclpy's spin does."""
        gc.collect()
        gc.freeze()
        try:
            seen = 0
            while self.context.ok() and not self._is_shutdown:
                if signals.count() > seen:  # a stop signal came (see process/signals.py)
                    seen = signals.count()
                    if not self._stop_requested(seen):
                        break
                try:
                    self.spin_once()
                except Exception:
                    if self.context.ok():
                        raise
                    break  # SIGINT shut the context down mid-pass: rcl calls now fail
            try:
                if self._n_subs < 0:  # stopped before its first pass (a stop noted
                    self._rebuild(self._subscriptions())  # while it was built)
                self.take_all(limit=None)
                self.local.deliver()
            except Exception:  # noqa: BLE001 - the middleware may be gone already
                pass
        finally:
            self._stack.close()
            if self.local.times is not None and self.local.times.acc:
                self.local.times.write()  # (a composed process: one that timed hops)
            gc.unfreeze()  # teardown as usual: the middleware's objects are collected
        raise ExternalShutdownException()

    def _stop_requested(self, n: int) -> bool:
        """A stop signal (the ``n``-th): True to keep spinning. A node that stops in
        order (``StopsInOrder``: the driver ramps the stage to its safe voltage, still
        publishing, then shuts the context down itself) is asked once; a second signal
        ends the spin at once, as it does for every other node on the first."""
        orderly = [x for x in self.nodes if isinstance(x, StopsInOrder)]
        if not orderly or n > 1:
            return False
        for x in orderly:
            if not x.shutdown_requested:
                x.request_shutdown()
        return True


def end_run(node: Node) -> None:
    """End the process's run from ``node`` (the driver: its run is the set's): every
    node spun with it gives its final report while the context still holds (composed,
    the driver's end shuts the context of all of them down), then the context goes."""
    ex = node.executor
    for n in (ex.nodes if isinstance(ex, LeanExecutor) else [node]):
        hooks(n).final_report()
    rclpy.try_shutdown()


# -- a node's main() ----------------------------------------------------------------------
def run_node(factory: Callable[[], Node], args: Sequence[str] | None = None) -> int:
    """Run one node the Jazzy way (init / spin / except / finally destroy, try_shutdown)
    with the stops of :mod:`piezo_stage.process.signals`: rclpy installs no signal
    handler of its own (``SignalHandlerOptions.NO``), ours work from the first import.

    Returns the exit code: 0 when the node ended by itself, 128 + the signal's number
    when a signal stopped it (an ended run, not a success: the launcher accepts it only
    from the nodes it signalled itself), 1 when it could not run (one line on stderr)."""
    return run_nodes([factory], args, warm_kernels=isinstance(factory, type) and issubclass(
        factory, LeanNode) and factory.USES_KERNELS)


def run_nodes(factories: Sequence[Callable[[], Node]], args: Sequence[str] | None = None,
              warm_kernels: bool = False) -> int:
    """``run_node`` for several nodes in one process on one executor (the loop
    composed: ``loop_container``): built in order, spun together, closed and
    destroyed in reverse order; one exit code, as ``run_node``'s. ``warm_kernels``:
    a node builds compiled kernels (``USES_KERNELS``): numba's one-time set-up is paid
    while the process waits at the launcher's start gate, not after it."""
    nodes: list = []
    node, code = None, 0
    try:
        signals.set_phase("building")
        if warm_kernels:
            prepare_kernels()
        preload_type_support()
        warm_caller_lookup()
        gc.collect()  # what the imports left, collected and frozen before the gate: the
        gc.freeze()   # collection at the spin's start then scans the nodes alone
        await_start_gate()
        rclpy.init(args=None if args is None else list(args),
                   signal_handler_options=SignalHandlerOptions.NO)
        for factory in factories:
            # a node whose construction must not be cut short (DEFERS_STOPS: the
            # recorder, its bag open and its readers acknowledging before it returns)
            # is built whole, and a stop that came meanwhile ends its spin's first pass
            with signals.deferred(isinstance(factory, type) and issubclass(
                    factory, LeanNode) and factory.DEFERS_STOPS):
                node = factory()
                check_overrides(node)  # a misspelled parameter is refused, not ignored
            nodes.append(node)
        signals.set_phase("running", ", ".join(n.get_fully_qualified_name()
                                               for n in nodes))
        LeanExecutor(nodes).spin()
    except (signals.Stopped, KeyboardInterrupt, ExternalShutdownException):
        pass
    except Exception as e:  # a node that cannot run says why and exits non-zero
        code = fatal(node, e, args)
    finally:
        phase = signals.STATE.phase
        signals.set_phase("stopping")
        signals.watch()  # a teardown that hangs says where, and ends
        try:
            for n in reversed(nodes):
                hooks(n).close()  # the node's own first: the bag, the hardware
        finally:
            signum = signals.requested()
            with signals.bounded_teardown(code if signum is None else 128 + signum):
                for n in reversed(nodes):
                    n.destroy_node()
                rclpy.try_shutdown()
    # the node is done: a stop arriving from here would meet the interpreter's exit,
    # which gives the default handlers back, and kill a node that had ended by itself
    # by the signal (the demo's driver, once: "killed by SIGINT"); ignored instead
    signals.hold()
    signum = signals.requested()
    if signum is None:
        return code
    where = "while running" if phase == "running" else "during start-up"
    did = next((s for s in (hooks(n).stop_summary() for n in nodes) if s), None)
    ended = signals.run_ended() if signum == signal.SIGINT else None
    if ended is not None and (phase == "running" or ended == "retried"):
        if did and ended != "retried":  # the run ended: what it leaves, not a stop
            sys.stderr.write(f"{signals.STATE.name}: at the run's end: {did}\n")
        return 0  # (a try run again at a lower rate: the launcher says so, once)
    sys.stderr.write(f"{signals.STATE.name or _node_name(args)}: stopped by "
                     f"{signal.Signals(signum).name} {where}"
                     f"{': ' + did if did else ''}\n")
    return 128 + signum


def prepare_kernels() -> None:
    """numba's one-time set-up of its CPU target (its typing and lowering registries:
    about 0.5 s of a 2-core host's CPU), which the first compiled kernel a process loads
    from the cache would pay otherwise: done before the node joins the graph, while the
    launcher looks for a set already running, it leaves the set's start-up."""
    from numba.core.registry import cpu_target
    cpu_target.typing_context.refresh()
    cpu_target.target_context.refresh()


# what rclpy's Node makes for itself: parameter services and events, /rosout, the type
# description service, /clock (use_sim_time)
RCLPY_OWN_TYPES = ("rcl_interfaces.msg", "rcl_interfaces.srv", "rosgraph_msgs.msg",
                   "type_description_interfaces.srv")


def preload_type_support() -> int:
    """Load the C type support of every message and service type the process has
    imported, and of those rclpy's Node makes for itself, before the node joins the
    graph: each package's support is a library loaded on its first use, and a
    process's first node takes far longer to build than the next ones (`bench
    startup`). Done while the launcher looks for a set already running, it
    leaves the set's start-up. The number of types loaded."""
    import importlib
    import re

    from rclpy.type_support import check_for_type_support
    for name in RCLPY_OWN_TYPES:
        try:
            importlib.import_module(name)
        except ImportError:  # (a package not installed: the node says so when built)
            continue
    loaded = 0
    pattern = re.compile(r"[A-Za-z0-9_]+\.(msg|srv)\._[A-Za-z0-9_]+")
    for name, module in list(sys.modules.items()):
        if module is None or not pattern.fullmatch(name):
            continue
        for value in list(vars(module).values()):
            if isinstance(value, type) and value.__module__ == name and \
                    hasattr(value, "__import_type_support__"):
                try:
                    check_for_type_support(value)
                    loaded += 1
                except Exception:  # noqa: BLE001 - building the node says what is wrong
                    continue
    return loaded


def warm_caller_lookup() -> None:
    """rclpy's logger names each line's caller (``inspect.getframeinfo``), and the
    process's first line maps the file of every module imported (``inspect.getmodule``'s
    cache): the driver's first line, its state's announcement as it configures, would
    pay that after the node joined the graph. Mapped here before the start gate
    instead; a module imported later is mapped at the next line, alone."""
    import inspect
    inspect.getframeinfo(sys._getframe())


START_GATE_ENV = "PIEZO_STAGE_START_GATE"  # launcher/launcher.py's
START_GATE_MAX_S = 120.0


def await_start_gate() -> None:
    """Wait, imported but not yet on the graph, for the launcher's go (the file its
    ``START_GATE_ENV`` names): the launcher looks for a set already running in the
    namespace meanwhile, and kills the nodes instead where one does. Stops work while
    waiting (the building phase: process/signals.py); no gate asked for, no wait."""
    import os
    path = os.environ.get(START_GATE_ENV)
    if not path:
        return
    end = time.monotonic() + START_GATE_MAX_S
    while not os.path.exists(path):
        if time.monotonic() > end:
            raise ConfigError(f"the launcher did not let the node start within "
                              f"{START_GATE_MAX_S:g} s")
        time.sleep(0.01)


def fatal(node: Node | None, error: BaseException, args: Sequence[str] | None = None) -> int:
    """A node that cannot run says why on one line of stderr; the exit code (2 for a
    configuration or data error, 1 otherwise, or 0 when the error only raced with a
    SIGINT's shutdown: rcl calls fail from then on)."""
    if not rclpy.ok():
        return 0
    name = node.get_fully_qualified_name() if node is not None else _node_name(args)
    sys.stderr.write(f"{name}: fatal: {error}\n")
    return 2 if isinstance(error, (ConfigError, DataError)) else 1


def _node_name(args: Sequence[str] | None) -> str:
    """The node's name for a start-up error (the node object may not exist yet)."""
    argv = list(args or sys.argv)
    name = sys.argv[0].rsplit("/", 1)[-1].removesuffix(".py").removesuffix("_node")
    ns = next((a.split(":=", 1)[1] for a in argv if a.startswith("__ns:=")), "")
    return f"{ns.rstrip('/')}/{name}" if ns else name
