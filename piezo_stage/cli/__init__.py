"""The ``piezo-stage`` command: thin argument parsing over the core and io.

Every command turns bad input into one line on stderr and exit code 2; outputs are
written to a temporary file and renamed, so they are complete or absent.
"""

from __future__ import annotations

import argparse
import sys

import numpy as np

from piezo_stage.core.errors import DataError, PiezoStageError, SolverError

EXIT_USAGE = 2
EXIT_SOLVER = 3


class _Parser(argparse.ArgumentParser):
    def error(self, message):  # one line, exit 2 (argparse prints usage as well)
        sys.stderr.write(f"{self.prog}: error: {message}\n")
        sys.exit(EXIT_USAGE)


def _die(msg: str, code: int = EXIT_USAGE):
    sys.stderr.write(f"piezo-stage: error: {msg}\n")
    sys.exit(code)


# -- simulate ---------------------------------------------------------------------------

def _load_plant(args, rate_hz):
    from piezo_stage.core.plant import PlantConfig
    from piezo_stage.io.model_file import load_model
    from piezo_stage.io.plant_file import (
        default_plant_config_path,
        enabled_effects,
        load_plant_config,
    )
    if args.model:
        model, effects = load_model(args.model)
        cfg = PlantConfig.exact(model, rate_hz)
        cfg.effects = enabled_effects(effects)
    else:
        cfg = load_plant_config(args.config or default_plant_config_path())
    if getattr(args, "no_noise", False):
        cfg.noise_rms_um = 0.0
        cfg.quantization_um = 0.0
    if getattr(args, "seed", None) is not None:
        cfg.seed = args.seed
    return cfg


def _check_voltages(rec, limits, source):
    lo, hi = limits
    for a, v in rec.v.items():
        bad = np.flatnonzero((v < lo) | (v > hi))
        if bad.size:
            i = int(bad[0])
            raise DataError(f"{source}: v{a} = {v[i]:g} V at line {i + 2} is outside "
                                  f"the voltage limits [{lo:g}, {hi:g}] V")


def cmd_simulate(args):
    from piezo_stage.core.plant import Plant
    from piezo_stage.core.record import Record
    from piezo_stage.io.csv_table import read_table, write_table
    cols = read_table(args.inp, ["t", "vx", "vy"])
    rec = Record(cols["t"], {"x": cols["vx"], "y": cols["vy"]}, source=args.inp)
    cfg = _load_plant(args, rec.fs_hz)
    _check_voltages(rec, cfg.model.voltage_limits, args.inp)
    plant = Plant(cfg, rec.fs_hz)
    w = plant.run(rec.v["x"], rec.v["y"])
    for a, x in w.items():
        if not np.all(np.isfinite(x)):
            i = int(np.flatnonzero(~np.isfinite(x))[0])
            raise DataError(f"the simulated {a} displacement is not finite from line {i + 2} "
                            "on (the model diverges); nothing written")
    write_table(args.out, {"t": rec.t, "vx": rec.v["x"], "vy": rec.v["y"],
                           "wx": w["x"], "wy": w["y"]})
    return 0


# -- invert -----------------------------------------------------------------------------

def cmd_invert(args):
    from piezo_stage.core.inverse import invert_seed_eq12, invert_stage
    from piezo_stage.core.record import Record
    from piezo_stage.io.csv_table import read_table, write_table
    from piezo_stage.io.model_file import load_model
    model, _ = load_model(args.model)
    missing = sorted({"x", "y"} - set(model.axes))
    if missing:
        raise DataError(f"{args.model} has no model for axis {', '.join(missing)}: its "
                        "voltages cannot be computed (give a model with both axes)")
    cols = read_table(args.inp, ["t", "wx", "wy"])
    rec = Record(cols["t"], w={"x": cols["wx"], "y": cols["wy"]}, source=args.inp)
    if args.method == "exact":
        res = invert_stage(model, rec.w["x"], rec.w["y"])
    else:
        res = {a: invert_seed_eq12(m, rec.w[a], model.voltage_limits)
               for a, m in model.axes.items()}
    lo = model.voltage_limits[0]
    v = {a: res[a].v if a in res else np.full(len(rec), lo) for a in ("x", "y")}
    write_table(args.out, {"t": rec.t, "vx": v["x"], "vy": v["y"]})
    for a, r in res.items():
        if r.n_saturated:
            i = int(np.flatnonzero(r.saturated)[0])
            sys.stderr.write(
                f"piezo-stage: warning: axis {a}: {r.n_saturated} of {len(rec)} targets "
                f"unreachable within [{model.voltage_limits[0]:g}, "
                f"{model.voltage_limits[1]:g}] V, saturated (first at t = {rec.t[i]:g} s, "
                f"w = {rec.w[a][i]:g} um)\n")
    return 0


