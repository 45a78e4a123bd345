"""`piezo-stage gap`: the sim-to-real gap diagnosis of a record."""

from __future__ import annotations

from piezo_stage.cli._common import limits, warn_small_span
from piezo_stage.core.errors import DataError

HELP = "diagnose the sim-to-real gap"


def add_arguments(s):
    s.add_argument("fit", help="record to fit on (CSV t,vx,vy,wx,wy or bag)")
    s.add_argument("--holdout", help="a different record to score on")
    s.add_argument("--model", help="the sim's model (default: identified from FIT)")
    s.add_argument("--axis", choices=("x", "y", "both"), default="both")
    s.add_argument("--json", metavar="FILE")
    s.add_argument("--report", metavar="DIR", help="Markdown report with PNG plots")
    s.add_argument("--limits", type=limits, metavar="LO,HI", help="the amplifier's "
                   "voltage limits [V], e.g. --limits=-90,90: --out-model's model's "
                   "(default: 0,150 widened to take both records)")
    s.add_argument("--out-model", metavar="MODEL.yaml",
                   help="write the model with the found effect (simulate --model uses it)")


def _warn_ranges(fit, hold) -> None:
    """One line on stderr when HOLDOUT's voltages leave FIT's range by more than a tenth
    of its span: the models fitted on FIT are used past what they saw there (they run,
    continuing straight from their ends; a large gap may be that, not an effect)."""
    import sys

    import numpy as np
    out = []
    for a in sorted(set(fit.v) & set(hold.v)):
        lo, hi = float(np.min(fit.v[a])), float(np.max(fit.v[a]))
        hlo, hhi = float(np.min(hold.v[a])), float(np.max(hold.v[a]))
        if hhi > hi + 0.1 * (hi - lo) or hlo < lo - 0.1 * (hi - lo):
            out.append(f"v{a} {hlo:.4g}..{hhi:.4g} V against FIT's {lo:.4g}..{hi:.4g} V")
    if out:
        sys.stderr.write("piezo-stage: warning: HOLDOUT goes past FIT's voltage range ("
                         + "; ".join(out) + "): the models are used past what they were "
                         "fitted on, and part of the gap may be that\n")


def _warn_implausible(per, fit) -> None:
    """One line on stderr when the sim misses HOLDOUT by more than FIT's whole stroke on
    an axis: no unmodelled effect does that; the two records differ in units or gain (a
    0-10 V control voltage against the amplifier's volts, another sensor scale), and the
    verdict is not to be trusted."""
    import sys

    import numpy as np
    out = []
    for a, d in per.items():
        before = d.ranking[0]["rms_before_um"] if d.ranking else 0.0
        stroke = float(np.ptp(fit.w[a]))
        if before > stroke:
            out.append(f"axis {a}: {before:.4g} um against FIT's {stroke:.4g} um")
    if out:
        sys.stderr.write("piezo-stage: warning: the sim misses HOLDOUT by more than FIT's "
                         "whole stroke (" + "; ".join(out) + "): no unmodelled effect "
                         "does that; are the records in the same units and gain (a 0-10 V "
                         "control voltage against amplifier volts?)\n")


def main(args):
    import json

    from piezo_stage.core.estimation.gap import diagnose
    from piezo_stage.io.files import atomic_write
    from piezo_stage.io.records import load_record
    fit = load_record(args.fit)
    hold = load_record(args.holdout) if args.holdout else None
    for note in fit.notes + (hold.notes if hold is not None else []):
        print(f"note: {note}")
    # the limits, before the diagnosis: DataError (exit 2)
    from piezo_stage.core.model.duhem import voltage_limits_for
    voltage_limits_for(fit.v.values(), args.limits)
    if args.out_model:
        warn_small_span(fit, args.limits, args.fit)
    base, base_effects = None, None
    if args.model:
        from piezo_stage.io.model_file import load_model
        base, base_effects = load_model(args.model)
    if hold is not None and set(fit.w) != set(hold.w):
        raise DataError(f"FIT has axes {sorted(fit.w)} but HOLDOUT has {sorted(hold.w)}")
    if hold is not None:
        _warn_ranges(fit, hold)
    from piezo_stage.progress import bar, steps
    with bar("gap: candidate fits", unit=" fits") as b:
        res = diagnose(fit, hold, base_model=base, base_effects=base_effects,
                       axes=None if args.axis == "both" else [args.axis], progress=steps(b),
                       limits_V=args.limits)
    per = res.per_axis
    if hold is not None:
        _warn_implausible(per, fit)
    print(f"verdict: {res['verdict']} ({res['reason']})" if len(per) == 1 else
          f"verdict: {res['verdict']} (the axis with the larger gap, {res['where']['axis']})")
    if len(per) > 1:
        for a, d in per.items():
            print(f"verdict {a}: {d.verdict} ({d.reason})")
    _print_ranking(per)
    sc = res["scored"]
    print(f"HOLDOUT figures [um]: each model as --out-model writes it, run as `simulate "
          f"--model` runs the file over HOLDOUT's voltages from its initial state (FIT's "
          f"start); RMS after HOLDOUT's first {sc['start_up_s']:g} s, its mean offset "
          f"removed; gap = the part above the noise floor (and a line the input does not "
          f"cause), in quadrature")
    print(f"where: axis {res['where']['axis']}, band {res['where']['band_hz'][0]:g}-"
          f"{res['where']['band_hz'][1]:g} Hz, segment {res['where']['segment']}; noise floor "
          f"{res['noise_floor_um']:.4f} um; {res['seconds']:.1f} s")
    _print_effects_and_budgets(per)
    if args.json:
        with atomic_write(args.json) as fh:
            json.dump(res.json, fh, indent=1, default=float)
    if args.report:
        from piezo_stage.io.gap_report import write_report
        print(f"report: {write_report(args.report, res, hold or fit)}")
    if args.out_model:
        from piezo_stage.io.model_file import save_document
        doc, bounded = res.document()
        save_document(args.out_model, doc)
        print(f"model written: {args.out_model} (" + "; ".join(
            f"{a}: {d.written_as}" for a, d in per.items()) + ")")
        for note in bounded:
            print(f"note: {note}")
    return 0


