"""`piezo-stage bench loop`: the lockstep loop (five processes and the recorder)
against a bare three-process ring of empty callbacks on the nodes' own transport path
and a two-process rclpy ping-pong, in the same run."""

from __future__ import annotations

from piezo_stage.benchmarks.procs import cpu_ticks, progress_runs


def ring_rate(env, steps=3000):
    """Steps/s of a bare 3-process ring with empty callbacks on the loop nodes' own
    transport path: the ceiling of any three-hop lockstep loop with it on this host."""
    import subprocess
    import sys
    ring = [sys.executable, "-m", "piezo_stage.benchmarks.procs", "ring"]
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



def loop_run(env, steps, foxglove_port=None, compose=None):
    """One lockstep run with the recorder: (steps/s, median ms, p99 ms, lost per topic,
    steal fraction), or (None, log tail) when the run failed. With ``foxglove_port``
    the live view runs too (its client is the caller's); ``compose``: the loop's nodes
    in one process ("loop", the default) or each alone ("none")."""
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
                    foxglove_port=foxglove_port, compose=compose)
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
    counts: dict[str, int] = {}
    for topic, *_ in iter_messages(bag):
        counts[topic] = counts.get(topic, 0) + 1
    lost = {t: steps + 1 - counts.get(t, 0) for t in
            ("/stage/joint_states", "/stage/sim/true_position", "/stage/reference",
             "/stage/command")}
    steal = (c1[1] - c0[1]) / max(1, c1[0] - c0[0])
    return (int(m.group(2)), float(m.group(3)), float(m.group(4)), lost, steal), None



def bench_loop(rep, steps=3000, runs=5):
    """The lockstep loop composed and apart, in pairs with the ring (``rep``: the
    report)."""
    import os
    import random
    import subprocess
    import sys
    env = dict(os.environ, ROS_DOMAIN_ID=str(random.randint(101, 200)),
               ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST")
    ping = [sys.executable, "-m", "piezo_stage.benchmarks.procs", "ping"]
    pong = subprocess.Popen(ping + ["pong"], env=env)
    try:
        r = subprocess.run(ping + ["ping", "2000"], env=env,
                           capture_output=True, text=True, timeout=300)
    finally:
        pong.terminate()
        pong.wait()
    rt_med, rt_p99 = map(float, r.stdout.split())
    rep.title("the lockstep closed loop, driver + feedforward + controller composed in "
              "one process (the default) against each in its own, + trajectory + recorder "
              "(Fast DDS, this host); the baselines: a two-process ping-pong, and a ring of 3 "
              "processes passing one message round (empty callbacks, the nodes' lean wait "
              "set and raw CDR, no recorder) run in each pair, the loop composed and apart "
              "one after the other (this host's speed drifts)")
    results, apart, rings, rows = [], [], [], []
    for k in progress_runs(range(runs), "bench loop: runs"):
        rings.append(ring_rate(env))
        res, err = loop_run(env, steps)
        sep, err2 = loop_run(env, steps, compose="none")
        if res is None or sep is None:
            rep.fail("the loop run failed:\n" + (err or err2))
            return 1
        rate, med, p99, lost, steal = res
        results.append(res)
        apart.append(sep)
        rows.append((k + 1, f"{rings[-1]:.0f}", rate, sep[0], f"{rate / sep[0]:.2f}",
                     f"{rate / rings[-1]:.2f}", f"{med:.3f} / {p99:.3f} ms",
                     f"{sum(lost.values())} / {sum(sep[3].values())}",
                     f"{100 * steal:.1f} %"))
    rates = sorted(r[0] for r in results)
    med_rate = rates[len(rates) // 2]
    med_period = sorted(r[1] for r in results)[len(results) // 2]
    ratios = sorted(r[0] / g for r, g in zip(results, rings))
    vs = sorted(r[0] / s[0] for r, s in zip(results, apart))
    lost = {t: max(max(r[3][t] for r in results), max(s[3][t] for s in apart))
            for t in results[0][3]}
    rep.table(("pair", "ring steps/s", "composed steps/s", "apart steps/s",
               "composed / apart", "composed / ring", "step period median / p99",
               "lost composed / apart", "CPU steal"), rows,
              f"{runs} pairs of {steps} steps")
    rep.figures([
        ("ping-pong round trip (2 processes), median / p99",
         f"{rt_med * 1e3:.3f} / {rt_p99 * 1e3:.3f} ms"),
        ("closed loop composed, median run", f"{med_rate} steps/s (range "
         f"{rates[0]}-{rates[-1]})"),
        ("step period median against the ping-pong round trip",
         f"{med_period / (rt_med * 1e3):.2f} x"),
        ("composed against the ring, median of the pairs",
         f"{ratios[len(ratios) // 2]:.2f} x ({ratios[0]:.2f}-{ratios[-1]:.2f})"),
        ("composed against apart, median of the pairs",
         f"{vs[len(vs) // 2]:.2f} x ({vs[0]:.2f}-{vs[-1]:.2f})"),
        ("messages lost per loop topic, worst run (0: every message is in the bag)",
         str(lost))], "the medians")
    rep.target(">= 1000 steps/s (median run)", med_rate >= 1000)
    rep.target("0 lost", not any(lost.values()))
    rep.target("composed >= 2 x apart (median pair)", vs[len(vs) // 2] >= 2)
    return 0
