"""`piezo-stage replay`: a recorded bag republished on its topics."""

from __future__ import annotations

from piezo_stage.cli._common import namespace, number
from piezo_stage.core.errors import DataError

HELP = "republish a recorded bag on its topics"


def add_arguments(s):
    s.add_argument("bag")
    s.add_argument("--rate", type=number(0, 1000), default=1.0,
                   help="playback speed (1: original timing; 0: as fast as possible)")
    s.add_argument("--namespace", type=namespace, default=None,
                   help="replace the recorded namespace")
    s.add_argument("--duration", type=number(0, 10**7, lo_open=True), metavar="S",
                   help="replay the record's first S seconds (the record's time, "
                   "whatever --rate)")


def main(args):
    import math

    from piezo_stage.apps.replay import replay
    from piezo_stage.process import teardown
    teardown.at_end()  # its participant torn down after its outcome is said, bounded
    if not (math.isfinite(args.rate) and args.rate >= 0):
        raise DataError(f"--rate {args.rate}: must be a finite number >= 0 (0: as fast as "
                        "possible)")
    return replay(args.bag, args.rate, args.namespace, duration_s=args.duration)
