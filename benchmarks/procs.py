"""The benchmarks' helper processes, as a module: ``python -m benchmarks.procs
WHAT ARGS...`` runs one of them (the benchmarks start them; each prints its figure).

* ``plain N FS OUT``: the simulated stage's ``Plant.run`` over N samples, timed; run
  with NUMBA_DISABLE_JIT=1 it is the kernels' plain-Python baseline (OUT: the output).
* ``ping pong`` / ``ping ping N``: a two-process round trip through rclpy's stock path.
* ``ring ME NEXT N``: one node of a 3-process ring on the loop nodes' own transport path
  (lean wait set, raw CDR) with empty callbacks; node ``a`` prints the steps/s.
* ``events N``: rclpy's own fast path, the physical anchor: a ring of 3 nodes in one
  process on rclpy's EventsExecutor passing a 2-joint JointState (deserialized at each
  hop), spun by ``spin_once`` (its ``spin()`` hangs a core in rclpy 7.1.6: docs/realtime.md);
  prints the steps/s.
* ``once QOS UM``: a lab's node (rclpy and trajectory_msgs only) that sends one
  trajectory, 0.3 s at UM on both axes, to /stage/trajectory with QOS (``latched`` or
  ``default``) as soon as its publisher matched one subscriber, waits for every
  reader's acknowledgement and exits (1 if none came).
"""

from __future__ import annotations

import sys
import time

import numpy as np


def plain(n: int, fs: float, out: str):
    from piezo_stage.core.model.plant import Plant
    from piezo_stage.io.plant_file import default_plant_config_path, load_plant_config
    t = np.arange(n) / fs
    vx = 75 - 75 * np.cos(2 * np.pi * 1.0 * t)
    vy = 75 - 75 * np.cos(2 * np.pi * 1.3 * t + 0.4)
    plant = Plant(load_plant_config(default_plant_config_path()), fs)
    t0 = time.perf_counter()
    w = plant.run(vx, vy)
    print(time.perf_counter() - t0)
    np.save(out, np.stack([w["x"], w["y"]]))


def ping(role: str, n: int = 0):
    import rclpy
    from rclpy.node import Node
    from std_msgs.msg import Header

    from piezo_stage.nodes._common import QOS_DATA
    rclpy.init()
    node = Node(role)
    if role == "pong":
        pub = node.create_publisher(Header, "/bench/pong", QOS_DATA)
        node.create_subscription(Header, "/bench/ping", pub.publish, QOS_DATA)
        try:
            rclpy.spin(node)
        except Exception:  # killed by the benchmark when it is done
            pass
    else:
        pub = node.create_publisher(Header, "/bench/ping", QOS_DATA)
        got = []
        node.create_subscription(Header, "/bench/pong",
                                 lambda m: got.append(time.perf_counter()), QOS_DATA)
        while pub.get_subscription_count() < 1 or node.count_publishers("/bench/pong") < 1:
            rclpy.spin_once(node, timeout_sec=0.05)
        time.sleep(0.5)
        t = []
        for k in range(n):
            t0 = time.perf_counter()
            pub.publish(Header(frame_id=str(k)))
            while len(got) <= k:
                rclpy.spin_once(node, timeout_sec=1.0)
            t.append(got[k] - t0)
        print(np.median(t), np.percentile(t, 99))
    node.destroy_node()
    rclpy.try_shutdown()


def ring(me: str, nxt: str, n_steps: int):
    import rclpy
    from rclpy.node import Node
    from rclpy.serialization import serialize_message
    from rclpy.signals import SignalHandlerOptions
    from std_msgs.msg import Header

    from piezo_stage.nodes._common import QOS_DATA
    from piezo_stage.nodes._executor import LeanExecutor, hot_subscription

    class Ring(Node):
        def __init__(self):
            super().__init__("ring_" + me)
            self.pub = self.create_publisher(Header, "/bench/ring_" + nxt, QOS_DATA)
            self.n, self.t0 = 0, 0.0
            hot_subscription(self, Header, "/bench/ring_" + me, self.cb, QOS_DATA, raw=True)
            if me == "a":
                self.create_timer(0.05, self.kick)

        def kick(self):
            if self.n == 0 and self.pub.get_subscription_count() >= 1 \
                    and self.count_publishers("/bench/ring_a") >= 1:
                time.sleep(1.0)
                self.pub.publish(serialize_message(Header()))
                self.n = -1

        def cb(self, data):
            if me == "a":
                self.n = max(self.n, 0) + 1
                if self.n == 1:
                    self.t0 = time.perf_counter()
                if self.n == n_steps:
                    print((n_steps - 1) / (time.perf_counter() - self.t0), flush=True)
                    rclpy.try_shutdown()
                    return
            self.pub.publish(data)

    rclpy.init(signal_handler_options=SignalHandlerOptions.NO)  # _signals: stops
    node = Ring()
    try:
        LeanExecutor(node).spin()
    except (KeyboardInterrupt, rclpy.executors.ExternalShutdownException):
        pass
    finally:
        node.destroy_node()
        rclpy.try_shutdown()
    return 0


