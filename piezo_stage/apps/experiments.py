"""`piezo-stage experiment`: the paper's control experiments run through the node set.

Every case is one run of the real node set (driver on the simulated stage or the DAQ,
feedforward, controller, trajectory, recorder) on a trajectory written for it, recorded
to its own bag; every figure is computed from the bags. Errors are against the true
position (``/stage/sim/true_position``, simulated stages) and, separately, against the
measured one, over the last ``EVAL_CYCLES`` cycles of the motion, and at least
``EVAL_MIN_S`` (tracking at 5 Hz and above: 2 cycles at 40 Hz are only 50 samples)
(the first cycles settle the hysteresis memory the approach left).

Experiments (the paper's section 4):

* ``decoupling``: one axis driven by a 1 Hz sine over 5-65 um, the other held at
  30 um; the held axis's motion is the coupling, with the feedforward's coupling
  compensation off and on (the paper's Figs. 17-18), feedforward only so that the feedback
  does not hide what the decoupling does;
* ``tracking``: the paper's y(t) = 21 + 24 sin(2 pi f t - pi/2) um on both axes at 1, 5,
  10 and 40 Hz with feedforward only, feedback only and composite (Figs. 19-20);
* ``amplitude``: 1 Hz, constant 60 um and variable 60/40/20 um cycles (Figs. 22-25);
  both start 1 um above the stage's 0 V rest (0 um is reachable only at exactly 0 V,
  so a feedback correction below it would clamp);
* ``noise``: no input, the stage at rest; the displacement shown (Fig. 21).

With a model that has unmodelled effects (``gap --out-model``) the tracking cases are
also run with the effect compensation off, so the table shows what it earns.
"""

from __future__ import annotations

import os
import shutil
from dataclasses import dataclass, field

import numpy as np

from piezo_stage.core.errors import ConfigError, DataError, RunError
from piezo_stage.core.loop.arming import ENABLED
from piezo_stage.core.types import Doc, Params, PerAxis
from piezo_stage.io.files import atomic_write

EXPERIMENTS = ("decoupling", "tracking", "amplitude", "noise")
CONTROLLERS = ("feedforward", "feedback", "composite")
FREQS_HZ = (1.0, 5.0, 10.0, 40.0)
RATE_HZ = 1000.0
EVAL_CYCLES = 2
EVAL_MIN_S = 0.5   # tracking: at least this long (40 Hz: 20 cycles, not 2 = 50 samples)
LEAD_S, TAIL_S = 0.2, 0.3  # trajectory holds its first point, then its last
LOCKSTEP_SLACK_S = 0.3  # a lockstep run's steps beyond its trajectory and approach
# real time: more (the feedforward sees the enable a look-ahead and a transport later)
REALTIME_SLACK_S = 0.7
NODES = ("stage_driver", "feedforward", "controller", "trajectory")


@dataclass
class Case:
    """One run: a trajectory, a controller, what is judged."""
    name: str
    freq_hz: float
    t: np.ndarray
    w: PerAxis[np.ndarray]                  # axis -> desired [um]
    controller: str               # feedforward | feedback | composite | none
    judged: tuple = ("x", "y")    # axes whose errors are figures
    moving: str = "x"             # an axis that moves (the window is found on it)
    eval_s: float = 2.0
    params: Params = field(default_factory=dict)  # node -> extra parameters
    group: str = ""               # decoupling: runs compared pairwise share a group
    saturated: int = 0            # targets saturated to the stage's range


def _traj(f_hz, cycles, wave):
    """A trajectory at RATE_HZ: LEAD_S at its first point, ``cycles`` of ``wave(t)``
    (t from 0), TAIL_S at its last point."""
    dt = 1.0 / RATE_HZ
    n_move = int(round(cycles / f_hz / dt))
    tm = np.arange(n_move + 1) * dt
    w = wave(tm)
    lead = np.full(int(LEAD_S / dt), w[0])
    tail = np.full(int(TAIL_S / dt), w[-1])
    x = np.concatenate([lead, w, tail])
    return np.arange(x.size) * dt, x


