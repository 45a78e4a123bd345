"""`piezo-stage bench faults`: what each single fault does to a running stage.

The node set runs in real time on the simulated stage, tracking the seed's 10 Hz
trajectory with a recorder. Faults are injected one at a time, each once the set is
armed again: the controller killed (and restarted), the controller stopped for 1 s
(SIGSTOP, SIGCONT), the feedforward killed (and restarted), a 0.2 s flood of NaN
commands, an e-stop (then disarm and arm). From the bag, per fault: the largest
voltage step in one tick (and as a share of the amplifier's slew limit), the largest
position error against the true position, the time from the fault to the safe voltage
against its bound stale_timeout_s + V / safe_ramp_V_per_s, and the time to re-arm.
"""

from __future__ import annotations

import math
import os
import random
import signal
import subprocess
import tempfile
import time

import numpy as np

from piezo_stage.io.run_bag import read_run

STALE, RAMP = 0.05, 500.0


def _inject(launch, probe, env, name):
    """Inject one fault; returns once it has been cleared (or None if it needs none)."""
    if name in ("controller killed", "feedforward killed"):
        node = name.split()[0]
        launch.procs[node].send_signal(signal.SIGKILL)
        launch.procs[node].wait(10)
        probe.wait(lambda: probe.state == "faulted", 5)
        probe.spin(0.3)
        launch.procs[node] = subprocess.Popen(launch.command(node), env=env)
    elif name == "controller stopped 1 s":
        p = launch.procs["controller"]
        p.send_signal(signal.SIGSTOP)
        probe.spin(1.0)
        p.send_signal(signal.SIGCONT)
    elif name == "NaN command flood 0.2 s":
        t_end = time.monotonic() + 0.2
        while time.monotonic() < t_end:
            probe.command(math.nan, math.nan, time.time_ns() + 5_000_000)
            probe.spin(0.0002)
    elif name == "e-stop, then disarm and arm":
        probe.estop()
        probe.spin(1.0)
        probe.arm(False)
        probe.wait(lambda: probe.arm(True).success, 10)


FAULTS = ("controller killed", "controller stopped 1 s", "feedforward killed",
          "NaN command flood 0.2 s", "e-stop, then disarm and arm")


def bench_faults() -> int:
    from piezo_stage.io.plant_file import default_plant_config_path, load_plant_config
    from piezo_stage.launch.launcher import Launch
    from piezo_stage.launch.probe import Probe
    from piezo_stage.paths import default_config
    slew = load_plant_config(default_plant_config_path()).slew_V_per_s
    d = random.randint(101, 200)
    env = dict(os.environ, ROS_DOMAIN_ID=str(d), ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST")
    os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
    bag = os.path.join(tempfile.mkdtemp(), "faults")
    o = {"stage_driver": {"mode": "realtime", "stale_timeout_s": STALE,
                          "safe_ramp_V_per_s": RAMP},
         "feedforward": {"model_file": default_config("stage_model.yaml")},
         "trajectory": {"kind": "seed", "frequency_hz": 10.0, "duration_s": 120.0}}
    launch = Launch(default_config("stage.yaml"), record=bag, overrides=o, env=env,
                    nodes=["stage_driver", "feedforward", "controller", "trajectory"])
    probe = Probe(d)
    marks = []
    try:
        launch.start()
        if not probe.wait_state("armed", 60):
            print("bench faults: the set did not arm")
            return 1
        from piezo_stage.bench import _runs
        for name in _runs(FAULTS, "bench faults: faults"):
            probe.spin(1.5)
            n = len(probe.states)
            t0 = time.time_ns()
            _inject(launch, probe, env, name)
            rearmed = probe.wait_state("armed", 30, after=n) if \
                any(s[0] != "armed" for s in probe.states[n:]) else True
            probe.spin(0.5)
            marks.append((name, t0, time.time_ns(), rearmed))
    finally:
        probe.close()
        launch.stop()
    run = read_run(bag)
    t, v = run.t_ns, run.v_V
    gaps = np.maximum(np.round(np.diff(t) / 1e6), 1)[:, None]
    print("bench faults: real-time node set on the simulated stage (seed's 10 Hz trajectory),"
          f" one fault at a time; stale_timeout_s {STALE}, safe_ramp_V_per_s {RAMP:g}, "
          f"slew limit {slew:g} V/s")
    print(f"  {'fault':<30} {'max step V':>10} {'x slew':>7} {'max err um':>10} "
          f"{'to safe s':>9} {'bound s':>8} {'re-armed':>9}")
    ok_all = True
    for name, a, b, rearmed in marks:
        k = (t >= a) & (t <= b)
        kk = k[1:] & k[:-1]
        step = float(np.abs(np.diff(v, axis=0))[kk].max()) if kk.any() else 0.0
        ratio = float((np.abs(np.diff(v, axis=0)) / gaps)[kk].max() / (slew * 1e-3)) \
            if kk.any() else 0.0
        e = run.errors_um(a, b)
        err = float(np.abs(e).max()) if e.size else float("nan")
        at0 = np.flatnonzero(k & np.all(v == 0.0, axis=1))
        held = float(np.abs(v[k]).max()) if k.any() else 0.0
        if at0.size:
            to_safe = (t[at0[0]] - a) * 1e-9
            bound = STALE + held / RAMP + 0.005
            safe_txt, bound_txt = f"{to_safe:9.3f}", f"{bound:8.3f}"
            ok_all &= to_safe <= bound
        else:
            safe_txt, bound_txt = f"{'never':>9}", f"{'-':>8}"
            ok_all &= name.startswith("NaN")  # a NaN flood must not disarm anything
        ok_all &= ratio <= 1.0 and bool(rearmed)
        print(f"  {name:<30} {step:10.2f} {ratio:7.2f} {err:10.3f} {safe_txt} {bound_txt} "
              f"{'yes' if rearmed else 'NO':>9}")
    print(f"  targets (no step beyond the slew limit; safe within stale + V/ramp; NaN "
          f"never disarms or moves the stage; every fault recovered): "
          f"{'met' if ok_all else 'NOT met'}")
    return 0
