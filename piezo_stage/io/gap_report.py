"""The gap report: a self-contained Markdown file with PNG plots, readable without
the JSON: the verdict and why, the ranking table, where the gap lies, and plots of
the residual over time, its spectrum, the loop overlay and before/after."""

from __future__ import annotations

import os

from scipy import signal

from piezo_stage.io.files import atomic_write


def write_report(out_dir, result, holdout):
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    os.makedirs(out_dir, exist_ok=True)
    lines = ["# Sim-to-real gap report", "",
             f"**Verdict: {result['verdict']}** — {result['reason']}", "",
             f"Noise floor (from the data): {result['noise_floor_um']:.4f} um. "
             "Scored on " + ("the FIT record itself (no holdout given)"
                             if result["holdout_is_fit"] else "the HOLDOUT record") + ". "
             f"Run time {result['seconds']:.1f} s.", ""]
    for axis, d in result.per_axis.items():
        lines += [f"## Axis {axis}: {d.verdict}", "", d.reason, "",
                  "| effect | rms before um | rms after um | gap before um | gap after um | "
                  "shrink % | parameters |", "|---|---|---|---|---|---|---|"]
        for r in d.ranking:
            params = ", ".join(f"{k}={v:.4g}" if isinstance(v, float) else f"{k}={v}"
                               for k, v in r["params"].items())
            lines.append(f"| {r['effect']} | {r['rms_before_um']:.4f} | {r['rms_after_um']:.4f} | "
                         f"{r['gap_before_um']:.4f} | {r['gap_after_um']:.4f} | "
                         f"{r['shrink_pct']:.1f} +- {r.get('shrink_pm_pct', float('nan')):.1f}"
                         f" | {params} |")
        wh = d.where
        lines += ["", f"Where: band {wh['band_hz'][0]:g}-{wh['band_hz'][1]:g} Hz, segment "
                  f"**{wh['segment']}** (RMS by segment: " +
                  ", ".join(f"{k} {v:.3f}" for k, v in wh['segment_rms_um'].items()) +
                  " um), by amplitude: " +
                  ", ".join(f"{k} {v:.3f}" for k, v in wh['amplitude_rms_um'].items()) + " um" +
                  (f", correlation with the other axis's input {wh['corr_other_input']:.2f}"
                   if "corr_other_input" in wh else "") + ".", ""]
        if d.effects:
            lines += ["Effects kept, in the order added (each refitted with the ones "
                      "before it, scored on the held-out record):", "",
                      "| effect | gap after um | shrink of the whole gap % | chosen by | "
                      "parameters |", "|---|---|---|---|---|"]
            for st in d.effects:
                params = ", ".join(f"{k}={v:.4g}" if isinstance(v, float) else f"{k}={v}"
                                   for k, v in st["params"].items())
                pm = st.get("shrink_pm_pct", float("nan"))
                lines.append(f"| {step_label(st)} | {st['gap_after_um']:.4f} | "
                             f"{st['shrink_pct']:.1f} +- {pm:.1f} | {st.get('rule', '')} | "
                             f"{params} |")
            lines.append("")
        b = d.budget
        if b:
            lines += ["Gap budget (um, parts add in quadrature):", "",
                      f"- held-out residual {b['residual_rms_um']:.4f} = noise floor "
                      f"{b['noise_floor_um']:.4f} + locked to the input "
                      f"{b['input_locked_um']:.4f} + not locked to the input "
                      f"{b['not_input_locked_um']:.4f} (closure {b['closure_pct']:+.1f} %)",
                      f"- gap {b['gap_um']:.4f}: explained " + (", ".join(
                          f"{k} {v:.4f}" for k, v in b["explained_um"].items()) or "nothing")
                      + f"; unexplained {b['unexplained_um']:.4f}"]
            if b.get("disturbance"):
                x = b["disturbance"]
                lines.append(f"- disturbance (not caused by the input): {x['rms_um']:.4f} "
                             f"um at {x['freq_hz']:.1f} Hz; feedback bandwidth to reject "
                             f"it >= {x['feedback_bandwidth_hz']:.0f} Hz")
            lines.append("")
        fig = axis_figure(d, holdout, axis)
        png = f"gap_{axis}.png"
        fig.savefig(os.path.join(out_dir, png), dpi=100)
        plt.close(fig)
        lines += [f"![axis {axis}]({png})", ""]
    with atomic_write(os.path.join(out_dir, "report.md")) as fh:
        fh.write("\n".join(lines) + "\n")
    return os.path.join(out_dir, "report.md")


