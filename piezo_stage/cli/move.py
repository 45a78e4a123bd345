"""`piezo-stage move X Y`: move a running set's stage and wait until it is on target, as
a vendor's ``MOV`` and ``ONT?`` would (piezo_stage.client underneath)."""

from __future__ import annotations

from piezo_stage.cli._common import namespace, number

HELP = "move a running set's stage to X Y [um] and wait until it is on target"

# exit codes beyond 0 (on target) and 2 (usage): what went wrong, for a script to tell
EXIT_FAULT, EXIT_NO_STAGE, EXIT_TIMEOUT = 1, 4, 5


def add_arguments(s):
    s.add_argument("x", type=number(-1e4, 1e4), help="target x [um]")
    s.add_argument("y", type=number(-1e4, 1e4), help="target y [um]")
    s.add_argument("--tol-um", type=number(1e-4, 100.0), default=None, metavar="T",
                   help="on-target tolerance [um] (default: the stage's, "
                   "on_target_tol_um)")
    s.add_argument("--settle-ms", type=number(0.0, 10_000.0), default=None, metavar="S",
                   help="the settling window the stage must stay within the tolerance "
                   "for [ms] (default: the stage's, on_target_window_ms)")
    s.add_argument("--timeout", type=number(0, 3600, lo_open=True), default=10.0,
                   metavar="S", help="seconds to wait for on target (exit 5 after)")
    s.add_argument("--namespace", type=namespace, default="/stage", help="the set's namespace")


def main(args):
    import sys

    from piezo_stage.cli._common import client_transport, die
    from piezo_stage.client import MoveRefused, MoveTimeout, NoStage, Stage, StageFault
    from piezo_stage.process import teardown
    client_transport()
    teardown.at_end()  # its participant torn down after its outcome is said, bounded
    try:
        with Stage(args.namespace, timeout=min(args.timeout, 30.0)) as stage:
            done = stage.move_to(args.x, args.y, args.tol_um, args.settle_ms, args.timeout)
    except NoStage as e:
        die(str(e), EXIT_NO_STAGE)
    except StageFault as e:
        die(str(e), EXIT_FAULT)
    except MoveTimeout as e:
        die(str(e), EXIT_TIMEOUT)
    except MoveRefused as e:  # the target: a data error
        die(str(e))
    err = ", ".join(f"{a} {e:+.3f} um" for a, e in done.error_um.items())
    sys.stdout.write(f"on target at ({args.x:g}, {args.y:g}) um: settled in "
                     f"{done.settle_s * 1e3:.1f} ms, error {err} ({done.move_id}, "
                     f"{done.elapsed_s:.2f} s waited)\n")
    return 0
