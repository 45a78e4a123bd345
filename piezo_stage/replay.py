"""`piezo-stage replay BAG`: republish a recorded bag's messages on their topics.

Raw CDR bytes are published as recorded (no deserialisation), at the original pace
scaled by ``rate`` (0: as fast as the subscribers take them), on the bag's one time
base (log times: simulated time for lockstep runs, wall clock for real-time ones).
/clock carries the bag's time every ``clock_period_s`` of it, so nodes on use_sim_time
follow the replay (as ``ros2 bag play --clock`` does); the recorded /clock is not
replayed. Diagnostics and the model hand-over are not replayed, so a live identifier
re-identifies from the data.
"""

from __future__ import annotations

import time

from piezo_stage.io.bag import iter_messages

SKIP = ("/diagnostics", "/model", "/rosout", "/parameter_events", "/clock")


def replay(bag, rate=1.0, namespace=None, clock_period_s=0.01) -> int:
    import rclpy
    from rclpy.executors import ExternalShutdownException
    from rosgraph_msgs.msg import Clock

    from piezo_stage.nodes._common import QOS_DATA
    from piezo_stage.nodes._tap import msg_class
    from piezo_stage_msgs_adapters import clock_msg
    rclpy.init()
    node = rclpy.create_node("replay")
    pubs, n = {}, 0
    try:
        msgs = [m for m in iter_messages(bag) if not m[0].endswith(SKIP)]
        for topic, msgtype, _, _ in msgs:
            if topic not in pubs:
                name = topic if not namespace else namespace.rstrip("/") + "/" + \
                    topic.rsplit("/", 1)[-1]
                pubs[topic] = node.create_publisher(msg_class(msgtype), name, QOS_DATA)
        clock = node.create_publisher(Clock, "/clock", 10)
        next_clock = None
        deadline = time.monotonic() + 5.0  # let subscribers match before the first sample
        while time.monotonic() < deadline and not all(p.get_subscription_count() for p in
                                                       pubs.values()):
            rclpy.spin_once(node, timeout_sec=0.05)
        t0_log, t0_wall = (msgs[0][2] if msgs else 0), time.monotonic()
        for topic, _, log_ns, data in msgs:
            if rate > 0:
                due = t0_wall + (log_ns - t0_log) * 1e-9 / rate
                while (left := due - time.monotonic()) > 0:  # one reading per check:
                    time.sleep(min(0.001, left))  # never a negative sleep
            if clock_period_s > 0 and (next_clock is None or log_ns >= next_clock):
                clock.publish(clock_msg(log_ns))
                next_clock = log_ns + int(clock_period_s * 1e9)
            pubs[topic].publish(data)
            n += 1
        for p in pubs.values():
            p.wait_for_all_acked()
        print(f"replayed {n} messages on {len(pubs)} topics")
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        node.destroy_node()
        rclpy.try_shutdown()
    return 0
