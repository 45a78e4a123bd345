"""Benchmarks: each prints its figures as ratios against a baseline run in the same process.

Never imported by tests for timing; run ``piezo-stage bench <what>``.
"""

from __future__ import annotations

import time

import numpy as np

from piezo_stage.bench_procs import cpu_ticks, progress_runs
from piezo_stage.core.plant import Plant
from piezo_stage.io.plant_file import default_plant_config_path, load_plant_config


def _plain_python_plant(n: int, fs: float):
    """The same Plant.run with numba switched off (NUMBA_DISABLE_JIT=1): every kernel
    runs as its plain-Python original, the baseline _jit.py promises. Returns (seconds,
    (wx, wy))."""
    import os
    import subprocess
    import sys
    import tempfile
    with tempfile.TemporaryDirectory() as d:
        out = os.path.join(d, "w.npy")
        r = subprocess.run([sys.executable, "-m", "piezo_stage.bench_procs", "plain",
                            str(n), str(fs), out],
                           env=dict(os.environ, NUMBA_DISABLE_JIT="1"), capture_output=True,
                           text=True, check=True)
        w = np.load(out)
    return float(r.stdout.split()[-1]), (w[0], w[1])


def bench_plant(n_samples: int):
    cfg = load_plant_config(default_plant_config_path())
    fs = cfg.internal_rate_hz  # one command per internal sample: every sample counted
    t = np.arange(n_samples) / fs
    vx = 75 - 75 * np.cos(2 * np.pi * 1.0 * t)
    vy = 75 - 75 * np.cos(2 * np.pi * 1.3 * t + 0.4)
    Plant(cfg, fs).run(vx[:1000], vy[:1000])  # compile (or load the cache) first

    plant = Plant(cfg, fs)
    t0 = time.perf_counter()
    w = plant.run(vx, vy)
    fast = time.perf_counter() - t0

    n_py = min(n_samples, 100_000)
    slow, (px, py) = _plain_python_plant(n_py, fs)
    agree = max(np.max(np.abs(px - w["x"][:n_py])), np.max(np.abs(py - w["y"][:n_py])))

    fast_rate = n_samples / fast
    slow_rate = n_py / slow
    print("bench plant: 2-axis simulated stage, segmented Duhem + hysteretic coupling + "
          "clamp/slew + sensor noise and quantisation")
    print(f"  compiled batch : {n_samples:>9d} samples in {fast:7.3f} s = "
          f"{fast_rate / 1e6:6.2f} M samples/s per axis")
    print(f"  plain Python   : {n_py:>9d} samples in {slow:7.3f} s = "
          f"{slow_rate / 1e6:6.3f} M samples/s per axis (baseline)")
    print(f"  speed-up       : {fast_rate / slow_rate:6.1f} x the same kernels uncompiled")
    print(f"  agreement      : max |batch - loop| = {agree:.2e} um")
    print(f"  target >= 1 M samples/s per axis: {'met' if fast_rate >= 1e6 else 'NOT met'}")
    return 0 if agree < 1e-6 else 1


def _sim_record(n, fs, seed=11):
    from piezo_stage.core.record import Record
    cfg = load_plant_config(default_plant_config_path())
    cfg.seed = seed
    t = np.arange(n) / fs
    v = 75 - 75 * np.cos(2 * np.pi * 1.0 * t)
    w = Plant(cfg, fs).run(v, np.zeros(n))
    return cfg, Record(t, {"x": v}, {"x": w["x"]})


def _baseline_least_squares(rec, x0_model):
    """Generic output-error fit of all parameters at once (scipy least_squares, TRF),
    started from the same shared-alpha grid guess the fast solver starts from."""
    from scipy.optimize import least_squares

    from piezo_stage.core.duhem import DuhemBranch, DuhemModel, DuhemState
    v, w = rec.v["x"], rec.w["x"]
    s = 150.0
    p0 = np.concatenate([[np.log(x0_model.ascending.alpha), np.log(x0_model.descending.alpha)],
                         x0_model.ascending.h(True) * s ** np.arange(4),
                         x0_model.descending.h(False) * s ** np.arange(4), [w[0]]])

    def resid(p):
        a = DuhemBranch.from_h(np.exp(p[0]), p[2:6] / s ** np.arange(4))
        d = DuhemBranch.from_h(np.exp(p[1]), p[6:10] / s ** np.arange(4))
        y, _ = DuhemModel(a, d, DuhemState(v[0], p[10])).simulate(v)
        return y - w

    r = least_squares(resid, p0, method="trf", x_scale="jac", max_nfev=2000)
    return float(np.sqrt(np.mean(r.fun ** 2))), r.nfev


