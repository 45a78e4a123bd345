"""`piezo-stage identify`: the Duhem model of a record."""

from __future__ import annotations

import numpy as np

from piezo_stage.cli._common import limits, number, warn_small_span
from piezo_stage.core.errors import DataError
from piezo_stage.core.types import Doc, Params

HELP = "identify the Duhem model from a record"


def add_arguments(s):
    s.add_argument("data", help="record: CSV (t,vx,vy,wx,wy or one axis) or a bag")
    s.add_argument("--axis", choices=("x", "y", "both"), default="both")
    s.add_argument("--method", choices=("fast", "afsa", "afsa-bat"), default="fast")
    s.add_argument("--class", dest="model_class",
                   choices=("duhem", "pi", "preisach", "auto"),
                   default="duhem", help="the hysteresis model class: duhem (the paper's "
                   "law), pi (Prandtl-Ishlinskii: a linear term and 12 play operators with "
                   "non-negative weights, return-point memory, exact inverse), preisach (a "
                   "discretized Preisach law: its density varies along the stroke too), or "
                   "auto (the one that predicts the record's own last 40 %% best, said per "
                   "axis)")
    g = s.add_mutually_exclusive_group()
    g.add_argument("--whole", action="store_true", help="one parameter set for both branches")
    g.add_argument("--segmented", action="store_true", help="a set per branch (default)")
    s.add_argument("--validate", metavar="DATA2", help="held-out record to validate on")
    s.add_argument("--seed", type=number(0, 2**32 - 1, integer=True), default=0)
    s.add_argument("--budget", type=number(1, 10**8, integer=True), metavar="EVALS",
                   help="objective evaluations")
    s.add_argument("--coupling", choices=("auto", "on", "off"), default="auto",
                   help="fit cross-coupling from the other axis (fast only)")
    s.add_argument("--voltage", choices=("auto", "exact"), default="auto",
                   help="exact: v is what the actuator got (never cleaned); auto: a noisy "
                   "(measured) v has its in-branch micro-reversals removed (bags: exact)")
    s.add_argument("--structure", default="cubic", metavar="cubic|auto|D",
                   help="branch shape: cubic (f of degree 3, g of 2: the paper's), D (f of "
                   "degree D, g of D-1, D in 1..12), or auto (the degree, 3..7, that "
                   "predicts the record's own last 40 %% best when fitted on the rest)")
    s.add_argument("--n", type=number(0, 12, integer=True), default=None,
                   help="degree of f (default 3; with --structure cubic only)")
    s.add_argument("--m", type=number(0, 12, integer=True), default=None,
                   help="degree of g (default 2; with --structure cubic only)")
    s.add_argument("--limits", type=limits, metavar="LO,HI", help="the amplifier's "
                   "voltage limits [V], written into the model, e.g. 0,150 or --limits=-90,90 "
                   "(default: 0,150 widened to take the record; the limits belong to the "
                   "amplifier, not the record)")
    s.add_argument("--delay", type=_delay, default="auto", metavar="auto|SECONDS",
                   help="the displacement's lag behind the voltage: auto (the fast "
                   "method: 0 to 5 samples, where it fits 5 %% better: a DAQ reads its "
                   "input a sample after it writes its output), or seconds (0: none); "
                   "written as the model's delay effect")
    s.add_argument("--out", metavar="MODEL.yaml", help="write the model file")
    s.add_argument("--json", metavar="FILE", help="write the full report as JSON")
    s.add_argument("--plot", metavar="PNG", help="loop and fit-error figure (default: "
                   "next to --out's model file, MODEL.png)")


def main(args):
    import os
    from contextlib import nullcontext

    from piezo_stage.io.plots import FigureWorker
    plot = args.plot or (os.path.splitext(args.out)[0] + ".png" if args.out else None)
    # the figure's process imports matplotlib on the other core while the fit runs
    with FigureWorker() if plot else nullcontext() as figures:
        return _identify(args, plot, figures)


