"""`piezo-stage bench loop`: the lockstep loop (five processes and the recorder)
against a bare three-process ring of empty callbacks on the nodes' own transport path
and a two-process rclpy ping-pong, in the same run; with ``--vs REV`` against the code
at a git revision too, its own loop run in each pair (``RevisionLoop``)."""

from __future__ import annotations

from benchmarks import ROOT
from benchmarks.procs import cpu_ticks, progress_runs


def ring_rate(env, steps=3000):
    """Steps/s of a bare 3-process ring with empty callbacks on the loop nodes' own
    transport path: the ceiling of any three-hop lockstep loop with it on this host."""
    import subprocess
    import sys
    ring = [sys.executable, "-m", "benchmarks.procs", "ring"]
    others = [subprocess.Popen(ring + [a, b, str(steps)], env=env, cwd=ROOT)
              for a, b in (("b", "c"), ("c", "a"))]
    try:
        r = subprocess.run(ring + ["a", "b", str(steps)], env=env, cwd=ROOT,
                           capture_output=True, text=True, timeout=300)
        return float(r.stdout.split()[0])
    finally:
        for p in others:
            p.kill()
            p.wait()


def events_ring_rate(env, steps=5000):
    """Steps/s of rclpy's own fast path: 3 nodes in one process on the EventsExecutor
    passing a 2-joint JointState (``procs events``), the physical anchor of a loop of
    three nodes composed in one process on this host."""
    import subprocess
    import sys
    r = subprocess.run([sys.executable, "-m", "benchmarks.procs", "events",
                        str(steps)], env=env, cwd=ROOT, capture_output=True, text=True,
                       timeout=300)
    if r.returncode != 0:
        raise RuntimeError(f"the EventsExecutor ring exited {r.returncode}: "
                           f"{(r.stderr.strip().splitlines() or [''])[-1]}")
    return float(r.stdout.split()[0])


def loop_run(env, steps, foxglove_port=None, compose=None, hop_times=None):
    """One lockstep run with the recorder: (steps/s, median ms, p99 ms, lost per topic,
    steal fraction), or (None, log tail) when the run failed. With ``foxglove_port``
    the live view runs too (its client is the caller's); ``compose``: the loop's nodes
    in one process ("loop", the default) or each alone ("none"); ``hop_times``: a file
    the composed process writes its per-hop costs to (``_executor.HopTimes``)."""
    import contextlib
    import os
    import re
    import tempfile

    from piezo_stage.io.bag import iter_messages
    from piezo_stage.launcher.launcher import Launch, LaunchOptions
    from piezo_stage.paths import default_config
    bag = os.path.join(tempfile.mkdtemp(), "bench")
    o = {"stage_driver": {"max_steps": steps, "exit_after_max_steps": True},
         "feedforward": {"model_file": default_config("stage_model.yaml")}}
    launch = Launch(default_config("stage.yaml"), LaunchOptions(record=bag, overrides=o,
        nodes=["stage_driver", "feedforward", "controller", "trajectory"],
        foxglove_port=foxglove_port, compose=compose),
        env=dict(env, PIEZO_STAGE_HOP_TIMES=hop_times) if hop_times else env)
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



# a revision's own lockstep run, in a process whose package is the revision's: its
# benchmarks' loop_run(env, steps), which every revision since the ring baseline has
REV_LOOP = ("import json, os, sys\n"
            "try:\n"
            "    from benchmarks.loop import loop_run\n"
            "except ImportError:  # a revision whose workbench sat in the package\n"
            "    from piezo_stage.benchmarks.loop import loop_run\n"
            "res, err = loop_run(dict(os.environ), int(sys.argv[1]))\n"
            "print(json.dumps({'res': res, 'err': err}))\n")


class RevisionLoop:
    """The lockstep loop of the code at git revision ``rev`` (a commit of this
    checkout, e.g. the one an issue was measured on): a clone of the checkout at
    ``rev`` in ``folder``, run with this interpreter and its packages, the clone's
    package first on the path (its nodes' processes inherit it). A DataError where
    the revision is none of this checkout's."""

    def __init__(self, rev: str, folder: str):
        import os
        import subprocess

        from benchmarks.procs import source_checkout
        from piezo_stage.core.errors import DataError
        src = source_checkout("bench loop --vs")
        r = subprocess.run(["git", "-C", src, "rev-parse", "--verify", "--quiet",
                            f"{rev}^{{commit}}"], capture_output=True, text=True)
        if r.returncode != 0:
            raise DataError(f"bench loop --vs {rev}: no such commit in {src}")
        self.sha = r.stdout.strip()
        self.label = self.sha[:7]
        self.dir = os.path.join(folder, f"rev-{self.label}")
        subprocess.run(["git", "clone", "-q", "--no-checkout", src, self.dir], check=True)
        subprocess.run(["git", "-C", self.dir, "checkout", "-q", self.sha], check=True)

    def run(self, env, steps):
        """One of the revision's lockstep runs: as ``loop_run``'s answer."""
        import json
        import subprocess
        import sys
        r = subprocess.run([sys.executable, "-c", REV_LOOP, str(steps)], cwd=self.dir,
                           env=dict(env, PYTHONPATH=self.dir), capture_output=True,
                           text=True, timeout=900)
        try:
            out = json.loads(r.stdout.strip().splitlines()[-1])
        except (IndexError, ValueError):
            return None, f"{self.label}: exit {r.returncode}\n{r.stderr[-2000:]}"
        if out["res"] is None:
            return None, f"{self.label}: {out['err']}"
        rate, med, p99, lost, steal = out["res"]
        return (int(rate), float(med), float(p99), lost, float(steal)), None


