"""`piezo-stage simulate`: a voltage record through the simulated stage."""

from __future__ import annotations

import numpy as np

from piezo_stage.cli._common import check_voltages, load_plant, number, warn_past_fit_range
from piezo_stage.core.errors import DataError

HELP = "run a voltage record through the simulated stage"


def add_arguments(s):
    s.add_argument("--in", dest="inp", required=True,
                   help="CSV with t and vx, vy or both (s, V); with wx/wy (a record) the "
                        "simulated displacement is scored against them")
    s.add_argument("--out", required=True,
                   help="output CSV t, the input's voltages and the simulated "
                        "displacement of their axes (wx, wy in um)")
    g = s.add_mutually_exclusive_group()
    g.add_argument("--config", help="plant config YAML (default config/sim_stage.yaml)")
    g.add_argument("--model", help="model file: the plant is exactly this model, nothing else")
    s.add_argument("--no-noise", action="store_true", help="no sensor noise or quantisation")
    s.add_argument("--seed", type=number(0, 2**32 - 1, integer=True),
                   help="noise seed (overrides the config)")


def main(args):
    from piezo_stage.core.estimation.gap.written import held_out, start_up_samples
    from piezo_stage.core.model.plant import Plant
    from piezo_stage.io.csv_table import read_record, read_table, write_table
    rec = read_record(args.inp, need_w=False)  # one axis or both
    measured = read_table(args.inp, ["t"], [f"w{a}" for a in rec.v])
    cfg = load_plant(args, rec.fs_hz)
    check_voltages(rec, cfg.model.voltage_limits, args.inp)
    warn_past_fit_range(cfg.model, rec.v, args.inp)
    plant = Plant(cfg, rec.fs_hz)
    lo, hi = cfg.model.voltage_limits
    rest = np.full(len(rec.t), min(max(0.0, lo), hi))  # an axis not given: at rest
    w = plant.run(rec.v.get("x", rest), rec.v.get("y", rest))
    for a in rec.v:
        if not np.all(np.isfinite(w[a])):
            i = int(np.flatnonzero(~np.isfinite(w[a]))[0])
            raise DataError(f"the simulated {a} displacement is not finite from line {i + 2} "
                            "on (the model diverges); nothing written")
    cols = {"t": rec.t}
    cols.update({f"v{a}": rec.v[a] for a in rec.v})
    cols.update({f"w{a}": w[a] for a in rec.v})
    write_table(args.out, cols)
    skip = start_up_samples(len(rec.t), rec.fs_hz)
    for a in rec.v:  # a record's own displacement: how far the simulation is from it
        if f"w{a}" in measured and len(rec.t) > skip:
            r = held_out(w[a], measured[f"w{a}"], skip)
            print(f"{a}: {float(np.sqrt(np.mean(r ** 2))):.4f} um RMS from {args.inp}'s "
                  f"w{a} (after its first {skip / rec.fs_hz:.3g} s, its mean offset "
                  "removed: gap's held-out figure)")
    return 0
