"""PNG figures of the commands' results, written atomically (complete or absent):
an identification (measured and modelled loop, fit error over time) and a tracking
run (desired and measured, error over time), like the seed's figures."""

from __future__ import annotations

import numpy as np

from piezo_stage.io.files import atomic_write


def _pyplot():
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    return plt


def _save(fig, path):
    with atomic_write(path, "wb") as fh:
        fig.savefig(fh, format="png", dpi=100)
    _pyplot().close(fig)
    return path


def identification_png(path, t, per_axis: dict):
    """``per_axis``: {axis: (v [V], measured [um], model [um])} -> the loop (measured
    and model against voltage) and the fit error over time, one row per axis."""
    plt = _pyplot()
    fig, ax = plt.subplots(len(per_axis), 2, figsize=(12, 3.8 * len(per_axis)),
                           squeeze=False)
    for row, (axis, (v, w, pred)) in enumerate(per_axis.items()):
        e = w - pred
        ax[row, 0].plot(v, w, ".", ms=0.6, color="0.6", label="measured")
        ax[row, 0].plot(v, pred, lw=0.8, color="tab:red", label="identified model")
        ax[row, 0].set(xlabel="voltage [V]", ylabel="displacement [um]",
                       title=f"axis {axis}: hysteresis loop")
        ax[row, 0].legend()
        ax[row, 1].plot(t, e, lw=0.5)
        ax[row, 1].set(xlabel="time [s]", ylabel="measured - model [um]",
                       title=f"axis {axis}: fit error, rms {np.sqrt(np.mean(e ** 2)):.4f} um, "
                             f"max {np.max(np.abs(e)):.4f} um")
    fig.tight_layout()
    return _save(fig, path)


def tracking_png(path, t, desired, measured, axes=("x", "y")):
    """``desired``, ``measured``: (n, len(axes)) [um] at times t [s] -> the desired and
    measured position and the tracking error over time, one row per axis."""
    plt = _pyplot()
    fig, ax = plt.subplots(len(axes), 2, figsize=(12, 3.8 * len(axes)), squeeze=False)
    for i, axis in enumerate(axes):
        e = measured[:, i] - desired[:, i]
        ax[i, 0].plot(t, desired[:, i], lw=1.0, label="desired")
        ax[i, 0].plot(t, measured[:, i], lw=0.6, label="measured")
        ax[i, 0].set(xlabel="time [s]", ylabel="position [um]", title=f"axis {axis}: tracking")
        ax[i, 0].legend()
        ax[i, 1].plot(t, e, lw=0.5)
        span = max(np.ptp(desired[:, i]), 1e-12)
        ax[i, 1].set(xlabel="time [s]", ylabel="measured - desired [um]",
                     title=f"axis {axis}: error, rms {np.sqrt(np.mean(e ** 2)):.4f} um "
                           f"({100 * np.sqrt(np.mean(e ** 2)) / span:.3f} % of the range)")
    fig.tight_layout()
    return _save(fig, path)


def experiment_png(path, evals):
    """``evals``: [(case, evaluation)] from piezo_stage.experiments -> per case, the
    desired and true position of each judged axis over its window, and the errors
    against the true and the measured position (the seed's Figs. 17-25 layout)."""
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
        ax[row, 0].set(ylabel="um", title=case.name)
        ax[row, 1].set(ylabel="error [um]", title=case.name + ": error")
        ax[row, 0].legend(fontsize=7, loc="upper right")
        ax[row, 1].legend(fontsize=7, loc="upper right")
    ax[-1, 0].set(xlabel="time in the window [s]")
    ax[-1, 1].set(xlabel="time in the window [s]")
    fig.tight_layout()
    return _save(fig, path)