def bench_loop(rep, vs=None, steps=3000, runs=5):
    """The lockstep loop composed and apart, in pairs with the ring, and with the
    code at git revision ``vs`` where given (``rep``: the report)."""
    import os
    import random
    import tempfile
    with tempfile.TemporaryDirectory(prefix="piezo-stage-loop-") as folder:
        rev = None
        if vs is not None:
            rev = RevisionLoop(vs, folder)
            env = dict(os.environ, ROS_DOMAIN_ID=str(random.randint(101, 200)),
                       ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST")
            _, err = rev.run(env, 300)  # its kernels compiled, its bytecode written
            if err:
                rep.fail("the revision's loop run failed:\n" + err)
                return 1
        return _bench_loop(rep, rev, steps, runs)


def _bench_loop(rep, rev, steps, runs):
    """``bench_loop`` with the revision's loop (``RevisionLoop``) or None."""
    import os
    import random
    import subprocess
    import sys
    env = dict(os.environ, ROS_DOMAIN_ID=str(random.randint(101, 200)),
               ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST")
    ping = [sys.executable, "-m", "benchmarks.procs", "ping"]
    pong = subprocess.Popen(ping + ["pong"], env=env, cwd=ROOT)
    try:
        r = subprocess.run(ping + ["ping", "2000"], env=env, cwd=ROOT,
                           capture_output=True, text=True, timeout=300)
    finally:
        pong.terminate()
        pong.wait()
    rt_med, rt_p99 = map(float, r.stdout.split())
    rep.title("the lockstep closed loop, driver + feedforward + controller composed in "
              "one process (the default) against each in its own, + trajectory + recorder "
              "(Fast DDS, this host); the baselines: a two-process ping-pong, and a ring of 3 "
              "processes passing one message round (empty callbacks, the nodes' lean wait "
              "set and raw CDR, no recorder) and rclpy's own fast path, 3 nodes in one "
              "process on its EventsExecutor passing a 2-joint JointState, run in each "
              "pair, the loop composed and apart one after the other (this host's speed drifts)"
              + (f"; and the code at {rev.label} (`--vs`), its own lockstep loop, run in "
                 "each pair, before the loop in odd pairs and after it in even ones"
                 if rev else ""))
    results, apart, rings, rows, revs, events = [], [], [], [], [], []
    for k in progress_runs(range(runs), "bench loop: runs"):
        rings.append(ring_rate(env))
        try:
            events.append(events_ring_rate(env))
        except (RuntimeError, ValueError, IndexError) as e:
            rep.fail(str(e))
            return 1
        if rev and k % 2 == 0:
            revs.append(rev.run(env, steps))
        res, err = loop_run(env, steps)
        sep, err2 = loop_run(env, steps, compose="none")
        if rev and k % 2 == 1:
            revs.append(rev.run(env, steps))
        err3 = revs[-1][1] if rev else None
        if res is None or sep is None or err3:
            rep.fail("the loop run failed:\n" + str(err or err2 or err3))
            return 1
        rate, med, p99, lost, steal = res
        results.append(res)
        apart.append(sep)
        row = [k + 1, f"{rings[-1]:.0f}", f"{events[-1]:.0f}", rate, sep[0],
               f"{rate / sep[0]:.2f}", f"{rate / rings[-1]:.2f}", f"{rate / events[-1]:.2f}",
               f"{med:.3f} / {p99:.3f} ms",
               f"{sum(lost.values())} / {sum(sep[3].values())}", f"{100 * steal:.1f} %"]
        if rev:
            old = revs[-1][0]
            row[5:5] = [old[0], f"{rate / old[0]:.2f}"]
        rows.append(tuple(row))
    rates = sorted(r[0] for r in results)
    med_rate = rates[len(rates) // 2]
    med_period = sorted(r[1] for r in results)[len(results) // 2]
    ratios = sorted(r[0] / g for r, g in zip(results, rings))
    vs = sorted(r[0] / s[0] for r, s in zip(results, apart))
    anchor = sorted(r[0] / e for r, e in zip(results, events))
    lost = {t: max(max(r[3][t] for r in results), max(s[3][t] for s in apart))
            for t in results[0][3]}
    head = ["pair", "ring steps/s", "EventsExecutor ring steps/s", "composed steps/s",
            "apart steps/s", "composed / apart", "composed / ring",
            "composed / EventsExecutor ring", "step period median / p99",
            "lost composed / apart", "CPU steal"]
    if rev:
        head[5:5] = [f"{rev.label} steps/s", f"composed / {rev.label}"]
    rep.table(tuple(head), rows, f"{runs} pairs of {steps} steps")
    figures = []
    if rev:
        olds = sorted(r[0] / o[0][0] for r, o in zip(results, revs))
        old_rates = sorted(o[0][0] for o in revs)
        old_lost = max(sum(o[0][3].values()) for o in revs)
        figures = [(f"the code at {rev.label}, median run",
                    f"{old_rates[len(old_rates) // 2]} steps/s (range {old_rates[0]}-"
                    f"{old_rates[-1]}); {old_lost} lost, worst run"),
                   (f"composed against the code at {rev.label}, median of the pairs",
                    f"{olds[len(olds) // 2]:.2f} x ({olds[0]:.2f}-{olds[-1]:.2f})")]
    rep.figures([
        ("ping-pong round trip (2 processes), median / p99",
         f"{rt_med * 1e3:.3f} / {rt_p99 * 1e3:.3f} ms"),
        ("closed loop composed, median run", f"{med_rate} steps/s (range "
         f"{rates[0]}-{rates[-1]})"),
        ("step period median against the ping-pong round trip",
         f"{med_period / (rt_med * 1e3):.2f} x"),
        ("composed against the ring, median of the pairs",
         f"{ratios[len(ratios) // 2]:.2f} x ({ratios[0]:.2f}-{ratios[-1]:.2f})"),
        ("EventsExecutor ring (3 nodes, one process), median run",
         f"{sorted(events)[len(events) // 2]:.0f} steps/s"),
        ("composed against the EventsExecutor ring, median of the pairs",
         f"{anchor[len(anchor) // 2]:.2f} x ({anchor[0]:.2f}-{anchor[-1]:.2f})"),
        ("composed against apart, median of the pairs",
         f"{vs[len(vs) // 2]:.2f} x ({vs[0]:.2f}-{vs[-1]:.2f})"),
        ("messages lost per loop topic, worst run (0: every message is in the bag)",
         str(lost)), *figures], "the medians")
    hop_table(rep, env, steps, 1e6 / sorted(events)[len(events) // 2])
    rep.target(">= 1000 steps/s (median run)", med_rate >= 1000)
    rep.target("0 lost", not any(lost.values()))
    rep.target("composed >= 2 x apart (median pair)", vs[len(vs) // 2] >= 2)
    rep.target("composed >= 0.5 x the EventsExecutor ring (median pair)",
               anchor[len(anchor) // 2] >= 0.5)
    if rev:
        rep.target(f"composed >= 2 x the code at {rev.label} (median pair)",
                   olds[len(olds) // 2] >= 2)
    return 0


def hop_table(rep, env, steps, ring_us):
    """One more composed run with the hops timed (``_executor.HopTimes``): per linked
    topic, the subscriber's callback (its node's work and its own publishes) and the
    publish that carries it (the middleware's send to the recorder and the other
    processes), per step, beside the EventsExecutor ring's step (``ring_us``)."""
    import json
    import os
    import tempfile
    path = os.path.join(tempfile.mkdtemp(), "hops.json")
    res, err = loop_run(env, steps, hop_times=path)
    if res is None or not os.path.exists(path):
        rep.fail("the timed loop run failed:\n" + str(err))
        return
    with open(path) as fh:
        acc = json.load(fh)
    step_us = 1e6 / res[0]
    n = max(c for c, _ in acc.values())  # steps (the most frequent hop: one a step)
    rows, work, sends = [], 0.0, 0.0
    for key in sorted(acc):
        kind, topic = key.split(" ", 1)
        count, secs = acc[key]
        us = 1e6 * secs / max(n, 1)
        if kind == "callback":
            work += us
        else:
            sends += us
        rows.append((kind, topic, f"{count / max(n, 1):.2f}", f"{us:.1f} us"))
    rep.table(("what", "topic", "a step", "time a step"), rows,
              f"one composed run of {steps} steps with its hops timed: each linked "
              "callback (its node's work and the publishes it makes) and each publish "
              "(the middleware's send, and the queue of a linked reader)")
    rep.figures([
        ("step period of the timed run", f"{step_us:.1f} us"),
        ("the three nodes' callbacks, a step (their publishes included)",
         f"{work:.1f} us = {work / step_us:.0%} of the step"),
        ("every publish, a step (the middleware's sends)",
         f"{sends:.1f} us = {sends / step_us:.0%} of the step"),
        ("the callbacks without their publishes (the nodes' own work)",
         f"{work - sends:.1f} us"),
        ("the EventsExecutor ring's step (3 hops, empty callbacks)", f"{ring_us:.1f} us"),
    ], "where a composed step's time goes")
