"""Stop signals at random moments: every node kind and the launcher, started as a lab
starts them and sent SIGINT or SIGTERM 0-3 s later (during imports, ``rclpy.init``,
discovery, spinning), some under CPU load. Counts hangs, tracebacks, wrong exit codes,
missing stop lines and nodes a launcher left behind.

``piezo-stage bench signals`` prints the counts; the test suite runs a short form of
the same trials (test/test_signals.py)."""

from __future__ import annotations

import linecache
import os
import random
import re
import signal
import subprocess
import sys
import tempfile
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

from piezo_stage.nodes import NODES
from piezo_stage.paths import default_config

KINDS = NODES + ("launcher",)
HANG_S = 10.0  # a stop not done by then is a hang (the process is then killed)


@dataclass
class Trial:
    """One process signalled once: what it was, when, and how it ended."""

    kind: str
    delay_s: float
    signum: int
    loaded: bool
    rc: int | None = None
    stop_s: float = float("nan")   # from the signal to the process's exit
    traceback: bool = False
    said: str = ""                 # the line that says what the stop did
    left_behind: int = 0           # launcher: nodes still running after it exited
    tail: str = ""                 # the end of what it printed (for a stop not clean)
    text: str = ""                 # all it printed on stderr

    @property
    def before_python(self) -> bool:
        """Signalled before the interpreter took any signal (its first milliseconds):
        the kernel's default action ended it at once, with nothing open and nothing
        said. Started by the launcher, a node is safe from this too (the signals are
        blocked across exec until our handlers are in place)."""
        return self.rc == -self.signum and self.stop_s < 0.05 and not self.traceback

    @property
    def python_startup(self) -> bool:
        """SIGINT in the interpreter's own start-up: after Python put in its handler
        (its first milliseconds) and before the module that installs ours was reached
        (site, runpy, the package's ``__init__``). Python raised KeyboardInterrupt
        there and the process ended at once; nothing of ours had run, so nothing was
        open. Started by the launcher, a node is safe from this too (see above)."""
        return (self.signum == signal.SIGINT and not self.said and not self.hung
                and before_our_handlers(self.text))

    @property
    def hung(self) -> bool:
        return self.rc is None

    @property
    def ok(self) -> bool:
        return self.before_python or self.python_startup or (
            not self.hung and not self.traceback and bool(self.said)
            and self.rc == 128 + self.signum and self.left_behind == 0)


_FRAME = re.compile(r'File "([^"]+)", line (\d+), in (\S+)')
# the package's own files; the editable install's finder (site-packages'
# ``__editable___piezo_stage_*_finder.py``, run by site from a .pth line) is start-up
_PACKAGE = os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))),
                        "piezo_stage") + os.sep


def before_our_handlers(text: str) -> bool:
    """Whether ``text`` holds a KeyboardInterrupt traceback raised before the process's
    own handlers were in place: each of its frames is the interpreter's (runpy,
    importlib, site and what site runs, such as an editable install's finder) or one
    of ours on the way to the handlers (a package's ``__init__``, the line of the entry
    module that imports them, that module's own top level or its ``install``). A frame
    anywhere else in the package means the handler missed."""
    if "KeyboardInterrupt" not in text or "Traceback" not in text:
        return False
    frames = _FRAME.findall(text)
    if not frames:
        return False
    for path, line, func in frames:
        if not (os.path.isabs(path) and path.startswith(_PACKAGE)):
            continue
        name = os.path.basename(path)
        if name in ("signals.py", "stopping.py") and func in ("<module>", "install"):
            continue
        if func == "<module>" and name == "__init__.py":
            continue
        if name == "rosidl_runtime.py":  # what the package's __init__ runs at import
            continue
        src = linecache.getline(path, int(line))
        if func in ("<module>", "main") and ("process.signals" in src or "stopping" in src):
            continue
        return False
    return True


def _command(kind: str, ns: str, out_dir: str) -> list[str]:
    cfg = default_config("stage.yaml")
    if kind == "launcher":
        return [sys.executable, "-m", "piezo_stage", "launch", cfg, "--namespace", ns,
                "--duration", "60", "--record", os.path.join(out_dir, "bag")]
    cmd = [sys.executable, "-m", f"piezo_stage.nodes.{kind}_node", "--ros-args",
           "-r", f"__ns:={ns}", "--params-file", cfg]
    if kind == "recorder":
        cmd += ["-p", f"output:={os.path.join(out_dir, 'bag')}"]
    if kind == "live_view":
        cmd += ["-p", "port:=0"]
    return cmd


def left_behind(ns: str) -> list[int]:
    """Processes still running whose command line names this trial's namespace."""
    pids = []
    for d in os.listdir("/proc"):
        if not d.isdigit():
            continue
        try:
            with open(f"/proc/{d}/cmdline", "rb") as fh:
                cmd = fh.read().split(b"\0")
            with open(f"/proc/{d}/stat") as fh:
                state = fh.read().rsplit(")", 1)[1].split()[0]
        except OSError:
            continue
        if f"__ns:={ns}".encode() in cmd and state != "Z":
            pids.append(int(d))
    return pids