# -- loop (the first demo: a real run of the simulated stage) -------------------------------

def cmd_loop(args):
    from piezo_stage.core.metrics import loop_figures
    from piezo_stage.core.plant import Plant
    fs = args.rate
    cfg = _load_plant(args, fs)
    lo, hi = cfg.model.voltage_limits
    amp = min(args.amplitude, hi - lo)
    t = np.arange(int(round(args.cycles * fs / args.freq))) / fs
    v = lo + amp / 2 * (1 - np.cos(2 * np.pi * args.freq * t))
    plant = Plant(cfg, fs)
    per = int(round(fs / args.freq))
    print(f"simulated stage: {args.freq:g} Hz, 0-{amp:g} V sine, {args.cycles} cycles at "
          f"{fs:g} Hz, noise {cfg.noise_rms_um:g} um RMS")
    print(f"{'driven':>6} {'axis':>4} {'range_um':>9} {'width_um':>9} {'width_pct':>9} "
          f"{'mid_width_um':>12} {'closure_um':>10} {'coupling_pp_um':>14}")
    for drive in ("x", "y"):
        plant.reset()
        other = "y" if drive == "x" else "x"
        vx, vy = (v, np.full_like(v, lo)) if drive == "x" else (np.full_like(v, lo), v)
        plant.run(vx, vy)
        true = plant.last_true
        last, prev = slice(-per, None), slice(-2 * per, -per)
        fig = loop_figures(v[last], true[drive][last])
        closure = float(np.max(np.abs(true[drive][last] - true[drive][prev])))
        coupling = float(np.ptp(true[other][last]))
        print(f"{drive:>6} {drive:>4} {fig['range_um']:9.3f} {fig['max_width_um']:9.3f} "
              f"{fig['max_width_pct']:9.2f} {fig['mid_width_um']:12.3f} {closure:10.2e} "
              f"{coupling:14.3f}")
    return 0


# -- identify ---------------------------------------------------------------------------

def cmd_identify(args):
    import json
    import os

    from piezo_stage.core.duhem import StageModel
    from piezo_stage.core.identify import IdentifyOptions, identify_axis, validate_axis
    from piezo_stage.io.files import atomic_write
    from piezo_stage.io.model_file import save_model
    from piezo_stage.io.records import load_record
    rec = load_record(args.data)
    val = load_record(args.validate) if args.validate else None
    if args.voltage == "exact":
        rec.voltage_exact = True
        if val is not None:
            val.voltage_exact = True
    axes = ["x", "y"] if args.axis == "both" else [args.axis]
    axes = [a for a in axes if a in rec.v and a in rec.w]
    if not axes:
        raise DataError(f"{args.data}: no complete axis ({args.axis}) in the record")
    opts = IdentifyOptions(method=args.method,
                           structure="whole" if args.whole else "segmented",
                           budget=args.budget, seed=args.seed, coupling=args.coupling,
                           n=args.n, m=args.m)
    from piezo_stage.progress import bar, best_so_far
    results, report = {}, {}
    for a in axes:
        with bar(f"identify {a} ({opts.method})") as b:
            r = identify_axis(rec, a, opts, best_so_far(b))
        results[a] = r
        report[a] = r.to_json()
        if val is not None:
            report[a].update(validate_axis(r, val))
    print(f"{'axis':>4} {'method':>8} {'structure':>9} {'fit_rms_um':>10} {'fit_pct':>8} "
          f"{'max_err_um':>10} {'noise_um':>8} {'val_rms_um':>10} {'val_pct':>8} "
          f"{'evals':>7} {'seconds':>7}")
    for a, j in report.items():
        vr = j.get("validate_rms_um", float("nan"))
        vp = j.get("validate_rms_pct", float("nan"))
        print(f"{a:>4} {j['method']:>8} {j['structure']:>9} {j['fit_rms_um']:10.4f} "
              f"{j['fit_rms_pct']:8.4f} {j['max_err_um']:10.4f} {j['noise_floor_um']:8.4f} "
              f"{vr:10.4f} {vp:8.4f} {j['evaluations']:7d} {j['seconds']:7.2f}")
    for note in {n for r in results.values() for n in r.notes}:
        print(f"note: {note}")
    if args.out:
        v_all = np.concatenate([rec.v[a] for a in rec.v])
        limits = (float(np.floor(min(0.0, v_all.min()))), float(np.ceil(max(v_all.max(), 1.0))))
        model = StageModel({a: r.model for a, r in results.items()},
                           {a: r.coupling for a, r in results.items() if r.coupling},
                           limits)
        meta = {"identification": {a: {k: report[a][k] for k in report[a]
                                        if k not in ("history", "parameters")}
                                   for a in report}}
        meta["identification"]["source"] = os.fspath(args.data)
        save_model(args.out, model, extra=meta)
    if args.json:
        with atomic_write(args.json) as fh:
            json.dump(report, fh, indent=1)
    plot = args.plot or (os.path.splitext(args.out)[0] + ".png" if args.out else None)
    if plot:
        from piezo_stage.core.identify.api import predict_axis
        from piezo_stage.io.plots import identification_png
        curves = {a: predict_axis(r, rec) for a, r in results.items()}
        print(f"plot: {identification_png(plot, rec.t, curves)}")
    return 0