def _seed_wave(f):
    return lambda t: 21.0 + 24.0 * np.sin(2 * np.pi * f * t - np.pi / 2)


def _controller_params(c):
    ctl: dict[str, object] = {"feedback": c in ("feedback", "composite")}
    if c == "feedback":  # the integral carries the whole voltage
        ctl["integral_limit_V"] = 150.0
    return {"feedforward": {"inverse_feedforward": c in ("feedforward", "composite")},
            "controller": ctl}


def merge_params(*ds: Doc) -> Params:
    """{node: parameters} mappings merged, later ones over earlier ones, per node."""
    out: dict[str, Doc] = {}
    for d in ds:
        for node, p in d.items():
            out.setdefault(node, {}).update(p)
    return out


def plan(name, freqs=FREQS_HZ, controllers=CONTROLLERS, with_effects=False):
    """The cases of experiment ``name``."""
    if name not in EXPERIMENTS:
        raise ConfigError(f"unknown experiment {name!r}; use one of {', '.join(EXPERIMENTS)}")
    cases = []
    if name == "tracking":
        for f in freqs:
            n_eval = max(EVAL_CYCLES, int(np.ceil(EVAL_MIN_S * f)))
            cycles = max(n_eval + 1, int(np.ceil(1.0 * f)) + n_eval)
            t, w = _traj(f, cycles, _seed_wave(f))
            for c in controllers:
                for comp in ((True, False) if with_effects else (True,)):
                    tag = "" if comp else " (effects not compensated)"
                    cases.append(Case(f"tracking {f:g} Hz {c}{tag}", f, t, {"x": w, "y": w}, c,
                                      eval_s=n_eval / f,
                                      params=merge_params(_controller_params(c), {
                                          "feedforward": {"compensate_effects": comp}})))
    elif name == "decoupling":
        f = 1.0
        # 5-65 um: most of the stroke, within both axes' reach at 150 V (y: ~71 um)
        t, w = _traj(f, EVAL_CYCLES + 1, lambda t: 35.0 + 30.0 * np.sin(2 * np.pi * t - np.pi / 2))
        for driven, held in (("x", "y"), ("y", "x")):
            hold = np.full_like(w, 30.0)
            for on in (False, True):
                cases.append(Case(f"decoupling {driven} driven, compensation "
                                  f"{'on' if on else 'off'}", f, t, {driven: w, held: hold},
                                  "feedforward", judged=(held,), moving=driven,
                                  eval_s=EVAL_CYCLES / f, group=f"{driven}->{held}",
                                  params=merge_params(_controller_params("feedforward"),
                                                {"feedforward": {"use_coupling": on}})))
    elif name == "amplitude":
        f = 1.0
        t, w = _traj(f, EVAL_CYCLES + 1, lambda t: 31.0 - 30.0 * np.cos(2 * np.pi * t))
        cases.append(Case("amplitude constant 60 um", f, t, {"x": w, "y": w}, "composite",
                          eval_s=EVAL_CYCLES / f, params=_controller_params("composite")))
        peaks = np.array([60.0, 40.0, 20.0])
        var = lambda t: 1.0 + peaks[np.floor(t).astype(int) % 3] / 2 * (  # noqa: E731
            1 - np.cos(2 * np.pi * t))
        t, w = _traj(f, 6, var)
        cases.append(Case("amplitude variable 60/40/20 um", f, t, {"x": w, "y": w},
                          "composite", eval_s=3.0, params=_controller_params("composite")))
    else:  # noise: nothing moves; the stage rests where 0 V puts it
        t = np.arange(int(3.0 * RATE_HZ)) / RATE_HZ
        z = np.zeros_like(t)
        cases.append(Case("noise at rest", 0.0, t, {"x": z, "y": z}, "none", moving="",
                          eval_s=2.0, params=_controller_params("none")))
    return cases


def _write_csv(path, t, w):
    with atomic_write(path) as fh:
        fh.write("t,wx,wy\n")
        for row in zip(t, w["x"], w["y"]):
            fh.write("%.6f,%.9g,%.9g\n" % row)


