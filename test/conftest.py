import os
import sys
import time

import numpy as np
import pytest

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
CONFIG = os.path.join(ROOT, "config")
sys.path.insert(0, ROOT)


@pytest.fixture(scope="session")
def stage_model():
    from piezo_stage.io.model_file import load_model
    return load_model(os.path.join(CONFIG, "stage_model.yaml"))[0]


@pytest.fixture(scope="session")
def plant_config_path():
    return os.path.join(CONFIG, "sim_stage.yaml")


def cli(*args, cwd=None):
    """`piezo-stage ARGS` as a user runs it, in the repository root by default."""
    import subprocess
    return subprocess.run([sys.executable, "-m", "piezo_stage.cli", *map(str, args)],
                          capture_output=True, text=True, timeout=120, cwd=cwd or ROOT)


def one_line_exit_2(r):
    """Bad input: exit 2 and one line on stderr, no traceback."""
    assert r.returncode == 2, (r.returncode, r.stderr[-500:])
    assert len(r.stderr.strip().splitlines()) == 1, r.stderr
    assert "Traceback" not in r.stderr


def sine_v(freq, fs, cycles, lo=0.0, hi=150.0, phase=0.0):
    t = np.arange(int(round(cycles * fs / freq))) / fs
    return t, lo + (hi - lo) / 2 * (1 - np.cos(2 * np.pi * freq * t + phase))


# -- Fast DDS's shared memory: what killed processes left behind ------------------------
# A participant killed (SIGKILL, a crash, a timeout's kill) leaves its segments and port
# files in /dev/shm; after a few suites there were 700-1,300 of them here. A new
# participant that opens such a port can crash inside Fast DDS (Fast-DDS issue 6501:
# check_sanity() on a stale segment; a lab node on the default transports died with
# SIGSEGV in a fresh clone's run) or write port errors into a command's output. The
# suite removes, at its start, the ones no process on this host has open or mapped,
# as `fastdds shm clean` (not in the wheels) would.
SHM = "/dev/shm"
STALE_AFTER_S = 60.0


def stale_fastdds_shm(shm=SHM, proc="/proc", older_than_s=STALE_AFTER_S) -> list:
    """Fast DDS's files in ``shm`` that no live process has open or mapped (its fds and
    its maps, read through ``proc``; a port's named mutex while its port is held) and
    that are older than ``older_than_s`` (a participant starting now may not have
    mapped what it just opened)."""
    try:
        names = [n for n in os.listdir(shm) if n.startswith(("fastrtps_", "fastdds_",
                                                              "sem.fastrtps_",
                                                              "sem.fastdds_"))]
    except OSError:
        return []
    if not names:
        return []
    used = set()
    for pid in os.listdir(proc):
        if not pid.isdigit():
            continue
        try:
            with open(os.path.join(proc, pid, "maps"), encoding="utf-8",
                      errors="replace") as fh:
                for line in fh:
                    if shm in line:
                        used.add(os.path.basename(line.split(None, 5)[-1].strip()
                                                  .removesuffix(" (deleted)")))
            fd_dir = os.path.join(proc, pid, "fd")
            for fd in os.listdir(fd_dir):
                try:
                    target = os.readlink(os.path.join(fd_dir, fd))
                except OSError:
                    continue
                if target.startswith(shm + "/"):
                    used.add(os.path.basename(target))
        except OSError:  # gone, or not ours to read
            continue
    # a port's named mutex is opened only while it is taken: it goes with its port
    held = {n.removesuffix("_el") for n in used}
    now = time.time()
    stale = []
    for n in names:
        if n in used or (n.startswith("sem.") and n[4:].removesuffix("_mutex") in held):
            continue
        try:
            if now - os.stat(os.path.join(shm, n)).st_mtime > older_than_s:
                stale.append(n)
        except OSError:
            continue
    return sorted(stale)


def pytest_configure(config):
    if hasattr(config, "workerinput"):  # a pytest-xdist worker: its controller did
        return
    for n in stale_fastdds_shm():
        try:
            os.unlink(os.path.join(SHM, n))
        except OSError:  # another user's, or gone already
            pass


# -- ROS domains: each test its own, never shared between parallel runs --------------
# Fast DDS takes domain ids 0-232; 0 is left to the user's own graph. Each test process
# (a pytest-xdist worker, or pytest alone) claims a slice of 1-228 that no other process
# on this host holds (a lock file, held while it runs) and hands its ids out in turn,
# so no two tests running at the same time ever share a domain: not two workers (random
# ids did, now and then), and not two suites on one host (a second suite's `demo` test
# once found the first one's set on its domain: "/stage is already running", exit 2).
SLICE = 38
_DOMAINS: dict = {"next": 0}


def _domain_slice():
    if "slice" not in _DOMAINS:
        _DOMAINS["slice"] = _claim_slice()
    return _DOMAINS["slice"]


