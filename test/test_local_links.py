"""Composed nodes hand each other their per-sample messages in the process
(nodes/_executor.py LocalLinks, rclcpp's intra-process communication): in publish
order, in the form each subscriber asked for, still on the middleware for every other
process, and counted by the gates; a latched topic stays on the middleware."""

import json
import subprocess
import sys

import pytest

LINKS_PROBE = r"""
import json, time, rclpy
from rclpy.node import Node
from geometry_msgs.msg import Vector3Stamped
from std_msgs.msg import String
from piezo_stage.nodes._common import QOS_DATA, QOS_EVENTS
from piezo_stage.nodes._executor import (LeanExecutor, LeanNode, hot_subscription,
                                         local_readers, subscriber_count)
from piezo_stage_msgs_adapters import voltage_cdr

rclpy.init()


class Sender(LeanNode, Node):
    def __init__(self):
        super().__init__("sender", namespace="/links")
        self.cmd = self.create_publisher(Vector3Stamped, "cmd", QOS_DATA)
        self.obj = self.create_publisher(String, "obj", QOS_DATA)
        self.ev = self.create_publisher(String, "ev", QOS_EVENTS)
        self.back = []
        hot_subscription(self, String, "back", lambda m: self.back.append(m.data), QOS_DATA)


class Taker(LeanNode, Node):
    def __init__(self):
        super().__init__("taker", namespace="/links")
        self.cmd, self.obj, self.ev, self.info = [], [], [], []
        self.back = self.create_publisher(String, "back", QOS_DATA)
        hot_subscription(self, Vector3Stamped, "cmd", self.on_cmd, QOS_DATA, raw=True,
                         with_info=True)
        hot_subscription(self, String, "obj", self.on_obj, QOS_DATA, raw=True)
        hot_subscription(self, String, "ev", lambda m: self.ev.append(m.data), QOS_EVENTS)

    def on_cmd(self, data, info):
        self.cmd.append(data)
        self.info.append(sorted(info))
        self.back.publish(String(data=str(len(self.cmd))))  # a reply, for the next pass

    def on_obj(self, data):
        self.obj.append(data)


a, b = Sender(), Taker()
# another process's view: a participant of its own (another context)
ctx = rclpy.Context()
rclpy.init(context=ctx)
outside = rclpy.create_node("outside", namespace="/links", context=ctx)
heard = []
outside.create_subscription(Vector3Stamped, "cmd", lambda m: heard.append(m), QOS_DATA,
                            raw=True)
ex = LeanExecutor([a, b])
topics = sorted(s.topic_name for s in b.subscriptions)
out = {"taker_on_middleware": topics, "local_cmd": local_readers("/links/cmd"),
       "local_ev": local_readers("/links/ev")}
end = time.monotonic() + 20
while a.cmd.get_subscription_count() < 1 and time.monotonic() < end:
    rclpy.spin_once(outside, timeout_sec=0.05)
out["counted"] = subscriber_count(a.cmd)
sent = [voltage_cdr(10**9 + k, {"x": 0.5 * k, "y": -k}) for k in range(50)]
a.ev.publish(String(data="announced"))
for m in sent:
    a.cmd.publish(m)
a.obj.publish(String(data="object"))
passes = 0
while (len(b.cmd) < 50 or len(a.back) < 50 or not b.ev) and passes < 200:
    ex.spin_once(0.05)
    passes += 1
end = time.monotonic() + 10
while len(heard) < 50 and time.monotonic() < end:
    rclpy.spin_once(outside, timeout_sec=0.05)
out.update(in_order=b.cmd == sent, n_cmd=len(b.cmd), obj=[bytes(x).hex() for x in b.obj],
           info=b.info[0] if b.info else [], ev=b.ev, back=a.back[:3] + a.back[-1:],
           outside=len(heard), outside_same=heard == sent)
from rclpy.serialization import serialize_message
out["obj_want"] = serialize_message(String(data="object")).hex()
print(json.dumps(out))
"""


