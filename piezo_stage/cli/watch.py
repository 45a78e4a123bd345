"""`piezo-stage watch BAG`: the story of a watched run (launch --watch)."""

from __future__ import annotations

HELP = "the story of a watched run: the live gap, each diagnosis, each model handed on"


def add_arguments(s):
    s.add_argument("bag", help="a bag of `piezo-stage launch --watch --record DIR`")
    s.add_argument("--every", type=float, default=5.0, metavar="S",
                   help="the live gap's RMS over spans this long (default 5 s)")
    s.add_argument("--plot", metavar="FILE.png",
                   help="a figure of the run: the live gap over time, each rise, "
                   "diagnosis and model handed on")


def main(args):
    import sys

    from piezo_stage.core.errors import DataError
    from piezo_stage.io.watch_bag import read_watch
    if not args.every > 0:
        sys.stderr.write("piezo-stage watch: --every must be > 0\n")
        return 2
    try:
        story = read_watch(args.bag)
    except (DataError, OSError) as e:
        sys.stderr.write(f"piezo-stage watch: {e}\n")
        return 2
    end = float(story.t_s[-1]) if len(story.t_s) else 0.0
    lv = story.level_um
    print(f"{args.bag}: {end:.1f} s; the live gap's level after arming x/y "
          + (f"{lv['x']:.4f}/{lv['y']:.4f} um" if lv else "not measured yet"))
    marks = sorted([(float(d["watch_at_s"]), "diagnosis") for d in story.diagnoses]
                   + [(t, "model") for t in story.models_s])
    print("live gap RMS x/y [um] by span:")
    t0 = 0.0
    while t0 < end - 0.5 * args.every or t0 == 0.0:
        t1 = end + 1e-9 if t0 + 1.5 * args.every > end else t0 + args.every
        g = story.rms_um(t0, t1)
        here = [m for at, m in marks if t0 <= at < t1]
        print(f"  {t0:6.1f}-{t1:6.1f} s  {g['x']:.4f} / {g['y']:.4f}"
              + (f"   <- {', '.join(here)}" if here else ""))
        t0 = t1
    for i, d in enumerate(story.diagnoses, 1):
        print(f"diagnosis {i}: the gap rose on {d.get('watch_axes', '?')} at "
              f"{float(d['watch_onset_s']):.1f} s, diagnosed on the window to "
              f"{float(d['watch_at_s']):.1f} s: {d.get('watch_effect', 'none')}, held-out "
              f"gap {d['watch_gap_before_um']} -> {d['watch_gap_after_um']} um "
              f"({d['watch_shrink_pct']} %), "
              + ("handed on" if d.get("watch_handed_on") == "true" else "not handed on")
              + f": {d.get('watch_reason', '')}")
    for t in story.holds_s:
        print(f"the set waited at {t:.3f} s while the window was diagnosed (lockstep)")
    for t in story.models_s:
        print(f"model on /model at {t:.1f} s")
    if not story.diagnoses:
        print("no diagnosis: the live gap never rose clearly above its level")
    if args.plot:
        from piezo_stage.io.watch_bag import plot_story
        plot_story(story, args.plot, args.bag)
        print(f"figure: {args.plot}")
    return 0
