"""`piezo-stage experiment`: the paper's control experiments through the node set."""

from __future__ import annotations

import json
import os

from piezo_stage.cli._common import namespace, number, param_overrides

HELP = "the paper's control experiments through the node set"


def add_arguments(s):
    from piezo_stage.apps.experiments import CONTROLLERS, EXPERIMENTS, FREQS_HZ
    s.add_argument("name", choices=EXPERIMENTS + ("scan",))
    s.add_argument("--plant", metavar="CONFIG.yaml", help="simulated plant (default "
                   "config/sim_stage.yaml; scan: sim_stage.yaml and sim_stage_effects.yaml)")
    s.add_argument("--model", metavar="MODEL.yaml", help="the feedforward's model, as "
                   "`gap --out-model` writes it (default: identified through the node set "
                   "first; scan: each plant's own)")
    s.add_argument("--mode", choices=("lockstep", "realtime"), default="lockstep")
    s.add_argument("--config", help="node parameters YAML (default config/stage.yaml)")
    s.add_argument("--params", action="append", metavar="FILE",
                   help="more node parameters (e.g. from `tune`), may repeat")
    s.add_argument("--freqs", type=_floats, default=FREQS_HZ, metavar="F1,F2",
                   help="tracking: frequencies [Hz] (default 1,5,10,40)")
    s.add_argument("--controllers", type=_controllers, default=CONTROLLERS,
                   metavar="C1,C2", help="tracking: " + ", ".join(CONTROLLERS))
    s.add_argument("--rate", type=number(1.0, 1e5), metavar="HZ",
                   help="scan: the control rate of the driver, feedforward and controller "
                   "(default: the parameters'; a simulated stage in lockstep runs any "
                   "whole number of its substeps, e.g. 5000)")
    s.add_argument("--json", metavar="FILE")
    s.add_argument("--record", metavar="DIR", help="where the bags go (default "
                   "bags/<time>)")
    s.add_argument("--report", metavar="DIR", help="table, JSON and PNG figure")
    s.add_argument("--namespace", type=namespace, default="/stage")
    s.add_argument("--seed", type=number(0, 2**31 - 1, integer=True), metavar="N",
                   help="the simulated stage's noise seed of the first case (the next "
                   "cases N+1, N+2...): a repeat with another seed draws new noise "
                   "(default: the plant config's)")


def _floats(text):
    import argparse
    try:
        out = tuple(float(x) for x in text.split(","))
    except ValueError:
        out = ()
    if not out or any(not 0 < f <= 200 for f in out):
        raise argparse.ArgumentTypeError(f"{text!r}: give frequencies in (0, 200] Hz, "
                                         "comma-separated")
    return out


def _controllers(text):
    import argparse

    from piezo_stage.apps.experiments import CONTROLLERS
    out = tuple(x.strip() for x in text.split(","))
    bad = [c for c in out if c not in CONTROLLERS]
    if bad or not out:
        raise argparse.ArgumentTypeError(f"{text!r}: use {', '.join(CONTROLLERS)}")
    return out


def _check_inputs(args):
    if args.plant:
        from piezo_stage.io.plant_file import load_plant_config
        load_plant_config(args.plant)  # ConfigError (exit 2) with where
    if args.model:
        from piezo_stage.io.model_file import load_model
        load_model(args.model)


def identify_first(out_dir, config, plant, mode, extra, namespace):
    """No model given: the identifier identifies one through the node set (the demo's
    excitation) and it is written to out_dir/identified_model.yaml."""
    from piezo_stage.apps.experiments import NODES, merge_params
    from piezo_stage.core.errors import RunError
    from piezo_stage.io.bag import deserialize, iter_messages
    from piezo_stage.io.files import atomic_write
    from piezo_stage.launcher.launcher import Launch, LaunchOptions, run_set
    bag = os.path.join(out_dir, "identification")
    drv = {"mode": mode}
    if plant:
        drv["plant_config"] = os.path.abspath(plant)
    if mode == "lockstep":
        drv.update(max_steps=5000, exit_after_max_steps=True)
    o = merge_params(extra or {}, {"stage_driver": drv,
                             "trajectory": {"kind": "seed", "duration_s": 0.5, "excite_s": 4.0},
                             "identifier": {"auto_cycles": 2},
                             "feedforward": {"model_required_after_s": 4.0}})
    launch = Launch(config, LaunchOptions(record=bag, overrides=o, namespace=namespace,
        nodes=list(NODES) + ["identifier"]))
    run_set(launch, "identification run", duration=7.0 if mode == "realtime" else 900.0)
    text = None
    for topic, msgtype, _, data in iter_messages(bag, topics=None):
        if topic.endswith("/model"):
            text = deserialize(data, msgtype).data
    if text is None:
        raise RunError("identification run: the identifier published no model")
    path = os.path.join(out_dir, "identified_model.yaml")
    with atomic_write(path) as fh:
        fh.write(text)
    return path