def lockstep_margin_s(case, config, extra=None) -> float:
    """Simulated time a lockstep run needs beyond its trajectory: the planner's approach
    from the stage at rest (0 um) to the first point, at the feedforward's approach
    speed and acceleration, and LOCKSTEP_SLACK_S for arming (a few samples). A stage
    resting elsewhere needs a longer approach: its run then ends before the trajectory
    does and the evaluation says so (RunError), nothing is judged on a short run."""
    from piezo_stage.core.loop.feedforward import PARAMETERS
    from piezo_stage.core.loop.planner import Approach
    from piezo_stage.core.params import defaults
    from piezo_stage.launcher.launcher import read_parameters
    p: Params = defaults(PARAMETERS)
    p.update(read_parameters(config).get("feedforward", {}))
    p.update({**(extra or {}).get("feedforward", {}), **case.params.get("feedforward", {})})
    first = {a: float(v[0]) for a, v in case.w.items()}
    ap = Approach(dict.fromkeys(first, 0.0), first, float(p["approach_speed_um_per_s"]),
                  float(p["approach_accel_um_per_s2"]))
    return ap.duration_s + LOCKSTEP_SLACK_S


def run_case(case, bag, config, plant=None, model=None, mode="lockstep", extra=None,
             namespace="/stage", env=None, exclusive=True, seed=None) -> None:
    """Run the node set for one case into ``bag``. RunError (exit 1) when the set fails;
    KeyboardInterrupt when the command is stopped. ``exclusive``: look for a set already
    running in the namespace first (about 2 s on a quiet domain); an experiment looks
    before its first case only, its later cases follow its own sets, each stopped before
    the next starts.

    The driver counts the run's samples from the one at which the stage first enabled
    (``max_steps_from_arming``): the approach, the trajectory and a little slack, in both
    modes, however long discovery and arming took before it."""
    from piezo_stage.launcher.launcher import Launch, LaunchOptions, run_set
    os.makedirs(os.path.dirname(os.path.abspath(bag)) or ".", exist_ok=True)
    csv = os.path.abspath(bag) + ".trajectory.csv"
    _write_csv(csv, case.t, case.w)
    total_s = float(case.t[-1]) + lockstep_margin_s(case, config, extra) + (
        0.0 if mode == "lockstep" else REALTIME_SLACK_S)
    drv = {"mode": mode}
    if plant:
        drv["plant_config"] = os.path.abspath(plant)
    drv.update(max_steps=int(total_s * control_rate(config, extra)), exit_after_max_steps=True,
               max_steps_from_arming=True)
    if seed is not None:  # the simulated stage's noise: a repeat draws anew
        drv["seed"] = int(seed)
    o = merge_params(extra or {}, {"stage_driver": drv, "trajectory": {"kind": "csv",
                                                                 "csv_path": csv}},
               {"feedforward": {"model_file": os.path.abspath(model)}} if model else {},
               case.params)
    launch = Launch(config, LaunchOptions(record=bag, overrides=o, namespace=namespace,
        nodes=list(NODES), exclusive=exclusive), env=env)
    run_set(launch, case.name, duration=900.0)


def enabled_span(states) -> tuple[int, float] | None:
    """(from, to) stamps [ns] of the last stretch in which the driver applied commands:
    from the enable that began it (the approach's start, stamped in sample time by the
    driver itself) to the next state that is not enabled (or the end). None: the stage
    never enabled. The 'armed' stamp is not used: it is when the driver heard the
    feedforward's phase, which in lockstep can be a second of samples after the
    trajectory clock started."""
    seq = sorted(states)
    start = None
    for i, (since, st) in enumerate(seq):
        if st in ENABLED and (i == 0 or seq[i - 1][1] not in ENABLED):
            start = i
    if start is None:
        return None
    end = next((since for since, st in seq[start + 1:] if st not in ENABLED), float("inf"))
    return seq[start][0], end


