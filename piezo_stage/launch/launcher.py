"""Start the node set as separate processes from one parameter file, stop it cleanly.

Each node runs as ``python -m piezo_stage.nodes.<node>_node --ros-args -r
__ns:=<namespace> --params-file CONFIG [-p name:=value ...]``, exactly what
``ros2 run`` would pass. In lockstep the launcher tells each publisher how many
subscribers to wait for (the set it started, recorder included), so no sample is
published before everyone listens. Ctrl-C (SIGINT) is forwarded: producers first,
then the driver (which ramps the stage to its safe voltage before it exits; the
launcher waits for it), the recorder last, so the bag holds everything, the ramp
included. A node that exits 0 by itself (the driver after max_steps) ends the run
cleanly; one that dies ends it with exit 1. The set starts disarmed and the driver arms
itself once the loop is closed (``auto_arm``), unless ``arm=False``.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time

import yaml

from piezo_stage.core.errors import ConfigError
from piezo_stage.nodes import NODES as ORDER  # the one list, in start order


def _params(config_path):
    try:
        with open(config_path) as fh:
            doc = yaml.safe_load(fh) or {}
    except FileNotFoundError:
        raise ConfigError(f"{config_path}: no such config file") from None
    except yaml.YAMLError:
        raise ConfigError(f"{config_path}: malformed YAML") from None
    if not isinstance(doc, dict):
        raise ConfigError(f"{config_path}: expected '<node>: ros__parameters:' sections")
    out = {}
    for key, sec in doc.items():
        node = str(key).rsplit("/", 1)[-1]  # '/**/stage_driver' or 'stage_driver'
        if node not in ORDER:
            raise ConfigError(f"{config_path}: unknown node {node!r}; known: {', '.join(ORDER)}")
        out[node] = (sec or {}).get("ros__parameters", {}) or {}
    return out


def _fmt(v):
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, (list, tuple)):
        return "[" + ",".join(_fmt(x) for x in v) + "]"
    return str(v)


class Launch:
    def __init__(self, config_path, record=None, namespace="/stage", overrides=None,
                 nodes=None, env=None, arm=True, foxglove_port=None):
        self.config_path = os.path.abspath(config_path)
        params = _params(self.config_path)
        # the recorder and the live view run when asked for (record, foxglove_port)
        self.nodes = [n for n in ORDER if n in (nodes or params)
                      and n not in ("recorder", "live_view")]
        if foxglove_port is not None:
            self.nodes.insert(0, "live_view")
        if record:
            self.nodes.insert(0, "recorder")
        self.foxglove_port = foxglove_port
        self.ns = namespace
        self.record = record
        drv = {**params.get("stage_driver", {}), **(overrides or {}).get("stage_driver", {})}
        mode = drv.get("mode", "lockstep")
        if mode not in ("lockstep", "realtime"):
            raise ConfigError(f"{config_path}: stage_driver mode {mode!r}: use lockstep "
                              "or realtime")
        self.lockstep = mode == "lockstep"
        self.arm = bool(arm)
        self.backend = drv.get("backend", "sim")
        self.overrides = {n: dict(o) for n, o in (overrides or {}).items()}
        self.env = dict(os.environ if env is None else env)
        if self.backend == "sim":  # keep a simulated run's discovery on this host
            self.env.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
        self.procs = {}
        self.failed = []

    def _gates(self):
        has = set(self.nodes)
        rec = int("recorder" in has)
        g = {"stage_driver": {"min_subscribers": rec + sum(n in has for n in
                                                           ("feedforward", "identifier",
                                                            "gap")),
                              "min_record_subscribers": rec},
             "feedforward": {"min_subscribers": rec + int("controller" in has),
                             "wait_for_trajectory": "trajectory" in has},
             "controller": {"min_subscribers": rec + int("stage_driver" in has)},
             "trajectory": {"min_subscribers": rec + int("feedforward" in has)},
             "gap": {"min_subscribers": rec}}
        if not self.lockstep:  # real time: the driver's clock starts once they listen
            g = {"trajectory": g["trajectory"], "gap": g["gap"],
                 "stage_driver": g["stage_driver"]}
        g.setdefault("stage_driver", {})["auto_arm"] = self.arm
        return g

    def command(self, node):
        cmd = [sys.executable, "-m", f"piezo_stage.nodes.{node}_node", "--ros-args",
               "-r", f"__ns:={self.ns}", "--params-file", self.config_path]
        for k, v in self.node_params(node).items():
            cmd += ["-p", f"{k}:={_fmt(v)}"]
        return cmd

    def node_params(self, node) -> dict:
        """What the launcher sets on ``node`` beyond the parameter file: start-up
        gating, the recorder's bag, one clock, the overrides (the ros2 launch file
        passes the same)."""
        extra = dict(self._gates().get(node, {}))
        if node == "recorder":
            extra.update(output=os.path.abspath(self.record), config_file=self.config_path,
                         log_time="stamp" if self.lockstep else "receive")
        if node == "live_view":
            extra["port"] = int(self.foxglove_port or 0)
        if self.lockstep:  # one clock: the driver's samples (/clock), bags included
            extra["use_sim_time"] = True
        extra.update(self.overrides.get(node, {}))
        return extra

    def start(self):
        for n in self.nodes:
            self.procs[n] = subprocess.Popen(self.command(n), env=self.env,
                                             start_new_session=True)

    def stop(self, timeout=15.0):
        """SIGINT to the producers, then the driver (it ramps down and exits), then
        the recorder; escalate if a node hangs."""
        producers = [n for n in reversed(self.nodes)
                     if n not in ("recorder", "stage_driver", "live_view")]
        for group in (producers, ["stage_driver"], ["recorder", "live_view"]):
            for n in group:
                p = self.procs.get(n)
                if p and p.poll() is None:
                    p.send_signal(signal.SIGINT)
            deadline = time.monotonic() + timeout
            for n in group:
                p = self.procs.get(n)
                if not p:
                    continue
                try:
                    p.wait(max(0.1, deadline - time.monotonic()))
                except subprocess.TimeoutExpired:
                    p.kill()
                    p.wait()
                    self.failed.append(f"{n} did not stop on SIGINT (killed)")

    def wait(self, duration=None):
        """Run until duration [s] passes, Ctrl-C, a node exits 0 (done) or one dies."""
        t_end = None if duration is None else time.monotonic() + duration
        try:
            while True:
                for n, p in self.procs.items():
                    rc = p.poll()
                    if rc is not None:
                        if rc != 0:
                            self.failed.append(f"{n} died with exit code {rc}")
                        return
                if t_end is not None and time.monotonic() >= t_end:
                    return
                time.sleep(0.05)
        except KeyboardInterrupt:
            return

    def run(self, duration=None) -> int:
        old = signal.signal(signal.SIGINT, signal.default_int_handler)
        try:
            self.start()
            self.wait(duration)
        finally:
            self.stop()
            signal.signal(signal.SIGINT, old)
        for n, p in self.procs.items():
            if p.returncode not in (0, None) and not any(f.startswith(n) for f in self.failed):
                self.failed.append(f"{n} exited with code {p.returncode}")
        for f in self.failed:
            sys.stderr.write(f"piezo-stage launch: {f}\n")
        return 1 if self.failed else 0