def main(args):
    import sys

    from piezo_stage.apps.experiments import run_experiment, table
    from piezo_stage.io.bag import new_bag_dir
    from piezo_stage.paths import default_config
    _check_inputs(args)
    extra = param_overrides(args.params)
    config = args.config or default_config("stage.yaml")
    if args.name == "scan":
        from piezo_stage.apps.scan import check_rate
        check_rate(config, extra, args.rate)  # DataError (exit 2) before any output
    elif args.rate is not None:
        sys.stderr.write("piezo-stage experiment: --rate is scan's (the other experiments' "
                         "trajectories are written at 1 kHz: set control_rate_hz through "
                         "--params)\n")
        return 2
    out_dir = args.record or new_bag_dir("bags")
    os.makedirs(out_dir, exist_ok=True)
    model = args.model
    if args.name == "scan":
        return scan(args, config, extra, out_dir)
    try:
        if model is None:
            print("no --model: identifying one through the node set first", flush=True)
            model = identify_first(out_dir, config, args.plant, args.mode, extra,
                                   args.namespace)
            print(f"identified model: {model}")
        doc, evals = run_experiment(args.name, out_dir, config, args.plant, model, args.mode,
                                    args.freqs, args.controllers, extra, args.namespace,
                                    seed=args.seed)
    except RuntimeError as e:
        sys.stderr.write(f"piezo-stage experiment: {e}\n")
        return 1
    except KeyboardInterrupt as stop:  # the finished cases' report, then the stop
        from piezo_stage.apps.experiments import Interrupted
        if isinstance(stop, Interrupted) and stop.doc["cases"]:
            from piezo_stage.process import stopping
            stopping.hold()  # (a second Ctrl-C does not cut the report short)
            from piezo_stage.io.plots import experiment_png
            done, total = stop.evals, stop.total
            doc = dict(stop.doc, stopped_after_cases=len(done), of_cases=total)
            print(f"stopped after {len(done)} of {total} cases: their report")
            _outputs(args, args.name, doc, table(doc),
                     f"plant: {doc['plant']}; model: {model}; mode: {args.mode}; "
                     f"stopped after {len(done)} of {total} cases",
                     lambda path: experiment_png(path, done), out_dir)
        raise
    from piezo_stage.io.plots import experiment_png
    return _outputs(args, args.name, doc, table(doc),
                    f"plant: {doc['plant']}; model: {model}; mode: {args.mode}",
                    lambda path: experiment_png(path, evals), out_dir)


def _outputs(args, name, doc, table_text, header, draw, out_dir):
    """The table on stdout; --json; --report DIR: NAME.json, NAME.md and NAME.png (by
    ``draw(path)``); all written whole or not at all."""
    from piezo_stage.io.files import atomic_write
    print(table_text)
    text = json.dumps(doc, indent=2)
    if args.json:
        with atomic_write(args.json) as fh:
            fh.write(text + "\n")
        print(f"json: {args.json}")
    if args.report:
        os.makedirs(args.report, exist_ok=True)
        with atomic_write(os.path.join(args.report, f"{name}.json")) as fh:
            fh.write(text + "\n")
        with atomic_write(os.path.join(args.report, f"{name}.md")) as fh:
            fh.write(f"# Experiment {name}\n\n{header}\n\n```\n{table_text}\n```\n\n"
                     f"![{name}]({name}.png)\n")
        print(f"report: {draw(os.path.join(args.report, name + '.png'))}")
    print(f"bags: {out_dir}")
    return 0


def scan(args, config, extra, out_dir):
    """`experiment scan`: rasters and the seed trajectory with and without learning."""
    import sys

    from piezo_stage.apps.scan import run_scan, table
    try:
        doc, evals = run_scan(out_dir, config, [args.plant] if args.plant else None,
                              args.model, args.mode, extra, args.namespace,
                              rate_hz=args.rate)
    except RuntimeError as e:
        sys.stderr.write(f"piezo-stage experiment: {e}\n")
        return 1
    from piezo_stage.io.plots import scan_png
    return _outputs(args, "scan", doc, table(doc),
                    f"plants: {', '.join(doc['plants'])}; model: {doc['model']}; "
                    f"mode: {args.mode}; control rate {doc['control_rate_hz']:g} Hz",
                    lambda path: scan_png(path, evals), out_dir)
