"""`piezo-stage bench learning`: learning feedforward in real time against lockstep, over
noise draws.

The case is the scan experiment's seed trajectory at 40 Hz on the effects plant
(config/sim_stage_effects.yaml, its own model), learning on, 24 periods at 1 kHz,
through the node set (driver, feedforward, controller with its feedback off,
trajectory, recorder). It runs once per plant noise seed in lockstep and once in real
time, in the same invocation; every figure comes from the bags, as the experiment
computes it: the mean absolute error against the true position in the 20th period (%
of the range), per axis.

Why over draws: at 1 kHz a 40 Hz period has 25 samples and the learned correction is a
running mean of noisy periods, so one lockstep run's figure is one draw of the sensor's
0.1 um noise; lockstep runs with other seeds scatter by about 1.5 x among themselves
(docs/experiments.md). Real time draws the same noise but meets it at other samples (its
motion starts seconds of samples later, after discovery and arming), so it is compared
with the lockstep runs' median, as well as seed by seed.
"""

from __future__ import annotations

import os
import random
import tempfile

import numpy as np

FREQ_HZ = 40.0
PERIODS = 24
TARGET = 1.5  # real time's median within this factor of lockstep's (issue 30, item 5)


# the rates a 40 Hz period is whole samples at (learning needs that), highest first
RATES_HZ = (1000.0, 400.0, 200.0)


def _one(mode: str, seed: int, out_dir: str, env: dict, plant: str, model: str,
         rate_hz: float) -> dict:
    from piezo_stage.apps.experiments import merge_params, run_case
    from piezo_stage.apps.scan import evaluate, plan
    from piezo_stage.io.run_bag import read_run
    from piezo_stage.paths import default_config
    case, = plan(PERIODS, (), (FREQ_HZ,), mode, rate_hz=rate_hz, learning=(True,))
    bag = os.path.join(out_dir, f"{mode}_{seed}")
    # both modes at the rate this host holds (measured once: min_margin 0 after it)
    rates = {n: {"control_rate_hz": rate_hz} for n in ("stage_driver", "feedforward",
                                                      "controller")}
    run_case(case, bag, default_config("stage.yaml"), plant, model, mode,
             merge_params(rates, {"stage_driver": {"seed": seed, "min_margin": 0.0}}),
             "/stage", env, exclusive=False)
    ev = evaluate(case, bag)
    run = read_run(bag)
    gaps = np.maximum(np.round(np.diff(run.t_ns) * case.rate_hz * 1e-9), 1)
    return {a: ev["axes"][a]["pct_after_20_periods"] for a in "xy"} | {
        "missed": int((gaps - 1).sum()),
        "learning": run.diagnostics.get("feedforward", {}).get("learning", "")}


def bench_learning(rep, draws: int = 5) -> int:
    """Learning feedforward, lockstep against real time per noise seed (``rep``: the
    report)."""
    env = dict(os.environ, ROS_DOMAIN_ID=str(random.randint(101, 200)),
               ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST")
    tmp = tempfile.mkdtemp()
    from piezo_stage.launcher.host_rate import host_rate
    rate, why = host_rate(env, RATES_HZ)
    if rate is None:
        rep.fail(f"this host holds no real-time rate with margin: {why}")
        return 1
    rates = ", ".join(f"{r:g}" for r in RATES_HZ)
    rep.title(f"the seed trajectory at {FREQ_HZ:g} Hz on the effects plant, learning on, "
              f"{PERIODS} periods at {rate:g} Hz (the highest of {rates} Hz this host "
              "holds with margin), the node set; each noise seed in lockstep and "
              "in real time; the 20th period's mean absolute error against the true "
              "position (% of the range)")
    from benchmarks.procs import progress_runs
    from piezo_stage.apps.scan import own_model
    from piezo_stage.paths import default_config
    plant = default_config("sim_stage_effects.yaml")
    model = own_model(plant, tmp)
    res: dict[str, list] = {"lockstep": [], "realtime": []}
    rows = []
    for seed in progress_runs(range(draws), "bench learning: seeds"):
        for mode in ("lockstep", "realtime"):
            res[mode].append(_one(mode, seed, tmp, env, plant, model, rate))
        ls, rt = res["lockstep"][-1], res["realtime"][-1]
        rows.append((seed, f"{ls['x']:.3f} / {ls['y']:.3f} %",
                     f"{rt['x']:.3f} / {rt['y']:.3f} %",
                     f"{max(rt[a] / ls[a] for a in 'xy'):.2f}", rt["missed"],
                     rt["learning"].split(";")[0]))
    med = {m: {a: float(np.median([r[a] for r in rs])) for a in "xy"}
           for m, rs in res.items()}
    ratio = {a: med["realtime"][a] / med["lockstep"][a] for a in "xy"}
    spread = {a: max(r[a] for r in res["lockstep"]) / min(r[a] for r in res["lockstep"])
              for a in "xy"}
    rows.append(("median", f"{med['lockstep']['x']:.3f} / {med['lockstep']['y']:.3f} %",
                 f"{med['realtime']['x']:.3f} / {med['realtime']['y']:.3f} %",
                 f"{ratio['x']:.2f} / {ratio['y']:.2f}", "", ""))
    rep.table(("seed", "lockstep x / y", "real time x / y", "real time / lockstep",
               "missed ticks", "learning"), rows,
              f"lockstep's own spread over the seeds (largest / smallest): "
              f"{spread['x']:.2f} / {spread['y']:.2f}")
    rep.target(f"real time's median <= {TARGET:g} x lockstep's (both axes)",
               max(ratio.values()) <= TARGET)
    return 0
