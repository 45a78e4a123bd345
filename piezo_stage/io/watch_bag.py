"""The story of a watched run, read back from its bag: the live gap over the run, each
diagnosis the gap node's watch made (its /diagnostics status, one per diagnosis), and
each model handed on (``model``), and in lockstep each sample the set waited at while a
window was diagnosed (``watch/hold``), on the stage's clock (seconds from the first
sample).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from piezo_stage.core.errors import DataError
from piezo_stage.io.bag import deserialize, iter_messages
from piezo_stage.io.run_bag import status_node
from piezo_stage_msgs_adapters.wire import HOLD_WAIT, joint_state_um, point_um


@dataclass
class WatchStory:
    """A watched run: the residual per sample ``t_s``/``r_um`` ((n, 2): x, y), the
    level after arming per axis, the diagnoses (each a dict of the ``watch_*`` values,
    in order), the stage times [s] at which models went out on ``model``, and
    (lockstep) the samples' stage times [s] the set waited at while it diagnosed."""

    t_s: np.ndarray
    r_um: np.ndarray
    level_um: dict[str, float] = field(default_factory=dict)
    diagnoses: list[dict[str, str]] = field(default_factory=list)
    models_s: list[float] = field(default_factory=list)
    holds_s: list[float] = field(default_factory=list)

    def rms_um(self, t0: float, t1: float) -> dict[str, float]:
        """The residual's RMS per axis between stage times ``t0`` and ``t1`` [um]."""
        k = (self.t_s >= t0) & (self.t_s < t1)
        return {a: float(np.sqrt(np.mean(self.r_um[k, i] ** 2))) if k.any() else
                float("nan") for i, a in enumerate("xy")}


def read_watch(bag: str) -> WatchStory:
    """The watched run in ``bag`` (DataError: no residual of a gap node in it)."""
    t, r = [], []
    first_ns: int | None = None
    log_to_stage: list[tuple[int, int]] = []  # (log time, stamp) of the stage's samples
    diag_log: list[tuple[int, dict[str, str]]] = []
    model_log: list[int] = []
    holds_ns: list[int] = []
    for topic, msgtype, log_ns, data in iter_messages(bag):
        if topic.endswith("/gap/residual"):
            ns, p = point_um(data)
            t.append(ns)
            r.append((p["x"], p["y"]))
        elif topic.endswith("/joint_states"):
            try:
                ns = joint_state_um(data)[0]
            except DataError:
                continue
            first_ns = ns if first_ns is None else min(first_ns, ns)
            if not log_to_stage or log_ns - log_to_stage[-1][0] > 10_000_000:
                log_to_stage.append((log_ns, ns))
        elif topic == "/diagnostics":
            for st in deserialize(data, msgtype).status:
                if status_node(st.name) == "gap":
                    diag_log.append((log_ns, {k.key: k.value for k in st.values}))
        elif topic.endswith("/model") and not topic.endswith("/gap/model"):
            model_log.append(log_ns)
        elif topic.endswith("/watch/hold"):
            h = deserialize(data, msgtype)
            if h.frame_id == HOLD_WAIT:
                holds_ns.append(h.stamp.sec * 1_000_000_000 + h.stamp.nanosec)
    if not t:
        raise DataError(f"{bag}: no gap/residual in it: the run had no gap node "
                        "(`piezo-stage launch --watch`)")
    if first_ns is None:
        first_ns = min(t)
    order = np.argsort(t)
    story = WatchStory((np.array(t)[order] - first_ns) * 1e-9, np.array(r)[order])
    story.holds_s = [(ns - first_ns) * 1e-9 for ns in holds_ns]
    seen = set()
    for _, kv in diag_log:
        if "watch_level_um" in kv and not story.level_um:
            lv = kv["watch_level_um"].split(",")
            if all(x != "nan" for x in lv):
                story.level_um = {a: float(x) for a, x in zip("xy", lv)}
        key = kv.get("watch_at_s")
        if key is not None and key not in seen:
            seen.add(key)
            story.diagnoses.append({k: v for k, v in kv.items() if k.startswith("watch_")})
    if log_to_stage:
        logs = np.array([x[0] for x in log_to_stage])
        stamps = np.array([x[1] for x in log_to_stage])
        for ns in model_log:  # the stage's sample recorded nearest the model's arrival
            i = int(np.clip(np.searchsorted(logs, ns), 0, len(logs) - 1))
            story.models_s.append((stamps[i] - first_ns) * 1e-9)
    return story


def plot_story(story: WatchStory, path: str, title: str = "") -> None:
    """The watched run as a figure (PNG, written whole or not at all): the live gap's
    RMS over 0.5 s per axis, its level after arming, each rise (its window shaded, the
    diagnosis at its end) and each model handed on."""
    import os

    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from piezo_stage.io.files import atomic_write
    fig, ax = plt.subplots(figsize=(9, 4))
    span = 0.5
    edges = np.arange(0.0, float(story.t_s[-1]) + span, span)
    idx = np.digitize(story.t_s, edges) - 1
    for i, a in enumerate("xy"):
        ss = np.bincount(idx, story.r_um[:, i] ** 2, len(edges))
        n = np.bincount(idx, None, len(edges))
        ok = n > 0
        ax.plot(edges[ok] + span / 2, np.sqrt(ss[ok] / n[ok]), label=f"live gap {a}")
        if a in story.level_um:
            ax.axhline(story.level_um[a], color=f"C{i}", ls=":", lw=1)
    for d in story.diagnoses:
        t0, t1 = float(d["watch_onset_s"]), float(d["watch_at_s"])
        ax.axvspan(t0, t1, color="0.85", zorder=0)
        ax.annotate(f"{d.get('watch_effect') or 'none'}: "
                    f"{d['watch_gap_before_um']} -> {d['watch_gap_after_um']} um",
                    (t1, ax.get_ylim()[1] * 0.9), fontsize=8)
    for t in story.models_s:
        ax.axvline(t, color="k", ls="--", lw=1)
    ax.set_xlabel("stage time [s]")
    ax.set_ylabel("RMS over 0.5 s [um]")
    ax.set_title(f"{os.path.basename(title.rstrip('/'))}: shaded, a rise's window "
                 "(diagnosed at its end); dashed, a model handed on", fontsize=9)
    ax.legend(fontsize=8)
    fig.tight_layout()
    with atomic_write(path, "wb") as fh:
        fig.savefig(fh, format="png", dpi=110)
    plt.close(fig)
