"""What every node shares: QoS profiles, the lean loop (executor), the Jazzy main(),
parameters. The control loop's shared pieces are in _loop.py."""

from __future__ import annotations

import gc
import time

import rclpy
from rclpy.callback_groups import CallbackGroup
from rclpy.executors import ExternalShutdownException
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

# Loop and record topics: reliable with a deep queue, so a briefly slow subscriber (the
# recorder) catches up instead of losing samples.
QOS_DATA = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=5000,
                      reliability=ReliabilityPolicy.RELIABLE,
                      durability=DurabilityPolicy.VOLATILE)
# Model and whole trajectories: the last one is kept for late joiners.
QOS_LATCHED = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=1,
                         reliability=ReliabilityPolicy.RELIABLE,
                         durability=DurabilityPolicy.TRANSIENT_LOCAL)
# State changes (the driver's arming state, the feedforward's phase): latched, and
# every change delivered in order, so a reader that takes them in batches misses none.
QOS_EVENTS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=20,
                        reliability=ReliabilityPolicy.RELIABLE,
                        durability=DurabilityPolicy.TRANSIENT_LOCAL)
QOS_DIAG = QoSProfile(depth=50, reliability=ReliabilityPolicy.RELIABLE)


class LeanLoop(CallbackGroup):
    """Callback group of a node's per-sample subscriptions: served by the lean loop in
    ``_spin`` and never by the executor (``can_execute`` is False), so the executor's
    slow path neither builds them into its wait set nor dispatches them."""

    def can_execute(self, entity):
        return False

    def beginning_execution(self, entity):
        return False

    def ending_execution(self, entity):
        pass


def steady_timer(node, period_s, callback):
    """A housekeeping timer (polls, flushes, links, diagnostics cadence) on the steady
    clock: it runs while simulated time stands still (before the first sample, after the
    last), where a ROS-time timer under use_sim_time would never fire."""
    from rclpy.clock import Clock, ClockType
    return node.create_timer(period_s, callback, clock=Clock(clock_type=ClockType.STEADY_TIME))


def hot_subscription(node, msg_type, topic, callback, qos, raw=False, with_info=False):
    """A per-sample subscription (loop inputs, the recorder's topics), dispatched by
    the lean loop. With ``raw`` the callback gets the CDR bytes; with ``with_info`` it
    also gets the middleware's message info (``received_timestamp`` [ns], ...)."""
    group = node.__dict__.setdefault("_lean_group", LeanLoop())
    sub = node.create_subscription(msg_type, topic, callback, qos, callback_group=group,
                                   raw=raw)
    sub.lean_info = with_info
    node.__dict__.setdefault("_hot", []).append(sub)
    node.hot_changed = True
    return sub


SLOW_PERIOD_S = 0.05  # the executor's turn (timers, services, other topics) in the lean loop


def _spin(node):
    """Spin. A node's hot subscriptions (``hot_subscription``) are served by a lean
    wait-set loop that takes and dispatches their messages directly; the default
    executor serves everything else (timers, services, parameters, other topics) every
    ``SLOW_PERIOD_S``. The default executor costs ~0.3-0.5 ms of CPU per callback here,
    too much for a 1 kHz loop through four processes.

    A node with a real-time tick sets ``lean_deadline`` (monotonic seconds of its next
    tick; 0.0 for a tick paced by the hardware, which blocks in it) and
    ``on_lean_tick()``, which the loop calls once the deadline has passed, right after
    taking what has arrived. The loop sleeps in the wait set until then."""
    from contextlib import ExitStack

    from rclpy.impl.implementation_singleton import rclpy_implementation as _rclpy
    executor = rclpy.executors.SingleThreadedExecutor(context=node.context)
    executor.add_node(node)
    ticking = hasattr(node, "on_lean_tick")
    if not getattr(node, "_hot", None) and not ticking:
        executor.spin()
        return
    ctx = node.context
    batch = float(getattr(node, "hot_batch_s", 0.0))
    stack = ExitStack()
    hot = []
    try:
        ws = None
        last = 0.0
        while ctx.ok():
            try:
                if ws is None or node.hot_changed:  # (re)build the wait set
                    node.hot_changed = False
                    stack.close()
                    hot = [(s.handle, s.msg_type, s.raw, s.callback, s.lean_info)
                           for s in getattr(node, "_hot", [])]
                    for h, *_ in hot:
                        stack.enter_context(h)
                    ws = _rclpy.WaitSet(len(hot), 0, 0, 0, 0, 0, ctx.handle) if hot else None
                timeout = 0.002  # s: wake at least every 2 ms for the slow work
                deadline = getattr(node, "lean_deadline", None) if ticking else None
                if deadline is not None:
                    timeout = min(timeout, max(0.0, deadline - time.monotonic()))
                if ws is not None:
                    ws.clear_entities()
                    for h, *_ in hot:
                        ws.add_subscription(h)
                    ws.wait(int(timeout * 1e9))
                elif timeout > 0:
                    time.sleep(timeout)
                _take_all(hot)
                now = time.monotonic()
                if deadline is not None and now >= deadline:
                    node.on_lean_tick()
                if now - last > SLOW_PERIOD_S:
                    last = now
                    executor.spin_once(timeout_sec=0)
                if batch:  # a node off the loop's critical path (the recorder) wakes less
                    t_end = now + batch
                    while ctx.ok() and time.monotonic() < t_end:
                        time.sleep(min(batch, 0.02))
            except Exception:
                if ctx.ok():
                    raise
                break  # SIGINT shut the context down mid-iteration: rcl calls now fail
        _drain(hot)
    finally:
        stack.close()
    raise ExternalShutdownException()


