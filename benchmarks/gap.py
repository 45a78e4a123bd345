"""`piezo-stage bench gap`: the blind suite's confusion matrices, the diagnosis's run
time on a two-axis record against the exact searches, and the structure stage."""

from __future__ import annotations

import time

import numpy as np


def bench_gap(rep, stages=200, seeds=3):
    """The rule's error rates on ``stages`` generated stages (seeds drawn now), the
    blind suites, two effects at once, the speed, the structure stage and fit here, use
    there (``rep``: the report)."""
    _bench_generated(rep, stages)
    from piezo_stage.apps.studies import gap_blind
    from piezo_stage.core.estimation.gap import diagnose
    rep.title("the blind suite: one unmodelled effect per record pair (FIT, HOLDOUT), the "
              "diagnosis not told which; axis x, 1 kHz, ~36 s protocol records (their "
              "chirp included)")
    from piezo_stage.progress import bar, steps
    with bar("bench gap: blind cases", total=2 * len(gap_blind.TRUTHS) * seeds,
             unit=" cases") as b:
        rows = gap_blind.run(seeds=seeds, progress=steps(b))
    for fam in ("own", "independent", None):
        labels, M = gap_blind.confusion(rows, fam)
        ok = sum(M[i, i] for i in range(len(gap_blind.TRUTHS)))
        rep.table(["truth \\ verdict", *labels],
                  [[tname, *map(int, M[i])] for i, tname in enumerate(gap_blind.TRUTHS)],
                  f"confusion matrix ({fam or 'both suites'}): correct {ok}/{M.sum()} = "
                  f"{100 * ok / M.sum():.0f} %")
        if fam is None:
            rep.target(">= 80 % right over both suites", ok >= 0.8 * M.sum())
    shr = [r["shrink_true_pct"] for r in rows if r["truth"] != "none" and
           r["shrink_true_pct"] is not None]
    hits = [r for r in rows if r["truth"] != "none" and r["verdict"] == r["truth"]]
    low = min(hits, key=lambda r: r["shrink_true_pct"])
    figs = [("held-out gap shrink with the true effect, median",
             f"{np.median(shr):.0f} %; >= 50 % in {sum(x >= 50 for x in shr)}/{len(shr)} "
             "cases"),
            ("the same where the verdict is right, least",
             f"{low['shrink_true_pct']:.0f} % ({low['family']}/{low['truth']} seed "
             f"{low['seed']})"),
            ("mean diagnosis time per axis record pair",
             f"{np.mean([r['seconds'] for r in rows]):.1f} s")]
    rep.target("held-out shrink >= 50 % where the verdict is right",
               low["shrink_true_pct"] >= 50)
    figs += [("miss", f"{r['family']}/{r['truth']} seed {r['seed']} -> {r['verdict']} "
              f"({r['reason']})") for r in rows if r["verdict"] != r["truth"]]
    with bar("bench gap: two effects at once", total=len(gap_blind.PAIRS) * 2,
             unit=" cases") as b:
        multi = gap_blind.run_multi(seeds=2, progress=steps(b))
    exact = sum(r["named"] == r["truth"] for r in multi)
    figs.append(("two at once (own simulator, 1 kHz, both axes; a floor vibration counts "
                 "as the disturbance class): the named set exactly right",
                 f"{exact}/{len(multi)} axis records = {100 * exact / len(multi):.0f} %"))
    rep.target("two at once: >= 80 % exactly right", exact >= 0.8 * len(multi))
    figs += [("miss, two at once", f"{'+'.join(sorted(r['truth']))} seed {r['seed']} axis "
              f"{r['axis']} -> {sorted(r['named']) or r['verdict']} ({r['reason']})")
             for r in multi if r["named"] != r["truth"]]
    # speed: a 35 s record at 5 kHz, two axes, each case also without the two speed-ups
    # (every search step on every column, the axes in threads) in the same run. The
    # issue's figures: 36 s per single-effect case, 134 s for our stage with three
    # effects (its machine)
    from piezo_stage.core.estimation import gap as gap_mod
    from piezo_stage.core.estimation.gap import searches as gap_searches

    def timed(fit, hold, fast=True):
        gap_searches.ONE_COLUMN_SEARCH = gap_mod.AXES_IN_PROCESSES = fast
        try:
            t0 = time.perf_counter()
            res = diagnose(fit, hold)
            return res, time.perf_counter() - t0
        finally:
            gap_searches.ONE_COLUMN_SEARCH = gap_mod.AXES_IN_PROCESSES = True
    fit, hold = gap_blind.make_pair("creep", "own", 0, fs=5000.0)
    (_, dt), (_, slow) = timed(fit, hold), timed(fit, hold, fast=False)
    figs.append((f"speed: a {fit.t[-1]:.1f} s record at 5 kHz, two axes, one effect",
                 f"{dt:.1f} s; without the speed-ups {slow:.1f} s, x{slow / dt:.2f}"))
    rep.target("one effect at 5 kHz <= 10 s", dt <= 10)
    effects = {"creep": {"gamma": 0.04}, "delay": {"delay_s": 0.0008},
               "dynamics": {"kind": "resonance", "fn_hz": 600.0, "zeta": 0.08}}
    for chirp in (2.0, 0.0):
        fit, hold = gap_blind.make_multi_pair(effects, 1, fs=5000.0, coupling=True,
                                              chirp_s=chirp)
        res, dt = timed(fit, hold)
        what = ("speed: the same with our stage's creep, 600 Hz resonance, 0.8 ms delay "
                f"and coupling{'' if chirp else ', protocol without its chirp (--chirp 0)'}")
        took = f"{dt:.1f} s"
        if chirp:
            _, slow = timed(fit, hold, fast=False)
            took += f"; without the speed-ups {slow:.1f} s, x{slow / dt:.2f}"
        figs.append((what, took))
        rep.target(what.replace("speed: the same", "three effects") + " <= 20 s", dt <= 20)
        figs += _named(res)
    rep.figures(figs, "the suites' figures, two effects at once and the speed")
    _bench_structure(rep)
    _bench_conditions(rep)
    return 0


