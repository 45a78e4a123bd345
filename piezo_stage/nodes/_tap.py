"""Taking every topic of the set as raw CDR: what the recorder and the live view share.

A ``TopicTap`` subscribes to the topic contract at start (so nothing of a lockstep run
is missed) and to every other topic that discovery finds in its namespace (another
stage's topics are its own bag's), through LeanExecutor, with
the bytes as received (no deserialize/serialize round trip). For each topic it calls
``on_topic(topic, msgtype, kind)`` once, then ``on_message(topic, data, stamp_ns,
info)`` per message, with the header stamp of stamped types (None otherwise).

Two topics are left out: ``move`` (``on_target`` names each move, its target and what
became of it), and ``trajectory``, the way in for trajectories. Its one subscriber is
the feedforward, which republishes what it accepted, byte for byte and latched, on
``trajectory/accepted``; the tap takes that. So a lab node that sends once, with any
QoS, as soon as a subscriber matched has reached the stage, and the bag holds exactly
what the stage ran, even when the recorder's own match came late (a second subscriber
on ``trajectory`` made "the first match" a race between the two: measured 4 of 10
sends run and 6 of 10 recorded).
"""

from __future__ import annotations

import importlib
import struct
from collections.abc import Callable
from typing import TYPE_CHECKING

from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy

from piezo_stage.nodes._common import (
    QOS_DATA,
    QOS_DIAG,
    QOS_EVENTS,
    QOS_LATCHED,
    MessageInfo,
    steady_timer,
)
from piezo_stage.nodes._executor import hot_subscription

if TYPE_CHECKING:
    from rclpy.node import Node

CONTRACT = {  # relative name: (type, QoS kind: data, latched, events, diag): what our
    # publishers offer
    "joint_states": ("sensor_msgs/msg/JointState", "data"),
    "sim/true_position": ("geometry_msgs/msg/PointStamped", "data"),
    "reference": ("sensor_msgs/msg/JointState", "data"),
    "command": ("geometry_msgs/msg/Vector3Stamped", "data"),
    "setpoint": ("geometry_msgs/msg/PointStamped", "data"),
    "gap/residual": ("geometry_msgs/msg/PointStamped", "data"),
    # the trajectory the feedforward accepted and runs (its exact bytes, latched)
    "trajectory/accepted": ("trajectory_msgs/msg/JointTrajectory", "latched"),
    "model": ("std_msgs/msg/String", "latched"),
    "state": ("diagnostic_msgs/msg/DiagnosticArray", "events"),
    "feedforward/phase": ("diagnostic_msgs/msg/KeyValue", "events"),
    # a move's state: its id, target and verdict (the move itself is the feedforward's)
    "on_target": ("diagnostic_msgs/msg/DiagnosticArray", "latched"),
    # a trajectory refused: its sender's name for it, and why
    "trajectory/refused": ("diagnostic_msgs/msg/DiagnosticArray", "events"),
    "/diagnostics": ("diagnostic_msgs/msg/DiagnosticArray", "diag"),
    # lockstep with the live watch: where the set waits while a window is diagnosed
    "watch/hold": ("std_msgs/msg/Header", "events"),
}
STAMPED = {t for t, _ in CONTRACT.values()} - {"std_msgs/msg/String",
                                               "diagnostic_msgs/msg/KeyValue",
                                               "trajectory_msgs/msg/JointTrajectory"}


def msg_class(msgtype: str) -> type:
    pkg, _, name = msgtype.split("/")
    return getattr(importlib.import_module(f"{pkg}.msg"), name)


def header_stamp_ns(data: bytes) -> int:
    """header.stamp of a stamped message's CDR bytes: a 4-byte encapsulation (its second
    byte says the endianness), then int32 sec and uint32 nanosec."""
    sec, nsec = struct.unpack_from("<iI" if data[1] == 1 else ">iI", data, 4)
    return sec * 1_000_000_000 + nsec


class TopicTap:
    """See the module docstring. ``best_effort``: data topics are taken best-effort
    (the live view: a slow viewer then costs the loop's publishers nothing; the
    recorder keeps reliable, it must lose nothing)."""

    def __init__(self, node: Node, on_topic: Callable[[str, str, str], None],
                 on_message: Callable[[str, bytes, int | None, MessageInfo], None],
                 best_effort: bool = False,
                 discover_s: float = 1.0) -> None:
        self.node, self.on_topic, self.on_message = node, on_topic, on_message
        self.best_effort = best_effort
        self.subs: dict[str, object] = {}
        for rel, (msgtype, kind) in CONTRACT.items():
            self.subscribe(self.resolve(rel), msgtype, kind)
        self.subs[self.resolve("trajectory")] = None  # the feedforward's alone (above),
        self.subs[self.resolve("move")] = None  # and so is a move (on_target names it)
        steady_timer(node, discover_s, self.discover)

    def resolve(self, rel: str) -> str:
        return rel if rel.startswith("/") else \
            f"{self.node.get_namespace().rstrip('/')}/{rel}"

    def qos(self, topic: str, kind: str) -> QoSProfile:
        if kind not in ("latched", "events", "diag"):
            if not self.best_effort:
                return QOS_DATA
            return QoSProfile(history=QOS_DATA.history, depth=QOS_DATA.depth,
                              reliability=ReliabilityPolicy.BEST_EFFORT,
                              durability=DurabilityPolicy.VOLATILE)
        return {"latched": QOS_LATCHED, "events": QOS_EVENTS, "diag": QOS_DIAG}[kind]

    def subscribe(self, topic: str, msgtype: str, kind: str = "data") -> None:
        if topic in self.subs:
            return
        cls = msg_class(msgtype)  # before on_topic: an unknown type raises here
        self.on_topic(topic, msgtype, kind)
        stamped = msgtype in STAMPED
        on_message = self.on_message

        def cb(data: bytes, info: MessageInfo) -> None:
            on_message(topic, data, header_stamp_ns(data) if stamped else None, info)
        self.subs[topic] = hot_subscription(self.node, cls, topic, cb,
                                            self.qos(topic, kind), raw=True, with_info=True)

    def discover(self) -> None:
        # the set's own namespace only: a second stage on the domain (/stage2) is its
        # own bag's, and subscribing to its topics loads both sets
        ns = self.node.get_namespace().rstrip("/") + "/"
        for topic, types in self.node.get_topic_names_and_types():
            if topic not in self.subs and topic.startswith(ns) and ns != "/":
                try:
                    self.subscribe(topic, types[0], kind="found")
                except (ImportError, AttributeError, KeyError, ValueError):
                    self.subs[topic] = None  # said once, not every second
                    self.node.get_logger().warning(f"cannot take {topic}: unknown type "
                                                   f"{types[0]}")
