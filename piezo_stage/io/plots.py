"""PNG figures of the commands' results, written atomically (complete or absent):
an identification (measured and modelled loop, fit error over time) and a tracking
run (desired and measured, error over time), like the paper's figures."""

from __future__ import annotations

from typing import Any

import numpy as np

from piezo_stage.core.types import PerAxis
from piezo_stage.io.files import atomic_write

# the figure functions a ``FigureWorker`` draws (by name: the request crosses a pipe)
DRAWN_APART = ("identification_png", "tracking_png")


class FigureWorker:
    """A figure drawn in a process of its own that imports matplotlib (0.7 s of a
    2-core host's CPU) while the command still computes what it will draw, on the other
    core: `identify` on a short record spent half its time on its figure.

    ``FigureWorker()`` starts the process (``python -m piezo_stage.io.plots``);
    ``draw(name, *args)`` hands it the figure function's arguments (pickled, over its
    stdin) and waits for the path it wrote; where the process cannot (it did not start,
    died, or the figure raised there), the figure is drawn here instead, so the worker
    changes when a figure is drawn, never whether. ``close()`` ends a worker never asked
    to draw (a command that failed first) at once: it has written nothing."""

    def __init__(self) -> None:
        import subprocess
        import sys
        self.proc: subprocess.Popen | None
        try:
            self.proc = subprocess.Popen(
                [sys.executable, "-m", "piezo_stage.io.plots"], stdin=subprocess.PIPE,
                stdout=subprocess.PIPE, stderr=subprocess.DEVNULL)
        except OSError:
            self.proc = None

    def draw(self, name: str, *args):
        """``name``'s figure (one of DRAWN_APART) from ``args`` -> its path."""
        import pickle
        proc = self.proc
        self.proc = None
        if proc is not None:
            try:
                out, _ = proc.communicate(pickle.dumps((name, args)), timeout=300)
                ok, got = pickle.loads(out)
                if ok:
                    return got
            except Exception:  # noqa: BLE001 - drawn here instead, below
                if proc.poll() is None:
                    proc.kill()
                    proc.wait()
        return globals()[name](*args)

    def close(self) -> None:
        proc, self.proc = self.proc, None
        if proc is not None:  # never asked: it has written nothing
            proc.kill()
            proc.communicate()

    def __enter__(self) -> FigureWorker:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def _serve() -> int:
    """The worker's side: matplotlib imported first, then one request from stdin (none:
    exit), its answer (True, path) or (False, why) on stdout. A stop signal is its
    command's: the worker ignores it and ends with its stdin."""
    import pickle
    import signal
    import sys
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, signal.SIG_IGN)
    _pyplot()
    data = sys.stdin.buffer.read()
    if not data:
        return 0
    try:
        name, args = pickle.loads(data)
        if name not in DRAWN_APART:
            raise ValueError(f"{name!r}: not a figure the worker draws")
        answer = (True, globals()[name](*args))
    except Exception as e:  # noqa: BLE001 - said to the command, which draws it itself
        answer = (False, f"{type(e).__name__}: {e}")
    sys.stdout.buffer.write(pickle.dumps(answer))
    return 0


def _pyplot():
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    return plt


def _grid_layout(fig, left_in=0.8, right_in=0.25, top_in=0.4, bottom_in=0.6,
                 wspace_in=0.8, hspace_in=0.85):
    """Margins and gaps of a grid of panels set in inches, what ``tight_layout`` would
    find for panels with one line of tick labels, an axis label and a one-line title,
    without measuring every text first: that measuring was a third of a figure's time
    (0.15 s of ``identify``'s 0.5 s figure on a 2-core host)."""
    w, h = fig.get_size_inches()
    rows, cols = fig.axes[0].get_subplotspec().get_gridspec().get_geometry()
    aw = (w - left_in - right_in - wspace_in * (cols - 1)) / cols
    ah = (h - top_in - bottom_in - hspace_in * (rows - 1)) / rows
    fig.subplots_adjust(left=left_in / w, right=1 - right_in / w, top=1 - top_in / h,
                        bottom=bottom_in / h, wspace=wspace_in / aw, hspace=hspace_in / ah)


def _save(fig, path):
    with atomic_write(path, "wb") as fh:
        fig.savefig(fh, format="png", dpi=100)
    _pyplot().close(fig)
    return path


