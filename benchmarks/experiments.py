"""`bench experiments`: does every one of the paper's experiments run every time?

Each kind (tracking, noise, amplitude, decoupling, scan) is run ``runs`` times as a
user runs it, ``piezo-stage experiment KIND`` as a whole process, once with the
shipped model (``--model config/stage_model.yaml``) and once without (the node set
identifies one first; scan: each plant's own model). Printed per kind and model: the
runs, the failures with their last line, and the median wall time of a run against
the noise experiment's (the shortest), measured in the same invocation. Every run
has its own ROS_DOMAIN_ID.
"""

from __future__ import annotations

import os
import shutil
import statistics
import subprocess
import sys
import tempfile
import time

KINDS = ("tracking", "noise", "amplitude", "decoupling", "scan")


def _one(kind: str, model: str | None, out: str) -> tuple[int, str, float]:
    """(exit code, last line on stderr, wall seconds) of one experiment run."""
    from benchmarks.procs import own_domain_env
    env = own_domain_env()
    cmd = [sys.executable, "-m", "piezo_stage.cli", "experiment", kind, "--record", out]
    if model:
        cmd += ["--model", model]
    t0 = time.monotonic()
    r = subprocess.run(cmd, capture_output=True, text=True, env=env, timeout=1800)
    lines = [ln for ln in r.stderr.splitlines() if ln.startswith("piezo-stage")]
    return r.returncode, (lines[-1] if lines else ""), time.monotonic() - t0


def bench_experiments(rep, runs: int = 10, kinds: tuple = KINDS) -> int:
    """Every experiment as a whole command, with and without --model (``rep``: the
    report)."""
    from piezo_stage.paths import default_config
    model = default_config("stage_model.yaml")
    rep.title(f"{', '.join(kinds)}, {runs} run(s) each as whole commands, with --model "
              f"{os.path.relpath(model)} and without (identified); lockstep")
    rows, failures = [], 0
    tmp = tempfile.mkdtemp(prefix="bench_experiments_")
    try:
        for kind in kinds:
            for m in (model, None):
                times, failed = [], []
                for k in range(runs):
                    out = os.path.join(tmp, f"{kind}_{'model' if m else 'none'}_{k}")
                    rc, last, s = _one(kind, m, out)
                    shutil.rmtree(out, ignore_errors=True)
                    times.append(s)
                    if rc != 0:
                        failed.append(f"exit {rc}: {last}")
                    rep.progress(f"{kind:<10} {'--model' if m else 'identified':<10} run "
                                 f"{k + 1}: exit {rc}, {s:.1f} s")
                rows.append((kind, m, times, failed))
                failures += len(failed)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    base = {bool(m): statistics.median(t) for kind, m, t, _ in rows if kind == "noise"}
    table = []
    for kind, m, times, failed in rows:
        med = statistics.median(times)
        table.append((kind, "--model" if m else "identified", len(times), len(failed),
                      f"{med:.1f}", f"{med / base[bool(m)]:.2f}" if bool(m) in base else "-",
                      "; ".join(f"{failed.count(f)} x {f}" for f in sorted(set(failed)))))
    rep.table(("experiment", "model", "runs", "failed", "median s", "x noise", "failures"),
              table)
    rep.target(f"no run fails ({failures} of {len(rows) * runs})", not failures)
    return 1 if failures else 0
