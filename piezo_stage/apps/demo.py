"""`piezo-stage demo`: the node set on the simulated stage, end to end.

Lockstep simulation; the trajectory node first excites the stage (1 Hz full-stroke
sine, tracked with the nominal feedforward and PID), the identifier identifies the
Duhem model after two cycles and hands it to the feedforward, then the stage tracks
the paper's y(t) = 21 + 24 sin(2 pi 10 t - pi/2) um on both axes. The run is recorded;
the summary is computed from the bag.
"""

from __future__ import annotations

import os
import sys

import numpy as np

from piezo_stage.io.bag import new_bag_dir


def tracking_from_run(run, t_from_s):
    """Desired (reference) and measured (joint_states) [um] per stamp after t_from_s:
    (t [s], desired (n, 2), measured (n, 2), models handed over), of ``run`` (a
    recorded run, io.run_bag.read_run)."""
    meas = dict(zip(run.t_ns.tolist(), run.w_um))
    stamps = sorted(k for k in run.desired_um if k in meas and k >= t_from_s * 1e9)
    d = np.array([run.desired_um[k] for k in stamps]).reshape(-1, 2)
    w = np.array([meas[k] for k in stamps]).reshape(-1, 2)
    return np.array(stamps) * 1e-9, d, w, run.models


def run_demo(args):
    from piezo_stage.launcher.running import begin_look
    with begin_look(args.namespace) as look:  # beside the imports
        return _run_demo(args, look)


def _run_demo(args, look):
    from piezo_stage.launcher.launcher import Launch, LaunchOptions, run_set
    from piezo_stage.paths import default_config
    bag = args.out or new_bag_dir("bags")
    rate = 1000.0
    total = args.excite + 0.2 + args.track + 0.2  # + arming and the approach
    steps = int(round(total * rate))
    overrides = {
        "stage_driver": {"mode": "lockstep", "max_steps": steps, "exit_after_max_steps": True},
        "trajectory": {"kind": "seed", "frequency_hz": 10.0, "duration_s": args.track,
                       "excite_s": args.excite},
        "identifier": {"auto_cycles": 2},
        # the loop waits for the identified model before tracking starts (deterministic
        # whatever the identification takes in wall-clock time)
        "feedforward": {"model_required_after_s": args.excite},
    }
    print(f"demo: lockstep simulated stage, {args.excite:g} s excitation + {args.track:g} s "
          f"of the paper's 10 Hz trajectory ({steps} steps at {rate:g} Hz)", flush=True)
    launch = Launch(default_config("stage.yaml"), LaunchOptions(record=bag,
        namespace=args.namespace, overrides=overrides), look=look)
    run_set(launch, "demo", duration=600.0)  # RunError: exit 1; a stop: 128 + signal
    if not os.path.isdir(bag):
        sys.stderr.write("piezo-stage demo: the node set wrote no bag\n")
        return 1
    from piezo_stage.io.run_bag import read_run
    run = read_run(bag)  # the one reader of a recorded run
    t, d, w, models = tracking_from_run(run, args.excite + 0.2 + 0.1)
    if d.size == 0:
        sys.stderr.write("piezo-stage demo: no tracking samples in the bag\n")
        return 1
    e = w - d
    span = np.ptp(d, axis=0)
    print(f"models handed to the feedforward: {models}")
    print(f"{'axis':>4} {'rms_um':>8} {'max_um':>8} {'rms_pct':>8}")
    for i, a in enumerate(("x", "y")):
        rms = float(np.sqrt(np.mean(e[:, i] ** 2)))
        print(f"{a:>4} {rms:8.4f} {np.max(np.abs(e[:, i])):8.4f} {100 * rms / span[i]:8.3f}")
    from piezo_stage.io.plots import tracking_png
    png = tracking_png(os.path.join(bag, "tracking.png"), run,
                       args.excite + 0.2 + 0.1, excite_s=args.excite)
    print(f"plot: {png} (the whole run)")
    print(f"bag: {bag}")
    return 0
