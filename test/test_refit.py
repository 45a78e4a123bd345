"""`piezo-stage refit`: an archive of runs re-identified in parallel, the effect that
grew named and dated."""

import csv
import json
import os
import subprocess
import sys
from datetime import datetime, timezone

import pytest

from piezo_stage.apps import refit as R
from piezo_stage.apps.studies.archive import START, crossing_day, make_archive
from piezo_stage.core.errors import DataError


def _refit(*args, timeout=600):
    return subprocess.run([sys.executable, "-m", "piezo_stage.cli", "refit", *map(str, args)],
                          capture_output=True, text=True, timeout=timeout)


def test_refit_names_the_growing_creep_the_drifting_resonance_and_the_day_30_percent(
        tmp_path):
    arch = tmp_path / "stage_two_daily_calibrations"  # (names longer than a column)
    make_archive(str(arch), runs=6, fs_hz=500.0, resonance=True)
    out = tmp_path / "refit"
    r = _refit(arch, "--out", out, "--against", arch / "reference.yaml", "--jobs", 2)
    assert r.returncode == 0, r.stderr[-3000:]
    doc = json.loads((out / "refit.json").read_text())
    rows = doc["bags"]
    assert [b["name"] for b in rows] == [f"stage_two_daily_calibrations_run{d:02d}"
                                         for d in range(6)]
    assert all(b["dated_by"] == "recorded start" for b in rows)
    assert all(b["axes"]["x"]["against"]["verdict"] in ("creep", "dynamics") for b in rows)
    g = {(e["axis"], e["effect"]): e for e in doc["growth"]}
    creep, res = g[("x", "creep")], g[("x", "dynamics")]
    # the truth: gamma 0.03 + 0.004 a day, +66.7 % by day 5, 30 % first on day 3
    assert 45.0 <= creep["change_pct"] <= 90.0, creep
    day = (datetime.fromisoformat(creep["crossed_utc"]) - START).days
    assert abs(day - crossing_day()) <= 1, (day, creep)
    assert f"x: creep +{creep['change_pct']:.0f} % since 2026-11-02" in r.stdout
    # and the resonance 125 Hz, 2 % lower a day: -10 % by day 5, never 30 %
    assert res["size_of"] == "fn_hz" and -15.0 <= res["change_pct"] <= -5.0, res
    assert res["crossed_utc"] is None and "x: dynamics -" in r.stdout
    # one model per bag, loadable; the table and the picture
    for b in rows:
        assert os.path.isfile(b["model"])
        # (held out: the second half of the span where x moves, its rest after the
        # last move left out: 0.50 um here, against 0.49 with that rest)
        assert b["axes"]["x"]["held_out_rms_um"] < 0.55
    assert rows[-1]["axes"]["x"]["change_um"] == 0.0  # the newest against itself
    with open(out / "refit.csv", newline="") as fh:
        table = list(csv.DictReader(fh))
    assert len(table) == 6 and table[0]["x_verdict"] in ("creep", "dynamics")
    assert float(table[-1]["x_creep"]) > float(table[0]["x_creep"])
    assert (out / "refit.png").stat().st_size > 10_000
    for b in rows:  # each bag's whole name in the table (it was cut from the left)
        assert any(ln.split()[1:2] == [b["name"]] for ln in r.stdout.splitlines()), \
            (b["name"], r.stdout)


def test_growth_dates_the_first_crossing_and_an_effect_that_appears():
    def row(day, effects):
        return {"started_utc": f"2026-11-{day:02d}T00:00:00+00:00",
                "axes": {"x": {"against": {"verdict": "creep", "effects": {
                    e: {"size": v, "size_of": "gamma" if e == "creep" else "explained_um",
                        "explained_um": 0.1} for e, v in effects.items()}}}}}
    rows = [row(1, {"creep": 0.10}), row(2, {"creep": 0.12}),
            row(3, {"creep": 0.14, "delay": 0.002}), row(4, {"creep": 0.11})]
    g = {e["effect"]: e for e in R.growth(rows)}
    assert g["creep"]["crossed_utc"].startswith("2026-11-03")  # +40 % on day 3
    assert g["creep"]["change_pct"] == pytest.approx(10.0)
    assert g["delay"]["crossed_utc"].startswith("2026-11-03")  # absent, then there
    lines = R.growth_lines(R.growth(rows))
    assert "x: creep +10 % since 2026-11-01 00:00:00 (gamma 0.1 -> 0.11); changed by 30 " \
           "% on 2026-11-03 00:00:00" in lines  # to the second: runs of a day told apart
    assert any(line.startswith("x: delay appeared on 2026-11-03") for line in lines)


