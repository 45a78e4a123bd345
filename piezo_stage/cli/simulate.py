"""`piezo-stage simulate`: a voltage record through the simulated stage."""

from __future__ import annotations

import numpy as np

from piezo_stage.cli._common import check_voltages, load_plant, number, warn_past_fit_range
from piezo_stage.core.errors import DataError

HELP = "run a voltage record through the simulated stage"


def add_arguments(s):
    s.add_argument("--in", dest="inp", required=True, help="CSV with t,vx,vy (s, V)")
    s.add_argument("--out", required=True, help="output CSV t,vx,vy,wx,wy (wx, wy in um)")
    g = s.add_mutually_exclusive_group()
    g.add_argument("--config", help="plant config YAML (default config/sim_stage.yaml)")
    g.add_argument("--model", help="model file: the plant is exactly this model, nothing else")
    s.add_argument("--no-noise", action="store_true", help="no sensor noise or quantisation")
    s.add_argument("--seed", type=number(0, 2**32 - 1, integer=True),
                   help="noise seed (overrides the config)")


def main(args):
    from piezo_stage.core.estimation.record import Record
    from piezo_stage.core.model.plant import Plant
    from piezo_stage.io.csv_table import read_table, write_table
    cols = read_table(args.inp, ["t", "vx", "vy"])
    rec = Record(cols["t"], {"x": cols["vx"], "y": cols["vy"]}, source=args.inp)
    cfg = load_plant(args, rec.fs_hz)
    check_voltages(rec, cfg.model.voltage_limits, args.inp)
    warn_past_fit_range(cfg.model, rec.v, args.inp)
    plant = Plant(cfg, rec.fs_hz)
    w = plant.run(rec.v["x"], rec.v["y"])
    for a, x in w.items():
        if not np.all(np.isfinite(x)):
            i = int(np.flatnonzero(~np.isfinite(x))[0])
            raise DataError(f"the simulated {a} displacement is not finite from line {i + 2} "
                            "on (the model diverges); nothing written")
    write_table(args.out, {"t": rec.t, "vx": rec.v["x"], "vy": rec.v["y"],
                           "wx": w["x"], "wy": w["y"]})
    return 0