def cmd_study(args):
    from piezo_stage.progress import bar
    from piezo_stage.studies import identification
    with bar("study: identifications", total=2 + 3 * args.seeds, unit=" fits") as b:
        rep = identification.run(args.out, seeds=args.seeds, budget=args.budget,
                                 progress=lambda m: b.write(m, file=sys.stderr),
                                 step=lambda: b.update(1))
    identification.print_report(rep)
    print(f"plots and study.json in {args.out}")
    return 0


def cmd_excite(args):
    from piezo_stage.core.excitation import gap_protocol
    from piezo_stage.io.csv_table import write_table
    if not 0 <= args.chirp <= 60:
        raise DataError(f"--chirp {args.chirp:g}: give 0 (none) to 60 seconds")
    t, vx, vy = gap_protocol(args.rate, args.v_min, args.v_max, seed=args.seed,
                             chirp_s=args.chirp)
    write_table(args.out, {"t": t, "vx": vx, "vy": vy})
    print(f"{args.out}: {len(t)} samples, {t[-1]:.1f} s at {args.rate:g} Hz "
          f"(protocol {args.protocol}, seed {args.seed})")
    return 0


def cmd_gap(args):
    import json

    from piezo_stage.core.gap import diagnose
    from piezo_stage.io.files import atomic_write
    from piezo_stage.io.records import load_record
    fit = load_record(args.fit)
    hold = load_record(args.holdout) if args.holdout else None
    base, base_effects = None, None
    if args.model:
        from piezo_stage.io.model_file import load_model
        base, base_effects = load_model(args.model)
    if hold is not None and set(fit.w) != set(hold.w):
        raise DataError(f"FIT has axes {sorted(fit.w)} but HOLDOUT has {sorted(hold.w)}")
    from piezo_stage.progress import bar, steps
    with bar("gap: candidate fits", unit=" fits") as b:
        res = diagnose(fit, hold, base_model=base, base_effects=base_effects,
                       axes=None if args.axis == "both" else [args.axis], progress=steps(b))
    per = res.per_axis
    print(f"verdict: {res['verdict']} ({res['reason']})")
    print(f"{'axis':>4} {'effect':>9} {'rms_before':>10} {'rms_after':>9} {'gap_before':>10} "
          f"{'gap_after':>9} {'shrink_pct':>10}")
    for a, d in per.items():
        for r in d.ranking:
            print(f"{a:>4} {r['effect']:>9} {r['rms_before_um']:10.4f} {r['rms_after_um']:9.4f} "
                  f"{r['gap_before_um']:10.4f} {r['gap_after_um']:9.4f} {r['shrink_pct']:10.1f}")
    print(f"where: axis {res['where']['axis']}, band {res['where']['band_hz'][0]:g}-"
          f"{res['where']['band_hz'][1]:g} Hz, segment {res['where']['segment']}; noise floor "
          f"{res['noise_floor_um']:.4f} um; {res['seconds']:.1f} s")
    for a, d in per.items():
        if d.effects:
            print(f"effects {a} (in the order added): " + ", ".join(
                f"{s['effect']} (gap {s['gap_after_um']:.4f} um)" for s in d.effects))
        b = d.budget
        expl = ", ".join(f"{k} {v:.4f}" for k, v in b["explained_um"].items()) or "nothing"
        print(f"budget {a} [um]: residual {b['residual_rms_um']:.4f} = noise "
              f"{b['noise_floor_um']:.4f} + input-locked {b['input_locked_um']:.4f} + not "
              f"input-locked {b['not_input_locked_um']:.4f} in quadrature (closure "
              f"{b['closure_pct']:+.1f} %); gap {b['gap_um']:.4f}: explained {expl}, "
              f"unexplained {b['unexplained_um']:.4f}")
        if b.get("disturbance"):
            x = b["disturbance"]
            print(f"disturbance {a}: {x['rms_um']:.4f} um at {x['freq_hz']:.1f} Hz (band "
                  f"{x['band_hz'][0]:.1f}-{x['band_hz'][1]:.1f} Hz), not caused by the "
                  f"input; feedback bandwidth to reject it: >= "
                  f"{x['feedback_bandwidth_hz']:.0f} Hz")
    if args.json:
        with atomic_write(args.json) as fh:
            json.dump(res.json, fh, indent=1, default=float)
    if args.report:
        from piezo_stage.io.gap_report import write_report
        print(f"report: {write_report(args.report, res, hold or fit)}")
    if args.out_model:
        from piezo_stage.io.model_file import save_model
        model, effects = res.model(fit)
        save_model(args.out_model, model, effects=effects or None)
        print(f"model with the found effects: {args.out_model}")
    return 0


