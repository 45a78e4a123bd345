"""`piezo-stage bench`: the performance benchmarks (figures as ratios).

The benchmarks are the workbench beside the package (the checkout's ``benchmarks/``
folder), never installed with it: this command runs them from a source checkout and
says so, in one line, from an installed package."""

from __future__ import annotations

import os
import sys
from types import ModuleType

from piezo_stage.cli._common import COMPOSITIONS, number

HELP = "performance benchmarks (figures as ratios), from a source checkout"


def workbench() -> ModuleType | None:
    """The checkout's ``benchmarks`` package, the checkout put first on this process's
    path (and on its helpers', which run from it); None where this package is an
    installed one, with no workbench beside it."""
    import importlib
    root = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
    if not os.path.isfile(os.path.join(root, "benchmarks", "__init__.py")):
        return None
    if root not in sys.path:
        sys.path.insert(0, root)
    return importlib.import_module("benchmarks")


def add_arguments(s):
    bench = workbench()
    s.add_argument("what", choices=tuple(bench.BENCHMARKS) if bench else None)
    s.add_argument("--markdown", type=_page, default=None, metavar="PAGE",
                   help="the report as markdown, each table headed by the date, commit "
                   "and host: written into PAGE's section for this benchmark (replaced "
                   "whole; docs/benchmarks.md is made so), or - for stdout")
    s.add_argument("--track", type=number(0, 3600, lo_open=True), default=20.0, metavar="S",
                   help="realtime: seconds of the paper's trajectory")
    s.add_argument("--draws", type=number(1, 100, integer=True), default=5, metavar="N",
                   help="learning: plant noise seeds, each run in lockstep and real time")
    s.add_argument("--samples", type=number(1000, 10**9, integer=True), default=2_000_000)
    s.add_argument("--runs", type=number(1, 1000, integer=True), default=10, metavar="N",
                   help="experiments: runs of each kind, with and without --model; "
                   "outside: trajectories from each publisher; setup: fresh clones of "
                   "each kind; lifecycle: calls of each")
    s.add_argument("--kinds", type=_kinds, default=None, metavar="K1,K2",
                   help="experiments: which (default tracking,noise,amplitude,"
                   "decoupling,scan)")
    s.add_argument("--steps", type=number(4, 10_000, integer=True), default=50, metavar="N",
                   help="settle: random 10 um steps on each stage")
    s.add_argument("--moves", type=number(4, 100_000, integer=True), default=200,
                   metavar="N", help="settle: random moves judged for false and missed "
                   "on-target")
    s.add_argument("--out", default=None, metavar="FILE",
                   help="settle: the default stage's motion-time model (JSON), for "
                   "piezo_stage.client")
    s.add_argument("--vs", default=None, metavar="REV",
                   help="loop: the code at git revision REV too (a clone of this "
                   "checkout at REV), its own lockstep loop in each pair")
    s.add_argument("--compose", choices=COMPOSITIONS, default=None,
                   help="realtime: which of the loop's nodes share a process in the real-"
                   "time set (as launch --compose; default the launcher's)")
    s.add_argument("--trials", type=number(1, 10000, integer=True), default=108, metavar="N",
                   help="signals: processes to start and signal (each kind in turn)")
    s.add_argument("--stages", type=number(1, 100_000, integer=True), default=200,
                   metavar="N", help="gap: stages generated with seeds drawn at the run, "
                   "for the rates of spurious and missed effects")
    s.add_argument("--minutes", type=number(0.5, 600), default=10.0, metavar="M",
                   help="watch: minutes of a stage that does not change, for the false "
                   "alarms per hour")


def _page(path):
    """A page the report can be written into (checked before a benchmark of minutes)."""
    import argparse
    import os
    if path == "-":
        return path
    folder = os.path.dirname(os.path.abspath(path))
    if not os.path.isdir(folder) or not os.access(folder, os.W_OK):
        raise argparse.ArgumentTypeError(f"{path}: no folder to write it in")
    if os.path.exists(path):
        text = open(path).read()
        if text.count("<!-- bench ") != text.count("<!-- /bench "):
            raise argparse.ArgumentTypeError(
                f"{path}: a <!-- bench X --> without its <!-- /bench X -->")
    return path


def _kinds(text):
    import argparse
    if workbench() is None:
        raise argparse.ArgumentTypeError(_NO_WORKBENCH)
    kinds = _experiment_kinds()
    out = tuple(x.strip() for x in text.split(","))
    if not out or any(k not in kinds for k in out):
        raise argparse.ArgumentTypeError(f"{text!r}: use {', '.join(kinds)}")
    return out


_NO_WORKBENCH = ("the benchmarks run from a source checkout (its benchmarks/ folder beside "
                 "piezo_stage/); this piezo_stage is an installed package")


def _experiment_kinds() -> tuple:
    """The experiments ``bench experiments`` runs (the workbench's, found first)."""
    import importlib
    return tuple(importlib.import_module("benchmarks.experiments").KINDS)


def main(args):
    bench = workbench()
    if bench is None:
        from piezo_stage.core.errors import DataError
        raise DataError(f"bench {args.what}: {_NO_WORKBENCH}")
    if args.kinds is None:
        args.kinds = _experiment_kinds()
    return bench.main(args)
