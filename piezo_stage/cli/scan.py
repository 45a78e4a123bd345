"""`piezo-stage scan`: a step scan against a running set: move, settle (on target), dwell
while a detector would integrate, next point. Per point the settle time and the
position during the dwell (mean and spread) go to a CSV beside the scan's bag."""

from __future__ import annotations

import argparse

from piezo_stage.cli._common import namespace, number, pair

HELP = "a step scan on a running set: move, settle, dwell, next point (per-point CSV)"
COLUMNS = ("point", "x_um", "y_um", "settle_ms", "x_mean_um", "y_mean_um", "x_std_um",
           "y_std_um", "samples", "elapsed_s")


def _grid(text):
    try:
        nx, ny = (int(x) for x in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r}: give two whole numbers, NX,NY") \
            from None
    if not (1 <= nx <= 10_000 and 1 <= ny <= 10_000):
        raise argparse.ArgumentTypeError(f"{text!r}: each within 1-10,000")
    return nx, ny


def add_arguments(s):
    s.add_argument("--grid", type=_grid, default=(5, 5), metavar="NX,NY",
                   help="points along x and y (a z-stack along x: N,1)")
    s.add_argument("--size", type=pair, default=[20.0, 20.0], metavar="X,Y",
                   help="the scan's extent [um] (first to last point)")
    s.add_argument("--center", type=pair, default=[40.0, 40.0], metavar="X,Y",
                   help="the scan's centre [um]")
    s.add_argument("--dwell-ms", type=number(0.0, 600_000.0), default=20.0, metavar="MS",
                   help="time at rest on each point, from its on-target [ms]")
    s.add_argument("--tol-um", type=number(1e-4, 100.0), default=None, metavar="T",
                   help="on-target tolerance [um] (default: the stage's)")
    s.add_argument("--settle-ms", type=number(0.0, 10_000.0), default=None, metavar="S",
                   help="settling window [ms] (default: the stage's)")
    s.add_argument("--timeout", type=number(0, 3600, lo_open=True), default=10.0,
                   metavar="S", help="seconds to wait for each point's on-target")
    s.add_argument("--record", default=None, metavar="BAG",
                   help="record the scan to this MCAP bag (its points beside it, "
                   "BAG.points.csv)")
    s.add_argument("--out", default=None, metavar="CSV",
                   help="the per-point table (default: BAG.points.csv, or scan.csv)")
    s.add_argument("--namespace", type=namespace, default="/stage", help="the set's namespace")


def points(grid, size, center) -> list[tuple[float, float]]:
    """The scan's points, row by row, each row the other way round (serpentine)."""
    nx, ny = grid
    xs = [center[0] + size[0] * ((i / (nx - 1)) - 0.5) if nx > 1 else center[0]
          for i in range(nx)]
    ys = [center[1] + size[1] * ((j / (ny - 1)) - 0.5) if ny > 1 else center[1]
          for j in range(ny)]
    return [(x, y) for j, y in enumerate(ys) for x in (xs if j % 2 == 0 else xs[::-1])]


def main(args):
    import contextlib
    import os
    import sys
    import time

    from piezo_stage.cli._common import client_transport, die
    from piezo_stage.cli.move import EXIT_FAULT, EXIT_NO_STAGE, EXIT_TIMEOUT
    from piezo_stage.client import MoveTimeout, NoStage, Stage, StageError, StageFault
    from piezo_stage.process import teardown
    client_transport()  # off shared memory, as move (its recorder, if it starts one, too)
    teardown.at_end()  # its participant torn down after its outcome is said, bounded
    out = args.out or (f"{args.record.rstrip(os.sep)}.points.csv" if args.record
                       else "scan.csv")
    from piezo_stage.io.files import check_output
    check_output(out)  # before the scan, not after it
    pts = points(args.grid, args.size, args.center)
    rows: list[tuple] = []
    t_start = time.monotonic()
    try:
        with Stage(args.namespace, timeout=min(args.timeout, 30.0)) as stage:
            rec = stage.record(args.record) if args.record else contextlib.nullcontext()
            with rec:
                for k, (x, y) in enumerate(pts):
                    t0 = time.monotonic()
                    done = stage.move_to(x, y, args.tol_um, args.settle_ms, args.timeout)
                    d = stage.dwell(args.dwell_ms * 1e-3, done.stamp_ns)
                    rows.append((k, x, y, done.settle_s * 1e3, d.mean_um["x"],
                                 d.mean_um["y"], d.std_um["x"], d.std_um["y"], d.samples,
                                 time.monotonic() - t0))
    except NoStage as e:
        die(str(e), EXIT_NO_STAGE)
    except StageError as e:  # the points done are kept, said so
        if rows:
            _write(out, rows)
        die(f"point {len(rows) + 1} of {len(pts)}: {e}" + (
            f" ({len(rows)} points done: {out})" if rows else ""),
            EXIT_FAULT if isinstance(e, StageFault) else EXIT_TIMEOUT
            if isinstance(e, MoveTimeout) else 2)
    _write(out, rows)
    settle = sorted(r[3] for r in rows)
    sys.stdout.write(f"{out}: {len(rows)} points in {time.monotonic() - t_start:.1f} s; "
                     f"settle median {settle[len(settle) // 2]:.1f} ms, max "
                     f"{settle[-1]:.1f} ms" + (f"; bag {args.record}" if args.record
                                               else "") + "\n")
    return 0


def _write(out: str, rows: list[tuple]) -> None:
    from piezo_stage.io.csv_table import write_table
    write_table(out, {c: [r[i] for r in rows] for i, c in enumerate(COLUMNS)})