def _port(text):
    import argparse
    try:
        port = int(text)
    except ValueError:
        port = -1
    if not 1 <= port <= 65535:
        raise argparse.ArgumentTypeError(f"{text!r} is not a TCP port (1-65535)")
    return port


def cmd_launch(args):
    from piezo_stage.io.bag import new_bag_dir
    from piezo_stage.launch.launcher import Launch
    from piezo_stage.paths import default_config
    record = args.record
    if record == "auto":
        record = new_bag_dir("bags")
    from piezo_stage.cli.experiment import param_overrides
    launch = Launch(args.config or default_config("stage.yaml"), record=record,
                    namespace=args.namespace, arm=not args.no_arm,
                    foxglove_port=args.foxglove, overrides=param_overrides(args.params))
    if args.foxglove is not None:
        print(f"live view: ws://127.0.0.1:{args.foxglove} (Foxglove: Open connection, "
              "Foxglove WebSocket)", flush=True)
    rc = launch.run(args.duration)
    if record:
        print(f"bag: {record}")
    return rc


def cmd_demo(args):
    from piezo_stage.demo import run_demo
    return run_demo(args)


def cmd_replay(args):
    import math

    from piezo_stage.replay import replay
    if not (math.isfinite(args.rate) and args.rate >= 0):
        raise DataError(f"--rate {args.rate}: must be a finite number >= 0 (0: as fast as "
                        "possible)")
    return replay(args.bag, args.rate, args.namespace)


def cmd_bag(args):
    from piezo_stage.io.bag import repair_bag, scan_bag
    if args.action == "check":
        scan = scan_bag(args.bag)
        print(f"{args.bag}: {len(scan.messages)} readable messages on "
              f"{len(scan.channels)} topics; {scan.damage() or 'intact'}")
        return 0 if not scan.damage() else 1
    scan = repair_bag(args.bag)
    print(f"{args.bag}: rewritten with {len(scan.messages)} messages on "
          f"{len(scan.channels)} topics, a summary and metadata.yaml (original kept as "
          f"*.orig); it had: {scan.damage() or 'no damage'}")
    return 0


def cmd_bench(args):
    from piezo_stage import bench
    return bench.main(args)