def test_composed_nodes_pass_messages_in_the_process_and_to_the_middleware(ros_env):
    pytest.importorskip("rclpy")
    r = subprocess.run([sys.executable, "-c", LINKS_PROBE], env=ros_env,
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr[-2000:]
    out = json.loads(r.stdout.strip().splitlines()[-1])
    # the taker's per-sample volatile topics left the middleware; the latched one stayed
    assert out["taker_on_middleware"] == ["/links/ev"], out
    assert out["local_cmd"] == 1 and out["local_ev"] == 0, out
    # the gate counts the linked subscriber beside the outside one
    assert out["counted"] == 2, out
    # every message, in publish order, byte for byte; an object as the CDR asked for
    assert out["n_cmd"] == 50 and out["in_order"], out
    assert out["obj"] == [out["obj_want"]], out
    assert out["info"] == ["received_timestamp", "source_timestamp"], out
    assert out["ev"] == ["announced"], out
    # a reply published in a callback reaches its linked reader (a later pass)
    assert out["back"] == ["1", "2", "3", "50"], out
    # and another participant still gets every message over the middleware
    assert out["outside"] == 50 and out["outside_same"], out


IDLE_PROBE = r"""
import json, time, rclpy
from rclpy.node import Node
from std_msgs.msg import String
from piezo_stage.nodes._common import QOS_DATA, steady_timer
from piezo_stage.nodes._executor import LeanExecutor, LeanNode, hot_subscription

rclpy.init()


class Polling(LeanNode, Node):
    # a composed node as the loop's are before their first sample: a 10 ms start-gate
    # timer, a per-sample subscription on which nothing arrives yet
    def __init__(self, name):
        super().__init__(name, namespace="/idle")
        self.fired = 0
        steady_timer(self, 0.01, self.poll)
        hot_subscription(self, String, "samples", lambda m: None, QOS_DATA)

    def poll(self):
        self.fired += 1


nodes = [Polling("first"), Polling("second"), Polling("third")]
ex = LeanExecutor(nodes)
end = time.monotonic() + 0.5
while time.monotonic() < end:
    ex.spin_once()
print(json.dumps([n.fired for n in nodes]))
"""


def test_a_composed_process_with_no_sample_serves_every_ready_timer(ros_env):
    """Before its first sample a composed process serves every ready callback of its
    nodes each pass (their start gates are timers), not one every 50 ms: there the
    first node's 10 ms gate timer was always ready, took every slot, and the gates
    opened one after another (0.1, 0.22 and 0.35 s after configure)."""
    pytest.importorskip("rclpy")
    r = subprocess.run([sys.executable, "-c", IDLE_PROBE], env=ros_env,
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr[-2000:]
    fired = json.loads(r.stdout.strip().splitlines()[-1])
    # 0.5 s of 10 ms timers: one callback every 50 ms would give 10 in all, the
    # first node all of them
    assert min(fired) >= 10, fired


PRELOAD_PROBE = r"""
import json
from sensor_msgs.msg import JointState
from piezo_stage.nodes._executor import preload_type_support
before = [JointState._TYPE_SUPPORT is not None]
n = preload_type_support()
from rcl_interfaces.msg import ParameterEvent
from type_description_interfaces.srv import GetTypeDescription
print(json.dumps({"before": before, "n": n, "after": [
    JointState._TYPE_SUPPORT is not None, ParameterEvent._TYPE_SUPPORT is not None,
    GetTypeDescription._TYPE_SUPPORT is not None]}))
"""


def test_the_type_support_a_node_needs_is_loaded_before_it_joins_the_graph(ros_env):
    """``preload_type_support`` (run before the start gate) loads the C type support of
    the message types the process imported and of those rclpy's Node makes for itself
    (parameters, the type description service), where building the first node loaded
    them one library at a time, 0.24 s after the gate."""
    pytest.importorskip("rclpy")
    r = subprocess.run([sys.executable, "-c", PRELOAD_PROBE], env=ros_env,
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr[-2000:]
    out = json.loads(r.stdout.strip().splitlines()[-1])
    assert out["before"] == [False] and out["after"] == [True, True, True], out
    assert out["n"] > 10, out


ORDER_PROBE = r"""
import json, time, rclpy
from rclpy.node import Node
from geometry_msgs.msg import Vector3Stamped
from std_msgs.msg import String
from piezo_stage.nodes._common import QOS_DATA, QOS_EVENTS
from piezo_stage.nodes._executor import LeanExecutor, LeanNode, hot_subscription
from piezo_stage_msgs_adapters import voltage_cdr

rclpy.init()
ROUNDS = 60


class Announcer(LeanNode, Node):
    # as the driver: each round an announcement on a latched topic (the middleware),
    # then the data that follows it on a linked one
    def __init__(self):
        super().__init__("announcer", namespace="/order")
        self.ev = self.create_publisher(String, "ev", QOS_EVENTS)
        self.cmd = self.create_publisher(Vector3Stamped, "cmd", QOS_DATA)
        self.k = 0
        hot_subscription(self, String, "back", self.on_back, QOS_DATA)

    def send(self):
        self.ev.publish(String(data=str(self.k)))
        self.cmd.publish(voltage_cdr(10**9 + self.k, {"x": 0.0, "y": 0.0}))

    def on_back(self, msg):
        if self.k < ROUNDS:
            self.k += 1
            self.send()


class Follower(LeanNode, Node):
    def __init__(self):
        super().__init__("follower", namespace="/order")
        self.last_ev, self.seen, self.rounds = None, [], 0
        self.back = self.create_publisher(String, "back", QOS_DATA)
        hot_subscription(self, String, "ev", self.on_ev, QOS_EVENTS)
        hot_subscription(self, Vector3Stamped, "cmd", self.on_cmd, QOS_DATA, raw=True)

    def on_ev(self, msg):
        self.last_ev = int(msg.data)

    def on_cmd(self, data):
        self.seen.append(self.last_ev)  # the announcement this datum follows
        self.back.publish(String(data="next"))


a, b = Announcer(), Follower()
ex = LeanExecutor([a, b])
a.send()
end = time.monotonic() + 30
while len(b.seen) <= ROUNDS and time.monotonic() < end:
    ex.spin_once(0.05)
print(json.dumps({"seen": b.seen}))
"""


def test_an_announcement_on_the_middleware_reaches_its_composed_reader_before_the_data(
        ros_env):
    """Composed hops are handed over several to a pass, the middleware asked between
    them only now and then; a composed node's message on a topic another composed node
    reads from the middleware (a latched one: the driver's state) is taken before
    the linked data published after it (``LocalLinks.sent_on_middleware``)."""
    pytest.importorskip("rclpy")
    r = subprocess.run([sys.executable, "-c", ORDER_PROBE], env=ros_env,
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr[-2000:]
    seen = json.loads(r.stdout.strip().splitlines()[-1])["seen"]
    assert seen == list(range(61)), seen
