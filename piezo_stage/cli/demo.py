"""`piezo-stage demo`: the main job, the node set on the simulated stage."""

from __future__ import annotations

HELP = "the main job: node set on the simulated stage"


def add_arguments(s):
    s.add_argument("--out", help="bag directory (default bags/<timestamp>)")
    s.add_argument("--excite", type=float, default=3.0, help="excitation before tracking [s]")
    s.add_argument("--track", type=float, default=1.0, help="tracking of the seed's 10 Hz "
                   "trajectory [s]")
    s.add_argument("--namespace", default="/stage")


def main(args):
    from piezo_stage.demo import run_demo
    return run_demo(args)