def build_parser():
    p = _Parser(prog="piezo-stage", description=__doc__.splitlines()[0])
    sub = p.add_subparsers(dest="cmd", required=True, parser_class=_Parser)

    s = sub.add_parser("simulate", help="run a voltage record through the simulated stage")
    s.add_argument("--in", dest="inp", required=True, help="CSV with t,vx,vy (s, V)")
    s.add_argument("--out", required=True, help="output CSV t,vx,vy,wx,wy (wx, wy in um)")
    g = s.add_mutually_exclusive_group()
    g.add_argument("--config", help="plant config YAML (default config/sim_stage.yaml)")
    g.add_argument("--model", help="model file: the plant is exactly this model, nothing else")
    s.add_argument("--no-noise", action="store_true", help="no sensor noise or quantisation")
    s.add_argument("--seed", type=int, help="noise seed (overrides the config)")
    s.set_defaults(fn=cmd_simulate)

    s = sub.add_parser("invert", help="voltages that make a model follow a target")
    s.add_argument("--model", required=True, help="model file (YAML)")
    s.add_argument("--in", dest="inp", required=True, help="CSV with t,wx,wy (s, um)")
    s.add_argument("--out", required=True, help="output CSV t,vx,vy (V)")
    s.add_argument("--method", choices=("exact", "seed-eq12"), default="exact")
    s.set_defaults(fn=cmd_invert)

    s = sub.add_parser("excite", help="write a diagnostic excitation (t,vx,vy)")
    s.add_argument("--protocol", choices=("gap",), default="gap")
    s.add_argument("--out", default="excite_gap.csv")
    s.add_argument("--rate", type=float, default=5000.0, help="sample rate [Hz]")
    s.add_argument("--seed", type=int, default=0, help="varies amplitudes and step levels")
    s.add_argument("--v-min", type=float, default=0.0)
    s.add_argument("--v-max", type=float, default=150.0)
    s.add_argument("--chirp", type=float, default=0.0, metavar="S", help="add a small "
                   "chirp of S seconds per axis up to 0.4 x the rate (tells a resonance "
                   "from a delay)")
    s.set_defaults(fn=cmd_excite)

    s = sub.add_parser("gap", help="diagnose the sim-to-real gap")
    s.add_argument("fit", help="record to fit on (CSV t,vx,vy,wx,wy or bag)")
    s.add_argument("--holdout", help="a different record to score on")
    s.add_argument("--model", help="the sim's model (default: identified from FIT)")
    s.add_argument("--axis", choices=("x", "y", "both"), default="both")
    s.add_argument("--json", metavar="FILE")
    s.add_argument("--report", metavar="DIR", help="Markdown report with PNG plots")
    s.add_argument("--out-model", metavar="MODEL.yaml",
                   help="write the model with the found effect (simulate --model uses it)")
    s.set_defaults(fn=cmd_gap)

    s = sub.add_parser("launch", help="start the ROS 2 node set")
    s.add_argument("config", nargs="?", help="node parameters YAML (default config/stage.yaml)")
    s.add_argument("--record", metavar="DIR", help="record a bag to DIR ('auto': bags/<time>)")
    s.add_argument("--duration", type=float, metavar="S", help="stop after S seconds")
    s.add_argument("--namespace", default="/stage")
    s.add_argument("--no-arm", action="store_true", help="start disarmed and stay so "
                   "until armed on the arm service")
    s.add_argument("--foxglove", type=_port, nargs="?", const=8765, metavar="PORT",
                   help="serve the running topics to Foxglove over WebSocket (default "
                   "port 8765)")
    s.add_argument("--params", action="append", metavar="FILE",
                   help="more node parameters over CONFIG's (e.g. from `tune`), may repeat")
    s.set_defaults(fn=cmd_launch)

    s = sub.add_parser("demo", help="the main job: node set on the simulated stage")
    s.add_argument("--out", help="bag directory (default bags/<timestamp>)")
    s.add_argument("--excite", type=float, default=3.0, help="excitation before tracking [s]")
    s.add_argument("--track", type=float, default=1.0, help="tracking of the seed's 10 Hz "
                   "trajectory [s]")
    s.add_argument("--namespace", default="/stage")
    s.set_defaults(fn=cmd_demo)

    from piezo_stage.cli.experiment import add_parsers
    add_parsers(sub)

    s = sub.add_parser("replay", help="republish a recorded bag on its topics")
    s.add_argument("bag")
    s.add_argument("--rate", type=float, default=1.0,
                   help="playback speed (1: original timing; 0: as fast as possible)")
    s.add_argument("--namespace", default=None, help="replace the recorded namespace")
    s.set_defaults(fn=cmd_replay)

    s = sub.add_parser("bag", help="check or repair a recorded bag")
    s.add_argument("action", choices=("check", "repair"))
    s.add_argument("bag", help="bag directory or .mcap file")
    s.set_defaults(fn=cmd_bag)

    for name, hlp in (("loop", "hysteresis loop figures of the simulated stage"),):
        s = sub.add_parser(name, help=hlp)
        s.add_argument("--config", help="plant config YAML")
        s.add_argument("--freq", type=float, default=1.0, help="sine frequency [Hz]")
        s.add_argument("--amplitude", type=float, default=150.0, help="peak-peak [V]")
        s.add_argument("--cycles", type=int, default=3)
        s.add_argument("--rate", type=float, default=10_000.0, help="sample rate [Hz]")
        s.set_defaults(fn=cmd_loop, model=None, no_noise=False, seed=None)

    s = sub.add_parser("identify", help="identify the Duhem model from a record")
    s.add_argument("data", help="record: CSV (t,vx,vy,wx,wy or one axis) or a bag")
    s.add_argument("--axis", choices=("x", "y", "both"), default="both")
    s.add_argument("--method", choices=("fast", "afsa", "afsa-bat"), default="fast")
    g = s.add_mutually_exclusive_group()
    g.add_argument("--whole", action="store_true", help="one parameter set for both branches")
    g.add_argument("--segmented", action="store_true", help="a set per branch (default)")
    s.add_argument("--validate", metavar="DATA2", help="held-out record to validate on")
    s.add_argument("--seed", type=int, default=0)
    s.add_argument("--budget", type=int, metavar="EVALS", help="objective evaluations")
    s.add_argument("--coupling", choices=("auto", "on", "off"), default="auto",
                   help="fit cross-coupling from the other axis (fast only)")
    s.add_argument("--voltage", choices=("auto", "exact"), default="auto",
                   help="exact: v is what the actuator got (never cleaned); auto: a noisy "
                   "(measured) v has its in-branch micro-reversals removed (bags: exact)")
    s.add_argument("--n", type=int, default=3, help="degree of f (default 3)")
    s.add_argument("--m", type=int, default=2, help="degree of g (default 2)")
    s.add_argument("--out", metavar="MODEL.yaml", help="write the model file")
    s.add_argument("--json", metavar="FILE", help="write the full report as JSON")
    s.add_argument("--plot", metavar="PNG", help="loop and fit-error figure (default: "
                   "next to --out's model file, MODEL.png)")
    s.set_defaults(fn=cmd_identify)

    s = sub.add_parser("study", help="reproduce the seed's identification study")
    s.add_argument("what", choices=("identification",))
    s.add_argument("--out", default="out/identification_study", help="output folder")
    s.add_argument("--seeds", type=int, default=5)
    s.add_argument("--budget", type=int, default=60_000, help="evaluations per swarm run")
    s.set_defaults(fn=cmd_study)

    s = sub.add_parser("bench", help="performance benchmarks (figures as ratios)")
    s.add_argument("what", choices=("plant", "identify", "loop", "gap", "realtime",
                                    "faults", "liveview"))
    s.add_argument("--track", type=float, default=20.0, metavar="S",
                   help="realtime: seconds of the seed's trajectory")
    s.add_argument("--samples", type=int, default=2_000_000)
    s.set_defaults(fn=cmd_bench)
    return p