def identification_png(path, t, per_axis: PerAxis[Any], validation: tuple | None = None):
    """``per_axis``: {axis: (v [V], measured [um], model [um], samples left out at the
    start)} -> the loop (measured and model against voltage) and the fit error over
    time, one row per axis, its figures over the samples the table's are (the first
    ones, a lag's start-up, drawn but not counted); with ``validation`` (t_val [s],
    {axis: (v, measured, model)}), the record the model was scored on beside it: its
    loop and its error, in a second colour."""
    plt = _pyplot()
    fig, ax = plt.subplots(len(per_axis), 2, figsize=(12, 3.8 * len(per_axis)),
                           squeeze=False)
    t_val, val = validation if validation is not None else (None, {})
    for row, (axis, (v, w, pred, skip)) in enumerate(per_axis.items()):
        e = w - pred
        ax[row, 0].plot(v, w, ".", ms=0.6, color="0.6", label="measured (fit)")
        ax[row, 0].plot(v, pred, lw=0.8, color="tab:red", label="identified model")
        title = (f"axis {axis}: fit error, rms {np.sqrt(np.mean(e[skip:] ** 2)):.4f} um, "
                 f"max {np.max(np.abs(e[skip:])):.4f} um"
                 + (f"\nafter the first {skip} samples (the lag's start-up)" if skip
                    else ""))
        ax[row, 1].plot(t, e, lw=0.5, label="fit record")
        if axis in val:
            vv, wv, pv = val[axis]
            ev = wv - pv
            ax[row, 0].plot(vv, wv, ".", ms=0.6, color="tab:cyan",
                            label="measured (validation)")
            ax[row, 0].plot(vv, pv, lw=0.8, color="tab:purple", label="model (validation)")
            ax[row, 1].plot(np.asarray(t_val) - t_val[0] + t[-1], ev, lw=0.5,
                            color="tab:purple", label="validation record (after it)")
            ax[row, 1].legend(fontsize=8)
            title += f"\nvalidation rms {np.sqrt(np.mean(ev ** 2)):.4f} um"
        ax[row, 0].set(xlabel="voltage [V]", ylabel="displacement [um]",
                       title=f"axis {axis}: hysteresis loop")
        ax[row, 0].legend(fontsize=8)
        ax[row, 1].set(xlabel="time [s]", ylabel="measured - model [um]", title=title)
    _grid_layout(fig, top_in=0.6, hspace_in=1.05)
    return _save(fig, path)


def tracking_png(path, run, t_track_s, excite_s=0.0, axes=("x", "y")):
    """The whole recorded run (``run``: io.run_bag.Run), one row per axis: the
    measured and desired position over the run, with the excitation (the
    identification's data) shaded and the start of tracking marked; the tracking
    window alone (from ``t_track_s`` [s]), where desired and measured can be told
    apart; and the tracking error there."""
    plt = _pyplot()
    t = run.t_ns * 1e-9
    ref_t = np.array(sorted(run.desired_um)) if run.desired_um else np.zeros(0, np.int64)
    ref = np.array([run.desired_um[k] for k in ref_t]).reshape(-1, 2)
    meas = dict(zip(run.t_ns.tolist(), run.w_um))
    both = [k for k in ref_t.tolist() if k in meas and k >= t_track_s * 1e9]
    tt = np.array(both) * 1e-9
    d = np.array([run.desired_um[k] for k in both]).reshape(-1, 2)
    w = np.array([meas[k] for k in both]).reshape(-1, 2)
    fig, ax = plt.subplots(len(axes), 3, figsize=(16, 3.8 * len(axes)), squeeze=False)
    # one colour per signal in every panel: desired C0 (dashed), measured C1
    for i, axis in enumerate(axes):
        a = ax[i, 0]
        a.plot(t, run.w_um[:, i], lw=0.6, color="C1", label="measured")
        a.plot(ref_t * 1e-9, ref[:, i], lw=0.8, ls="--", color="C0", label="desired")
        if excite_s > 0:
            a.axvspan(t[0] if t.size else 0.0, excite_s, color="0.9",
                      label="excitation (identified from)")
        a.axvline(t_track_s, color="k", lw=0.8, ls=":", label="tracking from")
        a.set(xlabel="time [s]", ylabel="position [um]", title=f"axis {axis}: the whole run")
        a.legend(fontsize=7, loc="upper left")
        a = ax[i, 1]
        a.plot(tt, d[:, i], lw=1.0, ls="--", color="C0", label="desired")
        a.plot(tt, w[:, i], lw=0.6, color="C1", label="measured")
        a.set(xlabel="time [s]", ylabel="position [um]", title=f"axis {axis}: tracking")
        a.legend(fontsize=7)
        e = w[:, i] - d[:, i]
        rms = float(np.sqrt(np.mean(e ** 2))) if e.size else float("nan")
        span = max(float(np.ptp(d[:, i])) if d.size else 0.0, 1e-12)
        ax[i, 2].plot(tt, e, lw=0.5)
        ax[i, 2].set(xlabel="time [s]", ylabel="measured - desired [um]",
                     title=f"axis {axis}: error, rms {rms:.4f} um "
                           f"({100 * rms / span:.3f} % of the range)")
    _grid_layout(fig)
    return _save(fig, path)