def _identify(args, plot, figures):
    import json
    import os

    from piezo_stage.core.estimation.identify import IdentifyOptions, validate_axis
    from piezo_stage.core.estimation.identify.api import identify_stage
    from piezo_stage.core.model.duhem import voltage_limits_for
    from piezo_stage.io.files import atomic_write
    from piezo_stage.io.model_file import save_model
    from piezo_stage.io.records import load_record
    rec = load_record(args.data)
    voltage_limits_for(rec.v.values(), args.limits)  # before any fit: DataError
    warn_small_span(rec, args.limits, args.data)
    val = load_record(args.validate) if args.validate else None
    for note in rec.notes + (val.notes if val is not None else []):
        print(f"note: {note}")
    if args.voltage == "exact":
        rec.voltage_exact = True
        if val is not None:
            val.voltage_exact = True
    axes = _axes(rec, args)
    n, m = _degrees(args)
    opts = IdentifyOptions(method=args.method,
                           structure="whole" if args.whole else "segmented",
                           budget=args.budget, seed=args.seed, coupling=args.coupling,
                           n=n, m=m, delay=args.delay)
    classes = _classes(rec, axes, opts, args)
    pi_axes = {a: classes[a] for a in axes if classes[a] in ("pi", "preisach")}
    axes = [a for a in axes if classes[a] == "duhem"]
    opts_for, chosen = _structures(rec, axes, opts, args)
    from contextlib import ExitStack

    from piezo_stage.progress import bar, best_so_far
    with ExitStack() as bars:
        def progress_for(a):
            return best_so_far(bars.enter_context(bar(f"identify {a} ({opts.method})")))
        fitted = identify_stage(rec, axes, opts_for, args.limits, progress_for) \
            if axes else None
    results, report = (fitted.results if fitted else {}), {}
    for a, r in results.items():
        report[a] = r.to_json()
        report[a]["degrees"] = {"f": opts_for[a].n, "g": opts_for[a].m}
        if a in chosen:
            report[a]["structure_auto"] = {"chosen": chosen[a][0], "held_out_rms_um": {
                str(k): e for k, e in chosen[a][1].items()}}
        if val is not None:
            report[a].update(validate_axis(r, val))
    _print_table(report)
    pis = _fit_pi(rec, pi_axes, val, report, args.limits, opts)
    for note in {n for r in list(results.values()) + list(pis.values()) for n in r.notes}:
        print(f"note: {note}")
    if args.out:
        from piezo_stage.core.estimation.identify.api import delay_effect
        model = _stage_model(fitted, pis, rec, args.limits)
        effects = delay_effect({**results, **pis}) or None
        meta = {"identification": {a: {k: report[a][k] for k in report[a]
                                        if k not in ("history", "parameters")}
                                   for a in report}}
        meta["identification"]["source"] = os.fspath(args.data)
        for note in save_model(args.out, model, effects, extra=meta):
            print(f"note: {note}")
    if args.json:
        with atomic_write(args.json) as fh:
            json.dump(report, fh, indent=1)
    if plot:  # the fit figures as the table's: the same prediction, the same samples
        from piezo_stage.core.estimation.identify.api import fit_prediction, predict_axis
        curves = {a: fit_prediction(r, rec) for a, r in results.items()}
        curves.update({a: (rec.v[a], rec.w[a], p.predict(rec, a), 0)
                       for a, p in pis.items()})
        checked = None
        if val is not None:  # the record it was scored on, beside it
            vcurves = {a: predict_axis(r, val) for a, r in results.items() if a in val.w}
            vcurves.update({a: (val.v[a], val.w[a], p.predict(val, a))
                            for a, p in pis.items() if a in val.w})
            checked = (val.t, vcurves)
        print(f"plot: {figures.draw('identification_png', plot, rec.t, curves, checked)}")
    return 0