def step_label(st) -> str:
    """A kept effect as the diagnosis names it: a lag kept as a delay's shape says so."""
    return st["effect"] + (f" (the {st['shape_of']}'s shape)" if st.get("shape_of") else "")


def kept_label(d) -> str:
    """What the "after" model holds, as the legend names it: the effects the diagnosis
    kept, joined (a given model's own effects are the base's); with none kept, the
    best candidate the table ranks first."""
    return "+".join(st["effect"] for st in d.effects) or \
        (d.ranking[0]["effect"] if d.ranking else "none")


def axis_figure(d, holdout, axis):
    """One axis's figure: residual before/after, its spectrum, the loop overlay and
    the candidates' held-out gaps (alone and joined, each bar labelled with its value:
    a bar at 0 is seen as one)."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    base = d.candidates["none"]
    best = d.model or d.candidates.get(d.ranking[0]["effect"], base)
    w = holdout.w[axis]
    pb = base.predict(holdout, axis)
    pa = best.predict(holdout, axis)
    t = holdout.t
    fig, ax = plt.subplots(2, 2, figsize=(12, 7))
    ax[0, 0].plot(t, w - pb, lw=0.4, label="before (base model)")
    # named by what the diagnosis kept (a given model's own effects are the base's)
    after = kept_label(d)
    ax[0, 0].plot(t, w - pa, lw=0.4, label=f"after ({after})")
    ax[0, 0].set(xlabel="time [s]", ylabel="measured - model [um]", title="residual")
    ax[0, 0].legend()
    for r, lab in ((w - pb, "before"), (w - pa, "after")):
        f, P = signal.welch(r - r.mean(), fs=holdout.fs_hz,
                            nperseg=min(len(r), 4096))
        ax[0, 1].loglog(f[1:], P[1:], lw=0.8, label=lab)
    ax[0, 1].set(xlabel="frequency [Hz]", ylabel="PSD [um^2/Hz]", title="residual spectrum")
    ax[0, 1].legend()
    v = holdout.v[axis]
    ax[1, 0].plot(v, w, ".", ms=0.5, color="0.6", label="measured")
    ax[1, 0].plot(v, pb, lw=0.5, label="base model")
    ax[1, 0].set(xlabel="voltage [V]", ylabel="displacement [um]", title="loop overlay")
    ax[1, 0].legend()
    # each candidate alone, then the effects as joined (each with the ones before)
    effs = [r["effect"] for r in d.ranking]
    alone = ax[1, 1].bar(effs, [r["gap_after_um"] for r in d.ranking],
                         color="tab:blue", label="gap after, alone")
    ax[1, 1].bar_label(alone, fmt="%.3g", fontsize=6)  # a bar at 0 is seen as one
    joined = ["+".join(st["effect"] for st in d.effects[:i + 1])
              for i in range(len(d.effects))]
    if joined:
        bars = ax[1, 1].bar(joined, [st["gap_after_um"] for st in d.effects],
                            color="tab:orange", label="gap after, joined")
        ax[1, 1].bar_label(bars, fmt="%.3g", fontsize=6)
    ax[1, 1].axhline(d.ranking[0]["gap_before_um"], color="k", ls="--",
                     label="gap before")
    ax[1, 1].set(ylabel="held-out gap [um]",
                 title="before / after: each candidate, and as joined")
    ax[1, 1].tick_params(axis="x", labelrotation=30)
    # beside the bars, not over them
    ax[1, 1].legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.01, 1.0))
    fig.suptitle(f"axis {axis}: verdict {d.verdict}")
    fig.tight_layout()
    return fig
