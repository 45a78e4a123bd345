"""`bench lifecycle`: how long one `piezo-stage lifecycle` call takes against a running
set, whole process, beside the floor of any Python lifecycle client.

Two managed sets in turn (each its own ROS_DOMAIN_ID), configured and activated: one
in real time (``config/realtime.yaml`` at RT_RATE_HZ, a rate any 2-core host of ours
holds with margin: the loop leaves the host's cores mostly idle, as a lab's set does),
one in lockstep (the loop as fast as the host goes: every core busy, the worst case
for a new process). Against each, in
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


def _row(label: str, name: str, xs: list[float], base: float) -> tuple:
    xs = sorted(xs)
    med = xs[len(xs) // 2]
    return (label, name, len(xs), f"{xs[0]:.2f}", f"{med:.2f}", f"{xs[-1]:.2f}",
            f"{med / base:.2f} x")


def _against(mode: str, runs: int) -> dict[str, list[float]]:
    import tempfile

    from piezo_stage.launcher.launcher import Launch, LaunchOptions, read_parameters
    from piezo_stage.paths import default_config
    domain = random.randint(101, 200)
    env = dict(os.environ, ROS_DOMAIN_ID=str(domain),
               ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST")
    node = "/stage/stage_driver"
    cli = [sys.executable, "-m", "piezo_stage", "lifecycle", "stage_driver"]
    floor = [sys.executable, "-c", BASELINE, node]
    got: dict[str, list[float]] = {"get": [], "baseline": [], "deactivate": [],
                                   "activate": []}
    overrides = read_parameters(default_config("realtime.yaml")) if mode == "realtime" \
        else {}
    with tempfile.TemporaryDirectory() as tmp:
        launch = Launch(default_config("stage.yaml"), LaunchOptions(
            record=os.path.join(tmp, "bag"), trajectory=False, exclusive=False, managed=True,
            overrides=overrides, rate=RT_RATE_HZ if mode == "realtime" else None), env=env)
        try:
            launch.start()
            _timed(cli + ["active", "--timeout", "60"], env)  # configure, activate
            for _ in range(runs):
                for name, cmd in (("get", cli), ("baseline", floor)):
                    got[name].append(_timed(cmd, env)[0])
                for name in ("deactivate", "activate"):
                    got[name].append(_timed(cli + [name], env)[0])
        finally:
            launch.stop()
    return got


RT_RATE_HZ = 100.0

NAMES = {"baseline": "floor (rclpy get_state)", "get": "lifecycle (get)",
         "deactivate": "lifecycle deactivate", "activate": "lifecycle activate"}


def bench_lifecycle(rep, runs: int = 10) -> int:
    """`piezo-stage lifecycle` calls against managed sets, beside a bare rclpy client
    (``rep``: the report)."""
    rep.title(f"{runs} calls of each against a managed set ({os.cpu_count()} cores); whole "
              "processes, seconds")
    worst, rows = {}, []
    for mode in ("realtime", "lockstep"):
        got = _against(mode, runs)
        base = sorted(got["baseline"])[runs // 2]
        label = f"real-time set, {RT_RATE_HZ:g} Hz" if mode == "realtime" else "lockstep set"
        rows += [_row(label if i == 0 else "", NAMES[name], got[name], base)
                 for i, name in enumerate(NAMES)]
        worst[mode] = max(sorted(v)[runs // 2] for k, v in got.items() if k != "baseline")
    rep.table(("set", "call", "calls", "min", "median", "max", "median against the floor"),
              rows)
    rep.target("the slowest median call within 1.5 s once the set runs ("
               + ", ".join(f"{worst[m]:.2f} s {m}" for m in worst) + ")",
               max(worst.values()) <= 1.5)
    return 0