def bench_identify():
    import time

    from piezo_stage.core.identify import IdentifyOptions, identify_axis
    from piezo_stage.core.identify.fast import fit_fast
    from piezo_stage.core.identify.regress import DuhemRegression
    cfg, rec = _sim_record(10_000, 10_000.0)
    identify_axis(rec, "x")  # warm the compiled kernels
    t0 = time.perf_counter()
    res = identify_axis(rec, "x")
    fast_s = time.perf_counter() - t0
    ratio = res.fit["rms_um"] / cfg.noise_rms_um
    # baseline: generic nonlinear least squares from the alpha-grid starting point
    reg = DuhemRegression(rec.v["x"], rec.w["x"], "segmented")
    a0, f0, _ = fit_fast(reg, budget=21)
    start, _ = reg.models(a0, f0.theta)
    t0 = time.perf_counter()
    base_rms, base_nfev = _baseline_least_squares(rec, start)
    base_s = time.perf_counter() - t0
    print("bench identify: one axis, 10,000 samples, 1 Hz 0-150 V sine, noise 0.1 um RMS, "
          "no unmodelled effects")
    print(f"  fast (variable projection): {fast_s:7.3f} s, fit rms {res.fit['rms_um']:.4f} um "
          f"= {ratio:.3f} x sensor noise, {res.evaluations} evaluations")
    print(f"  baseline (least_squares on all 11 parameters): {base_s:7.3f} s, fit rms "
          f"{base_rms:.4f} um, {base_nfev} evaluations")
    print(f"  fast is {base_s / fast_s:.1f} x faster than the baseline; targets: rms <= 1.05 x "
          f"noise ({'met' if ratio <= 1.05 else 'NOT met'}), <= 0.5 s "
          f"({'met' if fast_s <= 0.5 else 'NOT met'})")
    _, rec2 = _sim_record(2000, 1000.0)
    for method in ("afsa", "afsa-bat"):
        t0 = time.perf_counter()
        r = identify_axis(rec2, "x", IdentifyOptions(method=method, seed=0))
        sw = time.perf_counter() - t0
        print(f"  {method:<8} 30 fish x 200 iterations per branch, 2,000 samples: {sw:6.2f} s "
              f"({sw / fast_s:5.1f} x fast), fit rms {r.fit['rms_um']:.4f} um, "
              f"{r.evaluations} evaluations; target <= 30 s "
              f"({'met' if sw <= 30 else 'NOT met'})")
    _bench_sparse_peer()
    return 0


