"""What every node shares: the QoS profiles and housekeeping timers on the steady clock.
The executor and the pieces of main() are in _executor.py, parameters in _params.py,
the control loop's shared pieces in _loop.py."""

from __future__ import annotations

from collections.abc import Callable, Mapping
from typing import Any, TypeAlias

from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from rclpy.timer import Timer

from piezo_stage.core.types import Doc

#: what rclpy hands a two-argument subscription callback beside the message: the
#: publication's ``source_timestamp``, ``received_timestamp`` [ns] and sequence numbers
MessageInfo: TypeAlias = Mapping[str, int]
#: a node's health for its diagnostics: (level 0 OK / 1 WARN / 2 ERROR, message, values)
Status: TypeAlias = tuple[int, str, Doc]

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
# Inputs from other nodes (trajectories, setpoints, moves): reliable and volatile, so
# every publisher matches and none warns.
QOS_INPUTS = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE)
# the graph's name of an endpoint whose node it has not yet heard of: an endpoint is
# discovered before its participant's node list names its node
UNKNOWN_NODE = "_NODE_NAME_UNKNOWN_"


def steady_timer(node: Node, period_s: float, callback: Callable[[], Any]) -> Timer:
    """A housekeeping timer (polls, flushes, links, diagnostics cadence) on the steady
    clock: it runs while simulated time stands still (before the first sample, after the
    last), where a ROS-time timer under use_sim_time would never fire."""
    from rclpy.clock import Clock, ClockType
    return node.create_timer(period_s, callback, clock=Clock(clock_type=ClockType.STEADY_TIME))
