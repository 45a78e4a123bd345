"""`piezo-stage study`: the paper's identification study reproduced."""

from __future__ import annotations

import sys

from piezo_stage.cli._common import number

HELP = "reproduce the paper's identification study"


def add_arguments(s):
    s.add_argument("what", choices=("identification",))
    s.add_argument("--out", default="out/identification_study", help="output folder")
    s.add_argument("--seeds", type=number(1, 1000, integer=True), default=5)
    s.add_argument("--budget", type=number(1, 10**8, integer=True), default=60_000,
                   help="evaluations per swarm run")


def main(args):
    from piezo_stage.apps.studies import identification
    from piezo_stage.progress import bar
    with bar("study: identifications", total=2 + 3 * args.seeds, unit=" fits") as b:
        rep = identification.run(args.out, seeds=args.seeds, budget=args.budget,
                                 progress=lambda m: b.write(m, file=sys.stderr),
                                 step=lambda: b.update(1))
    identification.print_report(rep)
    print(f"plots and study.json in {args.out}")
    return 0