def _window(case, run):
    """Stamps of the evaluation window: the last eval_s of the motion, within the last
    stretch the driver applied commands (at the end of a real-time run it disarms and
    the feedforward then holds where the stage is, which moves with the noise). A run
    that cannot give it is a RunError: the run failed, not its input."""
    ks = sorted(k for k in run.desired_um if k in run.true_um)
    span = enabled_span(run.states)
    if span is None:
        raise RunError(f"{case.name}: the set never armed (states: "
                       f"{', '.join(st for _, st in sorted(run.states)) or 'none'})")
    ks = [k for k in ks if span[0] <= k < span[1]]
    if len(ks) < 10:
        raise RunError(f"{case.name}: no tracking samples in the bag")
    i = "xy".index(case.moving) if case.moving else None
    d = np.array([run.desired_um[k] for k in ks])
    if i is None:
        end = ks[-1]
    else:
        moved = np.nonzero(np.abs(np.diff(d[:, i])) > 1e-9)[0]
        if moved.size == 0 or ks[moved[-1] + 1] > ks[-1] - int(0.5 * TAIL_S * 1e9):
            raise RunError(f"{case.name}: the run ended before the trajectory did")
        end = ks[moved[-1] + 1]
    start = end - int(round(case.eval_s * 1e9))
    if start < ks[0]:
        raise RunError(f"{case.name}: the run is shorter than its evaluation window "
                       f"({(end - ks[0]) * 1e-9:.3f} s of {case.eval_s:g} s armed)")
    return [k for k in ks if start < k <= end]


def evaluate(case, bag) -> Doc:
    """Per judged axis, the errors against the true and the measured position."""
    from piezo_stage.io.run_bag import read_run
    run = read_run(bag)
    ks = _window(case, run)
    meas = dict(zip(run.t_ns.tolist(), run.w_um))
    ks = [k for k in ks if k in meas]
    d = np.array([run.desired_um[k] for k in ks])
    pos = {"true": np.array([run.true_um[k] for k in ks]),
           "measured": np.array([meas[k] for k in ks])}
    ff = run.diagnostics.get("feedforward", {})
    out = {"t": (np.array(ks) - ks[0]) * 1e-9, "desired": d, **pos, "axes": {},
           "saturated_voltages": int(float(ff.get("saturated", 0))),
           "effects": ff.get("effects", "")}
    for a in case.judged:
        i = "xy".index(a)
        span = float(np.ptp(d[:, "xy".index(case.moving)])) if case.moving else 0.0
        for ref, w in pos.items():
            e = w[:, i] - d[:, i]
            if case.controller == "none":
                e = e - e.mean()  # at rest: the displacement about where the stage rests
            out["axes"][(a, ref)] = {
                "max_err_um": float(np.max(np.abs(e))),
                "rms_err_um": float(np.sqrt(np.mean(e ** 2))),
                "mean_abs_err_pct_of_range": (float(100 * np.mean(np.abs(e)) / span)
                                              if span > 0 else None)}
    return out


def saturate(cases, range_um, warn):
    """Targets outside the stage's range are saturated to it (with a warning, counted
    per case), never sent: the feedforward would refuse the whole trajectory."""
    lo, hi = range_um
    for c in cases:
        n = sum(int(np.sum((w < lo) | (w > hi))) for w in c.w.values())
        c.saturated = n
        if n:
            c.w = {a: np.clip(w, lo, hi) for a, w in c.w.items()}
            warn(f"{c.name}: {n} target(s) outside the range {lo:g}..{hi:g} um saturated")
    return cases


def _range(config, extra):
    from piezo_stage.launcher.launcher import read_parameters
    r = {**read_parameters(config).get("feedforward", {}),
         **(extra or {}).get("feedforward", {})}.get("range_um", [-10.0, 90.0])
    return float(r[0]), float(r[1])


def control_rate(config, extra):
    """The driver's control rate [Hz] (``--params`` may raise it where the backend can
    run it): its step count ends the run."""
    from piezo_stage.launcher.launcher import read_parameters
    return float({**read_parameters(config).get("stage_driver", {}),
                  **(extra or {}).get("stage_driver", {})}.get("control_rate_hz", RATE_HZ))