def test_bags_are_found_in_run_folders_and_dated_by_their_folder(tmp_path):
    import numpy as np

    from piezo_stage.core.estimation.record import Record
    from piezo_stage.io.bag import write_record_bag
    run = tmp_path / "bags" / "20261103-101500"
    t = np.arange(300) / 100.0
    rec = Record(t, {"x": np.sin(t)}, {"x": np.sin(t)})
    for name in ("a", "b"):
        write_record_bag(str(run / name), rec)
    found = R.find_bags([str(tmp_path / "bags")])
    assert [os.path.basename(b) for b in found] == ["a", "b"]
    assert R.find_bags([str(run / "a"), str(run)]) == [str(run / "a"), str(run / "b")]
    when, how = R.run_date(found[0])  # stamps from 0 (lockstep), no recorded start
    assert how == "folder name"
    assert when == datetime(2026, 11, 3, 10, 15, tzinfo=timezone.utc)
    (tmp_path / "none").mkdir()
    with pytest.raises(DataError, match="no bag in it"):
        R.find_bags([str(tmp_path / "none")])


def test_refit_bad_input_is_one_line_and_exit_2(tmp_path):
    import numpy as np

    from piezo_stage.core.estimation.record import Record
    from piezo_stage.io.bag import write_record_bag
    (tmp_path / "empty").mkdir()
    t = np.arange(400) / 100.0
    write_record_bag(str(tmp_path / "rest" / "r"), Record(  # a run at rest: skipped
        t, {"x": np.full(400, 5.0)}, {"x": np.random.default_rng(0).normal(0, 0.1, 400)}))
    for args in ([tmp_path / "missing", "--out", tmp_path / "o"],
                 [tmp_path / "empty", "--out", tmp_path / "o"],
                 [tmp_path / "rest", "--out", tmp_path / "o"],
                 [tmp_path / "rest", "--out", tmp_path / "o", "--against", tmp_path]):
        r = _refit(*args, timeout=60)
        assert r.returncode == 2, (args, r.stderr)
        assert len(r.stderr.strip().splitlines()) == 1, r.stderr
    assert not (tmp_path / "o" / "refit.csv").exists()  # no table of a refused archive


@pytest.mark.slow
def test_refit_on_a_dask_cluster_gives_the_local_table(tmp_path):
    """`refit --scheduler ADDRESS` runs the bags on a Dask distributed cluster (here a
    LocalCluster of two worker processes) and writes the table the local run writes."""
    distributed = pytest.importorskip("distributed")
    arch = tmp_path / "archive"
    make_archive(str(arch), runs=3, fs_hz=500.0)
    local = _refit(arch, "--out", tmp_path / "local", "--against", arch / "reference.yaml",
                   "--jobs", 1)
    assert local.returncode == 0, local.stderr[-3000:]
    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True,
                                  dashboard_address=None) as cluster:
        r = _refit(arch, "--out", tmp_path / "cluster", "--against",
                   arch / "reference.yaml", "--scheduler", cluster.scheduler_address)
    assert r.returncode == 0, r.stderr[-3000:]
    assert f"on the Dask cluster at {cluster.scheduler_address}" in r.stdout
    tables = []
    for run in ("local", "cluster"):
        with open(tmp_path / run / "refit.csv", newline="") as fh:
            tables.append(list(csv.DictReader(fh)))
    a, b = tables  # the same table, figure for figure (to the rounding of BLAS threads)
    assert len(a) == len(b) == 3 and [r.keys() for r in a] == [r.keys() for r in b]
    for ra, rb in zip(a, b):
        for k in ra:
            try:
                assert float(ra[k]) == pytest.approx(float(rb[k]), rel=1e-6, abs=1e-9), k
            except ValueError:
                assert ra[k] == rb[k], k
    bad = _refit(arch, "--out", tmp_path / "x", "--scheduler", "tcp://127.0.0.1:9",
                 timeout=120)
    assert bad.returncode == 2 and "no Dask scheduler answers" in bad.stderr, bad.stderr