def run_trial(trial: Trial, domain: int, index: int) -> Trial:
    """Start the process, signal it after ``trial.delay_s``, judge its stop."""
    ns = f"/sigtrial{index}"
    env = dict(os.environ, ROS_DOMAIN_ID=str(domain),
               ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST")
    with tempfile.TemporaryDirectory() as d:
        err_path = os.path.join(d, "stderr")
        with open(err_path, "w") as err:
            p = subprocess.Popen(_command(trial.kind, ns, d), env=env,
                                 stdout=subprocess.DEVNULL, stderr=err)
            time.sleep(trial.delay_s)
            p.send_signal(trial.signum)
            t0 = time.monotonic()
            try:
                trial.rc = p.wait(HANG_S)
                trial.stop_s = time.monotonic() - t0
            except subprocess.TimeoutExpired:
                p.kill()
                p.wait()
        with open(err_path, errors="replace") as fh:
            text = fh.read()
        if trial.kind == "launcher":
            time.sleep(0.2)
            stray = left_behind(ns)
            trial.left_behind = len(stray)
            for pid in stray:  # never leave a trial's node running on the machine
                try:
                    os.kill(pid, signal.SIGKILL)
                except ProcessLookupError:
                    pass
    trial.traceback = "Traceback" in text
    trial.tail, trial.text = text[-600:], text
    name = signal.Signals(trial.signum).name
    lines = [ln for ln in text.splitlines() if f"stopped by {name}" in ln]
    trial.said = lines[-1].strip() if lines else ""
    return trial


def stress(n: int, parallel: int = 2, loaded_share: float = 0.3, seed: int = 0,
           kinds=KINDS, max_delay_s: float = 3.0, domain0: int = 150) -> list[Trial]:
    """``n`` trials over ``kinds`` in turn, random delays up to ``max_delay_s``, SIGINT
    and SIGTERM alternately; the last ``loaded_share`` of them with every core kept
    busy by other processes. ``parallel`` trials at once, each on its own domain."""
    rng = random.Random(seed)
    trials = [Trial(kinds[i % len(kinds)], rng.uniform(0.0, max_delay_s),
                    (signal.SIGINT, signal.SIGTERM)[(i // len(kinds)) % 2],
                    i >= n * (1 - loaded_share)) for i in range(n)]
    burners: list[subprocess.Popen] = []
    done: list[Trial] = []
    try:
        for loaded in (False, True):
            batch = [t for t in trials if t.loaded == loaded]
            if loaded and batch:
                burners = [subprocess.Popen([sys.executable, "-c", "while True: pass"])
                           for _ in range(os.cpu_count() or 2)]
            with ThreadPoolExecutor(parallel) as pool:
                futs = [pool.submit(run_trial, t, domain0 + (len(done) + i) % parallel,
                                    len(done) + i) for i, t in enumerate(batch)]
                done += [f.result() for f in futs]
    finally:
        for b in burners:
            b.kill()
            b.wait()
    return done


def main(rep, n: int = 108) -> int:
    """``piezo-stage bench signals``: the stress run, counts per kind (``rep``: the
    report)."""
    t0 = time.monotonic()
    trials = stress(n)
    rep.title(f"{len(trials)} processes signalled 0-3 s after start "
              f"({sum(t.loaded for t in trials)} under CPU load), SIGINT and SIGTERM in "
              f"turn, {time.monotonic() - t0:.0f} s")
    rows = []
    for k in KINDS:
        ts = [t for t in trials if t.kind == k]
        if not ts:
            continue
        stops = sorted(t.stop_s for t in ts if not t.hung)
        med = stops[len(stops) // 2] if stops else float("nan")
        early = [t.before_python or t.python_startup for t in ts]
        rows.append((k, len(ts), sum(early), sum(t.hung for t in ts),
                     sum(t.traceback and not e for t, e in zip(ts, early)),
                     sum(not (t.hung or e) and t.rc != 128 + t.signum
                         for t, e in zip(ts, early)),
                     sum(not t.said and not e for t, e in zip(ts, early)),
                     sum(t.left_behind for t in ts),
                     f"{med:.2f} / {max(stops, default=float('nan')):.2f}"))
    rep.table(("kind", "trials", "early", "hangs", "tracebacks", "bad exit", "no line",
               "left", "stop s median / max"), rows,
              "early: signalled before any code of ours ran: in the interpreter's first "
              "milliseconds the kernel's default action ends it; a SIGINT a moment later, "
              "in site, runpy or a package __init__, gets Python's own KeyboardInterrupt "
              f"({sum(t.python_startup for t in trials)} here); either way it ends at once "
              "with nothing open. The launcher's nodes are safe from both.")
    bad = [t for t in trials if not t.ok]
    for t in bad[:10]:
        rep.note(f"not clean: {t.kind} {signal.Signals(t.signum).name} after "
                 f"{t.delay_s:.3f} s: exit {t.rc}; it printed ...{t.tail[-300:]!r}")
    slow = [t for t in trials if t.kind != "launcher" and t.stop_s > 2.0]
    rep.target(f"every process clean ({len(trials) - len(bad)}/{len(trials)})", not bad)
    rep.target(f"no node stops in over 2 s ({len(slow)})", not slow)
    return 0 if not bad else 1