def _claim_slice():
    """The first slice no other process on this host holds: (first id, size)."""
    import fcntl
    import tempfile
    where = os.path.join(tempfile.gettempdir(), "piezo_stage_test_domains")
    os.makedirs(where, exist_ok=True)
    for k in range(228 // SLICE):
        fh = open(os.path.join(where, f"slice{k}.lock"), "w")
        try:
            fcntl.flock(fh, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            fh.close()
            continue
        _DOMAINS["lock"] = fh  # held until this process ends (the OS lets it go then)
        return 1 + k * SLICE, SLICE
    raise RuntimeError(f"every slice of ROS domain ids is held by other test processes "
                       f"on this host ({228 // SLICE} at most at a time)")


@pytest.fixture
def ros_domains():
    """``take(n)``: the first of ``n`` consecutive domain ids for this test alone."""
    def take(n=1):
        lo, size = _domain_slice()
        if _DOMAINS["next"] + n > size:
            _DOMAINS["next"] = 0
        d = lo + _DOMAINS["next"]
        _DOMAINS["next"] += n
        return d
    return take


@pytest.fixture
def ros_env(ros_domains):
    """The environment for this test's node processes: its own domain, on this host."""
    os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"  # in-process probes too
    return dict(os.environ, ROS_DOMAIN_ID=str(ros_domains()),
                ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST", PYTHONPATH=ROOT)


def on_a_terminal(argv, env=None, cwd=None, timeout=300) -> str:
    """What ``argv`` writes (stdout and stderr) to a 100-column terminal, a
    pseudo-terminal here, as text; asserts it exited 0."""
    import fcntl
    import pty
    import struct
    import subprocess
    import termios
    master, slave = pty.openpty()
    fcntl.ioctl(slave, termios.TIOCSWINSZ, struct.pack("HHHH", 24, 100, 0, 0))
    try:
        p = subprocess.Popen([str(a) for a in argv], stdout=slave, stderr=slave, cwd=cwd,
                             env=env)
        os.close(slave)
        seen = b""
        while True:
            try:
                chunk = os.read(master, 4096)
            except OSError:  # the child closed the terminal
                break
            if not chunk:
                break
            seen += chunk
        assert p.wait(timeout=timeout) == 0, seen[-2000:]
    finally:
        os.close(master)
    return seen.decode(errors="replace")


# -- real time on this host: the rate the suite's real-time sets run at ------------------
# (the tests' sets then run at that rate with min_margin 0: judged by what they test, not
# by a second measurement of a host that the capacity run has measured already);
# the host is measured again when its figure is older than this: a phase of real-time
# tests takes about 5 minutes, and a host that slows within it (a CI run's phase: four
# tests faulted on stale commands within five minutes, all at the rate chosen at its
# start) is then judged at what it holds now; each capacity run takes about 6 s
REMEASURE_S = 90.0


class HostRates:
    """The real-time rate of this test process: ``measure(env)`` -> (rate or None, the
    figures in words), taken at the first ask, again when the last is older than
    ``every_s`` on ``clock``, and whenever asked ``fresh``. ``measured``: a line for
    each (the clock's time of day, the rate, the figures), for the suite's summary."""

    def __init__(self, measure, every_s=REMEASURE_S, clock=time.monotonic):
        self.measure, self.every_s, self.clock = measure, every_s, clock
        self.rate, self.why, self.at = None, "", None
        self.measured: list[str] = []

    def __call__(self, env, fresh=False):
        if fresh or self.at is None or self.clock() - self.at > self.every_s:
            self.rate, why = self.measure(env)
            self.at = self.clock()
            self.why = f"this host holds no real-time rate with margin: {why}"
            self.measured.append(f"{time.strftime('%H:%M:%S')} "
                                 f"{f'{self.rate:g} Hz' if self.rate else 'no rate'}: {why}")
        return self.rate, self.why


def _host_rate(env):
    from piezo_stage.launcher.host_rate import host_rate
    return host_rate(env)


_REALTIME = HostRates(_host_rate)


def realtime_rate_hz(env, fresh: bool = False) -> float:
    """The highest standard rate this host holds a real-time set at with the margin a
    set needs and room for its spread (piezo_stage/launcher/host_rate.py), measured at
    the first real-time test of this test process and again when that figure is older
    than REMEASURE_S (or ``fresh``: a test that runs again after a failure): the
    real-time tests run there and are judged there, never by a rate the host cannot
    hold. Every measurement goes into the suite's summary. Where it holds none:
    ``no_realtime_rate``."""
    rate, why = _REALTIME(env, fresh)
    if rate is None:
        no_realtime_rate(why)
    return rate


def realtime_twice(run, env, ros_domains, errors=(AssertionError,), name=None):
    """``run(env, rate, which)`` at the host's rate (``which`` "first"); when it fails
    with one of ``errors``, once more ("second") on a fresh domain at the rate the host
    holds now, measured again: real time on a shared 2-core VM, where a host that
    slowed since its last measurement is judged where it holds. Two failures fail. The
    first is a warning, so the suite's summary (and a CI log) shows every run taken
    twice and the rates of both."""
    import warnings
    rate = realtime_rate_hz(env)
    try:
        return run(env, rate, "first")
    except errors as e:
        again = dict(env, ROS_DOMAIN_ID=str(ros_domains()))
        now = realtime_rate_hz(again, fresh=True)
        warnings.warn(f"{name or run.__name__}: the first real-time run at {rate:g} Hz "
                      f"failed ({type(e).__name__}), ran it again on a fresh domain at "
                      f"{now:g} Hz: {str(e)[:2000]}", stacklevel=2)
        return run(again, now, "second")


def pytest_terminal_summary(terminalreporter):
    """The real-time rates this test process chose and the host's figures they were
    chosen by: a red real-time test is read beside what the host held then."""
    if _REALTIME.measured:
        terminalreporter.section("real-time rates chosen (host_rate)")
        for line in _REALTIME.measured:
            terminalreporter.write_line(line)


REALTIME_REQUIRED = "PIEZO_STAGE_REALTIME_REQUIRED"


def no_realtime_rate(why: str, environ=os.environ):
    """A host that holds no real-time rate: its real-time tests are skipped with the
    figures, or failed where the run says the host must run them (``REALTIME_REQUIRED``
    set, as CI's .ci/run sets it): a green CI then says its real-time tests ran, none
    skipped all at once because the host's capacity run came out short or empty."""
    if environ.get(REALTIME_REQUIRED, "") not in ("", "0"):
        pytest.fail(f"{why} ({REALTIME_REQUIRED} is set: this host must run them)",
                    pytrace=False)
    pytest.skip(why)
