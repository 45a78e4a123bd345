"""`piezo-stage lifecycle`: read or set a managed node's lifecycle state, as
`ros2 lifecycle get|set` would (the ros2 CLI is not installed here)."""

from __future__ import annotations

from piezo_stage.cli._common import namespace, number

HELP = "read or set a managed node's lifecycle state (the stage driver's)"


def add_arguments(s):
    s.add_argument("node", help="the node: stage_driver (in --namespace) or a full name "
                   "such as /stage/stage_driver")
    s.add_argument("target", nargs="?", help="a transition (configure, activate, "
                   "deactivate, cleanup, shutdown) or a state to reach (unconfigured, "
                   "inactive, active, finalized); none: print the state and the "
                   "transitions available")
    s.add_argument("--namespace", type=namespace, default="/stage",
                   help="for a relative node name")
    s.add_argument("--timeout", type=number(0, 600, lo_open=True), default=10.0,
                   metavar="S", help="how long to wait for the node's services [s]")


def main(args):
    import os

    from piezo_stage.cli._common import client_transport
    from piezo_stage.core.errors import ConfigError
    from piezo_stage.launcher.lifecycle import STATES, TRANSITIONS, drive, full_name
    from piezo_stage.process import teardown
    if args.target is not None and args.target not in TRANSITIONS + STATES:
        raise ConfigError(f"{args.target!r}: give a transition ({', '.join(TRANSITIONS)}) "
                          f"or a state ({', '.join(STATES)})")
    client_transport()
    teardown.at_end()  # its participant torn down after its outcome is said, bounded
    drive(full_name(args.node, args.namespace), args.target,
          int(os.environ.get("ROS_DOMAIN_ID") or 0), args.timeout)
    return 0
