"""The live watch on a simulated stage that changes during a run, without the node set:
the stage (core/model/plant.py with its ``changes``), the gap node's twin and watch
(``ResidualMonitor``, ``LiveWatch``), each window diagnosed at once and a refit taken
as the node takes it. The watch's test and `bench watch` judge these runs."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from piezo_stage.core.estimation.gap.monitor import ResidualMonitor
from piezo_stage.core.estimation.gap.watch import (
    LiveWatch,
    WatchEvent,
    diagnose_window,
    effects_of,
    model_in_use,
    settle_samples,
)
from piezo_stage.paths import default_config

CHANGES = {  # what switches on mid-run, as a plant file's ``changes`` says it
    "creep": {"creep": {"enabled": True, "gamma": 0.06, "tau_s": [0.05, 0.5, 5.0, 50.0]}},
    "drift": {"drift": {"enabled": True, "rate_um_per_s": 0.02, "amplitude_um": 0.5,
                        "tau_s": 60.0}},
}


def default_voltages(seconds: float, fs: float) -> np.ndarray:
    """Both axes' voltages [V] for the default trajectory's motion (a 10 Hz sine over
    the stage's stroke) for ``seconds``."""
    t = np.arange(int(round(seconds * fs))) / fs
    return 45.0 + 45.0 * np.sin(2 * np.pi * 10.0 * t - np.pi / 2)


@dataclass
class WatchedRun:
    """One run: the watch's events, each axis's block RMS with the watch (the twin
    switched at each hand-on) and without (the model of the start throughout), and the
    level after arming."""

    events: list[WatchEvent] = field(default_factory=list)
    blocks: dict[str, list[float]] = field(default_factory=dict)
    plain: dict[str, list[float]] = field(default_factory=dict)
    level: dict[str, float] = field(default_factory=dict)


def watched_run(change: str | None, seconds: float, at_s: float = 20.0, fs: float = 1000.0,
                seed: int = 0) -> WatchedRun:
    """The package's simulated stage driven by ``default_voltages``, ``change`` (a key of
    CHANGES, or None: a stage that does not change) switching on at ``at_s``, watched
    against the package's model."""
    from piezo_stage.core.model.model_doc import model_from_dict
    from piezo_stage.core.model.plant import Plant
    from piezo_stage.io.model_file import load_model
    from piezo_stage.io.plant_file import load_plant_config
    model, effects = load_model(default_config("stage_model.yaml"))
    cfg = load_plant_config(default_config("sim_stage.yaml"))
    cfg.seed = seed
    cfg.changes = [{"at_s": at_s, "effects": CHANGES[change]}] if change else []
    v = default_voltages(seconds, fs)
    w = Plant(cfg, fs).run(v, v)
    mon = ResidualMonitor(model, effects, fs, 1000)
    plain = LiveWatch(fs, model_in_use(model, effects))
    twin0 = Plant.of_model(model, effects, fs).run(v, v)
    r0 = np.column_stack([w["x"] - twin0["x"], w["y"] - twin0["y"]])
    r0 -= r0[:100].mean(axis=0)  # the monitor's zero
    watch = LiveWatch(fs, model_in_use(model, effects))
    out = WatchedRun()
    for i in range(len(v)):
        vi, wi = {"x": v[i], "y": v[i]}, {"x": w["x"][i], "y": w["y"][i]}
        plain.sample(vi, wi, {"x": r0[i, 0], "y": r0[i, 1]})
        req = watch.sample(vi, wi, mon.sample(wi, vi))
        if req is None:
            continue
        ev = watch.decide(req, diagnose_window(req))
        out.events.append(ev)
        if ev.handed_on and ev.model_doc is not None:
            m2, e2 = model_from_dict(ev.model_doc, "the watch's model")
            history = watch.since(req.start_index)
            assert history is not None
            mon.switch(m2, e2, history, settle=settle_samples(req))
            watch.adopted(ev.model_doc, effects_of(e2))
    out.blocks, out.plain, out.level = watch.blocks, plain.blocks, watch.level
    return out


def last_rms(blocks: dict[str, list[float]], n: int = 10) -> dict[str, float]:
    """The RMS of each axis's last ``n`` blocks [um]."""
    return {a: float(np.sqrt(np.mean(np.square(b[-n:])))) for a, b in blocks.items()}


def rises_per_hour(minutes: float, fs: float = 1000.0, seed: int = 1) -> tuple[int, float]:
    """A stage that does not change for ``minutes``: the rises its watch finds (each a
    false alarm; every one would be diagnosed) -> (rises, per hour)."""
    run = watched_run(None, minutes * 60.0, fs=fs, seed=seed)
    return len(run.events), len(run.events) / (minutes / 60.0)


__all__ = ["CHANGES", "WatchedRun", "default_voltages", "last_rms", "rises_per_hour",
           "watched_run"]
