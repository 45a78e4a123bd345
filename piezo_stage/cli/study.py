"""`piezo-stage study`: the paper's identification study reproduced."""

from __future__ import annotations

import sys

from piezo_stage.cli._common import number

HELP = "reproduce the paper's identification study, or learning feedforward offline"


def add_arguments(s):
    s.add_argument("what", choices=("identification", "learning"))
    s.add_argument("--out", default="out/identification_study",
                   help="identification: output folder")
    s.add_argument("--json", default=None, help="learning: the figures as JSON")
    s.add_argument("--periods", type=number(2, 10_000, integer=True), default=20,
                   help="learning: periods per case")
    s.add_argument("--model-error", type=number(-0.5, 0.5), default=0.0, metavar="F",
                   help="learning: every effect parameter of the model off by this "
                   "factor (0.2: 20 %%)")
    s.add_argument("--rate", type=float, choices=(1000.0, 2000.0, 5000.0), default=1000.0,
                   help="learning: the control rate [Hz] (default 1000)")
    s.add_argument("--seeds", type=number(1, 1000, integer=True), default=5,
                   help="identification: random seeds per solver (the paper's Table 3 "
                   "repeats; default 5)")
    s.add_argument("--budget", type=number(1, 10**8, integer=True), default=60_000,
                   help="evaluations per swarm run")


def main(args):
    if args.what == "learning":
        return learning(args)
    from piezo_stage.apps.studies import identification
    from piezo_stage.progress import bar
    with bar("study: identifications", total=2 + 3 * args.seeds, unit=" fits") as b:
        rep = identification.run(args.out, seeds=args.seeds, budget=args.budget,
                                 progress=lambda m: b.write(m, file=sys.stderr),
                                 step=lambda: b.update(1))
    identification.print_report(rep)
    print(f"plots and study.json in {args.out}")
    return 0


def learning(args):
    import json

    from piezo_stage.apps.studies import learning
    from piezo_stage.io.files import atomic_write
    from piezo_stage.progress import bar
    with bar("study: learning runs", total=2 * len(learning.cases()), unit=" runs") as b:
        rows = learning.run(args.periods, args.model_error, progress=lambda: b.update(1),
                            rate_hz=args.rate)
    learning.print_report(rows)
    if args.json:
        with atomic_write(args.json) as fh:
            json.dump({"cases": rows}, fh, indent=1)
        print(f"json: {args.json}")
    return 0