def _classes(rec, axes, opts, args) -> Doc:
    """Each axis's model class: the one asked, or with ``auto`` the one
    ``choose_class`` picks on the record's held-out last part (said in a line)."""
    classes = {a: args.model_class for a in axes}
    if args.model_class == "auto":
        from piezo_stage.core.estimation.identify.api import choose_class
        for a in axes:
            classes[a], held, why = choose_class(rec, a, opts, args.limits)
            print(f"class {a}: {classes[a]} (held-out RMS on the record's last 40 %: "
                  + ", ".join(f"{k} {e:.4f} um" for k, e in held.items()) + ")")
            for note in why:
                print(f"note: axis {a}: {note}")
    return classes


def _structures(rec, axes, opts, args) -> tuple[dict, Doc]:
    """(each axis's options, the degrees chosen with their held-out RMS): the options
    as asked, or with ``--structure auto`` the degree ``choose_degree`` picks."""
    chosen: dict[str, tuple] = {}
    if args.structure != "auto":
        return {a: opts for a in axes}, chosen
    from dataclasses import replace

    from piezo_stage.core.estimation.identify.api import choose_degree
    for a in axes:
        d, held = choose_degree(rec, a, opts)
        chosen[a] = (d, held)
        print(f"structure {a}: degree {d} (held-out RMS on the record's last 40 %: "
              + ", ".join(f"{k}: {e:.4f} um" for k, e in held.items()) + ")")
    return {a: replace(opts, n=chosen[a][0], m=max(chosen[a][0] - 1, 0))
            for a in axes}, chosen


def _print_table(report: Doc) -> None:
    """The identification's table: a line per axis."""
    print(f"{'axis':>4} {'method':>8} {'structure':>9} {'fit_rms_um':>10} {'fit_pct':>8} "
          f"{'max_err_um':>10} {'noise_um':>8} {'val_rms_um':>10} {'val_pct':>8} "
          f"{'evals':>7} {'seconds':>7}")
    for a, j in report.items():
        vr = j.get("validate_rms_um", float("nan"))
        vp = j.get("validate_rms_pct", float("nan"))
        print(f"{a:>4} {j['method']:>8} {j['structure']:>9} {j['fit_rms_um']:10.4f} "
              f"{j['fit_rms_pct']:8.4f} {j['max_err_um']:10.4f} {j['noise_floor_um']:8.4f} "
              f"{vr:10.4f} {vp:8.4f} {j['evaluations']:7d} {j['seconds']:7.2f}")


def _fit_pi(rec, axes, val, report, limits, opts) -> Params:
    """The classes with memory on ``axes`` ({axis: 'pi' or 'preisach'}): the
    Prandtl-Ishlinskii class or the discretized Preisach class, monotone weights
    (non-negative least squares), thresholds up to half the amplifier's range
    (``limits``, else 0-150 V widened to the record's), a coupling term as
    ``--coupling`` asks (core/estimation/identify/api.py's ``fit_class_axis``); one
    table row each, into ``report`` too. -> {axis: ClassFit}."""
    from piezo_stage.core.estimation.identify.api import fit_class_axis
    from piezo_stage.core.estimation.identify.prandtl import held_out_rms
    from piezo_stage.core.metrics import noise_floor
    out = {}
    for a, kind in axes.items():
        fitted = fit_class_axis(rec, a, kind, opts, limits)
        out[a], pi = fitted, fitted.law
        e = rec.w[a] - fitted.predict(rec, a)
        j = {"class": kind, "method": "nnls",
             "structure": "cells" if kind == "preisach" else "plays",
             "fit_rms_um": float(np.sqrt(np.mean(e ** 2))),
             "max_err_um": float(np.max(np.abs(e))),
             "noise_floor_um": noise_floor(rec.w[a]), "seconds": pi.fit_s,
             "linear_um_per_V": pi.linear_um_per_V,
             "play_operators": len(pi.operators.thresholds_V),
             "reach_V": float(pi.operators.thresholds_V[-1]),
             "smoothness": pi.smoothness, "coupling": fitted.coupling is not None,
             "delay_s": fitted.delay_s,
             "notes": fitted.notes}
        if val is not None:
            j["validate_rms_um"] = held_out_rms(fitted.predict(val, a), val.w[a],
                                                val.fs_hz, 0.0)
        report[a] = j
        print(f"{a:>4} {kind:>8} {j['structure']:>9} {j['fit_rms_um']:10.4f} {'':>8} "
              f"{j['max_err_um']:10.4f} {j['noise_floor_um']:8.4f} "
              f"{j.get('validate_rms_um', float('nan')):10.4f} {'':>8} {'':>7} "
              f"{j['seconds']:7.2f}")
    return out


