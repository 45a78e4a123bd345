"""`piezo-stage bench`: the performance benchmarks (figures as ratios)."""

from __future__ import annotations

from piezo_stage.cli._common import COMPOSITIONS, number

HELP = "performance benchmarks (figures as ratios)"


def add_arguments(s):
    from piezo_stage.benchmarks import BENCHMARKS
    s.add_argument("what", choices=tuple(BENCHMARKS))
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
        from piezo_stage.benchmarks.report import BEGIN, END
        text = open(path).read()
        if text.count("<!-- bench ") != text.count("<!-- /bench "):
            raise argparse.ArgumentTypeError(
                f"{path}: a {BEGIN.format('X')} without its {END.format('X')}")
    return path


def _kinds(text):
    import argparse

    from piezo_stage.benchmarks.experiments import KINDS
    out = tuple(x.strip() for x in text.split(","))
    if not out or any(k not in KINDS for k in out):
        raise argparse.ArgumentTypeError(f"{text!r}: use {', '.join(KINDS)}")
    return out


def main(args):
    if args.kinds is None:
        from piezo_stage.benchmarks.experiments import KINDS
        args.kinds = KINDS
    from piezo_stage import benchmarks
    return benchmarks.main(args)
