"""Start the node set as separate processes from one parameter file, stop it cleanly.

Each node runs as ``python -m piezo_stage.nodes.<node>_node --ros-args -r
__ns:=<namespace> --params-file CONFIG [-p name:=value ...]``, exactly what
``ros2 run`` would pass. In lockstep the launcher tells each publisher how many
subscribers to wait for (the set it started, recorder included), so no sample is
published before everyone listens. SIGINT, SIGTERM and SIGHUP to the launcher stop
the set in a safe order: the driver first (it disarms, which is no fault, and ramps the
stage to its safe voltage before it exits; the launcher waits for it), then the
producers, the recorder last, so the bag holds everything, the ramp included. No node
is left behind, even if the launcher is SIGKILLed (process/signals.py). A node that exits
0 by itself (the driver after max_steps) ends the run cleanly; one that dies, or that
someone else stopped, ends it with exit 1. The set starts disarmed and the driver arms
itself once the loop is closed (``auto_arm``), unless ``arm=False``.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from dataclasses import dataclass

from piezo_stage.core.errors import ConfigError, ModelError
from piezo_stage.core.ros_names import fully_qualified_namespace
from piezo_stage.core.types import Doc, Params
from piezo_stage.io.capacity_file import CAPACITY_FILE_ENV, read_refusal
from piezo_stage.io.files import load_yaml
from piezo_stage.launcher.transport import (  # noqa: F401 - the profiles, named here too
    LOCKSTEP_PROFILE,
    LOOPBACK_UDP_PROFILE,
    lockstep_transport_env,
    realtime_transport_env,
)
from piezo_stage.nodes import NODES as ORDER  # the one list, in start order
from piezo_stage.nodes.declared import (
    DECLARED,
    RCLPY_OWN,
    refusal,
    unknown_parameter,
)

STOP_SIGNALS = (signal.SIGINT, signal.SIGTERM)
LOOP_NODES = ("stage_driver", "feedforward", "controller")  # without them nothing arms
LOOP = "loop"  # the process of the composed loop nodes (nodes/loop_container.py)
# which of the loop's nodes share a process: "loop" all three (a lockstep sample then
# crosses no process: the fastest lockstep), "command" the feedforward and the
# controller (the command's work on one core, the driver's sample clock on the other),
# "none" each its own
COMPOSE = {"loop": ("controller", "feedforward", "stage_driver"),
           "command": ("controller", "feedforward"), "none": ()}
COMPOSE_DEFAULT = {"lockstep": "loop", "realtime": "command"}
LAUNCHER_PID_ENV = "PIEZO_STAGE_LAUNCHER_PID"  # process/signals.py reads it
RUN_ENDED_ENV = "PIEZO_STAGE_RUN_ENDED"        # and this
START_GATE_ENV = "PIEZO_STAGE_START_GATE"  # a file: nodes wait for it before they join
# rate auto: the runs a set may take in all, each at a lower rate than the last (the
# standard rate a refusal names, core/loop/capacity.py: from 1 kHz, 500, 250, 200 Hz).
# A rate named from a measurement at a higher one is often one step too high (the
# loop's fixed work a second weighs more per sample at a lower rate): a slow host may
# be refused three rates one after the other before one it holds
AUTO_ATTEMPTS = 4
# how long each group may take to stop after its SIGINT [s]: the driver ramps the stage
# down (up to its limit's span at ramp_V_per_s), the recorder finishes the bag
STOP_GRACE_S = {"stage_driver": 15.0, "producers": 5.0, "recorder": 15.0}


def read_parameters(config_path) -> Doc:
    """{node name: parameters} of a node-parameters YAML (the file ros2 run takes),
    checked: bounded, a mapping of '<node>: ros__parameters:' sections."""
    try:  # bounded: size, nesting, no aliases (the one YAML reader, io/model_file.py)
        doc = load_yaml(config_path, "config file") or {}
    except ModelError as e:
        raise ConfigError(str(e)) from None
    if not isinstance(doc, dict):
        raise ConfigError(f"{config_path}: expected '<node>: ros__parameters:' sections")
    out = {}
    for key, sec in doc.items():
        node = str(key).rsplit("/", 1)[-1]  # '/**/stage_driver' or 'stage_driver'
        if node not in ORDER:
            raise ConfigError(f"{config_path}: unknown node {node!r}; known: {', '.join(ORDER)}")
        if sec is not None and not isinstance(sec, dict):
            raise ConfigError(f"{config_path}: {node}: expected 'ros__parameters:'")
        stray = sorted(str(k) for k in (sec or {}) if k != "ros__parameters")
        if stray:  # what ros2's own reader refuses too: never silently left out
            raise ConfigError(f"{config_path}: {node}: {', '.join(stray)} outside "
                              "'ros__parameters:' (a node's parameters go under it)")
        out[node] = (sec or {}).get("ros__parameters", {}) or {}
        if not isinstance(out[node], dict):
            raise ConfigError(f"{config_path}: {node}: ros__parameters must be a mapping")
        for name in out[node]:  # the whole file, before any node starts
            if name not in DECLARED[node] and name not in RCLPY_OWN and \
                    not str(name).startswith("qos_overrides"):
                raise ConfigError(f"{config_path}: {node}: "
                                  f"{unknown_parameter(str(name), DECLARED[node])}")
            why = refusal(node, name, out[node][name])
            if why:  # a value the node would refuse, refused before any node starts
                raise ConfigError(f"{config_path}: {node}: {why}")
    return out


def check_files(params: Params) -> None:
    """ConfigError, one line, before any node starts, for a file the set's parameters
    ({node: parameters}) name that its node would refuse: a model (the feedforward's and
    the gap node's ``model_file``), the sim's plant (``plant_config``), the trajectory
    node's CSV (``csv_path`` with kind csv), a bag to replay, the recorder's metadata
    files: read by the same readers the nodes use, their errors (with their "did you
    mean") prefixed by the node and parameter (the value may come from any --params
    file)."""
    from piezo_stage.core.errors import PiezoStageError

    def check(node, name, read):
        path = params.get(node, {}).get(name) or ""
        if not path:
            return
        try:
            if not os.path.exists(path):
                raise ConfigError(f"{path}: no such file or directory")
            read(path)
        except PiezoStageError as e:
            raise ConfigError(f"{node}: {name}: {e}") from None

    from piezo_stage.io.model_file import load_model
    for node in ("feedforward", "gap"):
        check(node, "model_file", load_model)
    drv = params.get("stage_driver", {})
    backend = drv.get("backend", "sim")
    if backend == "sim":
        from piezo_stage.io.plant_file import load_plant_config
        check("stage_driver", "plant_config", load_plant_config)
    elif backend == "replay":
        from piezo_stage.io.bag import read_bag_record
        check("stage_driver", "replay_bag", read_bag_record)
    if params.get("trajectory", {}).get("kind") == "csv":
        from piezo_stage.io.csv_table import read_table
        check("trajectory", "csv_path", lambda p: read_table(p, ["t", "wx", "wy"]))
    for name in ("config_file", "model_file"):  # (the recorder keeps them as they are)
        check("recorder", name, lambda p: open(p, "rb").close())


def _fmt(v):
    """A parameter's value as a ``-p name:=VALUE`` rule: rcl reads VALUE as YAML, so
    a string YAML would read as something else (``""``, ``true``, ``1.5``, ``[a]``,
    ``a: b``) goes single-quoted (rcl refused ``model_file:=`` and the set died)."""
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, (list, tuple)):
        return "[" + ",".join(_fmt(x) for x in v) + "]"
    if isinstance(v, str):
        from piezo_stage.core.yaml_text import parse_yaml
        try:
            plain = parse_yaml(v, "parameter") == v and "," not in v and "\n" not in v
        except Exception:  # noqa: BLE001 - anything YAML does not read back as v
            plain = False
        return v if plain else "'" + v.replace("'", "''") + "'"
    return str(v)


# a run of ``armed_s`` seconds: the wall time it may take, at most, before the launcher
# gives up on it (start-up, then the armed run; lockstep runs on the host's pace, up to
# this many times slower than its own clock at a high control rate on a slow host)
START_ALLOWANCE_S = 120.0
LOCKSTEP_SLOWDOWN = 20.0


class Processes(dict):
    """The set's processes by name ({process: Popen}); a composed node's name finds its
    container's (``procs["controller"]`` is the loop's process where it is composed)."""

    def __init__(self, launch: "Launch"):
        super().__init__()
        self._launch = launch

    def __missing__(self, name: str):
        own = self._launch.process_of(name)
        if own != name and own in self:
            return dict.__getitem__(self, own)
        raise KeyError(name)


@dataclass(frozen=True)
class LaunchOptions:
    """What a ``Launch`` starts and how, built by keyword (the defaults: the whole set
    of the parameter file, armed, in /stage, nothing recorded).

    Attributes
    ----------
    record : str or None
        The bag folder the recorder writes (None: no recorder).
    namespace : str
        The set's namespace.
    overrides : dict or None
        Parameters per node over the file's ({node: {name: value}}).
    nodes : list of str or None
        The nodes to start (None: every node the file has a section for).
    arm : bool
        Whether the set arms by itself (False: started disarmed).
    foxglove_port : int or None
        The live view's port (None: no live view).
    trajectory : bool
        Whether the trajectory node runs (False: trajectories from outside nodes only).
    exclusive : bool
        Refuse a namespace where a set already runs.
    managed : bool
        The driver's lifecycle is left to an outside manager.
    armed_s : float or None
        Seconds to run from the sample the stage first enabled, on its own clock.
    compose : str or None
        Which of the loop's nodes share a process (None: the default for the mode).
    rate : float, "auto" or None
        The control rate of the loop's nodes (None: the file's; "auto": real time's
        highest the host holds).
    """
    record: str | None = None
    namespace: str = "/stage"
    overrides: Doc | None = None
    nodes: list | None = None
    arm: bool = True
    foxglove_port: int | None = None
    trajectory: bool = True
    exclusive: bool = True
    managed: bool = False
    armed_s: float | None = None
    compose: str | None = None
    rate: float | str | None = None
    watch: bool = False


class Launch:
    def _nodes_to_start(self, params: Params, o: LaunchOptions) -> list[str]:
        """The nodes this launch starts, in start order (``outside_trajectories`` set)."""
        # outside trajectories only (--no-trajectory, or the trajectory node's kind: none):
        # the set arms, holds position and takes trajectories from other nodes
        kind = {**params.get("trajectory", {}),
                **(o.overrides or {}).get("trajectory", {})}.get("kind")
        self.outside_trajectories = not o.trajectory or kind == "none"
        # the recorder and the live view run when asked for (record, foxglove_port)
        nodes = [n for n in ORDER if (n in (o.nodes or params) or (n == "gap" and o.watch))
                 and n not in ("recorder", "live_view")
                 and not (n == "trajectory" and self.outside_trajectories)]
        if o.foxglove_port is not None:
            nodes.insert(0, "live_view")
        if o.record:
            nodes.insert(0, "recorder")
        return nodes

    def _checked_mode(self, config_path, params: Params, drv: Doc, o: LaunchOptions) -> bool:
        """Whether the set runs in lockstep (else real time), its file checked: a mode
        of the two, no simulated time in real time, and the loop's three nodes where
        the set is to arm. ConfigError naming the file."""
        mode = drv.get("mode", "lockstep")
        if mode not in ("lockstep", "realtime"):
            raise ConfigError(f"{config_path}: stage_driver mode {mode!r}: use lockstep "
                              "or realtime")
        lockstep = mode == "lockstep"
        sim_time = [n for n in ORDER if (params.get(n, {}).get("use_sim_time") or (
            o.overrides or {}).get(n, {}).get("use_sim_time"))]
        if not lockstep and sim_time:
            raise ConfigError(f"{config_path}: use_sim_time on {', '.join(sim_time)} in a "
                              "real-time set: simulated time is lockstep's (the driver's "
                              "samples); leave it out")
        missing = [n for n in LOOP_NODES if n not in self.nodes]
        if o.nodes is None and o.arm and missing:
            raise ConfigError(
                f"{config_path}: no section for {', '.join(missing)}: the set could not "
                "close its loop, so it would never arm (a file of changes goes with "
                "--params, over config/stage.yaml; --no-arm starts such a set anyway)")
        return lockstep

    def __init__(self, config_path, options: LaunchOptions | None = None, env=None,
                 look=None):
        o = self.options = options or LaunchOptions()
        record, namespace, overrides = o.record, o.namespace, o.overrides
        arm, foxglove_port, exclusive = o.arm, o.foxglove_port, o.exclusive
        managed, armed_s, compose, rate = o.managed, o.armed_s, o.compose, o.rate
        self._look = look  # a running_set look begun before (launcher/running.py's Look)
        self.config_path = os.path.abspath(config_path)
        params = read_parameters(self.config_path)
        self.nodes = self._nodes_to_start(params, o)
        self.foxglove_port = foxglove_port
        self.ns = fully_qualified_namespace(namespace)  # "stage2": /stage2, as ROS launch
        self.record = record
        drv = {**params.get("stage_driver", {}), **(overrides or {}).get("stage_driver", {})}
        self.lockstep = self._checked_mode(config_path, params, drv, o)
        self.arm = bool(arm)
        self.managed = bool(managed)  # the driver's lifecycle left to an outside manager
        self.exclusive = bool(exclusive)  # refuse a namespace where a set runs already
        self.backend = drv.get("backend", "sim")
        self.overrides = {n: dict(x) for n, x in (overrides or {}).items()}
        # the control rate: a number for the loop's three nodes, or "auto" (real time:
        # the configured rate, and where the driver finds this host cannot hold it with
        # margin, again at the highest rate it can: core/loop/capacity.py; run())
        self.auto_rate = rate == "auto"
        if rate not in (None, "auto"):
            self.set_rate(float(rate))
        # a run of armed_s seconds on the stage's own clock from the sample it first
        # enabled (the driver counts them and ends the run): the start-up, however
        # long it takes on this host, is no part of it
        self.armed_s = None
        self._drv_params = drv
        if armed_s is not None and "stage_driver" in self.nodes:  # (managed or not)
            self.armed_s = float(armed_s)
            self._armed_steps()
        if o.watch:
            self._watched(params)
        self.env = dict(os.environ if env is None else env)
        if self.backend == "sim":  # keep a simulated run's discovery on this host
            self.env.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
        # real time: the set's participants leave out the shared-memory transport, whose
        # health check on a joining participant's port held every publish of a node
        # (realtime_transport_env), and publish synchronously: on UDP a
        # send is the caller's sendto, where the asynchronous mode's hand-off to a
        # writer thread per participant costs more CPU than it saves (docs/realtime.md).
        # Lockstep keeps the transports its byte-identical reruns
        # were measured with.
        transport = lockstep_transport_env(self.env) if self.lockstep else \
            realtime_transport_env(self.env)
        self.node_env = dict(transport)
        self.env.update(transport)  # set only where the user configured none
        # the loop's nodes in one process (nodes/loop_container.py; COMPOSE: which)
        compose = (COMPOSE_DEFAULT["lockstep" if self.lockstep else "realtime"]
                   if compose is None else compose)
        if compose not in COMPOSE:
            raise ConfigError(f"compose {compose!r}: one of {', '.join(COMPOSE)}")
        self.composed = [n for n in COMPOSE[compose] if n in self.nodes] \
            if all(n in self.nodes for n in COMPOSE[compose]) else []
        # every file the parameters name, read as its node would, before any starts
        check_files({n: {**params.get(n, {}), **self.overrides.get(n, {})}
                     for n in self.nodes})
        self.procs = Processes(self)
        self.failed: list[str] = []
        self.signalled: set[str] = set()   # the nodes this launcher sent SIGINT
        self.stopped_by = None   # the signal that told the launcher to stop
        self.quiet_stop = False  # a command that runs sets says a stop in its own line
        self.ended = False       # the run ended by itself (driver done, duration passed)
        self.retrying = False    # a try --rate auto runs again at a lower rate
        # made before the SIGINTs of a run that ended (_signals)
        self._ended_file: str | None = None

    def _gates(self):
        has = set(self.nodes)
        # the recorder and the live view subscribe to every topic: each publisher waits
        # for them too, or a gate could open on the taps before a loop node listens
        # (lockstep with --foxglove once hung so: the live view stood in for the
        # feedforward, whose first sample never came)
        rec = int("recorder" in has) + int("live_view" in has)
        g = {"stage_driver": {"min_subscribers": rec + sum(n in has for n in
                                                           ("feedforward", "identifier",
                                                            "gap")),
                              "min_record_subscribers": rec},
             "feedforward": {"min_subscribers": rec + int("controller" in has),
                             "wait_for_trajectory": "trajectory" in has},
             "controller": {"min_subscribers": rec + int("stage_driver" in has)},
             # the feedforward alone takes trajectories (the recorder the accepted one)
             "trajectory": {"min_subscribers": int("feedforward" in has)},
             "gap": {"min_subscribers": rec}}
        if not self.lockstep:  # real time: the driver's clock starts once they listen;
            # the loop closes (and the set arms) once the trajectory node's is there
            g = {"trajectory": g["trajectory"], "gap": g["gap"],
                 "stage_driver": g["stage_driver"],
                 "feedforward": {"wait_for_trajectory": "trajectory" in has}}
        g.setdefault("stage_driver", {})["auto_arm"] = self.arm
        if self.managed:
            g["stage_driver"]["managed"] = True
        return g

    def _watched(self, params: Params) -> None:
        """--watch: the gap node watches the model in use (the feedforward's file, else
        the gap node's, else the package's), the feedforward starts with that model,
        and the gap node runs at the loop's rate; in lockstep the set waits at a
        window's end while the watch diagnoses it (``watch_hold``)."""
        from piezo_stage.paths import default_config

        def given(node: str) -> str:
            return str({**params.get(node, {}), **self.overrides.get(node, {})}.get(
                "model_file") or "")
        model = given("feedforward") or given("gap") or default_config("stage_model.yaml")
        self.overrides.setdefault("gap", {}).update(watch=True, model_file=model,
                                                    control_rate_hz=self.rate_hz(),
                                                    watch_hold=bool(self.lockstep))
        self.overrides.setdefault("feedforward", {})["model_file"] = model

    def rate_hz(self) -> float:
        """The driver's control rate [Hz] as this set passes it."""
        return float(self.overrides.get("stage_driver", {}).get(
            "control_rate_hz", self._drv_params.get("control_rate_hz", 1000.0)))

    def set_rate(self, rate_hz: float) -> None:
        """Run the loop's three nodes at ``rate_hz`` (their control_rate_hz)."""
        for n in LOOP_NODES + (("gap",) if "gap" in self.nodes else ()):
            self.overrides.setdefault(n, {})["control_rate_hz"] = float(rate_hz)
        if getattr(self, "armed_s", None) is not None:
            self._armed_steps()

    def _armed_steps(self) -> None:
        """The driver counts ``armed_s`` seconds of samples from its first enable, and
        then ends the run."""
        assert self.armed_s is not None
        self.overrides.setdefault("stage_driver", {}).update(
            max_steps=max(1, int(round(self.armed_s * self.rate_hz()))),
            max_steps_from_arming=True, exit_after_max_steps=True)

    def command(self, node):
        if node == LOOP:  # the composed loop: each node's parameters named with it
            cmd = [sys.executable, "-m", "piezo_stage.nodes.loop_container", *self.composed]
            for n in self.composed:
                for k, v in self.node_params(n).items():
                    cmd += ["--param", f"{n}:{k}:={_fmt(v)}"]
            return cmd + ["--ros-args", "-r", f"__ns:={self.ns}", "--params-file",
                          self.config_path]
        cmd = [sys.executable, "-m", f"piezo_stage.nodes.{node}_node", "--ros-args",
               "-r", f"__ns:={self.ns}", "--params-file", self.config_path]
        for k, v in self.node_params(node).items():
            cmd += ["-p", f"{k}:={_fmt(v)}"]
        return cmd

    def processes(self) -> list[str]:
        """The processes in start order: each node's, the composed ones' (``LOOP``)
        where the last of them would start (the driver's last: its first sample finds
        the others listening)."""
        last = max((self.nodes.index(n) for n in self.composed), default=-1)
        out = []
        for i, n in enumerate(self.nodes):
            if n not in self.composed:
                out.append(n)
            elif i == last:
                out.append(LOOP)
        return out

    def process_of(self, node) -> str:
        """The process a node runs in."""
        return LOOP if node in self.composed else node

    def label(self, process) -> str:
        """A process in words: a node's name, or the composed loop's with its nodes."""
        return f"{LOOP} ({', '.join(self.composed)})" if process == LOOP else process

    def node_params(self, node) -> Doc:
        """What the launcher sets on ``node`` beyond the parameter file: start-up
        gating, the recorder's bag, one clock, the overrides (the ros2 launch file
        passes the same)."""
        extra = dict(self._gates().get(node, {}))
        if node == "recorder":
            extra.update(output=os.path.abspath(str(self.record)), config_file=self.config_path,
                         log_time="stamp" if self.lockstep else "receive")
        if node == "live_view":
            extra["port"] = int(self.foxglove_port or 0)
        if self.lockstep:  # one clock: the driver's samples (/clock), bags included
            extra["use_sim_time"] = True
        elif node == "feedforward":
            # a real-time set's driver may refuse to arm (its capacity judged while it
            # runs disarmed), and --rate auto runs the set again at a lower rate
            # (run()): what it took from outside would be lost with it, so it takes
            # nothing before it has armed, and an outside publisher waits for the set
            # that runs (a refusal never comes after the set took an input)
            extra["inputs_once_armed"] = True
        extra.update(self.overrides.get(node, {}))
        return extra

    def start(self):
        """Start the nodes in order. Each starts with SIGINT and SIGTERM blocked (the
        mask survives exec; the node unblocks them once its handlers are in place, so a
        stop sent at any moment is delivered, never lost or met by a traceback) and
        with the launcher's pid, so that it stops when the launcher dies (even by
        SIGKILL: see process/signals.py). A signal to the launcher while it starts them
        ends the starting; the nodes started so far are stopped in order."""
        import tempfile
        run_dir = tempfile.mkdtemp(prefix="piezo-stage-run-")
        self._ended_file = os.path.join(run_dir, "ended")
        gate = os.path.join(run_dir, "go")
        env = dict(self.env, **{LAUNCHER_PID_ENV: str(os.getpid()),
                                RUN_ENDED_ENV: self._ended_file,
                                START_GATE_ENV: gate if self.exclusive else ""})
        look = None
        if self.exclusive:  # one set per namespace (launcher/running.py), looked for while
            # the nodes import (they wait at the start gate before they join the graph:
            # _executor.run_nodes), so the look costs no start-up; begun by the command
            # before it read its config where it could (Look)
            look, self._look = self._look_for_this_set(), None
        for n in self.processes():
            if self.stopped_by is not None:  # told to stop while starting
                if look is not None:
                    look.cancel()
                return
            old = signal.pthread_sigmask(signal.SIG_BLOCK, STOP_SIGNALS)
            try:
                self.procs[n] = subprocess.Popen(self.command(n), env=env,
                                                 start_new_session=True)
            finally:
                signal.pthread_sigmask(signal.SIG_SETMASK, old)
        if look is not None:
            while not look.wait(0.02):  # a stop meanwhile: the nodes never pass the gate
                if self.stopped_by is not None:
                    look.cancel()
                    return
            try:
                who = look.result()
            except BaseException:
                self._discard()
                raise
            if who:
                self._discard()
                raise ConfigError(f"{self.ns} is already running ({who}): use "
                                  "--namespace or stop it")
            # the look's participant gone before the nodes join the graph (milliseconds;
            # bounded): a participant torn down while it discovers theirs can deadlock
            # in Fast DDS (launcher/running.py's Look)
            look.close()
            with open(gate, "w"):
                pass

    def _look_for_this_set(self):
        """The look begun for this set's namespace and domain, else one begun now."""
        from piezo_stage.launcher.running import Look
        domain = int(self.env.get("ROS_DOMAIN_ID") or 0)
        look = self._look
        if look is not None and (look.namespace.strip("/"), look.domain_id) == (
                self.ns.strip("/"), domain):
            return look
        if look is not None:
            look.cancel()
        return Look(self.ns, domain)

    def _discard(self) -> None:
        """The nodes started for a set that will not run: still at the start gate, they
        have joined nothing; they are killed and forgotten."""
        for p in self.procs.values():
            if p.poll() is None:
                p.kill()
            p.wait()
        self.procs = Processes(self)

    def stop(self, grace_s=STOP_GRACE_S):
        """Stop the set in its safe order: the driver first (it disarms, which is no
        fault, and ramps the stage to its safe voltage before it exits; the launcher
        waits for it), then the producers, then the recorder and the live view, so the
        bag holds everything, the ramp included. A node that has not stopped by its
        grace is killed, and that is a failure."""
        driver = self.process_of("stage_driver")
        producers = [n for n in reversed(self.processes())
                     if n not in ("recorder", driver, "live_view")]
        why = "retried" if self.retrying else "" if self.ended else None
        if why is not None and self.stopped_by is None and self._ended_file:
            with open(self._ended_file, "w") as fh:  # the nodes' SIGINT is the run's end
                fh.write(why)
        for group, grace in (([driver], grace_s["stage_driver"]),
                             (producers, grace_s["producers"]),
                             (["recorder", "live_view"], grace_s["recorder"])):
            for n in group:
                p = self.procs.get(n)
                if p and p.poll() is None:
                    p.send_signal(signal.SIGINT)
                    self.signalled.add(n)
            deadline = time.monotonic() + grace
            for n in group:
                p = self.procs.get(n)
                if not p:
                    continue
                try:
                    p.wait(max(0.1, deadline - time.monotonic()))
                except subprocess.TimeoutExpired:
                    p.kill()
                    p.wait()
                    self.failed.append(f"{self.label(n)} did not stop within {grace:g} s "
                                       "of SIGINT (killed)")
        if self._ended_file:
            import shutil
            shutil.rmtree(os.path.dirname(self._ended_file), ignore_errors=True)
            self._ended_file = None

    def wall_bound(self) -> float | None:
        """The wall time [s] a run of ``armed_s`` may take before the launcher gives up
        on it (None: no such run)."""
        if self.armed_s is None:
            return None
        return START_ALLOWANCE_S + self.armed_s * (LOCKSTEP_SLOWDOWN if self.lockstep
                                                   else 2.0)

    def wait(self, duration=None):
        """Run until duration [s] passes, a node exits 0 (done) or one dies, or a
        signal comes (SIGINT, SIGTERM, SIGHUP: see run). With ``armed_s`` the driver
        ends the run, ``duration`` bounds it (a run that never arms)."""
        t0 = time.monotonic()
        t_end = None if duration is None else t0 + duration
        from piezo_stage.progress import bar
        total = self.armed_s if self.armed_s is not None else duration
        with bar("launch", total=total, unit="s") as b:  # on a terminal only
            self._wait(t0, t_end, b)

    def _wait(self, t0, t_end, b):
        try:
            while True:
                now = round(time.monotonic() - t0, 1)
                if b.total:  # (an armed run's end is the driver's: the bar waits full)
                    now = min(now, b.total)
                b.update(now - b.n)
                for n, p in self.procs.items():
                    rc = p.poll()
                    if rc is not None:
                        if rc != 0:
                            self.failed.append(f"{self.label(n)} {_ended(rc)}")
                        else:
                            self.ended = True  # done: the run ended by itself
                        return
                if t_end is not None and time.monotonic() >= t_end:
                    if self.armed_s is not None:  # the driver never ended its run
                        self.failed.append(
                            f"the run of {self.armed_s:g} s after arming did not end "
                            f"within {t_end - t0:.0f} s (did the set arm? the driver's "
                            "state is on /stage/state)")
                    else:
                        self.ended = True
                    return
                if self.stopped_by is not None:
                    return
                time.sleep(0.05)
        except KeyboardInterrupt:  # wait() used without run(): Ctrl-C as usual
            return

    def stopped_cleanly(self, node) -> bool:
        """The node ended by itself (exit 0), or on this launcher's SIGINT (130)."""
        rc = self.procs[node].returncode
        return rc == 0 or (node in self.signalled and rc == 128 + signal.SIGINT)

    def _on_signal(self, signum, frame):
        """Only noted: start() and wait() look at it every 50 ms at most. Raising here
        could cut the orderly stop short and leave nodes behind."""
        if self.stopped_by is None:
            self.stopped_by = signum

    def run(self, duration=None) -> int:
        """Start, wait, stop in order; the exit code: 0 for a run that ended by
        ``duration`` or by its driver finishing, 128 + the signal's number for one the
        launcher was told to stop (every node stopped in order), 1 when a node failed
        (died, was stopped by someone else, or had to be killed). With ``rate="auto"``
        a set whose driver found this host cannot hold its rate with margin runs again
        at the highest rate it found the host holds (said in one line), each time at a
        lower rate, at most AUTO_ATTEMPTS times in all: a rate picked from the capacity
        measured at a higher one may be refused as well (a host with a core taken by
        another process: 1,000 Hz said 500 Hz, and 500 Hz measured 1.41 x)."""
        import tempfile
        old = {s: signal.signal(s, self._on_signal) for s in STOP_SIGNALS + (signal.SIGHUP,)}
        cap_dir = tempfile.mkdtemp(prefix="piezo-stage-capacity-")
        cap_file = os.path.join(cap_dir, "capacity.json")
        self.env[CAPACITY_FILE_ENV] = cap_file
        tried: list[float] = []
        refused: Doc | None = None
        try:
            for attempt in range(1, AUTO_ATTEMPTS + 1):
                tried.append(self.rate_hz())

                def again() -> bool:  # refused, and --rate auto runs it at a lower rate
                    r = read_refusal(cap_file)
                    return bool(self.auto_rate and attempt < AUTO_ATTEMPTS and r and
                                r.get("holdable_rate_hz") and self.stopped_by is None and
                                float(r["holdable_rate_hz"]) < self.rate_hz())
                try:
                    self.start()
                    self.wait(duration)
                    self.retrying = again()  # (its nodes then say nothing of a stop)
                finally:
                    self.stop()
                refused = read_refusal(cap_file)
                if not again():
                    break
                assert refused is not None
                self._again_at_the_rate_held(refused, cap_file)
        finally:
            import shutil
            shutil.rmtree(cap_dir, ignore_errors=True)
            for s, h in old.items():
                signal.signal(s, h)
        return self._verdict(refused, tried)

    def _again_at_the_rate_held(self, refused: Doc, cap_file: str) -> None:
        """A try refused (rate auto): the next one at the rate the host held, said in
        one line, with a fresh set of processes and no bag of the refused try."""
        rate = float(refused["holdable_rate_hz"])
        # the refused try never armed: its bag (if any) is replaced by this one
        bag = (f"; its bag replaces the {self.rate_hz():g} Hz try's in "
               f"{self.record}" if self.record else "")
        sys.stderr.write(f"piezo-stage launch: this host holds the loop at "
                         f"{refused['capacity_hz']:,.0f} samples/s, "
                         f"{refused['margin']:.2f} x {self.rate_hz():g} Hz: "
                         f"running again at {rate:g} Hz (rate auto{bag})\n")
        self.set_rate(rate)
        self.procs, self.failed, self.signalled = Processes(self), [], set()
        self.ended = self.retrying = False
        os.remove(cap_file)
        if self.record:  # the refused try's bag is no record of the run
            import shutil
            shutil.rmtree(self.record, ignore_errors=True)

    def _verdict(self, refused: Doc | None, tried: list[float]) -> int:
        """The run's exit code (``run``), each failure said in one line."""
        holder = LOOP if "stage_driver" in self.composed else "stage_driver"
        driver = self.procs.get(holder)
        if refused and driver is not None and driver.returncode == 2:
            # the driver's own line gave the figures; this one says what the launch did
            n = len(tried)
            runs = (f"; rate auto ran it {'once' if n == 1 else f'{n} times'}, at "
                    f"{', '.join(f'{r:g}' for r in tried)} Hz" if self.auto_rate else "")
            self.failed = [f for f in self.failed
                           if not f.startswith(self.label(holder) + " ")]
            self.failed.append(
                f"{self.label(holder)} refused to arm at {self.rate_hz():g} Hz: "
                f"this host holds the loop at {refused['capacity_hz']:,.0f} samples/s, "
                f"{refused['margin']:.2f} x, under min_margin "
                f"{refused['min_margin']:g}{runs}")
        for n, p in self.procs.items():
            if not self.stopped_cleanly(n) and not any(f.startswith(self.label(n) + " ")
                                                       for f in self.failed):
                self.failed.append(f"{self.label(n)} {_ended(p.returncode)}")
        for f in self.failed:
            sys.stderr.write(f"piezo-stage launch: {f}\n")
        if self.failed:
            return 1
        if self.stopped_by is not None and not self.quiet_stop:
            sys.stderr.write(f"piezo-stage launch: stopped by "
                             f"{signal.Signals(self.stopped_by).name}: every node stopped "
                             "in order (the driver first, at its safe voltage)\n")
            return 128 + self.stopped_by
        return 0


def run_set(launch: Launch, what: str, duration: float | None = None) -> None:
    """Run ``launch`` for a command (an experiment's case, the demo): a stop by a signal
    is the command's own stop (KeyboardInterrupt, with the signal noted, so it ends with
    one line and 128 + the signal, as a stop anywhere else in it); a set that failed is
    a RunError naming ``what`` and why (the command exits 1)."""
    from piezo_stage.core.errors import RunError
    from piezo_stage.process import stopping
    launch.quiet_stop = True
    rc = launch.run(duration)
    if launch.stopped_by is not None and not launch.failed:
        stopping.STATE.signum = launch.stopped_by
        raise KeyboardInterrupt
    if rc != 0:
        raise RunError(f"{what}: the node set failed: "
                       f"{'; '.join(launch.failed) or f'exit {rc}'}")


def _ended(rc) -> str:
    """How a node ended, in words, from its exit code."""
    if rc is None:
        return "did not end"
    if rc < 0:
        return f"was killed by {signal.Signals(-rc).name}"
    if rc > 128 and rc - 128 in {s.value for s in signal.Signals}:
        return (f"was stopped by {signal.Signals(rc - 128).name} from outside the "
                "launcher")
    return f"died with exit code {rc}"