def _print_ranking(per):
    """Each axis's candidates against the sim, the kept effects joined, and what
    --out-model writes, one line each (HOLDOUT figures [um])."""
    print(f"{'axis':>4} {'effect':>9} {'rms_before':>10} {'rms_after':>9} {'gap_before':>10} "
          f"{'gap_after':>9} {'shrink_pct':>10} {'+-':>5}")
    for a, d in per.items():
        for r in d.ranking:
            print(f"{a:>4} {r['effect']:>9} {r['rms_before_um']:10.4f} {r['rms_after_um']:9.4f} "
                  f"{r['gap_before_um']:10.4f} {r['gap_after_um']:9.4f} {r['shrink_pct']:10.1f} "
                  f"{r.get('shrink_pm_pct', float('nan')):5.1f}"
                  + (" (at its no-effect limit: its search did worse on FIT)"
                     if r["params"].get("no_effect_limit") else "")
                  + (f" (not writable: {r['params']['not_writable']})"
                     if r["params"].get("not_writable") else ""))
        if len(d.effects) > 1:  # the kept effects joined: the verdict's "in all" figure
            st, before = d.effects[-1], d.ranking[0]
            name = "+".join(x["effect"] for x in d.effects)
            print(f"{a:>4} {name:>9} {before['rms_before_um']:10.4f} "
                  f"{st['rms_after_um']:9.4f} {before['gap_before_um']:10.4f} "
                  f"{st['gap_after_um']:9.4f} {st['shrink_pct']:10.1f} "
                  f"{st.get('shrink_pm_pct', float('nan')):5.1f} (joined)")
        # what --out-model writes for the axis, its figure the file's on HOLDOUT
        before = d.ranking[0]
        g0 = before["gap_before_um"]
        print(f"{a:>4} {'written':>9} {before['rms_before_um']:10.4f} "
              f"{d.written_rms_um:9.4f} {g0:10.4f} {d.written_gap_um:9.4f} "
              f"{100.0 * (1 - d.written_gap_um / g0) if g0 > 0 else 0.0:10.1f} "
              f"{'':>5} ({d.written_as})")


def _print_effects_and_budgets(per):
    """Each axis's kept effects in the order added, its budget and any disturbance."""
    from piezo_stage.io.gap_report import step_label
    for a, d in per.items():
        if d.effects:
            print(f"effects {a} (in the order added): " + ", ".join(
                f"{step_label(s)} (gap {s['gap_after_um']:.4f} um, shrink {s['shrink_pct']:.0f} "
                f"+- {s.get('shrink_pm_pct', float('nan')):.0f} %)" for s in d.effects))
        b = d.budget
        expl = ", ".join(f"{k} {v:.4f}" for k, v in b["explained_um"].items()) or "nothing"
        print(f"budget {a} [um]: residual {b['residual_rms_um']:.4f} = noise "
              f"{b['noise_floor_um']:.4f} + input-locked {b['input_locked_um']:.4f} + not "
              f"input-locked {b['not_input_locked_um']:.4f} in quadrature (closure "
              f"{b['closure_pct']:+.1f} %); gap {b['gap_um']:.4f}: explained {expl}, "
              f"unexplained {b['unexplained_um']:.4f}")
        if b.get("disturbance"):
            x = b["disturbance"]
            print(f"disturbance {a}: {x['rms_um']:.4f} um at {x['freq_hz']:.1f} Hz (band "
                  f"{x['band_hz'][0]:.1f}-{x['band_hz'][1]:.1f} Hz), not caused by the "
                  f"input; feedback bandwidth to reject it: >= "
                  f"{x['feedback_bandwidth_hz']:.0f} Hz")
