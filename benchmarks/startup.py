"""`piezo-stage bench startup`: what a start costs before the work, in whole processes
as a user runs them.

* ``identify``: `piezo-stage identify REC --out M` (what it prints and writes, its
  figure too) against a plain Python script doing the same fit (``load_record``,
  ``identify_stage`` with the defaults, ``save_model``: no command line, no figure), in
  alternating pairs, on two records made as the README makes them: the identifier
  node's size (two cycles of a 1 Hz full-stroke sine at 1 kHz, simulated) and the
  README's excitation (`excite`, then `simulate`).
* ``launch to armed``: `piezo-stage launch --no-trajectory --duration 1` in lockstep,
  and with ``config/realtime.yaml`` at the rate this host holds with margin
  (launcher/host_rate.py), from the command's start to the driver's ``armed`` line.

Printed: min / median / max seconds; for identify the median pair's ratio.
"""

from __future__ import annotations

import os
import subprocess
import sys
import tempfile
import time

PLAIN = r"""
import sys
from piezo_stage.core.estimation.identify import IdentifyOptions
from piezo_stage.core.estimation.identify.api import identify_stage
from piezo_stage.io.model_file import save_model
from piezo_stage.io.records import load_record
rec = load_record(sys.argv[1])
save_model(sys.argv[2], identify_stage(rec, sorted(rec.w), IdentifyOptions()).model)
"""
COMMAND = [sys.executable, "-m", "piezo_stage"]
ARMED = "]: armed: "  # the driver's log line as the stage arms


def _run(argv: list[str], env: dict, cwd: str) -> float:
    """Seconds ``argv`` took as a whole process (RuntimeError with its last line)."""
    t0 = time.perf_counter()
    r = subprocess.run(argv, env=env, cwd=cwd, capture_output=True, text=True, timeout=600)
    dt = time.perf_counter() - t0
    if r.returncode != 0:
        last = (r.stderr.strip().splitlines() or [""])[-1]
        raise RuntimeError(f"{' '.join(argv[2:])}: exit {r.returncode}: {last}")
    return dt


def _records(env: dict, tmp: str) -> dict[str, str]:
    """{name: CSV} of the two records, made by the package's own commands."""
    import numpy as np
    t = np.arange(2200) / 1000.0
    v = 75.0 - 75.0 * np.cos(2 * np.pi * t)
    np.savetxt(os.path.join(tmp, "sine_v.csv"), np.c_[t, v, v], delimiter=",",
               header="t,vx,vy", comments="")
    _run(COMMAND + ["simulate", "--in", "sine_v.csv", "--out", "sine.csv"], env, tmp)
    _run(COMMAND + ["excite", "--out", "exc.csv"], env, tmp)
    _run(COMMAND + ["simulate", "--in", "exc.csv", "--out", "fit.csv"], env, tmp)
    return {"2 cycles of a 1 Hz sine, 2,200 samples": "sine.csv",
            "the README's excitation": "fit.csv"}


def _to_armed(argv: list[str], env: dict, cwd: str) -> tuple[float | None, str]:
    """(seconds from the command's start to the driver's armed line, or None where it
    never armed; the command's exit code and the driver's states on stderr, in
    words)."""
    t0 = time.perf_counter()
    p = subprocess.Popen(argv, env=env, cwd=cwd, stdout=subprocess.DEVNULL,
                         stderr=subprocess.PIPE, text=True)
    armed, states = None, []
    try:
        assert p.stderr is not None
        for line in p.stderr:
            if armed is None and ARMED in line:
                armed = time.perf_counter() - t0
            if "stage_driver]: " in line:
                states.append(line.split("stage_driver]: ", 1)[1].split(":", 1)[0])
        p.wait(timeout=120)
    finally:
        if p.poll() is None:
            p.kill()
            p.wait()
    return armed, f"exit {p.returncode}, the driver {' -> '.join(states) or 'silent'}"


