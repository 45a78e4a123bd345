"""`piezo-stage replay BAG`: republish a recorded bag's messages on their topics.

Raw CDR bytes are published as recorded (no deserialisation), at the original pace
scaled by ``rate`` (0: as fast as the subscribers take them), on the bag's one time
base (log times: simulated time for lockstep runs, wall clock for real-time ones).
/clock carries the bag's time every ``clock_period_s`` of it, so nodes on use_sim_time
follow the replay (as ``ros2 bag play --clock`` does); the recorded /clock is not
replayed. Diagnostics and the model hand-over are not replayed, so a live identifier
re-identifies from the data. A trajectory is published latched (transient local), as
an outside publisher is asked to, so a node that joins later still gets it.
``duration_s`` is the record's time (the first ``duration_s`` seconds of the bag,
whatever the rate). One line at the end says what was replayed, whether it ran to the
end, was cut by ``duration_s`` or interrupted.
"""

from __future__ import annotations

import time

from piezo_stage.io.bag import iter_messages
from piezo_stage.nodes._common import UNKNOWN_NODE as UNKNOWN

SKIP = ("/diagnostics", "/model", "/rosout", "/parameter_events", "/clock")
DEEP_ENOUGH_S = 0.1  # a subscriber's queue should hold this much of a topic's stream




def _subscribers(node, topic: str, wait_s: float = 1.0) -> list:
    """The topic's subscribers, given up to ``wait_s`` for the graph to learn their
    nodes' names (a subscription is discovered before its node's name arrives)."""
    t_end = time.monotonic() + wait_s
    while True:
        subs = node.get_subscriptions_info_by_topic(topic)
        if all(i.node_name != UNKNOWN for i in subs) or time.monotonic() > t_end:
            return subs
        time.sleep(0.02)


def _warn_shallow_subscribers(node, pubs, msgs, rate) -> None:
    """What a subscriber needs to keep a fast stream whole, said before it plays: a
    best-effort subscriber is named (a warning line: it drops samples); for the others
    one note per fast topic (over 100 messages a second at this rate) gives the queue
    depth that holds ``DEEP_ENOUGH_S`` of it (a default-QoS subscriber, depth 10,
    dropped 1 % of a 1 kHz joint_states replay while its callback ran; DDS discovery
    does not carry a subscriber's depth, so it cannot be told apart here)."""
    import sys

    from rclpy.qos import ReliabilityPolicy
    span: dict[str, tuple[int, int, int]] = {}  # topic -> first, last stamp, count
    for topic, _, log_ns, _ in msgs:
        first, last, n = span.get(topic, (log_ns, log_ns, 0))
        span[topic] = (first, log_ns, n + 1)
    for topic, pub in pubs.items():
        first, last, n = span[topic]
        per_s = n / max((last - first) * 1e-9, 1e-3) * (rate if rate > 0 else 10.0)
        if n < 100 or per_s <= 100:
            continue
        subs = _subscribers(node, pub.topic_name)
        for info in subs:
            if info.qos_profile.reliability == ReliabilityPolicy.BEST_EFFORT:
                who = "a subscriber" if info.node_name == UNKNOWN else \
                    f"{info.node_namespace.rstrip('/')}/{info.node_name}"
                sys.stderr.write(
                    f"piezo-stage replay: warning: {who} subscribes to {pub.topic_name} "
                    f"best effort: at {per_s:,.0f} messages/s it loses some; subscribe reliable\n")
        if subs:
            sys.stderr.write(
                f"piezo-stage replay: note: {pub.topic_name} streams {per_s:,.0f} "
                f"messages/s: a subscriber keeps every one with a queue of "
                f"{max(100, int(per_s * DEEP_ENOUGH_S)):,} or more, reliable (the "
                f"default depth of 10 drops what arrives while its callback runs; or "
                f"replay with a lower --rate)\n")


