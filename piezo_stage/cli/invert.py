"""`piezo-stage invert`: the voltages that make a model follow a target."""

from __future__ import annotations

import sys

import numpy as np

from piezo_stage.core.errors import DataError

HELP = "voltages that make a model follow a target"


def add_arguments(s):
    s.add_argument("--model", required=True, help="model file (YAML)")
    s.add_argument("--in", dest="inp", required=True, help="CSV with t,wx,wy (s, um)")
    s.add_argument("--out", required=True, help="output CSV t,vx,vy (V)")
    s.add_argument("--method", choices=("exact", "seed-eq12"), default="exact")


def main(args):
    from piezo_stage.core.inverse import invert_seed_eq12, invert_stage
    from piezo_stage.core.record import Record
    from piezo_stage.io.csv_table import read_table, write_table
    from piezo_stage.io.model_file import load_model
    model, _ = load_model(args.model)
    missing = sorted({"x", "y"} - set(model.axes))
    if missing:
        raise DataError(f"{args.model} has no model for axis {', '.join(missing)}: its "
                        "voltages cannot be computed (give a model with both axes)")
    cols = read_table(args.inp, ["t", "wx", "wy"])
    rec = Record(cols["t"], w={"x": cols["wx"], "y": cols["wy"]}, source=args.inp)
    if args.method == "exact":
        res = invert_stage(model, rec.w["x"], rec.w["y"])
    else:
        res = {a: invert_seed_eq12(m, rec.w[a], model.voltage_limits)
               for a, m in model.axes.items()}
    lo = model.voltage_limits[0]
    v = {a: res[a].v if a in res else np.full(len(rec), lo) for a in ("x", "y")}
    write_table(args.out, {"t": rec.t, "vx": v["x"], "vy": v["y"]})
    for a, r in res.items():
        if r.n_saturated:
            i = int(np.flatnonzero(r.saturated)[0])
            sys.stderr.write(
                f"piezo-stage: warning: axis {a}: {r.n_saturated} of {len(rec)} targets "
                f"unreachable within [{model.voltage_limits[0]:g}, "
                f"{model.voltage_limits[1]:g}] V, saturated (first at t = {rec.t[i]:g} s, "
                f"w = {rec.w[a][i]:g} um)\n")
    return 0