def _stats(xs: list[float]) -> tuple[str, str, str]:
    xs = sorted(xs)
    return f"{xs[0]:.2f}", f"{xs[len(xs) // 2]:.2f}", f"{xs[-1]:.2f}"


def bench_startup(rep, runs: int = 3) -> int:
    """Whole `identify` against a plain script, and launch to armed (``rep``: the
    report)."""
    from benchmarks.procs import own_domain_env, progress_runs
    from piezo_stage.launcher.host_rate import host_rate
    from piezo_stage.paths import default_config
    env = own_domain_env()
    rows, ratios = [], {}
    with tempfile.TemporaryDirectory(prefix="piezo-stage-startup-") as tmp:
        records = _records(env, tmp)
        for name, csv in records.items():
            got: dict[str, list[float]] = {"whole": [], "plain": []}
            pairs = []
            for i in progress_runs(range(runs), f"bench startup: identify, {name}"):
                order = ("whole", "plain") if i % 2 == 0 else ("plain", "whole")
                for kind in order:
                    argv = COMMAND + ["identify", csv, "--out", "m.yaml"] \
                        if kind == "whole" else [sys.executable, "-c", PLAIN, csv, "p.yaml"]
                    got[kind].append(_run(argv, env, tmp))
                pairs.append(got["whole"][-1] / got["plain"][-1])
            ratios[name] = sorted(pairs)[len(pairs) // 2]
            rows.append((name, "piezo-stage identify (whole process)", *_stats(got["whole"]),
                         f"{ratios[name]:.2f} x"))
            rows.append(("", "plain script, the same fit", *_stats(got["plain"]), "1"))
        rep.title(f"what a start costs: {runs} runs of each, whole processes, seconds "
                  f"({os.cpu_count()} CPUs)")
        rep.table(("record", "process", "min", "median", "max", "median pair"), rows,
                  "identify against a plain script doing the same fit, in alternating pairs")
        for name, r in ratios.items():
            rep.target(f"identify, {name}: the whole process <= 1.5 x the plain script "
                       f"({r:.2f} x)", r <= 1.5)

        with tempfile.TemporaryFile("w+") as log:  # the capacity run's node lines
            old = os.dup(2)
            os.dup2(log.fileno(), 2)
            try:
                rate, why = host_rate(env)
            finally:
                os.dup2(old, 2)
                os.close(old)
        sets = [("lockstep", COMMAND + ["launch", "--no-trajectory", "--duration", "1"])]
        if rate is not None:
            sets.append((f"real time at {rate:g} Hz", COMMAND + [
                "launch", "--params", default_config("realtime.yaml"), "--rate",
                f"{rate:g}", "--no-trajectory", "--duration", "1"]))
        else:
            rep.note(f"real time left out: this host holds no rate with margin ({why})")
        armed_rows = []
        env = own_domain_env()  # apart from the capacity run's nodes, still leaving
        for label, argv in sets:
            tries = [_to_armed(argv, env, tmp) for _ in progress_runs(
                range(runs), f"bench startup: launch to armed, {label}")]
            ok = [x for x, _ in tries if x is not None]
            for x, last in tries:
                if x is None:
                    rep.note(f"{label}: a launch never armed ({last})")
            if not ok:
                armed_rows.append((label, "-", "-", "-", f"never armed in {runs}"))
                rep.target(f"launch to armed, {label}: <= 3 s (never armed)", False)
                continue
            med = sorted(ok)[len(ok) // 2]
            armed_rows.append((label, *_stats(ok), f"{runs - len(ok)} of {runs}"))
            rep.target(f"launch to armed, {label}: median <= 3 s ({med:.2f} s)", med <= 3.0)
        rep.table(("set", "min", "median", "max", "never armed"), armed_rows,
                  "`piezo-stage launch --no-trajectory --duration 1`: from the command's "
                  "start to the driver's armed line (the recorder is not started)")
    return 0