def experiment_png(path, evals):
    """``evals``: [(case, evaluation)] from piezo_stage.apps.experiments -> per case, the
    desired and true position of each judged axis over its window, and the errors
    against the true and the measured position (the paper's Figs. 17-25 layout)."""
    plt = _pyplot()
    n = len(evals)
    fig, ax = plt.subplots(n, 2, figsize=(12, 2.4 * n), squeeze=False)
    for row, (case, ev) in enumerate(evals):
        t = ev["t"]
        for a in case.judged:
            i = "xy".index(a)
            ax[row, 0].plot(t, ev["desired"][:, i], lw=1.0, label=f"{a} desired")
            ax[row, 0].plot(t, ev["true"][:, i], lw=0.6, label=f"{a} true")
            ax[row, 1].plot(t, ev["measured"][:, i] - ev["desired"][:, i], lw=0.4,
                            color="0.7", label=f"{a} measured - desired")
            ax[row, 1].plot(t, ev["true"][:, i] - ev["desired"][:, i], lw=0.7,
                            label=f"{a} true - desired")
        ax[row, 0].set(ylabel="position [um]", title=case.name)
        ax[row, 1].set(ylabel="error [um]", title=case.name + ": error")
        for a in ax[row]:  # a held axis (30 um +- 0.1) read plainly, not as "+3e1"
            a.ticklabel_format(axis="y", useOffset=False, style="plain")
        ax[row, 0].legend(fontsize=7, loc="upper right")
        ax[row, 1].legend(fontsize=7, loc="upper right")
    ax[-1, 0].set(xlabel="time in the window [s]")
    ax[-1, 1].set(xlabel="time in the window [s]")
    fig.tight_layout()
    return _save(fig, path)


def scan_png(path, evals):
    """``evals``: [(plant, case, evaluation)] from piezo_stage.apps.scan -> per plant, the
    raster whose linearity error without learning is the largest, as the stage traced
    it against the ideal grid before and after learning (each line's fast-axis error
    drawn across the line, magnified, trace and retrace in their own colours), and
    every case's error per period."""
    plt = _pyplot()
    plants = list(dict.fromkeys(p for p, _, _ in evals))
    fig, ax = plt.subplots(len(plants), 3, figsize=(15, 4.6 * len(plants)), squeeze=False)
    for row, plant in enumerate(plants):
        mine = [(c, ev) for p, c, ev in evals if p == plant]
        rasters = [(c, ev) for c, ev in mine if c.kind == "raster"]
        worst = max((ev["axes"]["x"]["linearity_rms_pct_of_scan"], c.freq_hz)
                    for c, ev in rasters if not c.learning)[1] if rasters else None
        line_rate_hz = worst
        grids = {c.learning: (c, ev) for c, ev in rasters if c.freq_hz == worst}
        if len(grids) == 2:
            c0, ev0 = grids[False]
            spacing = float(np.ptp(ev0["desired"][:, 1])) / max(1, c0.periods - 1)
            # magnified by what is judged: the central 80 % of the sweeps after the first
            # period (the approach's transient would otherwise set the scale)
            emax = 0.0
            for c, ev in grids.values():
                later = ev["period"] > 0
                d0, e0 = ev["desired"][later, 0], (ev["true"] - ev["desired"])[later, 0]
                mid = np.abs(d0 - d0.min() - np.ptp(d0) / 2) <= 0.4 * np.ptp(d0)
                emax = max(emax, float(np.max(np.abs(e0[mid]))) if mid.any() else 0.0)
            want = 0.45 * spacing / max(emax, 1e-9)
            dec = 10 ** np.floor(np.log10(want))
            mag = float(max(m * dec for m in (1, 2, 5) if m * dec <= want))
            for col, learn in enumerate((False, True)):
                c, ev = grids[learn]
                d, e = ev["desired"], ev["true"][:, 0] - ev["desired"][:, 0]
                vel = np.gradient(d[:, 0])
                a = ax[row, col]
                a.plot(d[:, 0], d[:, 1], color="0.8", lw=0.6, label="ideal grid")
                for sel, colour, lab in ((vel > 0, "tab:blue", "trace"),
                                         (vel < 0, "tab:red", "retrace")):
                    a.plot(np.where(sel, d[:, 0], np.nan), d[:, 1] + mag * e, lw=0.6,
                           color=colour, label=f"{lab}: x error x{mag:g} drawn in y")
                a.set(xlabel="x [um]", ylabel="y [um]",
                      title=f"{plant}: raster {line_rate_hz:g} Hz, "
                      f"{'after' if learn else 'without'} learning")
                a.legend(fontsize=7, loc="upper right")
        a = ax[row, 2]
        for c, ev in mine:
            per = ev["axes"]["x"]["per_period_pct"]
            a.semilogy(np.arange(1, len(per) + 1), np.maximum(per, 1e-4),
                       "-" if c.learning else "--", lw=1.0, label=c.name)
        a.set(xlabel="period", ylabel="x mean |true - desired| [% of range]",
              title=f"{plant}: error per period (floor 1e-4 %)", ylim=(5e-5, None))
        a.legend(fontsize=7, ncol=2)
    fig.tight_layout()
    return _save(fig, path)


