"""`piezo-stage refit`: re-identify every bag of an archive and say how the stage changed."""

from __future__ import annotations

from piezo_stage.cli._common import limits, number

HELP = "re-identify every bag of an archive; how the stage changed, and when"


def add_arguments(s):
    s.add_argument("bags", nargs="+", metavar="BAG_OR_DIR",
                   help="bags, or folders holding them (a run folder, bags/)")
    s.add_argument("--out", required=True, metavar="DIR",
                   help="where the models (DIR/models/), refit.csv, refit.json and "
                   "refit.png go")
    s.add_argument("--jobs", type=number(1, 256, integer=True), default=None,
                   help="worker processes (default: the CPU count)")
    s.add_argument("--against", metavar="MODEL.yaml",
                   help="a reference model (the lab's calibration): each bag's gap "
                   "diagnosis against it, and which effect grew since the first bag")
    s.add_argument("--limits", type=limits, metavar="LO,HI",
                   help="the amplifier's voltage limits [V] for the written models")
    s.add_argument("--scheduler", metavar="ADDRESS",
                   help="run the bags on a Dask distributed cluster, its scheduler at "
                   "ADDRESS (tcp://host:8786; the optional extra .[dask]; its workers "
                   "need this package and read the bags and --out at the same paths)")


def main(args):
    import csv
    import json
    import os
    import statistics
    import time

    from piezo_stage.apps import refit as R
    from piezo_stage.io.files import atomic_write
    from piezo_stage.progress import bar, steps
    if args.against:
        from piezo_stage.io.model_file import load_model
        load_model(args.against)  # a bad reference: one line before any work
    bags = R.find_bags(args.bags)
    jobs = max(1, min(args.jobs or os.cpu_count() or 1, len(bags)))
    where = f"the Dask cluster at {args.scheduler}" if args.scheduler else \
        f"{jobs} worker(s)"
    print(f"refit: {len(bags)} bag(s) on {where}"
          + (f", against {args.against}" if args.against else ""))
    t0 = time.perf_counter()
    skipped: list[tuple[str, str]] = []  # (bag, why)
    with bar("refit", total=len(bags), unit="bag") as b:
        rows = R.refit(bags, args.out, jobs, args.limits, args.against, steps(b), skipped,
                       args.scheduler)
    for path, why in skipped:
        print(f"skipped: {why}" if path in why else f"skipped {path}: {why}")
    for r in rows:
        for note in r.get("notes", []):
            print(f"note: {note}")
    wall = time.perf_counter() - t0
    cols = R.table_columns(rows)
    with atomic_write(os.path.join(args.out, "refit.csv"), newline="") as fh:
        out = csv.writer(fh)
        out.writerow(list(cols))
        out.writerows(zip(*cols.values()))
    g = R.growth(rows) if args.against else []
    with atomic_write(os.path.join(args.out, "refit.json")) as fh:
        json.dump({"bags": rows, "skipped": [{"bag": p, "why": w} for p, w in skipped],
                   "growth": g,
                   "growth_threshold_pct": R.GROWTH_PCT}, fh, indent=1, default=str)
    from piezo_stage.io.plots import refit_png
    png = refit_png(os.path.join(args.out, "refit.png"), rows)
    axes = [a for a in ("x", "y") if any(a in r["axes"] for r in rows)]
    width = max([len(r["name"]) for r in rows] + [3])  # every name whole
    print(f"{'started (UTC)':<20} {'bag':<{width}} " + " ".join(
        f"{a + ' gain um/V':>13} {a + ' held-out um':>14} {a + ' change um':>12}"
        for a in axes) + ("  verdicts" if args.against else ""))
    for r in rows:
        cells = []
        for a in axes:
            ax = r["axes"].get(a, {})
            cells.append(f"{ax.get('gain_um_per_V', float('nan')):13.4f} "
                         f"{ax.get('held_out_rms_um', float('nan')):14.4f} "
                         f"{ax.get('change_um', float('nan')):12.4f}")
        verdicts = ", ".join(f"{a} {r['axes'][a]['against']['verdict']}" for a in axes
                             if "against" in r["axes"].get(a, {}))
        print(f"{r['started_utc'][:19]:<20} {r['name']:<{width}} " + " ".join(cells)
              + (f"  {verdicts}" if verdicts else ""))
    for line in R.growth_lines(g):
        print(line)
    if args.against and not g:
        print(f"no effect beyond {args.against} in any bag")
    one = statistics.median(r["seconds"] for r in rows)
    if args.scheduler:
        print(f"{len(rows)} bag(s) in {wall:.1f} s on {where}; one bag's refit "
              f"{one:.1f} s (median)")
    else:
        ideal = one * len(rows) / jobs
        print(f"{len(rows)} bag(s) in {wall:.1f} s on {jobs} worker(s); one bag's refit "
              f"{one:.1f} s (median), so {ideal:.1f} s ideal: {wall / ideal:.2f} x")
    print(f"table: {os.path.join(args.out, 'refit.csv')} (and refit.json); "
          f"models: {os.path.join(args.out, 'models')}; plot: {png}")
    return 0
