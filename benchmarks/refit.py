"""`piezo-stage bench refit`: the generated archive (apps/studies/archive.py: 20 daily
runs of our stage whose creep gamma grows by 0.004 a day from 0.03 and whose resonance
drifts 2 % lower a day) refitted against the stage's calibration by `piezo-stage refit`
as a whole process on every core. The figures: its wall time against the ideal (one
bag's refit x bags / workers, one bag timed alone in the same invocation: target <= 1.3
x), and the changes it names and dates against the truth."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import tempfile
import time


def bench_refit(rep, runs: int = 20) -> int:
    """An archive of daily runs refitted against its calibration (``rep``: the
    report)."""
    from datetime import datetime

    from piezo_stage.apps.studies.archive import (
        START,
        creep_gamma,
        crossing_day,
        make_archive,
        resonance_hz,
    )
    tmp = tempfile.mkdtemp(prefix="bench-refit-")
    arch = os.path.join(tmp, "archive")
    t0 = time.perf_counter()
    make_archive(arch, runs=runs, fs_hz=1000.0, resonance=True)
    made = time.perf_counter() - t0
    ref = os.path.join(arch, "reference.yaml")
    jobs = os.cpu_count() or 1

    def refit(bags, out, j):
        t = time.perf_counter()
        r = subprocess.run([sys.executable, "-m", "piezo_stage.cli", "refit", *bags,
                            "--out", out, "--against", ref, "--jobs", str(j)],
                           capture_output=True, text=True)
        if r.returncode != 0:
            raise RuntimeError(f"refit failed: {r.stderr.strip()[-500:]}")
        return time.perf_counter() - t, r.stdout
    one, _ = refit([os.path.join(arch, "run00")], os.path.join(tmp, "one"), 1)
    wall, out = refit([arch], os.path.join(tmp, "all"), jobs)
    ideal = one * runs / jobs
    with open(os.path.join(tmp, "all", "refit.json")) as fh:
        doc = json.load(fh)
    creep = next((g for g in doc["growth"] if g["effect"] == "creep"), None)
    true_pct = (creep_gamma(runs - 1) / creep_gamma(0) - 1) * 100
    rep.title(f"{runs} daily runs of our stage (axis x, 72 s at 1 kHz each, made in "
              f"{made:.1f} s), creep gamma {creep_gamma(0):.3f} + 0.004 a day, a "
              f"{resonance_hz(0):.0f} Hz resonance 2 % lower a day, refitted against its "
              f"calibration on {jobs} worker(s)")
    named = [set(b["axes"]["x"]["against"]["effects"]) for b in doc["bags"]]
    figs = [("one bag alone (a whole `refit` process)", f"{one:.1f} s"),
            ("the archive", f"{wall:.1f} s; ideal {one:.1f} x {runs} / {jobs} = "
             f"{ideal:.1f} s: {wall / ideal:.2f} x"),
            ("named", f"creep in {sum('creep' in n for n in named)} of {runs} bags, "
             f"dynamics in {sum('dynamics' in n for n in named)}")]
    res = next((g for g in doc["growth"] if g["effect"] == "dynamics"), None)
    true_res = (resonance_hz(runs - 1) / resonance_hz(0) - 1) * 100
    res_day = next((d for d in range(runs)
                    if resonance_hz(d) <= 0.7 * resonance_hz(0) + 1e-9), None)
    if res:
        day = (datetime.fromisoformat(res["crossed_utc"]) - START).days \
            if res["crossed_utc"] else None
        figs.append(("resonance over the archive", f"{res['change_pct']:+.0f} % (truth "
                     f"{true_res:+.0f} %); 30 % first on day {day} (truth: day {res_day})"))
    if creep:
        day = (datetime.fromisoformat(creep["crossed_utc"]) - START).days \
            if creep["crossed_utc"] else None
        figs.append(("creep over the archive", f"{creep['change_pct']:+.0f} % (truth "
                     f"{true_pct:+.0f} %); 30 % first on day {day} (truth: day "
                     f"{crossing_day()})"))
    figs += [("refit says", line) for line in out.splitlines() if line.startswith("x: ")]
    rep.figures(figs)
    rep.target("both changes named and dated", creep is not None and res is not None)
    rep.target("wall time <= 1.3 x ideal", wall / ideal <= 1.3)
    return 0
