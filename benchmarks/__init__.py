"""Benchmarks: each prints its figures as ratios against a baseline run in the same
invocation (never timed unit tests); ``piezo-stage bench <what>`` runs one.

One module per benchmark (plant, identify, loop, liveview, gap, realtime, learning,
faults, signals, experiments, outside, refit, setup, lifecycle, settle, accuracy,
doubles, scan, startup) and the
equipment they share:
``procs`` (helper processes, CPU ticks, the progress of repeated runs), ``probe`` (an
outside node),
``host_pauses`` (when the whole machine stopped), ``foxglove_probe`` (a live-view
client), ``report`` (what a benchmark found, as text or as the page's markdown).
"""

from __future__ import annotations

import importlib
import os

# the checkout the workbench sits in (beside the package, never installed with it): its
# helper processes run from here (``python -m benchmarks.procs`` finds this folder)
ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))

# what -> (module, function, the arguments it takes from the command line)
BENCHMARKS = {
    "plant": ("plant", "bench_plant", ("samples",)),
    "identify": ("identify", "bench_identify", ()),
    "loop": ("loop", "bench_loop", ("vs",)),
    "gap": ("gap", "bench_gap", ("stages",)),
    "liveview": ("liveview", "bench_liveview", ()),
    "faults": ("faults", "bench_faults", ()),
    "realtime": ("realtime", "bench_realtime", ("track", "compose")),
    "learning": ("learning", "bench_learning", ("draws",)),
    "signals": ("signals", "main", ("trials",)),
    "experiments": ("experiments", "bench_experiments", ("runs", "kinds")),
    "outside": ("outside", "bench_outside", ("runs",)),
    "refit": ("refit", "bench_refit", ()),
    "setup": ("setup", "bench_setup", ("runs",)),
    "lifecycle": ("lifecycle", "bench_lifecycle", ("runs",)),
    "settle": ("settle", "bench_settle", ("steps", "moves", "out")),
    "accuracy": ("accuracy", "bench_accuracy", ()),
    "doubles": ("doubles", "bench_doubles", ()),
    "scan": ("scan", "bench_scan", ()),
    "startup": ("startup", "bench_startup", ("runs",)),
    "watch": ("watch", "bench_watch", ("minutes",)),
}


def main(args) -> int:
    """Run the benchmark ``args.what`` with its command-line arguments; its report as
    text, or as markdown (``args.markdown``: a page to write its section into, or -)."""
    from benchmarks.report import Report
    module, function, takes = BENCHMARKS[args.what]
    run = getattr(importlib.import_module(f"benchmarks.{module}"), function)
    page = getattr(args, "markdown", None)
    rep = Report(args.what, markdown=page is not None)
    rc = run(rep, *(getattr(args, k) for k in takes))
    rep.finish(page)
    return rc
