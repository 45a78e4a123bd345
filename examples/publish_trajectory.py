#!/usr/bin/env python3
"""An outside node that gives the stage a trajectory and waits until it is done.

It uses rclpy and the common_interfaces messages only (nothing from piezo_stage), the
way a lab's own node would:

1. wait until the feedforward's subscription to <namespace>/trajectory is in the graph
   and every subscription there (the recorder's too) has been matched for 0.5 s, then
   publish a trajectory_msgs/JointTrajectory
   (joints x, y, positions in metres) there, latched (reliable, transient local, depth
   1), stamped a moment ahead so the stage starts it at that time;
2. wait on <namespace>/state (diagnostic_msgs/DiagnosticArray, latched) until the
   driver relays "done: trajectory of N points stamped S" for this very trajectory,
   publishing it again every REPEAT_S meanwhile (and when a subscriber matches): a
   recorder whose side of the match came late takes the topic volatile and gets only
   what is sent after; the stage's nodes take each trajectory once, by its bytes;
3. if no recorder in the namespace has matched yet, keep going (sending again on every
   new match) until one has, or DISCOVERY_S from the start: a participant that missed
   another's first announcements learns of it only from the next, 3 s later;
4. read where the stage is (sensor_msgs/JointState on <namespace>/joint_states) and
   print the error per axis against the last point; exit 0 if both are within the
   tolerance, 1 if not (or on a timeout).

    python examples/publish_trajectory.py                       # a small default path
    python examples/publish_trajectory.py --points "0,20,20 0.5,40,20 1.0,30,30"
    python examples/publish_trajectory.py --csv path.csv        # t [s], x [um], y [um]

Start the node set first, e.g. `piezo-stage launch config/realtime.yaml --no-trajectory`.
"""

import argparse
import csv
import sys
import time

import rclpy
from builtin_interfaces.msg import Duration
from diagnostic_msgs.msg import DiagnosticArray
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import JointState
from trajectory_msgs.msg import JointTrajectory, JointTrajectoryPoint

DEFAULT = [(0.0, 20.0, 20.0), (0.25, 40.0, 20.0), (0.5, 40.0, 40.0), (0.75, 20.0, 40.0),
           (1.0, 30.0, 30.0)]  # t [s], x [um], y [um]
LATCHED = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=1,
                     reliability=ReliabilityPolicy.RELIABLE,
                     durability=DurabilityPolicy.TRANSIENT_LOCAL)
REPEAT_S = 0.5  # the trajectory is sent again this often until the stage is done [s]
DISCOVERY_S = 4.0  # a recorder is waited for this long from the start (see the end) [s]
STATE = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=20,
                   reliability=ReliabilityPolicy.RELIABLE,
                   durability=DurabilityPolicy.TRANSIENT_LOCAL)


def recorder_ok(node, pub, ns):
    """A recorder's subscription in the namespace is in the graph, and the publisher has
    matched every subscription the graph shows on the topic."""
    subs = node.get_subscriptions_info_by_topic(f"{ns}/trajectory")
    return any(i.node_name == "recorder" and i.node_namespace == ns for i in subs) and \
        pub.get_subscription_count() >= len(subs)


