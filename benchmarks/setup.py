"""`piezo-stage bench setup`: a new user's first minute, from a source checkout. Fresh
clones of the checkout's HEAD, each `./dev.sh` from nothing: the set-up alone
(`./dev.sh --version`) with pip alone (PIEZO_STAGE_INSTALLER=pip, the baseline, as
dev.sh installed before uv) and as dev.sh does it now; then a fresh clone's whole
`./dev.sh demo` with the package caches emptied (uv's and pip's pointed at empty
folders: every wheel unpacked anew, as on a new machine), against the same without
requirements.lock (uv resolving setup.py, as before the lock), and `./dev.sh --version`
once set up. Each is a wall time on this host, the pip one paired in the same run."""

from __future__ import annotations

import os
import shutil
import subprocess
import tempfile
import time

from benchmarks.procs import source_checkout


def _timed(argv, cwd, env) -> float:
    t0 = time.monotonic()
    subprocess.run(argv, cwd=cwd, env=env, check=True, stdout=subprocess.DEVNULL,
                   stderr=subprocess.DEVNULL)
    return time.monotonic() - t0


def bench_setup(rep, runs: int = 2) -> int:
    """A new user's first minute from fresh clones (``rep``: the report)."""
    src = source_checkout("bench setup")
    env = {k: v for k, v in os.environ.items() if not k.startswith(("VIRTUAL_ENV",
                                                                      "PIEZO_STAGE_"))}
    env["ROS_DOMAIN_ID"] = env.get("ROS_DOMAIN_ID", "97")
    rows: dict[str, list[float]] = {"pip": [], "uv": [], "unpinned": [], "demo": [],
                                    "again": []}
    with tempfile.TemporaryDirectory(prefix="piezo-stage-setup-") as d:
        for i in range(runs):
            for how in ("pip", "uv"):
                clone = os.path.join(d, f"{how}{i}")
                subprocess.run(["git", "clone", "-q", src, clone], check=True)
                e = dict(env, PIEZO_STAGE_INSTALLER="pip") if how == "pip" else env
                rows[how].append(_timed(["./dev.sh", "--version"], clone, e))
                shutil.rmtree(clone)
            for how in ("unpinned", "demo"):
                clone = os.path.join(d, f"{how}{i}")
                subprocess.run(["git", "clone", "-q", src, clone], check=True)
                if how == "unpinned":  # the baseline: uv resolves setup.py itself
                    os.remove(os.path.join(clone, "requirements.lock"))
                empty = dict(env, UV_CACHE_DIR=os.path.join(d, f"uv-cache-{how}{i}"),
                             PIP_CACHE_DIR=os.path.join(d, f"pip-cache-{how}{i}"))
                rows[how].append(_timed(["./dev.sh", "demo"], clone, empty))
                if how == "demo":
                    rows["again"].append(_timed(["./dev.sh", "--version"], clone, env))
                shutil.rmtree(clone)
            rep.progress(f"run {i + 1}/{runs}: " + ", ".join(f"{k} {v[-1]:.1f} s"
                                                            for k, v in rows.items()))
    mid = {k: sorted(v)[len(v) // 2] for k, v in rows.items()}
    rep.title(f"fresh clones of the checkout set up by ./dev.sh, {runs} run(s) of each, "
              "medians")
    rep.table(("what", "s", "x pip"), [
        ("set-up, pip alone (the baseline)", f"{mid['pip']:.1f}", "1.00"),
        ("set-up, as dev.sh does it (uv)", f"{mid['uv']:.1f}",
         f"{mid['uv'] / mid['pip']:.2f}"),
        ("./dev.sh demo from a fresh clone, package caches empty, without requirements.lock "
         "(the baseline)", f"{mid['unpinned']:.1f}", ""),
        ("./dev.sh demo from a fresh clone, package caches empty", f"{mid['demo']:.1f}",
         f"{mid['demo'] / mid['unpinned']:.2f} x unpinned"),
        ("./dev.sh --version once set up", f"{mid['again']:.1f}", "")])
    rep.target("./dev.sh demo from a fresh clone, package caches empty, <= 30 s",
               mid["demo"] <= 30)
    rep.target("./dev.sh --version once set up <= 8 s", mid["again"] <= 8)
    return 0