def events_ring(n_steps: int) -> int:
    import rclpy
    from rclpy.context import Context
    from rclpy.experimental.events_executor import EventsExecutor
    from rclpy.node import Node
    from sensor_msgs.msg import JointState

    from piezo_stage.nodes._common import QOS_DATA
    ctx = Context()
    rclpy.init(context=ctx)
    count = {"n": 0, "t0": 0.0}

    class Hop(Node):
        def __init__(self, me: str, nxt: str):
            super().__init__("events_ring_" + me, context=ctx)
            self.me = me
            self.pub = self.create_publisher(JointState, "/bench/events_" + nxt, QOS_DATA)
            self.create_subscription(JointState, "/bench/events_" + me, self.cb, QOS_DATA)

        def cb(self, msg):
            if self.me == "a":
                count["n"] += 1
                if count["n"] == 1:
                    count["t0"] = time.perf_counter()
                if count["n"] == n_steps:
                    print((n_steps - 1) / (time.perf_counter() - count["t0"]), flush=True)
                    ctx.try_shutdown()
                    return
            self.pub.publish(msg)

    hops = [Hop(a, b) for a, b in (("a", "b"), ("b", "c"), ("c", "a"))]
    ex = EventsExecutor(context=ctx)
    for h in hops:
        ex.add_node(h)
    t_end = time.monotonic() + 30.0
    # every hop matched (discovery, in one process too), then the first message
    while not all(h.pub.get_subscription_count() >= 1 for h in hops):
        ex.spin_once(timeout_sec=0.05)
        if time.monotonic() > t_end:
            sys.stderr.write("benchmarks.procs events: the ring's hops never matched\n")
            return 1
    hops[0].pub.publish(JointState(name=["x", "y"], position=[0.0, 0.0],
                                   velocity=[0.0, 0.0], effort=[0.0, 0.0]))
    try:
        while ctx.ok():
            ex.spin_once(timeout_sec=0.2)
            if time.monotonic() > t_end + 300.0:
                sys.stderr.write("benchmarks.procs events: the ring did not finish\n")
                return 1
    except rclpy.executors.ExternalShutdownException:  # the last hop's shutdown
        pass
    return 0


def once(qos: str, um: float) -> int:
    import rclpy
    from rclpy.duration import Duration
    from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
    from trajectory_msgs.msg import JointTrajectory, JointTrajectoryPoint
    rclpy.init()
    node = rclpy.create_node("lab_once")
    profile = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                         durability=DurabilityPolicy.TRANSIENT_LOCAL) \
        if qos == "latched" else QoSProfile(depth=10)
    pub = node.create_publisher(JointTrajectory, "/stage/trajectory", profile)
    t_end = time.monotonic() + 30.0
    while pub.get_subscription_count() < 1 and time.monotonic() < t_end:
        rclpy.spin_once(node, timeout_sec=0.005)
    msg = JointTrajectory(joint_names=["x", "y"])
    for k in range(31):
        p = JointTrajectoryPoint(positions=[um * 1e-6, um * 1e-6])
        p.time_from_start.nanosec = k * 10_000_000
        msg.points.append(p)
    pub.publish(msg)
    ok = pub.wait_for_all_acked(Duration(seconds=10))
    node.destroy_node()
    rclpy.try_shutdown()
    return 0 if ok else 1


def main(argv):
    what, args = argv[0], argv[1:]
    if what == "once":
        return once(args[0], float(args[1]))
    if what == "plain":
        return plain(int(args[0]), float(args[1]), args[2])
    if what == "ping":
        return ping(args[0], int(args[1]) if len(args) > 1 else 0)
    if what == "ring":
        return ring(args[0], args[1], int(args[2]))
    if what == "events":
        return events_ring(int(args[0]))
    sys.stderr.write(f"benchmarks.procs: unknown helper {what!r}\n")
    return 2



def progress_runs(items, desc):
    """Iterate with a progress bar on a terminal (tqdm; silent otherwise)."""
    from piezo_stage.progress import bar
    items = list(items)
    with bar(desc, total=len(items), unit=" runs") as b:
        for x in items:
            yield x
            b.update(1)


def cpu_ticks():
    """(all, steal) CPU ticks of this machine so far (/proc/stat; zeros elsewhere)."""
    try:
        f = [int(x) for x in open("/proc/stat").readline().split()[1:]]
        return sum(f), f[7]
    except (OSError, IndexError, ValueError):
        return 0, 0


def source_checkout(what: str) -> str:
    """The source checkout this package runs from (a git work tree, a linked one
    too); a DataError naming ``what`` needs one where there is none."""
    import os
    here = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    if not os.path.isfile(os.path.join(here, "dev.sh")) or not os.path.exists(
            os.path.join(here, ".git")):  # (a worktree's .git is a file)
        from piezo_stage.core.errors import DataError
        raise DataError(f"{what} needs a source checkout with dev.sh; {here} is none")
    return here


def own_domain_env() -> dict:
    """This process's environment with a ROS_DOMAIN_ID of its own (a whole command run
    as a user runs it, apart from any set running meanwhile) and discovery on this host."""
    import os
    import random
    return dict(os.environ, ROS_DOMAIN_ID=str(random.randint(1, 100)),
                ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST")


def command_json(argv: list, out: str, timeout: float = 3600.0, cwd: str | None = None) -> dict:
    """``piezo-stage ARGV --record OUT --json OUT.json`` as a whole command, as a user
    runs it, with a ROS_DOMAIN_ID of its own: its JSON document (its bags removed).
    RuntimeError with the command's last line on stderr when it fails."""
    import json
    import shutil
    import subprocess
    env = own_domain_env()
    r = subprocess.run([sys.executable, "-m", "piezo_stage.cli", *argv, "--record", out,
                        "--json", out + ".json"], capture_output=True, text=True, env=env,
                       timeout=timeout, cwd=cwd)
    if r.returncode != 0:
        last = (r.stderr.strip().splitlines() or [""])[-1]
        raise RuntimeError(f"{' '.join(argv[:2])} exited {r.returncode}: {last}")
    with open(out + ".json") as fh:
        doc = json.load(fh)
    shutil.rmtree(out, ignore_errors=True)
    return doc


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]) or 0)
