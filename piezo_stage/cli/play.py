"""`piezo-stage play`: a voltage waveform played on a backend's own clock, recorded."""

from __future__ import annotations

import numpy as np

from piezo_stage.cli._common import number

HELP = "play a voltage waveform (excite or invert CSV) on a stage and record it"
DEVICE_FORMS = {"pi": "tcp:HOST[:PORT], serial:DEVICE[:BAUD] or usb:SERIAL:PID",
                "nv200": "tcp:HOST[:PORT],tcp:HOST[:PORT] for x and y",
                "daq": "the device name, e.g. Dev1"}


def add_arguments(s):
    from piezo_stage.drivers.playback import PLAY_BACKENDS
    s.add_argument("inp", metavar="WAVE.csv", help="CSV with t,vx,vy (s, V), as excite "
                   "and invert write it, or t and one axis's column (the other held at "
                   "the driver's safe voltage)")
    s.add_argument("--backend", choices=PLAY_BACKENDS, default="sim",
                   help="sim: the simulated stage; pi: a PI controller's wave generator "
                   "and data recorder (pipython); nv200: two NV200 amplifiers' "
                   "generators and recorders, at most 1024 points (nv200); daq: NI-DAQ "
                   "hardware-timed (nidaqmx)")
    s.add_argument("--config", help="sim: the simulated stage's plant YAML (default "
                   "config/sim_stage.yaml)")
    s.set_defaults(model=None)
    s.add_argument("--params", help="pi, daq: a node-parameters YAML (as launch takes): "
                   "the stage_driver's backend parameters (limits, slew, channels, "
                   "pi_axes...) and safe_voltage_V, safe_ramp_V_per_s")
    s.add_argument("--device", help="pi: the controller (tcp:HOST[:PORT], "
                   "serial:DEVICE[:BAUD], usb:SERIAL:PID); nv200: the two amplifiers, "
                   "x and y, comma separated (tcp:HOST[:PORT],tcp:HOST[:PORT]); daq: "
                   "the device name (Dev1)")
    s.add_argument("--seed", type=number(0, 2**32 - 1, integer=True),
                   help="sim: noise seed (overrides the config)")
    s.add_argument("--out", required=True, help="the record: CSV t,vx,vy,wx,wy (as "
                   "simulate writes) or, without .csv, a bag folder")


def main(args):
    from piezo_stage.cli._common import load_plant, param_overrides
    from piezo_stage.core.errors import DataError
    from piezo_stage.core.estimation.record import Record
    from piezo_stage.core.loop.arming import ArmingParams
    from piezo_stage.drivers.playback import play_record
    from piezo_stage.io.csv_table import read_record, write_table
    rec = read_record(args.inp, need_w=False)  # both axes, or one (the other at rest)
    if len(rec) < 2:
        raise DataError(f"{args.inp}: a waveform needs at least two samples")
    params = param_overrides([args.params]).get("stage_driver", {}) if args.params else {}
    given = {"daq": "ao_channels", "pi": "pi_address", "nv200": "nv200_addresses"}
    if args.backend in given and not args.device and given[args.backend] not in params:
        raise DataError(f"--backend {args.backend} needs --device (which controller: "
                        f"{DEVICE_FORMS[args.backend]}), or {given[args.backend]} in --params")
    if args.device:
        if args.backend == "daq":
            for key, default in (("ao_channels", ["Dev1/ao0", "Dev1/ao1"]),
                                 ("ai_channels", ["Dev1/ai0", "Dev1/ai1"])):
                params[key] = [f"{args.device}/{ch.split('/', 1)[-1]}"
                               for ch in params.get(key, default)]
        elif args.backend == "nv200":
            params["nv200_addresses"] = args.device.split(",")
        else:
            params["pi_address"] = args.device
    arm = ArmingParams()
    safe = float(params.pop("safe_voltage_V", arm.safe_V))
    ramp = float(params.pop("safe_ramp_V_per_s", arm.ramp_V_per_s))
    # an axis the waveform leaves out is held at the driver's safe voltage
    rec = Record(rec.t, {a: rec.v.get(a, np.full(len(rec), safe)) for a in ("x", "y")},
                 source=args.inp)
    cfg = load_plant(args, rec.fs_hz) if args.backend == "sim" else None
    out = play_record(args.backend, rec, params, cfg, safe, ramp)
    if args.out.lower().endswith(".csv"):
        write_table(args.out, {"t": out.t, "vx": out.v["x"], "vy": out.v["y"],
                               "wx": out.w["x"], "wy": out.w["y"]})
    else:
        import os
        import shutil
        import tempfile

        from piezo_stage.io.bag import write_record_bag
        parent = os.path.dirname(os.path.abspath(args.out))
        os.makedirs(parent, exist_ok=True)  # --out DIR/run1: DIR is made
        tmp = tempfile.mkdtemp(prefix=".play-", dir=parent)
        try:
            write_record_bag(os.path.join(tmp, "bag"), out, metadata={
                "piezo_stage_play": {"waveform": os.path.abspath(args.inp),
                                     "backend": args.backend, "played_on": out.source}})
            if os.path.exists(args.out):
                raise DataError(f"--out {args.out} exists; give a new bag folder")
            os.rename(os.path.join(tmp, "bag"), args.out)
        finally:
            shutil.rmtree(tmp, ignore_errors=True)
    print(f"played {len(rec)} samples at {rec.fs_hz:g} Hz on {out.source.split(' on ', 1)[-1]}"
          f": wrote {args.out}")
    return 0
