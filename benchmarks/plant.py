"""`piezo-stage bench plant`: the simulated stage's compiled kernels against their
plain-Python originals (NUMBA_DISABLE_JIT=1 in a helper process), same samples."""

from __future__ import annotations

import time

import numpy as np

from benchmarks import ROOT
from piezo_stage.core.model.plant import Plant
from piezo_stage.io.plant_file import default_plant_config_path, load_plant_config


def _plain_python_plant(n: int, fs: float):
    """The same Plant.run with numba switched off (NUMBA_DISABLE_JIT=1): every kernel
    runs as its plain-Python original, the baseline core/_jit.py promises. Returns (seconds,
    (wx, wy))."""
    import os
    import subprocess
    import sys
    import tempfile
    with tempfile.TemporaryDirectory() as d:
        out = os.path.join(d, "w.npy")
        r = subprocess.run([sys.executable, "-m", "benchmarks.procs", "plain",
                            str(n), str(fs), out],
                           env=dict(os.environ, NUMBA_DISABLE_JIT="1"), cwd=ROOT,
                           capture_output=True,
                           text=True, check=True)
        w = np.load(out)
    return float(r.stdout.split()[-1]), (w[0], w[1])



def bench_plant(rep, n_samples: int):
    """The compiled plant against its plain-Python kernels (``rep``: the report)."""
    cfg = load_plant_config(default_plant_config_path())
    fs = cfg.internal_rate_hz  # one command per internal sample: every sample counted
    t = np.arange(n_samples) / fs
    vx = 75 - 75 * np.cos(2 * np.pi * 1.0 * t)
    vy = 75 - 75 * np.cos(2 * np.pi * 1.3 * t + 0.4)
    Plant(cfg, fs).run(vx[:1000], vy[:1000])  # compile (or load the cache) first

    plant = Plant(cfg, fs)
    t0 = time.perf_counter()
    w = plant.run(vx, vy)
    fast = time.perf_counter() - t0

    n_py = min(n_samples, 100_000)
    slow, (px, py) = _plain_python_plant(n_py, fs)
    agree = max(np.max(np.abs(px - w["x"][:n_py])), np.max(np.abs(py - w["y"][:n_py])))

    fast_rate = n_samples / fast
    slow_rate = n_py / slow
    rep.title("the 2-axis simulated stage (segmented Duhem, hysteretic coupling, "
              "clamp and slew, sensor noise and quantisation), compiled, against the same "
              "kernels as plain Python")
    rep.table(("run", "samples", "time", "rate per axis"), [
        ("compiled batch (numba)", f"{n_samples:,}", f"{fast:.3f} s",
         f"{fast_rate / 1e6:.2f} M samples/s"),
        ("the same kernels as plain Python (baseline)", f"{n_py:,}", f"{slow:.3f} s",
         f"{slow_rate / 1e6:.3f} M samples/s"),
        ("ratio", "", "", f"{fast_rate / slow_rate:.1f} x; batch and loop agree to "
         f"{agree:.2g} um")])
    rep.target(">= 1 M samples/s per axis", fast_rate >= 1e6)
    return 0 if agree < 1e-6 else 1
