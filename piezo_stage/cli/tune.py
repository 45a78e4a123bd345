"""`piezo-stage tune`: PID gains from the identified model, or from a relay experiment
on the running stage."""

from __future__ import annotations

import os
import sys

from piezo_stage.cli._common import die, number, param_overrides

HELP = "PID gains from the identified model or a relay experiment"


def add_arguments(s):
    s.add_argument("model", nargs="?", help="model file to tune from (its dynamics and "
                   "delay are used when present); not with --relay")
    s.add_argument("--rate", type=number(1, 1_000_000), default=1000.0, help="control rate [Hz]")
    s.add_argument("--phase-margin", type=number(0, 90, lo_open=True), default=60.0, metavar="DEG")
    s.add_argument("--gain-margin", type=number(0, 60, lo_open=True), default=10.0, metavar="DB")
    s.add_argument("--latency", type=number(0, 100), default=1.0, metavar="PERIODS",
                   help="model: sample-to-applied latency of the loop [periods] (lockstep: "
                   "1; a relay experiment measures it)")
    s.add_argument("--out", metavar="PARAMS.yaml", help="write a parameter file that "
                   "`launch --params` and `experiment --params` take")
    r = s.add_argument_group("relay experiment (the node set runs; nothing is assumed "
                             "about the stage)")
    r.add_argument("--relay", metavar="CONFIG.yaml", nargs="?", const="",
                   help="run it with these node parameters (default config/stage.yaml)")
    r.add_argument("--plant", metavar="CONFIG.yaml", help="simulated plant")
    r.add_argument("--model", dest="ff_model", metavar="MODEL.yaml",
                   help="the feedforward's model for the hold voltage (default: the "
                   "config's; the relay's bias adapts either way)")
    r.add_argument("--mode", choices=("lockstep", "realtime"), default="lockstep")
    r.add_argument("--params", action="append", metavar="FILE",
                   help="more node parameters, may repeat")
    r.add_argument("--relay-amplitude", type=number(0, 150, lo_open=True), default=2.0,
                   metavar="V")
    r.add_argument("--relay-hysteresis", type=number(0, 100), default=0.0, metavar="UM",
                   help="0 unless the sensor noise makes the relay chatter")
    r.add_argument("--setpoint", type=number(-1000, 1000), default=30.0, metavar="UM")
    r.add_argument("--duration", type=number(0, 3600, lo_open=True), default=3.0, metavar="S")
    r.add_argument("--record", metavar="DIR", help="keep the relay run's bag here")


def main(args):
    from piezo_stage.core.loop.tuning import tune
    from piezo_stage.io.files import atomic_write
    if (args.model is None) == (args.relay is None):
        die("tune: give a MODEL or --relay [CONFIG], one of them")
    if args.relay is None:
        from piezo_stage.io.model_file import load_model
        model, effects = load_model(args.model)
        res = tune(model, effects, rate_hz=args.rate, phase_margin_deg=args.phase_margin,
                   gain_margin_db=args.gain_margin, latency_periods=args.latency)
    else:
        res = _relay(args)
        if res is None:
            return 1
    print(res.summary())
    if args.out:
        with atomic_write(args.out) as fh:
            fh.write(res.params_yaml())
        print(f"parameters: {args.out} (piezo-stage launch CONFIG --params {args.out})")
    return 0


def _relay(args):
    """The relay experiment through the node set, then the tuning from its points;
    None (after one line on stderr) when the node set failed."""
    import tempfile

    from piezo_stage.apps.experiments import run_relay
    from piezo_stage.core.loop.tuning import tune_relay
    from piezo_stage.paths import default_config
    if args.rate != 1000.0:
        die("tune --relay: the node set runs at 1000 Hz (--rate is for a model)")
    if not (0 < args.relay_amplitude <= 75 and 0 <= args.relay_hysteresis <= 50
            and args.duration > 0):
        die("tune --relay: amplitude in (0, 75] V, hysteresis in [0, 50] um, duration > 0")
    if args.plant:  # ConfigError / DataError (exit 2) with where
        from piezo_stage.io.plant_file import load_plant_config
        load_plant_config(args.plant)
    if args.ff_model:
        from piezo_stage.io.model_file import load_model
        load_model(args.ff_model)
    config = args.relay or default_config("stage.yaml")
    out = args.record or tempfile.mkdtemp(prefix="piezo_relay_")
    bag = os.path.join(out, "relay")
    print(f"relay experiment: both axes held at {args.setpoint:g} um, relay +-"
          f"{args.relay_amplitude:g} V (hysteresis {args.relay_hysteresis:g} um), "
          f"{args.duration:g} s, {args.mode}", flush=True)
    try:
        points = run_relay(bag, config, args.plant, args.ff_model, args.mode, args.setpoint,
                           args.duration, args.relay_amplitude, args.relay_hysteresis,
                           extra=param_overrides(args.params))
    except RuntimeError as e:
        sys.stderr.write(f"piezo-stage tune: {e}\n")
        return None
    res = tune_relay(points, 1000.0, args.phase_margin, args.gain_margin,
                     source=f"relay experiment, bag {bag}")
    if args.record:
        print(f"bag: {bag}")
    return res