def _drain(hot):
    """On shutdown, what had already arrived is still handed over (the recorder's last
    few milliseconds)."""
    try:
        _take_all(hot, limit=None)
    except Exception:  # noqa: BLE001 - the middleware may be gone already
        pass


TAKE_LIMIT = 256  # messages per subscription per pass of the lean loop


def _take_all(hot, limit=TAKE_LIMIT):
    """Dispatch what has arrived, at most ``limit`` messages per subscription (None:
    all): a node that falls behind its input still gives the executor (services,
    parameters, timers) and its tick their turn, instead of taking forever."""
    for h, msg_type, raw, callback, info in hot:
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


def _shutdown_only(signum, frame):
    """SIGINT: rclpy's own handler (installed by init, chained to this one) has already
    shut the context down from its thread; the spin loops see that and return. Raising
    KeyboardInterrupt here instead would unwind from an arbitrary point inside the
    executor, which on rare occasions left a node hanging or crashing at teardown."""


def run(node_factory, args=None, graceful=False):
    """Jazzy form: init; try spin; except interrupt/external shutdown; finally clean up.

    ``graceful``: SIGINT and SIGTERM do not shut the context down; they call the node's
    ``request_shutdown()``, and the node shuts the context down itself once it is safe
    (the driver first ramps the stage to its safe voltage, still publishing). A second
    signal shuts down at once."""
    import signal
    opts = None
    if graceful:
        from rclpy.signals import SignalHandlerOptions
        opts = SignalHandlerOptions.NO
        holder = {}

        def on_signal(signum, frame):
            node = holder.get("node")
            if node is None or getattr(node, "shutdown_requested", False):
                rclpy.try_shutdown()
            else:
                node.request_shutdown()
        signal.signal(signal.SIGINT, on_signal)
        signal.signal(signal.SIGTERM, on_signal)
    else:
        signal.signal(signal.SIGINT, _shutdown_only)  # before init: rclpy chains to it
    rclpy.init(args=args, signal_handler_options=opts)
    node = None
    code = 0
    try:
        node = node_factory()
        if graceful:
            holder["node"] = node
        # what exists now (modules, the node) lives for the whole run: keep it out of the
        # cyclic collector's scans, so a full collection is not a multi-ms loop stall
        gc.collect()
        gc.freeze()
        _spin(node)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    except Exception as e:  # a node that cannot run says why and exits non-zero
        if not rclpy.ok():
            return code  # raced with SIGINT's shutdown (rcl calls fail from then on)
        import sys
        name = node.get_fully_qualified_name() if node is not None else _node_name(args)
        sys.stderr.write(f"{name}: fatal: {e}\n")
        code = 1
    finally:
        gc.unfreeze()  # teardown as usual: the middleware's objects are collected
        if node is not None:
            close = getattr(node, "close", None)
            if close:
                close()
            node.destroy_node()
        rclpy.try_shutdown()
    return code


def _node_name(args):
    """The node's name for a start-up error (the node object may not exist yet)."""
    import sys
    argv = list(args or sys.argv)
    name = sys.argv[0].rsplit("/", 1)[-1].removesuffix(".py").removesuffix("_node")
    ns = next((a.split(":=", 1)[1] for a in argv if a.startswith("__ns:=")), "")
    return f"{ns.rstrip('/')}/{name}" if ns else name
