"""`piezo-stage launch`: the ROS 2 node set (our launcher)."""

from __future__ import annotations

from piezo_stage.cli._common import COMPOSITIONS, namespace, number, param_overrides, port

HELP = "start the ROS 2 node set"


def add_arguments(s):
    s.add_argument("config", nargs="?", help="node parameters YAML (default config/stage.yaml)")
    s.add_argument("--record", metavar="DIR", help="record a bag to DIR ('auto': bags/<time>)")
    s.add_argument("--duration", type=number(0, 10**7, lo_open=True), metavar="S",
                   help="run S seconds after the stage arms, on its own clock (lockstep: "
                   "sample time), then stop; the start-up is not counted (with "
                   "--managed, or without a driver: S seconds from the launch)")
    s.add_argument("--namespace", type=namespace, default="/stage")
    s.add_argument("--rate", type=_rate, metavar="HZ|auto",
                   help="the loop's control rate [Hz] (its three nodes' control_rate_hz), "
                   "or auto: real time at the configured rate where this host holds it "
                   "with margin, else again at the lower rate the refusal names (four runs "
                   "at most) "
                   "(docs/realtime.md)")
    s.add_argument("--no-arm", action="store_true", help="start disarmed and stay so "
                   "until armed on the arm service")
    s.add_argument("--managed", action="store_true",
                   help="leave the stage driver's lifecycle to an outside manager: it "
                   "starts unconfigured (backend closed) and waits for configure and "
                   "activate on its lifecycle services (`piezo-stage lifecycle`, or any "
                   "lifecycle_msgs client)")
    s.add_argument("--no-trajectory", action="store_true",
                   help="leave the built-in trajectory node out: the set arms, holds "
                   "position and follows trajectories published by other nodes (the same "
                   "as 'kind: none' in the trajectory node's parameters)")
    s.add_argument("--foxglove", type=port, nargs="?", const=8765, metavar="PORT",
                   help="serve the running topics to Foxglove over WebSocket (default "
                   "port 8765)")
    s.add_argument("--params", action="append", metavar="FILE",
                   help="more node parameters over CONFIG's (e.g. from `tune`), may repeat")
    s.add_argument("--compose", choices=COMPOSITIONS,
                   help="which of the loop's nodes share a process (ROS's composition: "
                   "still separate nodes on the same topics): loop, the driver, "
                   "feedforward and controller; command, the feedforward and controller; "
                   "none, each its own (default: loop in lockstep, command in real "
                   "time, where it holds more samples a second on two cores; "
                   "docs/realtime.md)")
    s.add_argument("--watch", action="store_true",
                   help="the gap node watches the live gap against the model in use: where "
                   "it rises clearly, it names the effect that grew and hands a refit "
                   "with it to the feedforward when that shrinks the gap on the newest "
                   "data (docs/watch.md)")
    s.add_argument("--seed", type=number(0, 2**31 - 1, integer=True), metavar="N",
                   help="the simulated stage's noise seed (default: its config's): a "
                   "second run to hold out must differ from the first")


def main(args):
    from piezo_stage.launcher.running import begin_look
    with begin_look(args.namespace) as look:  # beside the imports and the config's checks
        return _launch(args, look)


def _launch(args, look):
    from piezo_stage.io.bag import new_bag_dir
    from piezo_stage.launcher.launcher import Launch, LaunchOptions
    from piezo_stage.paths import default_config
    record = args.record
    if record == "auto":
        record = new_bag_dir("bags")
    overrides = param_overrides(args.params)
    if args.seed is not None:
        overrides.setdefault("stage_driver", {})["seed"] = args.seed
    launch = Launch(args.config or default_config("stage.yaml"), LaunchOptions(record=record,
        namespace=args.namespace, arm=not args.no_arm, foxglove_port=args.foxglove,
        overrides=overrides, trajectory=not args.no_trajectory, managed=args.managed,
        armed_s=args.duration, rate=args.rate, compose=args.compose, watch=args.watch),
        look=look)
    if args.foxglove is not None:
        print(f"live view: ws://127.0.0.1:{args.foxglove} (Foxglove: Open connection, "
              "Foxglove WebSocket)", flush=True)
    print(f"launch: {', '.join(launch.nodes)} in {launch.ns} "
          f"({'lockstep' if launch.lockstep else 'real time'}"
          + ((f", for {args.duration:g} s after arming" if launch.armed_s is not None
              else f", for {args.duration:g} s") if args.duration else ", until Ctrl-C")
          + f"; {_composition(launch)}"
          + ("; the driver unconfigured until a manager configures and activates it"
             if args.managed else "")
          + "; Ctrl-C stops them in order, the driver first)", flush=True)
    rc = launch.run(launch.wall_bound() if launch.armed_s is not None else args.duration)
    if record:
        import os
        import sys
        if not os.path.isdir(record):
            print(f"no bag: the recorder was stopped before it opened {record}")
            return rc or 1
        print(f"bag: {record}")
        samples = _samples(record, launch.ns)
        if samples == 0:
            sys.stderr.write(f"piezo-stage launch: {record} holds no sample of "
                             f"{launch.ns}/joint_states: the set was stopped before its "
                             "driver published one (during its start-up)\n")
            return rc or 1
    return rc


def _composition(launch) -> str:
    """Which nodes share a process, in words (the launch's first line)."""
    if not launch.composed:
        return "each node in its own process"
    return f"{' + '.join(launch.composed)} composed in one process"


def _rate(text):
    """argparse type: auto, or a rate in Hz."""
    import argparse
    if text == "auto":
        return text
    try:
        return number(1.0, 1e5)(text)
    except argparse.ArgumentTypeError:
        raise argparse.ArgumentTypeError(f"{text!r}: give auto or a rate in Hz "
                                         "(1-100000)") from None


def _samples(bag, ns) -> int:
    """How many of the driver's samples (joint_states) a bag holds (-1: unreadable)."""
    from piezo_stage.core.errors import DataError
    from piezo_stage.io.bag import iter_messages
    try:
        return sum(1 for _ in iter_messages(bag, topics=[f"{ns.rstrip('/')}/joint_states"],
                                            on_damage=lambda line: None))
    except (DataError, OSError):
        return -1
