"""Benchmarks: each prints its figures as ratios against a baseline run in the same process.

Never imported by tests for timing; run ``piezo-stage bench <what>``.
"""

from __future__ import annotations

import time

import numpy as np

from piezo_stage.core.duhem import DuhemHysteresis
from piezo_stage.core.plant import Plant, PlantConfig
from piezo_stage.io.plant_file import default_plant_config_path, load_plant_config


def _python_plant_loop(cfg: PlantConfig, vx, vy):
    """The same plant (hysteresis, coupling, clamp, slew, noise) as a plain Python loop."""
    m = cfg.model
    hx, hy = DuhemHysteresis(m.axes["x"]), DuhemHysteresis(m.axes["y"])
    cx, cy = DuhemHysteresis(m.coupling["x"]), DuhemHysteresis(m.coupling["y"])
    lo, hi = m.voltage_limits
    step = cfg.slew_V_per_s / cfg.internal_rate_hz
    rng = np.random.default_rng(cfg.seed)
    noise = rng.standard_normal((len(vx), 2)) * cfg.noise_rms_um
    q = cfg.quantization_um
    px = py = 0.0
    wx = np.empty(len(vx))
    wy = np.empty(len(vx))
    for k in range(len(vx)):
        ax = min(max(min(max(vx[k], lo), hi), px - step), px + step)
        ay = min(max(min(max(vy[k], lo), hi), py - step), py + step)
        px, py = ax, ay
        x = hx.step(ax) + cx.step(ay) + noise[k, 0]
        y = hy.step(ay) + cy.step(ax) + noise[k, 1]
        wx[k] = round(x / q) * q
        wy[k] = round(y / q) * q
    return wx, wy


def bench_plant(n_samples: int):
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
    t0 = time.perf_counter()
    px, py = _python_plant_loop(cfg, vx[:n_py], vy[:n_py])
    slow = time.perf_counter() - t0
    agree = max(np.max(np.abs(px - w["x"][:n_py])), np.max(np.abs(py - w["y"][:n_py])))

    fast_rate = n_samples / fast
    slow_rate = n_py / slow
    print("bench plant: 2-axis simulated stage, segmented Duhem + hysteretic coupling + "
          "clamp/slew + sensor noise and quantisation")
    print(f"  compiled batch : {n_samples:>9d} samples in {fast:7.3f} s = "
          f"{fast_rate / 1e6:6.2f} M samples/s per axis")
    print(f"  python loop    : {n_py:>9d} samples in {slow:7.3f} s = "
          f"{slow_rate / 1e6:6.3f} M samples/s per axis (baseline)")
    print(f"  speed-up       : {fast_rate / slow_rate:6.1f} x the plain Python loop")
    print(f"  agreement      : max |batch - loop| = {agree:.2e} um")
    print(f"  target >= 1 M samples/s per axis: {'met' if fast_rate >= 1e6 else 'NOT met'}")
    return 0 if agree < 1e-6 else 1


def main(args):
    if args.what == "plant":
        return bench_plant(args.samples)
    raise SystemExit(f"unknown benchmark {args.what}")
