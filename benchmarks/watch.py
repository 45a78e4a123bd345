"""`piezo-stage bench watch`: the live watch (the gap node's ``watch``) on the simulated
stage whose creep, or a drift, switches on at 20 s of a 60 s run of the default
trajectory's motion, and on one that does not change for ``minutes``: how soon the rise
is found and diagnosed, what is named, the live gap over the last 10 s with the watch
and without it against its level after arming, and the false alarms per hour
(apps/studies/watch_cases.py: the core's twin, watch and diagnosis, no node set)."""

from __future__ import annotations

import time


def bench_watch(rep, minutes: float = 10.0) -> int:
    """The two changes and the quiet stage (``rep``: the report)."""
    from piezo_stage.apps.studies.watch_cases import last_rms, rises_per_hour, watched_run
    from piezo_stage.core.estimation.gap.watch import WatchOptions
    o = WatchOptions()
    rep.title(f"the package's simulated stage, 60 s at 1 kHz, a change at 20 s; the "
              f"watch's window {o.fit_s:g} s FIT + {o.holdout_s:g} s HOLDOUT after a rise "
              f"of {o.sustain_blocks} blocks of {o.block_s:g} s above {o.rise:g} x the "
              f"level and {o.sigmas:g} spreads")
    rows, met = [], True
    for change in ("creep", "drift"):
        t0 = time.perf_counter()
        run = watched_run(change, 60.0)
        took = time.perf_counter() - t0
        handed = [e for e in run.events if e.handed_on]
        first = handed[0] if handed else (run.events[0] if run.events else None)
        after, plain = last_rms(run.blocks), last_rms(run.plain)
        ratio = max(after[a] / run.level[a] for a in after)
        ratio_plain = min(plain[a] / run.level[a] for a in plain)
        named = "+".join(e.effect for e in handed) or "nothing"
        rows.append([change, f"{first.onset_s - 20.0:.1f}" if first else "-",
                     f"{first.at_s - 20.0:.1f}" if first else "-", named,
                     f"{first.gap_before_um:.3f} -> {first.gap_after_um:.3f}" if first
                     else "-", f"{ratio:.2f}", f"{ratio_plain:.2f}", f"{took:.0f}"])
        ok = bool(handed) and handed[0].effect == change and handed[0].at_s <= 35.0 and \
            ratio <= 1.5 and ratio_plain >= 2.0
        rep.target(f"{change}: named within 15 s, last 10 s <= 1.5 x the level with the "
                   "watch, >= 2 x without", ok)
        met = met and ok
    rep.table(["change at 20 s", "rise found after [s]", "window diagnosed after [s]",
               "named and handed on", "held-out gap [um]", "last 10 s / level, watched",
               "unwatched", "run + diagnoses [s]"], rows)
    t0 = time.perf_counter()
    rises, per_hour = rises_per_hour(minutes)
    bound = 3.0 / (minutes / 60.0)  # the 95 % upper bound of a Poisson count of 0
    rep.figures([("a stage that does not change", f"{minutes:g} min: {rises} rise(s), "
                  f"{per_hour:.1f} false alarms per hour" + (
                      f" (95 % upper bound {bound:.0f} per hour)" if rises == 0 else "")
                  + f"; {time.perf_counter() - t0:.0f} s")])
    rep.target("no effect named on a stage that does not change", rises == 0)
    return 0 if met and rises == 0 else 1
