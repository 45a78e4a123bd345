"""`piezo-stage tune`: PID gains from the identified model."""

from __future__ import annotations

HELP = "PID gains from the identified model"


def add_arguments(s):
    s.add_argument("model", help="model file (its dynamics and delay are used when present)")
    s.add_argument("--rate", type=float, default=1000.0, help="control rate [Hz]")
    s.add_argument("--phase-margin", type=float, default=60.0, metavar="DEG")
    s.add_argument("--gain-margin", type=float, default=10.0, metavar="DB")
    s.add_argument("--latency", type=float, default=1.0, metavar="PERIODS",
                   help="sample-to-applied latency of the loop [periods] (lockstep: 1)")
    s.add_argument("--out", metavar="PARAMS.yaml", help="write a parameter file that "
                   "`launch --params` and `experiment --params` take")


def main(args):
    from piezo_stage.core.tuning import tune
    from piezo_stage.io.files import atomic_write
    from piezo_stage.io.model_file import load_model
    model, effects = load_model(args.model)
    res = tune(model, effects, rate_hz=args.rate, phase_margin_deg=args.phase_margin,
               gain_margin_db=args.gain_margin, latency_periods=args.latency)
    print(res.summary())
    if args.out:
        with atomic_write(args.out) as fh:
            fh.write(res.params_yaml())
        print(f"parameters: {args.out} (piezo-stage launch CONFIG --params {args.out})")
    return 0
