#!/usr/bin/env python3
"""An outside node that gives the stage a trajectory and waits until it is done.

It uses rclpy and the common_interfaces messages only (nothing from piezo_stage), the
way a lab's own node would:

1. wait until its publisher on <namespace>/trajectory has matched the feedforward (the
   one subscriber there), then publish a trajectory_msgs/JointTrajectory (joints x, y,
   positions in metres) once, latched (reliable, transient local, depth 1), stamped a
   moment ahead so the stage starts it at that time. The feedforward republishes what
   it accepted on <namespace>/trajectory/accepted, where the recorder takes it;
2. wait on <namespace>/state (diagnostic_msgs/DiagnosticArray, latched) until the
   driver relays the feedforward's phase as done (key-values ``feedforward_phase``
   "done" and ``feedforward_follows`` "trajectory of N points stamped S") for this very
   trajectory; a fault of the stage's that begins after the sample it saw last before
   publishing ends the wait (the latched topic also replays older changes: an earlier
   fault, since recovered from, is not this trajectory's); a refusal of this very
   trajectory on <namespace>/trajectory/refused (diagnostic_msgs/DiagnosticArray: the
   trajectory's header.frame_id, which this node sets to a name of its own, and the
   reason) ends it at once: the reason printed, exit 2;
3. read where the stage is (sensor_msgs/JointState on <namespace>/joint_states, taken
   only before publishing and at the end: they come at the control rate) and print the
   error per axis against the last point; exit 0 if both are within the tolerance, 1 if
   not (or on a timeout).

    python examples/publish_trajectory.py                       # a small default path
    python examples/publish_trajectory.py --points "0,20,20 0.5,40,20 1.0,30,30"
    python examples/publish_trajectory.py --csv path.csv        # t [s], x [um], y [um]

Start the node set first, e.g. `piezo-stage launch --params config/realtime.yaml
--no-trajectory`.
"""

import argparse
import csv
import signal
import sys
import time


def _stopped(signum, frame):
    """Ctrl-C or SIGTERM, from the first line on: one line, exit 128 + the signal (the
    node is destroyed on the way out; rclpy's own handlers are left out, rclpy.init)."""
    print(f"publish_trajectory: stopped by {signal.Signals(signum).name} before the "
          "stage finished", file=sys.stderr)
    raise SystemExit(128 + signum)


signal.signal(signal.SIGINT, _stopped)
signal.signal(signal.SIGTERM, _stopped)

import rclpy  # noqa: E402
from builtin_interfaces.msg import Duration  # noqa: E402
from diagnostic_msgs.msg import DiagnosticArray  # noqa: E402
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy  # noqa: E402
from sensor_msgs.msg import JointState  # noqa: E402
from trajectory_msgs.msg import JointTrajectory, JointTrajectoryPoint  # noqa: E402

DEFAULT = [(0.0, 20.0, 20.0), (0.25, 40.0, 20.0), (0.5, 40.0, 40.0), (0.75, 20.0, 40.0),
           (1.0, 30.0, 30.0)]  # t [s], x [um], y [um]
LATCHED = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=1,
                     reliability=ReliabilityPolicy.RELIABLE,
                     durability=DurabilityPolicy.TRANSIENT_LOCAL)
STATE = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=20,
                   reliability=ReliabilityPolicy.RELIABLE,
                   durability=DurabilityPolicy.TRANSIENT_LOCAL)


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