def _date_format(fmt: str):
    import matplotlib.dates as mdates
    return mdates.DateFormatter(fmt)


def refit_png(path, rows: list):
    """An archive's refits over time (``apps/refit`` rows, date order): per axis the
    gain and the held-out error, the change of each model against the newest and,
    against a reference, each effect's size (relative to its first value)."""
    from datetime import datetime
    plt = _pyplot()
    axes = [a for a in ("x", "y") if any(a in r["axes"] for r in rows)]
    against = any("against" in r["axes"].get(a, {}) for r in rows for a in axes)
    ncol = 3 if against else 2
    fig, ax = plt.subplots(len(axes), ncol, figsize=(5 * ncol, 3.4 * len(axes)),
                           squeeze=False)
    when = [datetime.fromisoformat(r["started_utc"]) for r in rows]
    for i, a in enumerate(axes):
        def col(key):
            return [r["axes"].get(a, {}).get(key, np.nan) for r in rows]
        ax[i, 0].plot(when, col("gain_um_per_V"), "o-", ms=3, color="tab:blue")
        ax[i, 0].set(ylabel="gain [um/V]", title=f"axis {a}: gain over its fitted span")
        ax[i, 1].plot(when, col("held_out_rms_um"), "o-", ms=3, color="tab:orange",
                      label="its own model, held out")
        ax[i, 1].plot(when, col("change_um"), "s--", ms=3, color="tab:green",
                      label="against the newest model")
        ax[i, 1].set(ylabel="RMS [um]", title=f"axis {a}: error and change")
        ax[i, 1].legend(fontsize=8)
        if against:
            named = sorted({e for r in rows for e in r["axes"].get(a, {})
                            .get("against", {}).get("effects", {})})
            for e in named:
                y = [r["axes"].get(a, {}).get("against", {}).get("effects", {})
                     .get(e, {}).get("size", 0.0) for r in rows]
                y0 = next((v for v in y if v), 1.0)
                ax[i, 2].plot(when, np.asarray(y) / y0, "o-", ms=3, label=e)
            ax[i, 2].axhline(1.0, color="0.7", lw=0.8)
            ax[i, 2].set(ylabel="size / first", title=f"axis {a}: effects against the "
                         "reference")
            if named:
                ax[i, 2].legend(fontsize=8)
            else:  # an empty panel says so
                ax[i, 2].text(0.5, 0.5, "none found", transform=ax[i, 2].transAxes,
                              ha="center", va="center", color="0.4")
        one_day = bool(when) and (max(when) - min(when)).total_seconds() < 86400
        day = f", {when[0]:%Y-%m-%d}" if one_day else ""
        for j in range(ncol):  # dated to the second where the runs share a day
            ax[i, j].tick_params(axis="x", labelrotation=30, labelsize=8)
            ax[i, j].xaxis.set_major_formatter(_date_format("%H:%M:%S" if one_day
                                                           else "%Y-%m-%d"))
            ax[i, j].set_xlabel(f"run started (UTC{day})")
    fig.tight_layout()
    return _save(fig, path)


if __name__ == "__main__":
    raise SystemExit(_serve())
