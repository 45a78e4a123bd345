"""`piezo-stage loop`: hysteresis loop figures of the simulated stage."""

from __future__ import annotations

import numpy as np

from piezo_stage.cli._common import load_plant, number

HELP = "hysteresis loop figures of the simulated stage"


def add_arguments(s):
    s.add_argument("--config", help="plant config YAML")
    s.add_argument("--freq", type=number(0, 10_000, lo_open=True), default=1.0,
                   help="sine frequency [Hz]")
    s.add_argument("--amplitude", type=number(0, 1000, lo_open=True), default=150.0,
                   help="peak-peak [V]")
    s.add_argument("--cycles", type=number(1, 10_000, integer=True), default=3)
    s.add_argument("--rate", type=number(1, 1_000_000), default=10_000.0, help="sample rate [Hz]")
    s.set_defaults(model=None, no_noise=False, seed=None)


def main(args):
    from piezo_stage.core.metrics import loop_figures
    from piezo_stage.core.model.plant import Plant
    fs = args.rate
    cfg = load_plant(args, fs)
    lo, hi = cfg.model.voltage_limits
    amp = min(args.amplitude, hi - lo)
    t = np.arange(int(round(args.cycles * fs / args.freq))) / fs
    v = lo + amp / 2 * (1 - np.cos(2 * np.pi * args.freq * t))
    plant = Plant(cfg, fs)
    per = int(round(fs / args.freq))
    print(f"simulated stage: {args.freq:g} Hz, 0-{amp:g} V sine, {args.cycles} cycles at "
          f"{fs:g} Hz, noise {cfg.noise_rms_um:g} um RMS")
    print(f"{'driven':>6} {'axis':>4} {'range_um':>9} {'width_um':>9} {'width_pct':>9} "
          f"{'mid_width_um':>12} {'closure_um':>10} {'coupling_pp_um':>14}")
    for drive in ("x", "y"):
        plant.reset()
        other = "y" if drive == "x" else "x"
        vx, vy = (v, np.full_like(v, lo)) if drive == "x" else (np.full_like(v, lo), v)
        plant.run(vx, vy)
        true = plant.last_true
        last, prev = slice(-per, None), slice(-2 * per, -per)
        fig = loop_figures(v[last], true[drive][last])
        closure = float(np.max(np.abs(true[drive][last] - true[drive][prev])))
        coupling = float(np.ptp(true[other][last]))
        print(f"{drive:>6} {drive:>4} {fig['range_um']:9.3f} {fig['max_width_um']:9.3f} "
              f"{fig['max_width_pct']:9.2f} {fig['mid_width_um']:12.3f} {closure:10.2e} "
              f"{coupling:14.3f}")
    return 0