def points_from(args):
    if args.csv:
        with open(args.csv, newline="") as fh:
            rows = [r for r in csv.reader(fh) if r and not r[0].lstrip().startswith("#")]
        if rows and not rows[0][0].strip().replace(".", "", 1).isdigit():
            rows = rows[1:]  # a header line
        return [tuple(float(v) for v in r[:3]) for r in rows]
    if args.points:
        return [tuple(float(v) for v in p.split(",")) for p in args.points.split()]
    return DEFAULT


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--namespace", default="/stage")
    ap.add_argument("--points", help='"t,x,y t,x,y ..." in s and um')
    ap.add_argument("--csv", help="a CSV of t [s], x [um], y [um]")
    ap.add_argument("--start-in", type=float, default=0.5, help="start this long from now [s]")
    ap.add_argument("--tolerance", type=float, default=0.5, help="final error allowed [um]")
    ap.add_argument("--timeout", type=float, default=60.0, help="give up after [s]")
    args = ap.parse_args(argv)
    try:
        pts = points_from(args)
    except (OSError, ValueError, IndexError) as e:
        print(f"publish_trajectory: bad points: {e}", file=sys.stderr)
        return 2
    if not pts or any(len(p) != 3 for p in pts):
        print("publish_trajectory: each point needs t, x, y", file=sys.stderr)
        return 2
    ns = "/" + args.namespace.strip("/")

    started = time.monotonic()
    rclpy.init()
    node = rclpy.create_node("publish_trajectory")
    seen = {"state": {}, "position": None}

    def on_state(msg):
        if msg.status:
            seen["state"] = {kv.key: kv.value for kv in msg.status[0].values}

    def on_joints(msg):
        if list(msg.name[:2]) == ["x", "y"] and len(msg.position) >= 2:
            seen["position"] = (msg.position[0] * 1e6, msg.position[1] * 1e6)

    node.create_subscription(DiagnosticArray, f"{ns}/state", on_state, STATE)
    node.create_subscription(JointState, f"{ns}/joint_states", on_joints, 10)
    pub = node.create_publisher(JointTrajectory, f"{ns}/trajectory", LATCHED)
    try:
        # the feedforward's subscription in the graph (not just the recorder's): a stamp
        # "start at T" is then taken before T
        end = time.monotonic() + args.timeout
        while time.monotonic() < end and not any(
                i.node_name == "feedforward" and i.node_namespace == ns
                for i in node.get_subscriptions_info_by_topic(f"{ns}/trajectory")):
            rclpy.spin_once(node, timeout_sec=0.05)
        if time.monotonic() >= end:
            print(f"no feedforward on {ns}/trajectory: is the node set running?",
                  file=sys.stderr)
            return 1
        # every subscription the graph shows on the topic matched (the recorder's too,
        # so the bag holds this trajectory), and so for 0.5 s on end: discovery brings
        # the other nodes' subscriptions one by one (the feedforward's may come before
        # the recorder's), and each subscriber completes its side of a match a moment
        # after this publisher; a volatile subscriber gets only what is sent after that.
        # At most 5 s: a latched message still reaches a subscriber that matches later
        # if it asks for history.
        # A recorder the graph lists in the namespace must be among them: its node can
        # be known a moment before its subscription is.
        settle, held_since = min(end, time.monotonic() + 5.0), None
        while time.monotonic() < settle:
            matched = pub.get_subscription_count()
            subs = node.get_subscriptions_info_by_topic(f"{ns}/trajectory")
            recorder = any(n == "recorder" and s == ns
                           for n, s in node.get_node_names_and_namespaces())
            if matched >= 1 and matched >= len(subs) and (not recorder or any(
                    i.node_name == "recorder" and i.node_namespace == ns for i in subs)):
                held_since = held_since or time.monotonic()
                if time.monotonic() - held_since >= 0.5:
                    break
            else:
                held_since = None
            rclpy.spin_once(node, timeout_sec=0.05)
        msg = JointTrajectory(joint_names=["x", "y"])
        start = node.get_clock().now().nanoseconds + int(args.start_in * 1e9)
        msg.header.stamp.sec, msg.header.stamp.nanosec = divmod(start, 1_000_000_000)
        for t, x, y in pts:
            sec, nsec = divmod(int(round(t * 1e9)), 1_000_000_000)
            msg.points.append(JointTrajectoryPoint(
                positions=[x * 1e-6, y * 1e-6], time_from_start=Duration(sec=sec, nanosec=nsec)))
        pub.publish(msg)  # latched: taken whenever the stage's nodes match
        recorder_matched = recorder_ok(node, pub, ns)
        reached, sent = pub.get_subscription_count(), time.monotonic()
        mine = f"done: trajectory of {len(pts)} points stamped {start}"
        print(f"published {len(pts)} points to {ns}/trajectory, starting in "
              f"{args.start_in:g} s; waiting for the stage", flush=True)
        end = time.monotonic() + args.timeout
        while time.monotonic() < end and seen["state"].get("feedforward") != mine:
            rclpy.spin_once(node, timeout_sec=0.05)
            if pub.get_subscription_count() > reached or time.monotonic() - sent > REPEAT_S:
                # a subscriber matched after the last send, or REPEAT_S went by: once
                # more. Each side of a match completes on its own; a volatile subscriber
                # (a recorder: it matches every publisher that way) whose side came after
                # a send never gets that send, and the publisher cannot tell. The set's
                # nodes take a trajectory once, by its bytes: the stage sees no change.
                reached, sent = pub.get_subscription_count(), time.monotonic()
                pub.publish(msg)
            if seen["state"].get("state") == "faulted":
                print(f"the stage faulted: {seen['state'].get('reason')}", file=sys.stderr)
                return 1
        if seen["state"].get("feedforward") != mine:
            print(f"the stage did not finish within {args.timeout:g} s (its feedforward: "
                  f"{seen['state'].get('feedforward') or 'nothing heard'})", file=sys.stderr)
            return 1
        # a recorder this node has not seen at all may still be discovering it: a
        # participant that missed another's first announcements learns of it from the
        # next one, and Fast DDS announces every 3 s. Until a recorder in the namespace
        # has been matched for 0.5 s, or DISCOVERY_S from the start: keep sending on
        # every new match (a set without a recorder costs this wait once)
        settle = time.monotonic() + 0.2  # the newest samples at the last point
        recorded_since = 0.0 if recorder_matched else None
        while time.monotonic() < settle or (
                time.monotonic() - started < DISCOVERY_S and (
                    recorded_since is None or time.monotonic() - recorded_since < 0.5)):
            rclpy.spin_once(node, timeout_sec=0.02)
            if pub.get_subscription_count() > reached:
                reached = pub.get_subscription_count()
                pub.publish(msg)
                recorded_since = None
            if recorded_since is None and recorder_ok(node, pub, ns):
                recorded_since = time.monotonic()
        x, y = seen["position"] or (float("nan"), float("nan"))
        ex, ey = x - pts[-1][1], y - pts[-1][2]
        print(f"done: final error x {ex:+.3f} um, y {ey:+.3f} um")
        return 0 if abs(ex) <= args.tolerance and abs(ey) <= args.tolerance else 1
    except KeyboardInterrupt:
        print("publish_trajectory: stopped (Ctrl-C)", file=sys.stderr)
        return 130
    finally:
        node.destroy_node()
        rclpy.try_shutdown()


if __name__ == "__main__":
    sys.exit(main())
