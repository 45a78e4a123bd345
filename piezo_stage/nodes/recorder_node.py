"""recorder: every topic, as raw serialized messages, into a rosbag2-layout MCAP bag.

Subscribes to the topic contract at start (so nothing of a lockstep run is missed)
and to any other topic it discovers. Messages are written as the CDR bytes received
(no deserialize/serialize round trip); stamped messages are logged at their header
stamp, others at receive time. Chunks are flushed every ``flush_period_s`` so a
SIGKILL loses at most that much; SIGINT finalises a complete bag. The run's config and
model files go in as MCAP metadata.
"""

import importlib
import sys
import os
import struct

from piezo_stage.io.bag import BagWriter, new_bag_dir
from piezo_stage.nodes._common import (QOS_DATA, QOS_DIAG, QOS_EVENTS,
                                       QOS_LATCHED, hot_subscription, run, steady_timer)
from piezo_stage.nodes._params import declare
from piezo_stage.nodes._loop import Diagnostics, set_realtime_priority
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy

CONTRACT = {  # relative name: (type, QoS kind: data, latched, events, diag)
    # (the kind is what our publishers offer; the recorder subscribes volatile to
    # trajectories, which outside nodes publish with any durability)
    "joint_states": ("sensor_msgs/msg/JointState", "data"),
    "sim/true_position": ("geometry_msgs/msg/PointStamped", "data"),
    "reference": ("sensor_msgs/msg/JointState", "data"),
    "command": ("geometry_msgs/msg/Vector3Stamped", "data"),
    "setpoint": ("geometry_msgs/msg/PointStamped", "data"),
    "gap/residual": ("geometry_msgs/msg/PointStamped", "data"),
    "trajectory": ("trajectory_msgs/msg/JointTrajectory", "latched"),
    "model": ("std_msgs/msg/String", "latched"),
    "state": ("diagnostic_msgs/msg/DiagnosticArray", "events"),
    "feedforward/phase": ("std_msgs/msg/String", "events"),
    "/diagnostics": ("diagnostic_msgs/msg/DiagnosticArray", "diag"),
}
STAMPED = {t for t, _ in CONTRACT.values()} - {"std_msgs/msg/String",
                                               "trajectory_msgs/msg/JointTrajectory"}


def msg_class(msgtype: str):
    pkg, _, name = msgtype.split("/")
    return getattr(importlib.import_module(f"{pkg}.msg"), name)


class Recorder(Node):
    def __init__(self):
        super().__init__("recorder")
        out = declare(self, "output", "", "bag directory ('' = bags/<timestamp>)") or new_bag_dir("bags")
        meta = {}
        for key in ("config_file", "model_file"):
            path = declare(self, key, "", f"{key.split('_')[0]} to store as metadata")
            if path and os.path.isfile(path):
                meta["piezo_stage_" + key.split("_")[0]] = {"path": path,
                                                            "yaml": open(path).read()}
        self.bag = BagWriter(out, metadata=meta)
        # off the loop's critical path: take what arrived every few ms, not per message
        self.hot_batch_s = declare(self, "batch_period_s", 0.004, "wait between takes "
                                   "[s]; queues hold 5000 samples per topic", lo=0.0, hi=60.0,
                                   live=lambda v: setattr(self, "hot_batch_s", v))
        self.log_received = declare(self, "log_time", "stamp", "bag log time: stamp "
                                    "(lockstep) | receive (real time)",
                                    choices=("stamp", "receive")) == "receive"
        prio = declare(self, "thread_priority", 40, "real-time recording (log_time "
                       "receive): SCHED_FIFO priority of the middleware's receiving threads "
                       "(the writing stays at normal priority; 0: leave the scheduler "
                       "alone)", lo=0, hi=99)
        if self.log_received:
            set_realtime_priority(prio, self.get_logger(), main_thread=False)
        self.get_logger().info(f"recording to {out}")
        self.subs = {}
        for rel, (msgtype, kind) in CONTRACT.items():
            self.subscribe(self.resolve_topic_name(rel), msgtype, kind)
        steady_timer(self, 1.0, self.discover)
        steady_timer(self, declare(self, "flush_period_s", 0.5, "chunk flush period [s]",
                                  lo=0.01, hi=60.0), self.bag.flush)
        Diagnostics(self, lambda: (0, f"recording to {out}: {sum(self.bag.counts.values())} "
                                   f"messages on {len(self.bag.counts)} topics",
                                   {"bag": out, "batch_period_s": self.hot_batch_s,
                                    **self.bag.counts}), "recording")

    def resolve_topic_name(self, rel):
        return rel if rel.startswith("/") else f"{self.get_namespace().rstrip('/')}/{rel}"

    def subscribe(self, topic, msgtype, kind="data"):
        if topic in self.subs:
            return
        self.bag.add_topic(topic, msgtype, self.offered(topic, kind))
        stamped = msgtype in STAMPED
        qos = {"latched": QOS_LATCHED, "events": QOS_EVENTS, "diag": QOS_DIAG}.get(
            kind, QOS_DATA) if not topic.endswith("/trajectory") else QOS_DATA
        self.subs[topic] = hot_subscription(  # everything recorded: the lean loop
            self, msg_class(msgtype), topic,
            lambda data, info: self.write(topic, data, stamped, info), qos, raw=True,
            with_info=True)

    def offered(self, topic, kind):
        """The QoS the topic's publishers offer (as ``ros2 bag record`` stores it): asked
        of the graph when a publisher is there (topics found by discovery), else what
        our nodes offer for that kind."""
        from piezo_stage.io.bag import QOS_KINDS
        if kind not in QOS_KINDS:
            infos = self.get_publishers_info_by_topic(topic)
            if infos:
                q = infos[0].qos_profile
                latched = q.durability == DurabilityPolicy.TRANSIENT_LOCAL
                return "latched" if latched and q.depth <= 1 else \
                    "events" if latched else "data"
            return "data"
        return kind

    def discover(self):
        for topic, types in self.get_topic_names_and_types():
            if topic not in self.subs and not topic.startswith("/rosout") \
                    and not topic.startswith("/parameter_events"):
                try:
                    self.subscribe(topic, types[0], kind="found")
                except (ImportError, AttributeError, KeyError):
                    self.get_logger().warning(f"cannot record {topic}: unknown type {types[0]}")

    def write(self, topic, data, stamped, info):
        if self.log_received:
            received = info.get("received_timestamp") or self.get_clock().now().nanoseconds
        if stamped:  # CDR: 4-byte encapsulation, then header.stamp (int32 sec, uint32 ns)
            sec, nsec = struct.unpack_from("<iI" if data[1] == 1 else ">iI", data, 4)
            t = sec * 1_000_000_000 + nsec
        else:  # lockstep: the set's clock (simulated time under use_sim_time)
            t = received if self.log_received else self.get_clock().now().nanoseconds
        # log time: when it arrived (real time), or its stamp (lockstep's simulated
        # time, so reruns are identical); publish time: its stamp
        self.bag.write(topic, data, received if self.log_received else t, t)

    def close(self):
        self.bag.finish()
        # the ROS context may already be shut down here: plain stderr, not the logger
        sys.stderr.write(f"[recorder] bag complete: {dict(self.bag.counts)}\n")


def main(args=None):
    return run(Recorder, args)


if __name__ == "__main__":
    raise SystemExit(main())