def _bench_sparse_peer():
    """Ours beside the sparse hysteresis peer (Chandra et al. 2023, pysindy) on the
    issue's kind of record: one axis, a 1 Hz full-stroke sine at 5 kHz, fit on 3 s and
    held out on the next 4 s, from the default stage and from the structure stage
    (memory, a tanh envelope). Held-out RMS against the measured and the true
    displacement; ours re-estimate the initial output on HOLDOUT (as --validate),
    the peer starts at HOLDOUT's first measured sample (as its authors validate)."""
    import time

    from piezo_stage.core.errors import ConfigError
    from piezo_stage.core.gap import fit_candidate
    from piezo_stage.core.identify import identify_axis
    from piezo_stage.core.identify.api import predict_axis
    from piezo_stage.studies import sparse_peer
    from piezo_stage.studies.gap_blind import scan_cut

    def rms(e):
        return float(np.sqrt(np.mean(e ** 2))) if np.all(np.isfinite(e)) else float("nan")
    print("\n  the sparse peer (Chandra et al. 2023: dw/dt sparse in the monomials of degree "
          "<= 2 of w, v, dv/dt, |dv/dt|, |w|; pysindy STLSQ 0.01) beside ours; one axis, "
          "1 Hz 0-150 V sine, 5 kHz, fit 3 s, held out on the next 4 s")
    for config in ("sim_stage.yaml", "structure_stage.yaml"):
        fit, hold, true = scan_cut(config=config)
        rows = []
        t0 = time.perf_counter()
        res = identify_axis(fit, "x")
        fast_s = time.perf_counter() - t0
        pred = predict_axis(res, hold)[2]
        rows.append(("ours, fast (cubic branches)", fast_s, pred))
        t0 = time.perf_counter()
        base = fit_candidate(fit, "x", "none")
        mem = fit_candidate(fit, "x", "structure", base, base.effects, memory=True)
        mem_s = time.perf_counter() - t0
        rows.append(("ours, structure (degree 5 + 16 play operators)", mem_s,
                     mem.predict(hold, "x")))
        try:
            peer = sparse_peer.fit(fit, "x")
        except ConfigError as e:
            print(f"  {config}: the peer is left out ({e})")
        else:
            t0 = time.perf_counter()
            out = peer.simulate(hold, "x")
            rows.append((f"peer, sparse ({len(peer.terms)} terms; simulated in "
                         f"{time.perf_counter() - t0:.2f} s)", peer.fit_s, out))
        print(f"  {config} (sensor noise {rms(hold.w['x'] - true):.3f} um):")
        for name, sec, w in rows:
            print(f"    {name:<58} fit {sec:6.2f} s   held-out {rms(w - hold.w['x']):.4f} um "
                  f"measured, {rms(w - true):.4f} um true")


def _ring_rate(env, steps=3000):
    """Steps/s of a bare 3-process ring with empty callbacks on the loop nodes' own
    transport path: the ceiling of any three-hop lockstep loop with it on this host."""
    import subprocess
    import sys
    ring = [sys.executable, "-m", "piezo_stage.bench_procs", "ring"]
    others = [subprocess.Popen(ring + [a, b, str(steps)], env=env)
              for a, b in (("b", "c"), ("c", "a"))]
    try:
        r = subprocess.run(ring + ["a", "b", str(steps)], env=env,
                           capture_output=True, text=True, timeout=300)
        return float(r.stdout.split()[0])
    finally:
        for p in others:
            p.kill()
            p.wait()


def _loop_run(env, steps, foxglove_port=None):
    """One lockstep run with the recorder: (steps/s, median ms, p99 ms, lost per topic,
    steal fraction), or (None, log tail) when the run failed. With ``foxglove_port``
    the live view runs too (its client is the caller's)."""
    import contextlib
    import os
    import re
    import tempfile

    from piezo_stage.io.bag import iter_messages
    from piezo_stage.launch.launcher import Launch
    from piezo_stage.paths import default_config
    bag = os.path.join(tempfile.mkdtemp(), "bench")
    o = {"stage_driver": {"max_steps": steps, "exit_after_max_steps": True},
         "feedforward": {"model_file": default_config("stage_model.yaml")}}
    launch = Launch(default_config("stage.yaml"), record=bag, overrides=o, env=env,
                    nodes=["stage_driver", "feedforward", "controller", "trajectory"],
                    foxglove_port=foxglove_port)
    log = tempfile.TemporaryFile("w+")
    c0 = cpu_ticks()
    with contextlib.redirect_stderr(log):
        old = os.dup(2)
        os.dup2(log.fileno(), 2)
        try:
            rc = launch.run(duration=600)
        finally:
            os.dup2(old, 2)
    c1 = cpu_ticks()
    log.seek(0)
    text = log.read()
    m = re.search(r"done after (\d+) samples: (\d+) steps/s, step period median ([\d.]+) "
                  r"ms, p99 ([\d.]+) ms", text)
    if not m or rc != 0:
        return None, f"exit {rc}; {'; '.join(launch.failed)}\n{text[-2000:]}"
    counts = {}
    for topic, *_ in iter_messages(bag):
        counts[topic] = counts.get(topic, 0) + 1
    lost = {t: steps + 1 - counts.get(t, 0) for t in
            ("/stage/joint_states", "/stage/sim/true_position", "/stage/reference",
             "/stage/command")}
    steal = (c1[1] - c0[1]) / max(1, c1[0] - c0[0])
    return (int(m.group(2)), float(m.group(3)), float(m.group(4)), lost, steal), None