def _bench_conditions(rep):
    """Fit here, use there (apps/studies/conditions.py), beside the classical
    Prandtl-Ishlinskii peer fitted on the same samples: held-out RMS [um] after the
    first second, each model's offset removed."""
    from piezo_stage.apps.studies import conditions
    rep.table(conditions.COLUMNS, conditions.table_rows(conditions.run()),
              "fit here, use there (1 kHz, axis x; held-out RMS after 1 s, offsets removed, "
              "um): ours (identify), the model gap --out-model writes (loaded and run "
              "through our simulator), the classical Prandtl-Ishlinskii peer (linear + 12 "
              "plays, least squares), ours fitted on HOLDOUT itself")



def _bench_structure(rep):
    """bench gap's block for issue 25: a stage whose hysteresis is not our model class
    (config/structure_stage.yaml: play operators, memory, a tanh envelope). Two seed
    pairs of the protocol with its nested loops, both axes; then the kind of record
    real stages give (gap_blind.scan_cut). The truth of the locked part: the base
    model's error against the plant's true displacement (gap_blind.locked_truth)."""
    from piezo_stage.apps.studies.gap_blind import locked_truth, scan_cut, structure_pair
    from piezo_stage.core.estimation.gap import diagnose
    worse = total = 0
    rows = []
    for seeds in ((1, 2), (3, 4)):
        fit, hold, true = structure_pair(seeds)
        res = diagnose(fit, hold)
        for a, d in res["axes"].items():
            truth = locked_truth(fit, hold, true[a], a)
            b = d["budget"]
            none = next(r for r in d["ranking"] if r["effect"] == "none")["fit_rms_um"]
            worse += sum(r["fit_rms_um"] > none * (1 + 1e-9) for r in d["ranking"])
            total += len(d["ranking"])
            last = d["effects"][-1] if d["effects"] else None
            rows.append((f"seeds {seeds} axis {a}", d["verdict"],
                         ", ".join(s["effect"] for s in d["effects"]) or "nothing",
                         f"{last['shrink_pct']:.0f} +- {last['shrink_pm_pct']:.0f} %"
                         if last else "", f"{b['input_locked_um']:.3f} um vs {truth:.3f} um "
                         f"({100 * (b['input_locked_um'] / truth - 1):+.0f} %)"))
            if last:
                rep.target(f"structure stage, seeds {seeds} axis {a}: held-out shrink "
                           ">= 60 %", last["shrink_pct"] >= 60)
            rep.target(f"structure stage, seeds {seeds} axis {a}: locked part within 15 % "
                       "of the truth", abs(b["input_locked_um"] / truth - 1) <= 0.15)
    fit, hold, true = scan_cut()
    res = diagnose(fit, hold)
    truth = locked_truth(fit, hold, true, "x")
    b = res["budget"]
    kept = res["effects"][0] if res["effects"] else None
    after = next((r["rms_after_um"] for r in res["ranking"] if r["effect"] == res["verdict"]),
                 float("nan"))
    rows.append(("a scan cut from a run (1 Hz, 5 kHz, fit 3 s, held out 4 s)",
                 res["verdict"], ", ".join(s["effect"] for s in res["effects"]) or "nothing",
                 f"{kept['shrink_pct']:.0f} +- {kept['shrink_pm_pct']:.0f} %" if kept else "",
                 f"{b['input_locked_um']:.3f} um ({b['locked_estimator']['kind']}) vs "
                 f"{truth:.3f} um; held-out RMS {b['residual_rms_um']:.3f} -> {after:.3f} um "
                 f"(noise {b['noise_floor_um']:.3f})"))
    if kept:
        rep.target("structure stage, the scan cut: held-out shrink >= 40 %",
                   kept["shrink_pct"] >= 40)
    rep.table(("record", "verdict", "named", "held-out shrink", "locked vs truth"), rows,
              "structure stage (play-operator hysteresis: memory, tanh envelope; our "
              "coupling): the protocol with nested loops, 1 kHz, both axes; candidate fits "
              f"worse on FIT than their base: {worse} of {total}")