def _stage_model(fitted, pis, rec, limits):
    """The stage model of the Duhem axes (``fitted``) and the classes with memory
    (a Duhem law that is exactly their linear term, their play operators beside it,
    their coupling term)."""
    from piezo_stage.core.model.duhem import StageModel, voltage_limits_for
    parts = {a: r.parts() for a, r in fitted.results.items()} if fitted else {}
    for a, p in pis.items():  # at rest at the record's first voltage, as fitted
        parts[a] = p.parts(float(rec.v[a][0]))
    return StageModel.from_fits(parts, voltage_limits_for(list(rec.v.values()), limits))


def _delay(text):
    """argparse type: auto, or a delay in seconds >= 0."""
    import argparse
    if text == "auto":
        return text
    try:
        d = float(text)
    except ValueError:
        d = float("nan")
    if not (np.isfinite(d) and 0 <= d <= 0.1):
        raise argparse.ArgumentTypeError(f"{text!r}: give auto or seconds in [0, 0.1]")
    return d


def _axes(rec, args) -> list:
    """The axes to fit. An axis the record lacks or holds idle is named, with the
    --axis that fits what moves: an error when it was asked for by name, or when it
    leaves nothing; one line on stderr when --axis both fits the other alone."""
    import sys

    from piezo_stage.core.estimation.identify.segmentation import voltage_noise
    wanted = ["x", "y"] if args.axis == "both" else [args.axis]
    present = [a for a in ("x", "y") if a in rec.v and a in rec.w]
    moving = [a for a in present
              if np.ptp(rec.v[a]) > max(1e-9, 10.0 * voltage_noise(rec.v[a]))]

    def why(a):
        if a in present:
            v = np.asarray(rec.v[a], float)
            held = (f"is constant at {v[0]:.4g} V" if np.ptp(v) <= 1e-9 else
                    f"stays within {np.ptp(v):.3g} V of {np.median(v):.4g} V")
            return f"axis {a} is idle (its voltage {held}): nothing to identify"
        if a in rec.v or a in rec.w:
            return f"the record lacks the voltage or the displacement of axis {a}"
        return f"the record has no axis {a}"
    for a in wanted:
        if a in moving:
            continue
        rest = [m for m in moving if m != a]
        if args.axis != "both" or not rest:
            hint = f"; identify {rest[0]} with --axis {rest[0]}" if rest else ""
            raise DataError(f"{args.data}: {why(a)}{hint}")
        print(f"note: {args.data}: {why(a)}; fitting {rest[0]} alone (--axis {rest[0]})",
              file=sys.stderr)
    return [a for a in wanted if a in moving]


def _degrees(args) -> tuple[int, int]:
    """(n, m) from --structure and --n/--m (usage errors: exit 2)."""
    if args.structure in ("cubic", "auto"):
        if args.structure == "auto" and (args.n is not None or args.m is not None):
            raise DataError("--structure auto chooses the degrees: leave out --n/--m")
        return (3 if args.n is None else args.n), (2 if args.m is None else args.m)
    try:
        d = int(args.structure)
    except ValueError:
        raise DataError(f"--structure {args.structure!r}: give cubic, auto or a degree "
                        "1..12") from None
    if not 1 <= d <= 12:
        raise DataError(f"--structure {d}: the degree must be 1..12")
    if args.n is not None or args.m is not None:
        raise DataError(f"--structure {d} sets the degrees (f {d}, g {d - 1}): leave out "
                        "--n/--m")
    return d, d - 1