INPUTS = ("inp", "model", "config", "data", "validate", "fit", "holdout", "bag", "plant")
FILE_OUTPUTS = ("json", "out_model", "plot")  # and "out" where it names a file (not a folder)
DIR_COMMANDS = ("study", "demo", "launch", "experiment")  # whose --out is a folder


def check_paths(args):
    """Outputs never overwrite an input, and can be written: else DataError (exit 2)."""
    import os
    ins = {os.path.realpath(p) for k in INPUTS if isinstance(p := getattr(args, k, None), str)}
    outs = [(k, p) for k in FILE_OUTPUTS + ("out", "report")
            if isinstance(p := getattr(args, k, None), str)]
    for k, p in outs:
        flag = "--" + k.replace("_", "-")
        if os.path.realpath(p) in ins:
            raise DataError(f"{flag} {p} is also an input: outputs never overwrite inputs")
        if k in FILE_OUTPUTS or (k == "out" and args.cmd not in DIR_COMMANDS):
            if os.path.isdir(p):
                raise DataError(f"{flag} {p} is a directory; give a file name")
            parent = os.path.dirname(os.path.abspath(p))
            while not os.path.exists(parent):
                parent = os.path.dirname(parent)
            if not os.access(parent, os.W_OK):
                raise DataError(f"{flag} {p}: {parent} is not writable")


def main(argv=None):
    args = build_parser().parse_args(argv)
    try:
        check_paths(args)
        return args.fn(args) or 0
    except SolverError as e:  # the data were fine; the solver did not deliver
        _die(str(e), EXIT_SOLVER)
    except PiezoStageError as e:
        _die(str(e))
    except KeyboardInterrupt:
        return 130


if __name__ == "__main__":
    sys.exit(main())
