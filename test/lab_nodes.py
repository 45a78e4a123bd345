"""Lab nodes the node tests run beside a set (outside processes, rclpy only), and what
their runs must show in the bag."""

import numpy as np

from piezo_stage.io.bag import deserialize, iter_messages

# a lab node that publishes one trajectory (the same message, so the same bytes) TIMES
# times, each once its run before ended: a trajectory is its publication (default QoS:
# volatile, reliable)
SAME_AGAIN = r"""
import sys, time, rclpy
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from builtin_interfaces.msg import Duration as D
from diagnostic_msgs.msg import KeyValue
from trajectory_msgs.msg import JointTrajectory, JointTrajectoryPoint
times = int(sys.argv[1])
rclpy.init()
n = Node('lab_same_again')
pub = n.create_publisher(JointTrajectory, '/stage/trajectory', 10)
events = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=20,
                    reliability=ReliabilityPolicy.RELIABLE,
                    durability=DurabilityPolicy.TRANSIENT_LOCAL)
phases = []
n.create_subscription(KeyValue, '/stage/feedforward/phase',
                      lambda m: phases.append(m.key), events)
msg = JointTrajectory(joint_names=['x', 'y'])
for k, (x, y) in enumerate(((20e-6, 20e-6), (40e-6, 25e-6), (30e-6, 30e-6))):
    msg.points.append(JointTrajectoryPoint(positions=[x, y],
                                           time_from_start=D(sec=0, nanosec=k * 10**8)))
def spin_until(cond, timeout):
    t_end = time.time() + timeout
    while not cond() and time.time() < t_end:
        rclpy.spin_once(n, timeout_sec=0.02)
    return cond()
assert spin_until(lambda: pub.get_subscription_count() >= 1, 120)
spin_until(lambda: False, 1.0)  # the phases' history first
for _ in range(times):
    seen = len(phases)
    pub.publish(msg)  # (reliable: kept for the feedforward until it has it)
    # its run: a phase other than done, then done
    ran = lambda: any(p != 'done' for p in phases[seen:]) and phases[-1:] == ['done']
    assert spin_until(ran, 60), phases[seen:]
n.destroy_node()
rclpy.try_shutdown()
"""


# a lab node that names its trajectory as a request (header.frame_id "request:..."):
# it sends request #1 twice at once and once more after its run, then request #2 once;
# the stage runs each request once (core/loop/stamps.py request_key)
REQUEST_AGAIN = SAME_AGAIN.split("for _ in range(times):")[0] + r"""
def send(name, times):
    seen = len(phases)
    msg.header.frame_id = name
    for _ in range(times):
        pub.publish(msg)
    return seen
ran = lambda seen: any(p != 'done' for p in phases[seen:]) and phases[-1:] == ['done']
seen = send('request:/lab@1#1', 2)
assert spin_until(lambda: ran(seen), 60), phases[seen:]
seen = send('request:/lab@1#1', 1)  # taken already: not run again
spin_until(lambda: False, 2.0)
assert phases[seen:] == [], phases[seen:]
seen = send('request:/lab@1#2', 1)
assert spin_until(lambda: ran(seen), 60), phases[seen:]
n.destroy_node()
rclpy.try_shutdown()
"""


def topic_data(bag, suffix):
    return [(log, data) for topic, _, log, data in iter_messages(bag) if topic.endswith(suffix)]


def assert_ran_each(bag, times):
    """``times`` trajectories accepted and in the bag, each run through its middle point
    (x 40 um) and held at its last (30, 30) um before the next came: read from the
    desired positions alone, in sample order (the recorder's log times are the wall
    clock's, a lockstep set's stamps its own samples', so they do not split the runs)."""
    accepted = sorted(log for log, _ in topic_data(bag, "/stage/trajectory/accepted"))
    assert len(accepted) == times, accepted
    last = {}
    for _, data in topic_data(bag, "/diagnostics"):
        for st in deserialize(data, "diagnostic_msgs/msg/DiagnosticArray").status:
            last[st.name] = {kv.key: kv.value for kv in st.values}
    ff = next(v for k, v in last.items() if k.endswith("feedforward: inverse feedforward"))
    assert int(float(ff["trajectories"])) == times, ff
    from piezo_stage_msgs_adapters.wire import joint_state_um
    samples = sorted((joint_state_um(d) for _, d in topic_data(bag, "/joint_states")),
                     key=lambda s: s[0])
    w = np.array([[x["x"], x["y"]] for _, x, _ in samples])
    # each run: a spell through its middle point (x above 38 um, from below 34: the
    # measured position's noise crosses no line twice), then its end held for 20
    # samples in a row before the next spell (a set's stop ramps it down after the last)
    starts, low = [], True
    for k, x in enumerate(w[:, 0]):
        if low and x > 38.0:
            starts.append(k)
        low = x < 34.0 if not low else low and not x > 38.0
    assert len(starts) == times, (starts, w[:, 0].max())
    for a, b in zip(starts, list(starts[1:]) + [len(w)]):
        at_end = np.abs(w[a:b] - [30.0, 30.0]).max(axis=1) < 0.5
        runs = np.convolve(at_end.astype(int), np.ones(20, int), "valid")
        assert runs.size and runs.max() == 20, w[a:b][-20:]
