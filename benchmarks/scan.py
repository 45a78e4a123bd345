"""`bench scan`: learning feedforward on repeated motion, the figures of the scan pages.

First the offline study (``piezo-stage study learning``: the feedforward's own core
pieces closed around the simulated stage, feedforward only) at 20 and 60 periods and
with every effect parameter of the model 20 % off for 200 periods; then the node set
itself (``piezo-stage experiment scan --json FILE`` as a whole command, lockstep): the
rasters and the seed trajectory on the default and the effects plant at 1 kHz and at
5 kHz, and the 600 Hz stage at 5 kHz. Every figure is against the true position; the
baseline of each row is the same case without learning, run in the same invocation.
docs/experiments.md links here for its figures.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import tempfile

NAMESPACE = "/bench_scan"
FLOOR_PCT = 0.01  # % of the range: the sensor's noise learnt into the command, about


def _xy(by: dict, fmt=lambda v: f"{v:.3f}") -> str:
    return " / ".join(fmt(by[a]) for a in ("x", "y") if a in by) + " %"


def _study(rep, periods: int, model_error: float = 0.0) -> list[dict]:
    from piezo_stage.apps.studies import learning
    rep.progress(f"piezo-stage study learning --periods {periods}"
                 + (f" --model-error {model_error:g}" if model_error else ""))
    return learning.run(periods, model_error)


def _last(r: dict, which: str) -> dict:
    return {a: p[-1] for a, p in r[which]["per_period"].items()}


def _lin(r: dict) -> str:
    lin = r["with"]["linearity_pct"]
    return f" (linearity {lin['rms'][-1]:.3f} %)" if lin else ""


def _scan(rep, tmp: str, *more: str) -> dict:
    """``experiment scan`` as a whole command; its JSON document."""
    from benchmarks.procs import command_json
    rep.progress("piezo-stage experiment scan " + " ".join(more))
    return command_json(["experiment", "scan", *more, "--namespace", NAMESPACE],
                        os.path.join(tmp, f"scan_{len(os.listdir(tmp))}"), timeout=7200)


def _scan_rows(doc: dict) -> list[tuple]:
    """(plant, case) rows: without and with learning (x / y %, a raster's linearity),
    the periods learning took."""
    by: dict[tuple, dict] = {}
    for c in doc["cases"]:
        by.setdefault((c["plant"], c["name"].replace(" learning", "")), {}).setdefault(
            c["learning"], {})[c["axis"]] = c
    rows = []
    for (plant, name), runs in by.items():
        cells = []
        for learn in (False, True):
            axes = runs.get(learn, {})
            if not axes:
                cells.append("")
                continue
            txt = _xy({a: c["mean_abs_err_pct_of_range"] for a, c in axes.items()})
            at20 = {a: c.get("pct_after_20_periods") for a, c in axes.items()}
            if learn and all(v is not None for v in at20.values()):
                txt += f" (after 20: {_xy(at20)})"
            lin = axes.get("x", {}).get("linearity_rms_pct_of_scan")
            if lin is not None:
                txt += f" (lin {lin:.3f} %)"
            cells.append(txt)
        conv = max((c["periods_to_converge"] for c in runs.get(True, {}).values()),
                   default=0)
        rows.append((plant.replace("sim_stage_", "").replace("sim_stage", "default"),
                     name, *cells, conv))
    return rows


def bench_scan(rep) -> int:
    """Learning feedforward, offline and through the node set (``rep``: the report)."""
    from piezo_stage.paths import default_config
    rep.title("learning feedforward on repeated motion: the offline study, then the node "
              "set (`experiment scan`, lockstep); mean absolute error against the true "
              "position, % of the range, x / y (raster: linearity RMS, % of the scan)")
    tmp = tempfile.mkdtemp(prefix="bench_scan_")
    try:
        s20, s60 = _study(rep, 20), _study(rep, 60)
        s200 = _study(rep, 200, 0.2)
        docs = [("1 kHz", _scan(rep, tmp)),
                ("5 kHz", _scan(rep, tmp, "--rate", "5000")),
                ("5 kHz, the 600 Hz stage", _scan(rep, tmp, "--plant",
                                                  default_config("sim_stage_600hz.yaml"),
                                                  "--rate", "5000"))]
    except (RuntimeError, subprocess.TimeoutExpired) as e:
        rep.fail(str(e))
        return 1
    finally:
        shutil.rmtree(tmp, ignore_errors=True)

    rows, worst = [], 0.0
    for a, b, c in zip(s20, s60, s200):
        rows.append((a["name"], _xy(_last(a, "without")), _xy(_last(a, "with")) + _lin(a),
                     _xy(_last(b, "with")) + _lin(b),
                     f"{_xy(_last(c, 'with'))}{_lin(c)} ({_xy(_last(c, 'without'))})"))
        # grown: the last period against the first learned one, above the noise floor
        worst = max(worst, *(max(p[-1], FLOOR_PCT) / max(p[0], FLOOR_PCT)
                             for p in c["with"]["per_period"].values()))
    rep.table(("case (offline study, 1 kHz)", "no learning", "20 periods", "60 periods",
               "model 20 % off, 200 periods (its no-learning figure)"), rows,
              "`study learning`: the paper's trajectory lifted by 4 um, rasters 40 x 40 um")

    targets = []
    for label, doc in docs:
        rep.table(("plant", "case", "no learning", "learning", "converged after"),
                  _scan_rows(doc), f"`experiment scan` at {label}, last of "
                  f"{doc['cases'][0]['periods']} periods")
        if label.startswith("5 kHz") and "600" not in label:
            for c in doc["cases"]:
                if not c["learning"] or c.get("pct_after_20_periods") is None:
                    continue
                if c["kind"] == "seed" and c["freq_hz"] in (40.0, 100.0):
                    targets.append((c, c["pct_after_20_periods"],
                                    0.05 if c["freq_hz"] == 40.0 else 0.15, "error"))
                if c["kind"] == "raster" and c["freq_hz"] == 20.0 and c["axis"] == "x":
                    targets.append((c, c["linearity_rms_pct_of_scan"], 0.05, "linearity"))
    for name, most in (("seed 40 Hz", 0.05), ("seed 100 Hz", 0.15),
                       ("raster 20 Hz", 0.05)):
        got = [v for c, v, m, _ in targets if c["name"].startswith(name)]
        rep.target(f"5 kHz, both plants, after 20 periods of learning: {name} <= {most:g} % "
                   f"({max(got):.3f} % at most)" if got else f"{name}: not run",
                   bool(got) and max(got) <= most)
    rep.target(f"the model 20 % off: no learned case grows over 200 periods (the last period "
               f"at most {worst:.2f} x the first, above {FLOOR_PCT:g} %)", worst <= 1.0)
    return 0
