"""A lab's archive of runs, simulated, for `refit`'s tests and `bench refit`: one run a
day on our simulated stage (axis x), each the gap protocol recorded twice (a FIT half
and a HOLDOUT half, as `refit` splits a bag), written as bags the way the recorder
writes them (joint states, the run's start in the metadata). The stage's creep grows
by the same step each day, so the day its gamma first exceeds the first day's by 30 %
is known (``crossing_day``)."""

from __future__ import annotations

import copy
import os
from datetime import datetime, timedelta, timezone

import numpy as np

START = datetime(2026, 11, 2, 9, 0, tzinfo=timezone.utc)


def creep_gamma(day: int, gamma0: float = 0.03, per_day: float = 0.004) -> float:
    """The stage's creep on ``day`` (0: the first run)."""
    return gamma0 + per_day * day


def resonance_hz(day: int, fs_hz: float = 1000.0, per_day: float = 0.02) -> float:
    """The stage's resonance on ``day``: 0.25 fs_hz at first, 2 % lower a day (a mount
    loosening), so 30 % lower from day 15 on."""
    return 0.25 * fs_hz * (1.0 - per_day * day)


def crossing_day(pct: float = 30.0, **kw) -> int:
    """The first day whose creep exceeds the first day's by ``pct`` or more."""
    day = 0
    while creep_gamma(day, **kw) < creep_gamma(0, **kw) * (1 + pct / 100.0) - 1e-12:
        day += 1
    return day


def make_archive(out_dir: str, runs: int = 20, fs_hz: float = 1000.0,
                 resonance: bool = False) -> list[str]:
    """``runs`` bags in ``out_dir`` (run00, run01, ...), one a day from START; returns
    their paths. ``resonance``: the stage also has a resonance that drifts down
    (``resonance_hz``). Also writes ``out_dir/reference.yaml``: the stage's model without its
    creep (the lab's calibration)."""
    from piezo_stage.core.estimation.excitation import gap_protocol
    from piezo_stage.core.estimation.record import Record
    from piezo_stage.core.model.plant import Plant
    from piezo_stage.io.bag import write_record_bag
    from piezo_stage.io.model_file import save_model
    from piezo_stage.io.plant_file import default_plant_config_path, load_plant_config
    base = load_plant_config(default_plant_config_path())
    os.makedirs(out_dir, exist_ok=True)
    save_model(os.path.join(out_dir, "reference.yaml"), base.model)
    paths = []
    for day in range(runs):
        cfg = copy.deepcopy(base)
        cfg.effects = {"creep": {"gamma": creep_gamma(day)}}
        if resonance:
            cfg.effects["dynamics"] = {"kind": "resonance", "zeta": 0.1,
                                       "fn_hz": resonance_hz(day, fs_hz)}
        cfg.seed = 100 + day
        parts = [gap_protocol(fs_hz, seed=2 * day + k)[1] for k in range(2)]  # x only
        vx = np.concatenate(parts)
        vy = np.zeros_like(vx)
        w = Plant(cfg, fs_hz).run(vx, vy)
        t = np.arange(vx.size) / fs_hz
        rec = Record(t, {"x": vx}, {"x": w["x"]}, source=f"day {day}")
        path = os.path.join(out_dir, f"run{day:02d}")
        started = START + timedelta(days=day)
        write_record_bag(path, rec, metadata={"piezo_stage_run": {
            "started_utc": started.isoformat()}})
        paths.append(path)
    return paths
