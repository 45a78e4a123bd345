"""`piezo-stage invert`: the voltages that make a model follow a target."""

from __future__ import annotations

import sys

import numpy as np

from piezo_stage.core.errors import DataError
from piezo_stage.core.types import EffectsBlock

HELP = "voltages that make a model follow a target"


def add_arguments(s):
    s.add_argument("--model", required=True, help="model file (YAML)")
    s.add_argument("--in", dest="inp", required=True, help="CSV with t,wx,wy (s, um), "
                   "or t and one axis's column (the other axis held at rest, 0 V within "
                   "the model's limits)")
    s.add_argument("--out", required=True, help="output CSV t,vx,vy (V)")
    s.add_argument("--method", choices=("exact", "seed-eq12"), default="exact")
    s.add_argument("--effects", action="store_true",
                   help="also invert the model's effects (delay, dynamics, creep) at the "
                   "target's sample rate, previewing the known target: for a waveform "
                   "played at the controller's own rate (`play`)")


def main(args):
    from piezo_stage.core.estimation.record import Record
    from piezo_stage.core.model.inverse import invert_seed_eq12, invert_stage
    from piezo_stage.io.csv_table import read_table, write_table
    from piezo_stage.io.model_file import load_model
    model, effects = load_model(args.model)
    # a target of one axis is inverted on that axis, the other held at rest (0 V within
    # the limits; its coupling into the given axis taken in); an axis the model lacks
    # rests there too
    cols = read_table(args.inp, ["t"], ["wx", "wy"])
    given = [a for a in ("x", "y") if f"w{a}" in cols]
    if not given:
        raise DataError(f"{args.inp}: no target column (need t and wx, wy or both)")
    asked = sorted(a for a in given if a not in model.axes)
    if asked:
        raise DataError(f"{args.model} has no model for axis {', '.join(asked)}: its "
                        f"voltages cannot be computed (give a model with both axes, or a "
                        f"target of t and the model's axes alone)")
    lo, hi = model.voltage_limits
    n = len(cols["t"])
    rest = np.full(n, min(max(0.0, lo), hi))
    held = {a: rest for a in ("x", "y") if a not in given}
    rec = Record(cols["t"], w={a: cols.get(f"w{a}", np.zeros(n)) for a in ("x", "y")},
                 source=args.inp)
    if args.effects:
        if args.method != "exact":
            raise DataError("--effects needs --method exact")
        if not effects:
            raise DataError(f"{args.model} has no effects to invert (`gap --out-model` "
                            "writes them)")
        rec = Record(rec.t, w={**rec.w, **compensate_effects(effects, rec, given)},
                     source=args.inp)
    if args.method == "exact":
        res = invert_stage(model, rec.w["x"], rec.w["y"],
                           dt_s=1.0 / rec.fs_hz if model.rate_dependent else 0.0,
                           held_V=held)
    else:
        res = {a: invert_seed_eq12(m, rec.w[a], model.voltage_limits)
               for a, m in model.axes.items() if a in given}
    v = {a: res[a].v if a in res else rest for a in ("x", "y")}
    from piezo_stage.cli._common import warn_past_fit_range
    warn_past_fit_range(model, v, args.model)
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


def compensate_effects(effects: EffectsBlock, rec, axes=("x", "y")) -> EffectsBlock:
    """The hysteresis targets {axis: um} of ``axes`` that make the model's effects give
    ``rec``'s positions at its samples: each axis's inverse fed its target
    ``lead_ticks`` ahead (the last target held past the end); the record must be
    uniformly sampled."""
    from piezo_stage.core.loop.compensation import EffectCompensator
    dt = np.diff(rec.t)
    if dt.size == 0 or np.ptp(dt) > 1e-6 * float(np.median(dt)):
        raise DataError("--effects needs a uniformly sampled target (one rate)")
    comp = EffectCompensator(effects, 1.0 / float(np.median(dt)), tuple(axes))
    n, lead = len(rec), comp.lead_ticks
    ahead = {a: np.concatenate([rec.w[a], np.full(lead[a], rec.w[a][-1])]) for a in lead}
    comp.reset({a: float(rec.w[a][0]) for a in lead})
    out = {a: np.empty(n) for a in lead}
    for k in range(n):
        h = comp.step({a: float(ahead[a][k + lead[a]]) for a in lead})
        for a in lead:
            out[a][k] = h[a]
    note = comp.describe()
    sys.stderr.write(f"piezo-stage: {note}\n")
    return out
