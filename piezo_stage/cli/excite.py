"""`piezo-stage excite`: a diagnostic excitation (t, vx, vy)."""

from __future__ import annotations

from piezo_stage.cli._common import number
from piezo_stage.core.errors import DataError
from piezo_stage.core.estimation.excitation import CHIRP_S

HELP = "write a diagnostic excitation (t,vx,vy)"


def add_arguments(s):
    s.add_argument("--protocol", choices=("gap",), default="gap")
    s.add_argument("--out", default="excite_gap.csv")
    s.add_argument("--rate", type=number(10, 200_000), default=5000.0, help="sample rate [Hz]")
    s.add_argument("--seed", type=number(0, 2**32 - 1, integer=True), default=0,
                   help="varies amplitudes and step levels")
    s.add_argument("--v-min", type=number(-1000, 1000), default=0.0)
    s.add_argument("--v-max", type=number(-1000, 1000), default=150.0)
    s.add_argument("--chirp", type=number(0, 60), default=CHIRP_S, metavar="S", help="the small "
                   "chirp per axis up to 0.4 x the rate, S seconds (tells a resonance from "
                   "a delay; default %(default)g, 0: none)")
    s.add_argument("--nested", action="store_true", help="add nested minor loops (1 Hz "
                   "at 100/66/33 %% of the span, and loops inside the major one), which "
                   "show a hysteresis's memory; about 22 s more")


def main(args):
    from piezo_stage.core.estimation.excitation import gap_protocol
    from piezo_stage.io.csv_table import write_table
    if not 0 <= args.chirp <= 60:
        raise DataError(f"--chirp {args.chirp:g}: give 0 (none) to 60 seconds")
    t, vx, vy = gap_protocol(args.rate, args.v_min, args.v_max, seed=args.seed,
                             chirp_s=args.chirp, nested=args.nested)
    write_table(args.out, {"t": t, "vx": vx, "vy": vy})
    print(f"{args.out}: {len(t)} samples, {t[-1]:.1f} s at {args.rate:g} Hz "
          f"(protocol {args.protocol}, seed {args.seed})")
    return 0
