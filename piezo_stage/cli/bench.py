"""`piezo-stage bench`: the performance benchmarks (figures as ratios)."""

from __future__ import annotations

HELP = "performance benchmarks (figures as ratios)"


def add_arguments(s):
    s.add_argument("what", choices=("plant", "identify", "loop", "gap", "realtime",
                                    "faults", "liveview", "signals"))
    s.add_argument("--track", type=float, default=20.0, metavar="S",
                   help="realtime: seconds of the seed's trajectory")
    s.add_argument("--samples", type=int, default=2_000_000)
    s.add_argument("--trials", type=int, default=108, metavar="N",
                   help="signals: processes to start and signal (each kind in turn)")


def main(args):
    from piezo_stage import bench
    return bench.main(args)