class Interrupted(KeyboardInterrupt):
    """A stop in the middle of an experiment, with what the finished cases gave:
    ``doc`` and ``evals`` as ``run_experiment`` returns them."""

    def __init__(self, doc: Doc, evals: list, total: int):
        super().__init__()
        self.doc, self.evals, self.total = doc, evals, total


def run_experiment(name, out_dir, config, plant=None, model=None, mode="lockstep",
                   freqs=FREQS_HZ, controllers=CONTROLLERS, extra=None, namespace="/stage",
                   env=None, log=print, warn=None, seed=None):
    """Run every case of ``name``; bags under ``out_dir``. Returns the JSON document and
    the per-case evaluations (for the plots). ``seed``: the simulated stage's noise
    seed of the first case (the next cases the following ones; None: the plant's own).
    A stop (KeyboardInterrupt) after some cases raises ``Interrupted`` with theirs."""
    import sys

    from piezo_stage.io.model_file import load_model
    from piezo_stage.progress import bar
    effects = bool(load_model(model)[1]) if model else False
    cases = saturate(plan(name, freqs, controllers, with_effects=effects),
                     _range(config, extra),
                     warn or (lambda m: sys.stderr.write(f"warning: {m}\n")))
    doc = {"experiment": name, "plant": os.path.abspath(plant) if plant else "default",
           "model": os.path.abspath(model) if model else None, "mode": mode, "cases": []}
    if seed is not None:
        doc["seed"] = int(seed)
    evals: list = []
    with bar(total=len(cases), desc=f"experiment {name}", unit="run") as pb:
        try:  # a stop anywhere between cases too (after a case's line, before the next)
            for k, case in enumerate(cases):
                bag = os.path.join(out_dir, f"{k:02d}_" + "".join(
                    c if c.isalnum() else "_" for c in case.name).strip("_"))
                if os.path.exists(bag):
                    shutil.rmtree(bag)
                run_case(case, bag, config, plant, model, mode, extra, namespace, env,
                         exclusive=k == 0, seed=None if seed is None else int(seed) + k)
                ev = evaluate(case, bag)
                rows = [{"name": case.name, "axis": a, "freq_hz": case.freq_hz,
                         "controller": case.controller, "reference": ref,
                         **fig, "saturated_targets": case.saturated,
                         "saturated_voltages": ev["saturated_voltages"],
                         "effects": ev["effects"], "bag": os.path.abspath(bag)}
                        for (a, ref), fig in ev["axes"].items()]
                evals.append((case, ev))
                doc["cases"].extend(rows)
                pb.update(1)
                log(f"  {case.name}: " + ", ".join(
                    f"{a} {ref} rms {f['rms_err_um']:.4f} um"
                    for (a, ref), f in ev["axes"].items()))
        except KeyboardInterrupt:
            if len(doc["cases"]) < sum(len(ev["axes"]) for _, ev in evals):
                evals.pop()  # stopped between a case's two records: the case is not done
            if name == "decoupling":
                _reductions(doc)
            raise Interrupted(doc, evals, len(cases)) from None
    if name == "decoupling":
        _reductions(doc)
    return doc, evals


def _reductions(doc):
    """Decoupling: each 'on' case gets the coupling RMS before (off) and after (on)."""
    by: dict[tuple, Doc] = {}
    for c in doc["cases"]:
        driven = c["name"].split()[1]
        by.setdefault((driven, c["axis"], c["reference"]), {})[
            "on" if c["name"].endswith("on") else "off"] = c
    for pair in by.values():
        if "on" in pair and "off" in pair:
            before, after = pair["off"]["rms_err_um"], pair["on"]["rms_err_um"]
            for c in pair.values():
                c.update(coupling_rms_before_um=before, coupling_rms_after_um=after,
                         reduction_pct=100.0 * (1 - after / before) if before > 0 else None)


