"""`piezo-stage raster`: a raster scan as a trajectory file (t, wx, wy)."""

from __future__ import annotations

from piezo_stage.cli._common import number, pair

HELP = "write a raster scan trajectory (t,wx,wy): fast-axis triangle, slow-axis steps"


def add_arguments(s):
    s.add_argument("--out", default="raster.csv", help="trajectory CSV (t,wx,wy)")
    s.add_argument("--line-rate", type=number(0, 10_000, lo_open=True), default=20.0,
                   metavar="HZ", help="line periods (trace and retrace) per second")
    s.add_argument("--lines", type=number(2, 100_000, integer=True), default=16)
    s.add_argument("--size", type=pair, default=[40.0, 40.0], metavar="FAST,SLOW",
                   help="scan size [um]")
    s.add_argument("--center", type=pair, default=[40.0, 40.0], metavar="FAST,SLOW",
                   help="scan centre [um]")
    s.add_argument("--corner", type=number(0, 0.5), default=0.1,
                   help="share of each line spent turning around")
    s.add_argument("--slow", choices=("steps", "ramp"), default="steps")
    s.add_argument("--fast-axis", choices=("x", "y"), default="x")
    s.add_argument("--dt", type=number(1e-6, 1.0), default=1e-3, metavar="S",
                   help="point spacing [s]")


def main(args):
    from piezo_stage.core.loop.trajectory import raster
    from piezo_stage.io.csv_table import write_table
    t, w = raster(args.line_rate, args.lines, args.size, args.center, args.corner,
                  args.slow, args.fast_axis, args.dt)
    write_table(args.out, {"t": t, "wx": w["x"], "wy": w["y"]})
    print(f"{args.out}: {len(t)} points, {args.lines} lines at {args.line_rate:g} Hz "
          f"({t[-1]:.3f} s), {args.size[0]:g} x {args.size[1]:g} um around "
          f"({args.center[0]:g}, {args.center[1]:g}) um, fast axis {args.fast_axis}")
    return 0