def stamp_ns(header) -> int:
    """A message header's stamp [ns]."""
    return header.stamp.sec * 1_000_000_000 + header.stamp.nanosec


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--namespace", default="/stage")
    ap.add_argument("--points", help='"t,x,y t,x,y ..." in s and um')
    ap.add_argument("--csv", help="a CSV of t [s], x [um], y [um]")
    ap.add_argument("--start-in", type=float, default=0.5, help="start this long from now "
                    "[s]; 0: as soon as the stage has approached the first point")
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

    rclpy.init(signal_handler_options=rclpy.signals.SignalHandlerOptions.NO)
    node = rclpy.create_node("publish_trajectory")
    seen = {"state": {}, "position": None}

    def on_state(msg):
        if msg.status:
            seen["state"] = {kv.key: kv.value for kv in msg.status[0].values}
            seen["since"] = stamp_ns(msg.header)

    def on_refused(msg):
        if msg.status:
            kv = {v.key: v.value for v in msg.status[0].values}
            seen.setdefault("refused", {})[kv.get("frame_id", "")] = kv.get("reason", "")

    def on_joints(msg):
        if list(msg.name[:2]) == ["x", "y"] and len(msg.position) >= 2:
            seen["position"] = (msg.position[0] * 1e6, msg.position[1] * 1e6)
            seen["sample"] = stamp_ns(msg.header)

    node.create_subscription(DiagnosticArray, f"{ns}/state", on_state, STATE)
    node.create_subscription(DiagnosticArray, f"{ns}/trajectory/refused", on_refused, STATE)
    # the stage's samples come at the control rate (1 kHz): this node takes them only
    # while it needs one (before publishing, and at the end), not the whole run long
    # (a Python callback a sample cost a third of a CPU, which the set's start-up
    # measurement of its host counted against a 1 kHz rate)
    joints = node.create_subscription(JointState, f"{ns}/joint_states", on_joints, 10)
    pub = node.create_publisher(JointTrajectory, f"{ns}/trajectory", LATCHED)
    try:
        # matched by the feedforward, the one subscriber on the topic: a stamp "start
        # at T" is then taken before T
        end = time.monotonic() + args.timeout
        while time.monotonic() < end and pub.get_subscription_count() < 1:
            rclpy.spin_once(node, timeout_sec=0.05)
        # and a sample of the stage's: the state topic is latched, so it replays the
        # driver's last changes, an old fault among them; a fault that counts is one
        # that began after the sample this node last saw before publishing (the stage's
        # own clock, in lockstep too)
        while time.monotonic() < end and "sample" not in seen:
            rclpy.spin_once(node, timeout_sec=0.05)
        if time.monotonic() >= end:
            print(f"no feedforward on {ns}/trajectory, or no samples on "
                  f"{ns}/joint_states: is the node set running?", file=sys.stderr)
            return 1
        published_after = seen["sample"]
        node.destroy_subscription(joints)
        msg = JointTrajectory(joint_names=["x", "y"])
        # its name: a refusal of it on trajectory/refused carries it back
        msg.header.frame_id = f"publish_trajectory-{node.get_clock().now().nanoseconds}"
        # 0: no start time (the stage starts it once it has approached the first point;
        # a lockstep set, whose clock is its own samples, takes only this)
        start = node.get_clock().now().nanoseconds + int(args.start_in * 1e9) \
            if args.start_in > 0 else 0
        msg.header.stamp.sec, msg.header.stamp.nanosec = divmod(start, 1_000_000_000)
        for t, x, y in pts:
            sec, nsec = divmod(int(round(t * 1e9)), 1_000_000_000)
            msg.points.append(JointTrajectoryPoint(
                positions=[x * 1e-6, y * 1e-6], time_from_start=Duration(sec=sec, nanosec=nsec)))
        pub.publish(msg)  # latched: a feedforward whose side matched later still gets it
        mine = ("done", f"trajectory of {len(pts)} points stamped {start}")

        def phase():  # the driver relays the feedforward's phase as two key-values
            st = seen["state"]
            return st.get("feedforward_phase"), st.get("feedforward_follows")
        print(f"published {len(pts)} points to {ns}/trajectory, starting "
              f"{f'in {args.start_in:g} s' if start else 'after the approach'}; waiting "
              "for the stage", flush=True)
        end = time.monotonic() + args.timeout
        while time.monotonic() < end and phase() != mine:
            rclpy.spin_once(node, timeout_sec=0.05)
            if msg.header.frame_id in seen.get("refused", {}):
                print(f"the stage refused the trajectory: "
                      f"{seen['refused'][msg.header.frame_id]}", file=sys.stderr)
                return 2
            if seen["state"].get("state") == "faulted" and seen["since"] > published_after:
                print(f"the stage faulted: {seen['state'].get('reason')}", file=sys.stderr)
                return 1
        if phase() != mine:
            print(f"the stage did not finish within {args.timeout:g} s (its feedforward: "
                  f"{': '.join(x for x in phase() if x) or 'nothing heard'}; the stage: "
                  f"{seen['state'].get('state', 'nothing heard')})", file=sys.stderr)
            return 1
        settle = time.monotonic() + 0.2  # the newest samples at the last point
        seen["position"] = None  # (and one from now: this node's joint_states
        # subscription may match later than the latched state, on a busy host)
        node.create_subscription(JointState, f"{ns}/joint_states", on_joints, 10)
        end = max(end, time.monotonic() + 10.0)  # its match, however late the end came
        while time.monotonic() < settle or (seen["position"] is None
                                            and time.monotonic() < end):
            rclpy.spin_once(node, timeout_sec=0.02)
        x, y = seen["position"] or (float("nan"), float("nan"))
        ex, ey = x - pts[-1][1], y - pts[-1][2]
        print(f"done: final error x {ex:+.3f} um, y {ey:+.3f} um")
        return 0 if abs(ex) <= args.tolerance and abs(ey) <= args.tolerance else 1
    finally:
        node.destroy_node()
        rclpy.try_shutdown()


if __name__ == "__main__":
    sys.exit(main())