def table(doc) -> str:
    """The cases as a fixed-width table (one line per case, axis and reference)."""
    lines = [f"{'case':<52} {'axis':>4} {'ref':>8} {'max_um':>8} {'rms_um':>8} "
             f"{'mean_pct':>8} {'reduction':>9}"]
    for c in doc["cases"]:
        pct = c["mean_abs_err_pct_of_range"]
        red = c.get("reduction_pct")
        lines.append(f"{c['name']:<52} {c['axis']:>4} {c['reference']:>8} "
                     f"{c['max_err_um']:8.4f} {c['rms_err_um']:8.4f} "
                     f"{'-' if pct is None else f'{pct:.3f}':>8} "
                     f"{'' if red is None else f'{red:.1f} %':>9}")
    return "\n".join(lines)


# -- the relay experiment of `piezo-stage tune --relay` ------------------------------------
def relay_case(setpoint_um: float = 30.0, duration_s: float = 3.0, amplitude_V: float = 2.0,
               hysteresis_um: float = 0.0) -> Case:
    """Both axes held at ``setpoint_um`` with the feedforward's hold voltage, the
    controller's feedback a relay (core.control.Relay) of ``amplitude_V``."""
    t = np.arange(int(round(duration_s * RATE_HZ)) + 1) / RATE_HZ
    w = np.full_like(t, float(setpoint_um))
    return Case("relay", 0.0, t, {"x": w, "y": w.copy()}, "relay", moving="",
                eval_s=duration_s, params={
                    "feedforward": {"inverse_feedforward": True},
                    "controller": {"feedback": True, "relay_amplitude_V": float(amplitude_V),
                                   "relay_hysteresis_um": float(hysteresis_um)}})


def relay_points(bag, amplitude_V: float, settle_s: float = 1.0) -> Doc:
    """Each axis's ultimate point (core.tuning.relay_point) from a relay run's bag: the
    samples of the enabled stretch from ``settle_s`` after its start to the end of the
    held trajectory, on the driver's sample grid (a missed tick holds its voltage and
    its position is interpolated); the latency is the driver's look-ahead."""
    from piezo_stage.core.loop.tuning import relay_point
    from piezo_stage.io.run_bag import read_run
    run = read_run(bag)
    span = enabled_span(run.states)
    if span is None:
        raise RunError("relay run: the set never armed")
    a0, a1 = span[0] + int(settle_s * 1e9), span[1]
    ref = [k for k in run.desired_um if a0 <= k < a1]
    if not ref:
        raise DataError("relay run: no samples after the settling time")
    dt_ns = int(round(1e9 / RATE_HZ))
    sel = (run.t_ns >= a0) & (run.t_ns <= max(ref))
    t, v, w = run.t_ns[sel], run.v_V[sel], run.w_um[sel]
    if t.size < 50:
        raise DataError(f"relay run: {t.size} samples after settling; run it longer")
    grid = np.arange(int(t[0]), int(t[-1]) + 1, dt_ns)
    idx = np.searchsorted(t, grid, side="right") - 1          # the voltage held
    lookahead_ms = float(run.driver.get("lookahead_ms", 1e3 / RATE_HZ))
    latency = max(1, int(round(lookahead_ms * 1e6 / dt_ns)))
    out = {}
    for j, a in enumerate("xy"):
        y = np.interp(grid, t, w[:, j])
        out[a] = relay_point(v[idx, j], y, RATE_HZ, amplitude_V, latency)
    return out


def run_relay(bag, config, plant=None, model=None, mode="lockstep", setpoint_um=30.0,
              duration_s=3.0, amplitude_V=2.0, hysteresis_um=0.0, settle_s=1.0, extra=None,
              namespace="/stage", env=None) -> Doc:
    """Run the relay experiment through the node set into ``bag``; each axis's
    ultimate point. RunError when the node set fails."""
    if not settle_s + 0.5 < duration_s:
        raise ConfigError("relay: the duration must exceed the settling time by 0.5 s")
    case = relay_case(setpoint_um, duration_s, amplitude_V, hysteresis_um)
    run_case(case, bag, config, plant, model, mode, extra, namespace, env)
    return relay_points(bag, amplitude_V, settle_s)
