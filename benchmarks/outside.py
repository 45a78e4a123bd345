"""`bench outside`: is every trajectory a lab's own node sends run by the stage and held
in the bag?

A node set without its trajectory node (``launch --no-trajectory``), in lockstep and in
real time, each with its own ROS_DOMAIN_ID and bag. Outside publishers, each a new
process with ROS defaults (its own participant, discovered afresh), send ``runs``
trajectories each, every one at its own level (um):

* ``latched``: reliable, transient local, depth 1; sent once as soon as the publisher
  matched one subscriber;
* ``default``: the default QoS (reliable, volatile, depth 10); sent once as soon as the
  publisher matched one subscriber (then it waits for the acknowledgements and exits);
* ``example``: examples/publish_trajectory.py, which waits for the stage to finish.

A trajectory counts as run when the desired positions in the bag reach its level, and
as recorded when the bag's ``trajectory/accepted`` holds it. Printed per mode and
publisher: sent, run, recorded, and the publisher processes that failed.
"""

from __future__ import annotations

import os
import random
import shutil
import subprocess
import sys
import tempfile

import numpy as np

from benchmarks import ROOT

KINDS = ("latched", "default", "example")
EXAMPLE = os.path.join(ROOT, "examples", "publish_trajectory.py")


def _send(kind: str, um: float, env: dict) -> int:
    if kind == "example":
        cmd = [sys.executable, EXAMPLE, "--points", f"0,{um:g},{um:g} 0.3,{um:g},{um:g}",
               "--start-in", "0", "--tolerance", "5", "--timeout", "60"]
    else:
        cmd = [sys.executable, "-m", "benchmarks.procs", "once", kind, f"{um:g}"]
    try:
        return subprocess.run(cmd, env=env, cwd=ROOT, capture_output=True,
                              timeout=90).returncode
    except subprocess.TimeoutExpired:
        return -1


def _mode(mode: str, runs: int, tmp: str) -> dict:
    """{kind: (sent levels, failed sends)} and the bag of one mode's set."""
    from benchmarks.probe import Probe
    from piezo_stage.launcher.launcher import Launch, LaunchOptions
    from piezo_stage.paths import default_config
    domain = random.randint(101, 200)
    env = dict(os.environ, ROS_DOMAIN_ID=str(domain),
               ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST")
    bag = os.path.join(tmp, mode)
    rate = None
    if mode == "realtime":  # where this host holds the set (it is judged there)
        from piezo_stage.launcher.host_rate import host_rate
        rate, why = host_rate(env)
        if rate is None:
            raise RuntimeError(f"this host holds no real-time rate with margin: {why}")
    launch = Launch(default_config("stage.yaml"), LaunchOptions(record=bag, trajectory=False,
        exclusive=False, rate=rate,
        overrides={"stage_driver": {"mode": mode, "min_margin": 0.0}}), env=env)
    sent: dict[str, tuple[list, int]] = {k: ([], 0) for k in KINDS}
    probe = Probe(domain)
    try:
        launch.start()
        if not probe.wait_state("armed", 60):
            raise RuntimeError(f"{mode}: the set did not arm")
        level = 15.0
        for k in range(runs):
            for kind in KINDS:
                rc = _send(kind, level, env)
                levels, failed = sent[kind]
                levels.append(level)
                sent[kind] = (levels, failed + (rc != 0))
                probe.spin(0.8)  # the approach and the 0.3 s at the level
                level += 0.5
    finally:
        probe.close()
        launch.stop()
    return {"sent": sent, "bag": bag}


def _judge(res: dict) -> dict:
    from piezo_stage.io.bag import deserialize, iter_messages
    from piezo_stage.io.run_bag import read_run
    accepted = [round(deserialize(d, t).points[0].positions[0] * 1e6, 3)
                for topic, t, _, d in iter_messages(res["bag"])
                if topic.endswith("/trajectory/accepted")]
    run = read_run(res["bag"])
    desired = np.array([v[0] for v in run.desired_um.values()])
    out = {}
    for kind, (levels, failed) in res["sent"].items():
        ran = sum(bool(np.any(np.abs(desired - lv) < 1e-6)) for lv in levels)
        held = sum(round(lv, 3) in accepted for lv in levels)
        out[kind] = (len(levels), ran, held, failed)
    return out


def bench_outside(rep, runs: int = 10) -> int:
    """Trajectories from outside publishers, judged from the bag (``rep``: the
    report)."""
    rep.title(f"{runs} trajectories from each outside publisher ({', '.join(KINDS)}), "
              "each a new process, to a `launch --no-trajectory` set in lockstep and in "
              "real time")
    tmp = tempfile.mkdtemp(prefix="bench_outside_")
    rows, misses = [], 0
    try:
        for mode in ("lockstep", "realtime"):
            for kind, (n, ran, held, failed) in _judge(_mode(mode, runs, tmp)).items():
                rows.append((mode, kind, n, ran, held, failed, f"{100 * ran / n:.1f}"))
                misses += (n - ran) + (n - held) + failed
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    rep.table(("mode", "publisher", "sent", "run", "recorded", "failed", "run %"), rows)
    rep.target(f"every trajectory run and recorded (misses: {misses})", not misses)
    return 1 if misses else 0