def replay(bag, rate=1.0, namespace=None, clock_period_s=0.01, duration_s=None) -> int:
    import rclpy
    from rclpy.executors import ExternalShutdownException
    from rosgraph_msgs.msg import Clock

    from piezo_stage.nodes._common import QOS_DATA, QOS_LATCHED
    from piezo_stage.nodes._tap import msg_class
    from piezo_stage.process import stopping
    from piezo_stage.progress import bar
    from piezo_stage_msgs_adapters import clock_msg
    # the node modules' import took the stop signals for a node's start-up
    # (process/signals.py); this is a command: a stop unwinds it, and it says how far it got
    stopping.install()
    code = 0
    msgs = [m for m in iter_messages(bag) if not m[0].endswith(SKIP)]
    t0_log = msgs[0][2] if msgs else 0
    span_s = (msgs[-1][2] - t0_log) * 1e-9 if msgs else 0.0
    if duration_s is not None:
        msgs = [m for m in msgs if (m[2] - t0_log) * 1e-9 <= duration_s]
    print(f"replay: {len(msgs)} messages, {min(span_s, duration_s or span_s):.3f} s of the "
          f"record at rate {rate:g}; waiting up to 5 s for subscribers, then playing",
          flush=True)
    rclpy.init()
    node = rclpy.create_node("replay")
    pubs, n, how, log_ns = {}, 0, "to the end", t0_log
    t0_wall = time.monotonic()
    try:
        for topic, msgtype, _, _ in msgs:
            if topic not in pubs:
                name = topic if not namespace else namespace.rstrip("/") + "/" + \
                    topic.rsplit("/", 1)[-1]
                qos = QOS_LATCHED if topic.endswith(("/trajectory", "/accepted")) \
                    else QOS_DATA
                pubs[topic] = node.create_publisher(msg_class(msgtype), name, qos)
        clock = node.create_publisher(Clock, "/clock", 10)
        next_clock = None
        deadline = time.monotonic() + 5.0  # let subscribers match before the first sample
        while time.monotonic() < deadline and not all(p.get_subscription_count() for p in
                                                       pubs.values()):
            rclpy.spin_once(node, timeout_sec=0.05)
        _warn_shallow_subscribers(node, pubs, msgs, rate)
        t0_wall = time.monotonic()
        # on a terminal: how far the replay is, in the record's seconds
        with bar("replay", total=round(span_s, 1), unit="s of record") as b:
            for topic, _, log_ns, data in msgs:
                if rate > 0:
                    due = t0_wall + (log_ns - t0_log) * 1e-9 / rate
                    while (left := due - time.monotonic()) > 0:  # one reading per check:
                        time.sleep(min(0.001, left))  # never a negative sleep
                if clock_period_s > 0 and (next_clock is None or log_ns >= next_clock):
                    clock.publish(clock_msg(log_ns))
                    next_clock = log_ns + int(clock_period_s * 1e9)
                    b.update(round((log_ns - t0_log) * 1e-9, 1) - b.n)
                pubs[topic].publish(data)
                n += 1
        for p in pubs.values():
            p.wait_for_all_acked()
        if duration_s is not None and duration_s < span_s:
            how = f"cut at --duration {duration_s:g} s of the record"
    except (KeyboardInterrupt, ExternalShutdownException):
        import signal
        how = f"stopped by {signal.Signals(stopping.STATE.signum).name}"
        code = 128 + stopping.STATE.signum
    finally:
        from piezo_stage.process import teardown

        def leave() -> None:
            try:
                node.destroy_node()
            finally:
                rclpy.try_shutdown()
        teardown.leave(leave)  # at the command's end, bounded (process/teardown.py)
    print(f"replayed {n} messages on {len(pubs)} topics: {(log_ns - t0_log) * 1e-9:.3f} s "
          f"of the record's {span_s:.3f} s in {time.monotonic() - t0_wall:.3f} s, {how}",
          flush=True)
    return code
