"""`piezo-stage demo`: the main job, the node set on the simulated stage."""

from __future__ import annotations

from piezo_stage.cli._common import namespace, number

HELP = "the main job: node set on the simulated stage"


def add_arguments(s):
    s.add_argument("--out", help="bag directory (default bags/<timestamp>)")
    s.add_argument("--excite", type=number(0, 600), default=3.0,
                   help="excitation before tracking [s]")
    s.add_argument("--track", type=number(0, 600, lo_open=True), default=1.0,
                   help="tracking of the paper's 10 Hz "
                   "trajectory [s]")
    s.add_argument("--namespace", type=namespace, default="/stage")


def main(args):
    from piezo_stage.apps.demo import run_demo
    return run_demo(args)