def bench_loop(steps=3000, runs=5):
    import os
    import random
    import subprocess
    import sys
    env = dict(os.environ, ROS_DOMAIN_ID=str(random.randint(101, 200)),
               ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST")
    ping = [sys.executable, "-m", "piezo_stage.bench_procs", "ping"]
    pong = subprocess.Popen(ping + ["pong"], env=env)
    try:
        r = subprocess.run(ping + ["ping", "2000"], env=env,
                           capture_output=True, text=True, timeout=300)
    finally:
        pong.terminate()
        pong.wait()
    rt_med, rt_p99 = map(float, r.stdout.split())
    print("bench loop: lockstep closed loop, driver + feedforward + controller + trajectory "
          "+ recorder as separate processes (Fast DDS, this host)")
    print(f"  baseline ping-pong (2 processes): round trip median {rt_med * 1e3:.3f} ms, "
          f"p99 {rt_p99 * 1e3:.3f} ms")
    print("  baseline ring: 3 processes passing one message round, empty callbacks, the "
          "nodes' lean wait set and raw CDR, no recorder; run before each loop run, so "
          "each ratio pairs two runs minutes apart at most (this host's speed drifts)")
    results, rings = [], []
    for k in progress_runs(range(runs), "bench loop: runs"):
        rings.append(_ring_rate(env))
        res, err = _loop_run(env, steps)
        if res is None:
            print("  the loop run failed:\n" + err)
            return 1
        rate, med, p99, lost, steal = res
        results.append(res)
        print(f"  pair {k + 1}: ring {rings[-1]:.0f} steps/s; loop {rate} steps/s = "
              f"{rate / rings[-1]:.2f} x the ring, step period median {med:.3f} ms, p99 "
              f"{p99:.3f} ms; lost {sum(lost.values())}; CPU steal by the host "
              f"{100 * steal:.1f} %")
    rates = sorted(r[0] for r in results)
    med_rate = rates[len(rates) // 2]
    med_period = sorted(r[1] for r in results)[len(results) // 2]
    ratios = sorted(r[0] / g for r, g in zip(results, rings))
    lost = {t: max(r[3][t] for r in results) for t in results[0][3]}
    print(f"  closed loop, median of {runs} runs of {steps} steps: {med_rate} steps/s "
          f"(range {rates[0]}-{rates[-1]}), step period median {med_period:.3f} ms = "
          f"{med_period / (rt_med * 1e3):.2f} x the ping-pong round trip; "
          f"{ratios[len(ratios) // 2]:.2f} x the ring's rate (median of the pairs, range "
          f"{ratios[0]:.2f}-{ratios[-1]:.2f}; target >= 0.5)")
    print(f"  recorder: messages lost per loop topic, worst run {lost} (0 = every "
          f"published message is in the bag)")
    print(f"  target >= 1000 steps/s (median run): "
          f"{'met' if med_rate >= 1000 else 'NOT met'}; 0 lost: "
          f"{'met' if not any(lost.values()) else 'NOT met'}")
    return 0


def _watched_loop_run(env, steps, port):
    """A lockstep run with the live view and a client watching joint_states: the run's
    figures, and (messages received, their rate per wall-clock second)."""
    import threading

    from piezo_stage.launch.foxglove_probe import connect, receive
    done, got = threading.Event(), {}

    def watch():
        try:
            with connect(port, timeout_s=120) as ws:
                got["data"] = receive(ws, "/stage/joint_states", timeout_s=600,
                                      stop=done.is_set)[1]
        except Exception as e:  # noqa: BLE001 - reported with the run's figures
            got["error"] = f"client: {type(e).__name__}: {e}"
    client = threading.Thread(target=watch, daemon=True)
    client.start()
    res, err = _loop_run(env, steps, foxglove_port=port)
    done.set()
    client.join(10)
    data = got.get("data", [])
    err = err or got.get("error")
    span = data[-1][2] - data[0][2] if len(data) > 1 else 0.0
    return res, err, len(data), (len(data) - 1) / span if span > 0 else 0.0


def bench_liveview(steps=6000, pairs=3):
    """The lockstep loop with and without the live view and a watching client,
    alternated in the same invocation (the host's load drifts): the slowdown, and
    what the client receives."""
    import os
    import random
    import socket
    env = dict(os.environ, ROS_DOMAIN_ID=str(random.randint(101, 200)),
               ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST")
    print(f"bench liveview: lockstep loop ({steps} steps, recorder on) without and with "
          "the live view (Foxglove WebSocket) and a client watching joint_states, "
          f"alternated, {pairs} pairs")
    plain, watched, rates = [], [], []
    for k in progress_runs(range(pairs), "bench liveview: pairs"):
        res, err = _loop_run(env, steps)
        if res is None:
            print("  the loop run failed:\n" + err)
            return 1
        with socket.socket() as s:
            s.bind(("127.0.0.1", 0))
            port = s.getsockname()[1]
        res_w, err, n, rate = _watched_loop_run(env, steps, port)
        if res_w is None:
            print("  the watched loop run failed:\n" + err)
            return 1
        plain.append(res[0])
        watched.append(res_w[0])
        rates.append(rate)
        if n == 0:
            print(f"  pair {k + 1}: the client received nothing ({err or 'no error'})")
        if sum(res_w[3].values()):
            print(f"  pair {k + 1}: messages lost in the watched run: {res_w[3]}")
        print(f"  pair {k + 1}: without {res[0]} steps/s, with {res_w[0]} steps/s "
              f"(ratio {res_w[0] / res[0]:.2f}); the client got {n} joint_states, "
              f"{rate:.0f}/s; lost in the bag {sum(res_w[3].values())}")
    med = lambda xs: sorted(xs)[len(xs) // 2]  # noqa: E731
    slow = 1 - med(watched) / med(plain)
    print(f"  median: without {med(plain)} steps/s, with {med(watched)} steps/s: the loop "
          f"is {100 * slow:.1f} % slower; the client receives {med(rates):.0f} "
          "joint_states/s (max_rate_hz 200)")
    print(f"  target >= 100 joint_states/s to the client: "
          f"{'met' if med(rates) >= 100 else 'NOT met'}; loop slowed <= 10 %: "
          f"{'met' if slow <= 0.10 else 'NOT met'}")
    return 0


def bench_gap(seeds=3):
    import time

    from piezo_stage.core.gap import diagnose
    from piezo_stage.studies import gap_blind
    print("bench gap: blind suite, one unmodelled effect per record pair (FIT, HOLDOUT), "
          "diagnosis not told which; axis x, 1 kHz, ~36 s protocol records (its chirp "
          "included)")
    from piezo_stage.progress import bar, steps
    with bar("bench gap: blind cases", total=2 * len(gap_blind.TRUTHS) * seeds,
             unit=" cases") as b:
        rows = gap_blind.run(seeds=seeds, progress=steps(b))
    for fam in ("own", "independent", None):
        labels, M = gap_blind.confusion(rows, fam)
        ok = sum(M[i, i] for i in range(len(gap_blind.TRUTHS)))
        print(f"\n  confusion matrix ({fam or 'all'}): rows truth, columns verdict; "
              f"correct {ok}/{M.sum()} = {100 * ok / M.sum():.0f} %")
        print("  " + " " * 10 + "".join(f"{lab[:8]:>9}" for lab in labels))
        for i, tname in enumerate(gap_blind.TRUTHS):
            print(f"  {tname:<10}" + "".join(f"{x:>9d}" for x in M[i]))
    shr = [r["shrink_true_pct"] for r in rows if r["truth"] != "none" and
           r["shrink_true_pct"] is not None]
    hits = [r for r in rows if r["truth"] != "none" and r["verdict"] == r["truth"]]
    low = min(hits, key=lambda r: r["shrink_true_pct"])
    print(f"\n  held-out gap shrink with the true effect: median {np.median(shr):.0f} %; "
          f">= 50 % in {sum(x >= 50 for x in shr)}/{len(shr)} cases; where the verdict is "
          f"right, min {low['shrink_true_pct']:.0f} % ({low['family']}/{low['truth']} seed "
          f"{low['seed']}; target >= 50 %)")
    print(f"  mean diagnosis time per axis record pair: "
          f"{np.mean([r['seconds'] for r in rows]):.1f} s")
    for r in rows:
        if r["verdict"] != r["truth"]:
            print(f"  miss: {r['family']}/{r['truth']} seed {r['seed']} -> {r['verdict']} "
                  f"({r['reason']})")
    with bar("bench gap: two effects at once", total=len(gap_blind.PAIRS) * 2,
             unit=" cases") as b:
        multi = gap_blind.run_multi(seeds=2, progress=steps(b))
    exact = sum(r["named"] == r["truth"] for r in multi)
    print(f"\n  two at once (own simulator, 1 kHz, both axes; a floor vibration counts as "
          f"the disturbance class): the named set exactly "
          f"right on {exact}/{len(multi)} axis records = {100 * exact / len(multi):.0f} % "
          f"(target >= 80 %)")
    for r in multi:
        if r["named"] != r["truth"]:
            print(f"  miss: {'+'.join(sorted(r['truth']))} seed {r['seed']} axis {r['axis']}"
                  f" -> {sorted(r['named']) or r['verdict']} ({r['reason']})")
    # speed: a 35 s record at 5 kHz, two axes, each case also without the two speed-ups
    # (every search step on every column, the axes in threads) in the same run. The
    # issue's figures: 36 s per single-effect case, 134 s for our stage with three
    # effects (its machine)
    from piezo_stage.core import gap as gap_mod
    from piezo_stage.core.gap import candidates as gap_candidates

    def timed(fit, hold, fast=True):
        gap_candidates.ONE_COLUMN_SEARCH = gap_mod.AXES_IN_PROCESSES = fast
        try:
            t0 = time.perf_counter()
            res = diagnose(fit, hold)
            return res, time.perf_counter() - t0
        finally:
            gap_candidates.ONE_COLUMN_SEARCH = gap_mod.AXES_IN_PROCESSES = True
    fit, hold = gap_blind.make_pair("creep", "own", 0, fs=5000.0)
    (_, dt), (_, slow) = timed(fit, hold), timed(fit, hold, fast=False)
    print(f"\n  speed: {fit.t[-1]:.1f} s record at 5 kHz, two axes, one effect: {dt:.1f} s "
          f"(target <= 10 s: {'met' if dt <= 10 else 'NOT met'}); without the speed-ups "
          f"{slow:.1f} s, x{slow / dt:.2f}")
    effects = {"creep": {"gamma": 0.04}, "delay": {"delay_s": 0.0008},
               "dynamics": {"kind": "resonance", "fn_hz": 600.0, "zeta": 0.08}}
    for chirp in (2.0, 0.0):
        fit, hold = gap_blind.make_multi_pair(effects, 1, fs=5000.0, coupling=True,
                                              chirp_s=chirp)
        res, dt = timed(fit, hold)
        print(f"  speed: the same with our stage's creep, 600 Hz resonance, 0.8 ms delay and "
              f"coupling{'' if chirp else ', protocol without its chirp (--chirp 0)'}: "
              f"{dt:.1f} s (target <= 20 s: {'met' if dt <= 20 else 'NOT met'})", end="")
        if chirp:
            _, slow = timed(fit, hold, fast=False)
            print(f"; without the speed-ups {slow:.1f} s, x{slow / dt:.2f}", end="")
        print()
        _print_named(res)
    _bench_structure()
    return 0


def _bench_structure():
    """bench gap's block for issue 25: a stage whose hysteresis is not our model class
    (config/structure_stage.yaml: play operators, memory, a tanh envelope). Two seed
    pairs of the protocol with its nested loops, both axes; then the kind of record
    real stages give (gap_blind.scan_cut). The truth of the locked part: the base
    model's error against the plant's true displacement (gap_blind.locked_truth)."""
    from piezo_stage.core.gap import diagnose
    from piezo_stage.studies.gap_blind import locked_truth, scan_cut, structure_pair
    print("\n  structure stage (play-operator hysteresis: memory, tanh envelope; our "
          "coupling): protocol with nested loops, 1 kHz, both axes")
    worse = total = 0
    for seeds in ((1, 2), (3, 4)):
        fit, hold, true = structure_pair(seeds)
        res = diagnose(fit, hold)
        for a, d in res["axes"].items():
            truth = locked_truth(fit, hold, true[a], a)
            b = d["budget"]
            none = next(r for r in d["ranking"] if r["effect"] == "none")["fit_rms_um"]
            worse += sum(r["fit_rms_um"] > none * (1 + 1e-9) for r in d["ranking"])
            total += len(d["ranking"])
            last = d["effects"][-1] if d["effects"] else None
            print(f"    seeds {seeds} axis {a}: verdict {d['verdict']}, named "
                  + (", ".join(s["effect"] for s in d["effects"]) or "nothing")
                  + (f"; held-out gap shrink {last['shrink_pct']:.0f} +- "
                     f"{last['shrink_pm_pct']:.0f} % (target >= 60 %)" if last else "")
                  + f"; locked {b['input_locked_um']:.3f} um vs truth {truth:.3f} um "
                  f"({100 * (b['input_locked_um'] / truth - 1):+.0f} %, target within 15 %)")
    fit, hold, true = scan_cut()
    res = diagnose(fit, hold)
    truth = locked_truth(fit, hold, true, "x")
    b = res["budget"]
    kept = res["effects"][0] if res["effects"] else None
    after = next((r["rms_after_um"] for r in res["ranking"] if r["effect"] == res["verdict"]),
                 float("nan"))
    print(f"    a scan cut from a run (1 Hz, 5 kHz, fit 3 s, held out 4 s): verdict "
          f"{res['verdict']}" + (f", closes {kept['shrink_pct']:.0f} +- "
                                 f"{kept['shrink_pm_pct']:.0f} % (target >= 40 %)"
                                 if kept else "")
          + f"; locked {b['input_locked_um']:.3f} um ({b['locked_estimator']['kind']}) vs "
          f"truth {truth:.3f} um; held-out RMS {b['residual_rms_um']:.3f} -> {after:.3f} "
          f"um (noise {b['noise_floor_um']:.3f})")
    print(f"    candidate fits worse on FIT than their base: {worse} of {total}")


def _print_named(res):
    """Per axis: the effects the diagnosis kept, and what they closed."""
    for a, d in res["axes"].items():
        b = d["budget"]
        print(f"    axis {a}: named " + ", then ".join(
            s["effect"] + (f" (or {'/'.join(s['equally_well'])})" if s["equally_well"] else "")
            for s in d["effects"]) + f"; held-out gap {b['gap_um']:.3f} -> "
            f"{b['unexplained_um']:.3f} um ({100 * (1 - b['unexplained_um'] / b['gap_um']):.0f}"
            " % shrink, target >= 80 %)" + "".join(
                f"; {s['effect']} {_fmt_params(s['params'])}" for s in d["effects"]
                if s["effect"] in ("delay", "dynamics")))


def _fmt_params(p):
    return "(" + ", ".join(f"{k} {v:.4g}" for k, v in p.items()
                           if isinstance(v, float)) + ")"


def main(args):
    if args.what == "plant":
        return bench_plant(args.samples)
    if args.what == "identify":
        return bench_identify()
    if args.what == "loop":
        return bench_loop()
    if args.what == "gap":
        return bench_gap()
    if args.what == "liveview":
        return bench_liveview()
    if args.what == "faults":
        from piezo_stage.bench_faults import bench_faults
        return bench_faults()
    if args.what == "realtime":
        from piezo_stage.bench_realtime import bench_realtime
        return bench_realtime(args.track)
    if args.what == "signals":
        from piezo_stage.bench_signals import main as bench_signals
        return bench_signals(args.trials)
    raise SystemExit(f"unknown benchmark {args.what}")
