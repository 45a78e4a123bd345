"""`bench lifecycle`: how long one `piezo-stage lifecycle` call takes against a running
set, whole process, beside the floor of any Python lifecycle client.

A managed set in lockstep (its own ROS_DOMAIN_ID), configured and activated. Then, in
alternating pairs, ``runs`` times each:

* ``get``: `piezo-stage lifecycle stage_driver` (the state and its transitions);
* ``baseline``: a plain Python process that imports rclpy, creates one node and asks
  ``get_state`` once (what `ros2 lifecycle get` does, without ros2cli's daemon): the
  floor of a new process joining the domain;

and ``runs`` round trips of `deactivate` then `activate` (each its own process).
Printed: min / median / max seconds of each and the ratio of medians to the baseline.
"""

from __future__ import annotations

import os
import random
import subprocess
import sys
import time

BASELINE = r"""
import sys
import rclpy
from lifecycle_msgs.srv import GetState
rclpy.init()
node = rclpy.create_node("lifecycle_floor", start_parameter_services=False,
                         enable_rosout=False)
cli = node.create_client(GetState, sys.argv[1] + "/get_state")
cli.wait_for_service(timeout_sec=30)
fut = cli.call_async(GetState.Request())
rclpy.spin_until_future_complete(node, fut, timeout_sec=30)
print(fut.result().current_state.label)
node.destroy_node()
rclpy.try_shutdown()
"""


def _timed(cmd: list[str], env: dict) -> tuple[float, str]:
    t0 = time.perf_counter()
    r = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=120)
    dt = time.perf_counter() - t0
    if r.returncode != 0:
        raise RuntimeError(f"{' '.join(cmd[2:])}: exit {r.returncode}: "
                           f"{r.stderr.strip().splitlines()[-1:]}")
    return dt, r.stdout.strip()


def _line(name: str, xs: list[float], base: float) -> str:
    xs = sorted(xs)
    med = xs[len(xs) // 2]
    return (f"{name:22} {xs[0]:6.2f} {med:6.2f} {xs[-1]:6.2f}   {med / base:5.2f} x"
            f"   ({len(xs)} calls)")


def bench_lifecycle(runs: int = 10) -> int:
    import tempfile

    from piezo_stage.launch.launcher import Launch
    from piezo_stage.paths import default_config
    domain = random.randint(101, 200)
    env = dict(os.environ, ROS_DOMAIN_ID=str(domain),
               ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST")
    node = "/stage/stage_driver"
    cli = [sys.executable, "-m", "piezo_stage", "lifecycle", "stage_driver"]
    floor = [sys.executable, "-c", BASELINE, node]
    got: dict[str, list[float]] = {"get": [], "baseline": [], "deactivate": [],
                                   "activate": []}
    with tempfile.TemporaryDirectory() as tmp:
        launch = Launch(default_config("stage.yaml"), record=os.path.join(tmp, "bag"),
                        env=env, trajectory=False, exclusive=False, managed=True)
        try:
            launch.start()
            _timed(cli + ["active", "--timeout", "60"], env)  # configure, activate
            for _ in range(runs):
                for name, cmd in (("get", cli), ("baseline", floor)):
                    dt, out = _timed(cmd, env)
                    got[name].append(dt)
                for name in ("deactivate", "activate"):
                    dt, out = _timed(cli + [name], env)
                    got[name].append(dt)
        finally:
            launch.stop()
    base = sorted(got["baseline"])[runs // 2]
    print(f"bench lifecycle: {runs} calls each against a managed lockstep set "
          f"({os.cpu_count()} cores); whole processes, seconds")
    print(f"{'':22} {'min':>6} {'median':>6} {'max':>6}   vs the floor")
    for name in ("baseline", "get", "deactivate", "activate"):
        print(_line({"baseline": "floor (rclpy get_state)", "get": "lifecycle (get)",
                     "deactivate": "lifecycle deactivate",
                     "activate": "lifecycle activate"}[name], got[name], base))
    worst = max(sorted(v)[runs // 2] for k, v in got.items() if k != "baseline")
    print(f"slowest median call: {worst:.2f} s (target: within 1.5 s)")
    return 0