def _named(res):
    """Per axis: the effects the diagnosis kept, and what they closed (figures' rows)."""
    out = []
    for a, d in res["axes"].items():
        b = d["budget"]
        out.append((f"  axis {a}: named", ", then ".join(
            s["effect"] + (f" (or {'/'.join(s['equally_well'])})" if s["equally_well"] else "")
            for s in d["effects"]) + f"; held-out gap {b['gap_um']:.3f} -> "
            f"{b['unexplained_um']:.3f} um ({100 * (1 - b['unexplained_um'] / b['gap_um']):.0f}"
            " % shrink, target >= 80 %)" + "".join(
                f"; {s['effect']} {_fmt_params(s['params'])}" for s in d["effects"]
                if s["effect"] in ("delay", "dynamics"))))
    return out



def _fmt_params(p):
    return "(" + ", ".join(f"{k} {v:.4g}" for k, v in p.items()
                           if isinstance(v, float)) + ")"


def _bench_generated(rep, stages):
    """The diagnosis on ``stages`` stages generated with seeds drawn now (never those
    its thresholds were tuned on: gap_blind.generated_case draws each stage's
    hysteresis, one or two effects of every pair of the candidates or none, their
    sizes, the noise, the rate and the protocol's holds and chirp): how often it names
    an effect that is not there (spurious) and how often it leaves out one that is and
    moves HOLDOUT by the sensor's noise or more (missed), with 95 % intervals."""
    from piezo_stage.apps.studies import gap_blind
    from piezo_stage.progress import bar, steps
    base = int(np.random.SeedSequence().entropy % (2 ** 31 - 2 * stages))
    with bar("bench gap: generated stages", total=stages, unit=" stages") as b:
        rows = gap_blind.run_generated(range(base, base + stages), progress=steps(b))
    n = len(rows)
    spur = [r for r in rows if r["spurious"]]
    miss = [r for r in rows if r["missed"]]
    unseen = sum(len(r["unseen"]) for r in rows)

    def rate(k):
        lo, hi = gap_blind.wilson(k, n)
        return f"{k}/{n} = {100 * k / n:.1f} % (95 % interval {100 * lo:.1f}-{100 * hi:.1f} %)"
    rep.title(f"generated stages: {n} drawn with seeds {base}..{base + n - 1} (drawn at the "
              "run): our stage's kind with its hysteresis scaled, no effect, one, or a pair "
              "of creep, dynamics, delay, drift, coupling, their sizes, the noise "
              "(0.05-0.15 um), 1 or 2 kHz, holds of 2-4 s and a chirp of 1-3 s; both axes")
    by_kind: dict = {}
    for r in rows:
        k = "+".join(r["truth"]) or "none"
        c = by_kind.setdefault(k, [0, 0, 0])
        c[0] += 1
        c[1] += bool(r["spurious"])
        c[2] += bool(r["missed"])
    rep.table(["case", "stages", "spurious", "missed"],
              [[k, *c] for k, c in sorted(by_kind.items())],
              "per case kind (a stage counts once whatever its axes named)")
    figs = [("spurious: a stage where an axis named an effect that is not on", rate(len(spur))),
            ("missed: a stage where an axis left out an effect that is on and moves its "
             "HOLDOUT by the sensor's noise or more", rate(len(miss))),
            ("effects on but moving HOLDOUT by less than the noise (neither counted)",
             str(unseen)),
            ("mean diagnosis time per stage (both axes)",
             f"{np.mean([r['seconds'] for r in rows]):.1f} s")]
    figs += [("spurious", f"seed {r['seed']} {'+'.join(r['truth']) or 'none'} -> "
              f"{r['named']} ({'; '.join(r['reasons'].values())[:300]})") for r in spur]
    figs += [("missed", f"seed {r['seed']} {'+'.join(r['truth']) or 'none'} -> "
              f"{r['named']} (sizes {r['visible_um']}, noise "
              f"{r['params']['noise_um']:.3f} um)") for r in miss]
    rep.figures(figs, "the error rates, and each error")
    rep.table(["footprint on HOLDOUT (x the noise)", "effects on an axis", "not named there"],
              [list(b) for b in gap_blind.missed_by_footprint(rows)],
              "where the misses lie: each effect on an axis by how far it moves that axis's "
              "HOLDOUT (noise-free, the plant with it against without it, the mean removed)")
    rep.target("spurious effects <= 2 % of the generated stages", len(spur) <= 0.02 * n)
    rep.target("missed effects <= 5 % of the generated stages", len(miss) <= 0.05 * n)
