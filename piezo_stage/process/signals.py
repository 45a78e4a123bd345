"""How a node stops: SIGINT and SIGTERM work at every moment of a node's life.

A node module imports this module before anything else, so the handlers are in place
before the heavy imports (numpy, scipy, rclpy take 1-2 s). What a signal does depends on
where the node is (``phase``):

- ``starting`` (imports, before ``rclpy.init``): nothing is open yet (no middleware
  participant, no hardware), so the process says so on one line and exits at once with
  128 + the signal's number. No KeyboardInterrupt traceback.
- ``building`` (``rclpy.init`` and the node's constructor): :class:`Stopped` is raised
  where the node is; ``run_node`` destroys what exists and exits. Inside
  :func:`deferred` (a constructor that does not block and must not be cut short: the
  recorder's) the signal is only noted, and the spin's first pass ends the node.
- ``running`` (spinning): the signal is only noted; the executor polls
  :func:`requested` every pass (at least every 50 ms) and ends the spin, or asks the
  node's ``request_shutdown()`` (the driver ramps the stage to its safe voltage first; a
  second signal stops it at once). Raising from an arbitrary point of the executor
  instead once left nodes hanging at teardown.
- inside :func:`interruptible` (a long fit in a callback): :class:`Stopped` is raised.
- ``stopping`` (teardown): noted, nothing else.

A node that does not end within ``STATE.watch_s`` of the first stop signal (4 s; the
driver's includes its ramp), or of the start of its teardown when it ended by itself,
prints every thread's stack (faulthandler) and exits 1: a hang says where it was, and
ends before the launcher's grace runs out and it has to kill.

The middleware's part of a teardown (the node's DDS entities and, with its last node,
the participant) comes after the node's own (the bag finished, the hardware at its safe
voltage and closed), under :func:`bounded_teardown`: it has ``MIDDLEWARE_TEARDOWN_S``,
and if it has not ended by then the node prints the stacks and one line saying so, and
exits with the code its stop had earned (130 for the launcher's SIGINT), not 1. Nothing
of the node's run is lost there, and Fast DDS 2.14 has been seen to hang in that part
(rclpy's ``destroy_node`` after a complete run, its peers exiting at the same moment;
docs/realtime.md#stopping-a-run has the counts). The exit is a native timer's (``timer_create``
with ``SIGEV_THREAD`` calling ``_exit``): a hang inside the middleware holds Python's
GIL, so no Python thread or signal handler could act.

Started by the launcher, a node begins with SIGINT and SIGTERM blocked (the launcher
blocks them around the fork, and the mask survives exec): a signal sent before this
module is imported waits, and is delivered the moment :func:`install` unblocks it. The
launcher also passes its pid (``PIEZO_STAGE_LAUNCHER_PID``): the node asks the kernel
for a SIGTERM when the launcher dies (``PR_SET_PDEATHSIG``), so even a SIGKILLed
launcher leaves no node behind, the driver included (it ramps down as for any SIGTERM).
"""

from __future__ import annotations

import faulthandler
import os
import signal
import sys
from collections.abc import Iterator
from contextlib import contextmanager
from types import FrameType
from typing import Any

from piezo_stage.process.stopping import again_soon, cannot_raise_here

SIGNALS = (signal.SIGINT, signal.SIGTERM)
LAUNCHER_PID_ENV = "PIEZO_STAGE_LAUNCHER_PID"
RUN_ENDED_ENV = "PIEZO_STAGE_RUN_ENDED"  # a file the launcher makes when the run ended
_PR_SET_PDEATHSIG = 1


class Stopped(BaseException):
    """A stop signal, raised where the node was (start-up, a long fit). A BaseException,
    as KeyboardInterrupt is, so ``except Exception`` handlers do not swallow it."""

    def __init__(self, signum: int) -> None:
        super().__init__(signal.Signals(signum).name)
        self.signum = signum


class _State:
    phase = "starting"
    signum: int | None = None  # the first stop signal
    count = 0                  # how many have come
    name = ""                  # the node's name, for the one line a stop prints
    raise_depth = 0            # > 0 inside interruptible()
    deferring = False          # inside deferred(): building, a stop is only noted
    again = False              # a stop sent again, out of a ctypes callback
    watch_s = 4.0              # a stop that takes longer prints the stacks and exits 1
    watching = False


STATE = _State()


def _name() -> str:
    if STATE.name:
        return STATE.name
    main = sys.modules.get("__main__")
    spec = getattr(main, "__spec__", None)
    mod = spec.name if spec is not None else os.path.basename(sys.argv[0] or "node")
    return mod.rsplit(".", 1)[-1].removesuffix(".py").removesuffix("_node")


def _on_signal(signum: int, frame: FrameType | None) -> None:
    if STATE.again:  # the stop we sent again ourselves (below): counted already
        STATE.again, STATE.count = False, STATE.count - 1
    STATE.count += 1
    if STATE.signum is None:
        STATE.signum = signum
    if STATE.phase == "starting":
        sys.stderr.write(f"{_name()}: stopped by {signal.Signals(signum).name} during "
                         "start-up (nothing was open yet)\n")
        sys.stderr.flush()
        os._exit(128 + signum)
    watch()
    if (STATE.phase == "building" and not STATE.deferring) or STATE.raise_depth > 0:
        if not cannot_raise_here(frame):
            raise Stopped(signum)
        # raised there it would be printed and dropped (or break an import's module
        # lock): the same stop again in a moment,
        # once back in Python (or, running by then, noted: the spin stops the node)
        STATE.again = True
        again_soon(signum)


def hold() -> None:
    """The node has ended: the stop signals are ignored from here to the exit (an
    ignored signal stays ignored through the interpreter's exit, a handled one does
    not), and one that came before counts (:func:`requested`)."""
    for s in SIGNALS:
        signal.signal(s, signal.SIG_IGN)


def run_ended() -> str | None:
    """Why the launcher stopped the set where its run ended (its driver finished, or
    its duration passed: "" ; a try that ``--rate auto`` runs again at a lower rate:
    "retried"), None where it was told to stop: it makes the file named in
    ``PIEZO_STAGE_RUN_ENDED``, holding the why, before its SIGINTs. A node's SIGINT
    then is the run's end, and the node says nothing of being stopped."""
    path = os.environ.get(RUN_ENDED_ENV, "")
    if not path:
        return None
    try:
        with open(path, encoding="utf-8") as fh:
            return fh.read().strip()
    except OSError:
        return None


def watch(seconds: float | None = None) -> None:
    """From now on the node has ``STATE.watch_s`` to end (once armed, it stays), or
    from now ``seconds`` (a node that knows its stop takes longer: the driver's ramp)."""
    if seconds is not None:
        STATE.watch_s = float(seconds)
    elif STATE.watching:
        return
    STATE.watching = True
    try:
        faulthandler.dump_traceback_later(STATE.watch_s, exit=True, file=sys.stderr)
    except (ValueError, OSError, AttributeError):  # no usable stderr
        pass


def install() -> None:
    """Take SIGINT and SIGTERM, unblock them (a launcher-started node begins with them
    blocked), and ask for a SIGTERM when the launcher that started us dies."""
    for s in SIGNALS:
        signal.signal(s, _on_signal)
    parent = os.environ.pop(LAUNCHER_PID_ENV, "")
    if parent.isdigit() and sys.platform.startswith("linux"):
        try:
            import ctypes
            libc = ctypes.CDLL(None, use_errno=True)
            libc.prctl(_PR_SET_PDEATHSIG, int(signal.SIGTERM), 0, 0, 0)
        except (OSError, AttributeError):
            pass
        if os.getppid() != int(parent):  # it died before we asked: stop now
            os.kill(os.getpid(), signal.SIGTERM)
    signal.pthread_sigmask(signal.SIG_UNBLOCK, SIGNALS)


def set_phase(phase: str, name: str | None = None) -> None:
    """Move to ``building``, ``running`` or ``stopping``; a signal that came while
    building is raised as soon as the node gets there."""
    if name:
        STATE.name = name
    STATE.phase = phase
    if phase == "building" and STATE.signum is not None:
        raise Stopped(STATE.signum)


def requested() -> int | None:
    """The first stop signal's number, or None."""
    return STATE.signum


def count() -> int:
    """How many stop signals have come."""
    return STATE.count


# -- the middleware's part of a teardown, bounded --------------------------------------
MIDDLEWARE_TEARDOWN_S = 2.0  # it takes 10-100 ms when nothing hangs
_SIGEV_THREAD, _CLOCK_MONOTONIC = 2, 1
_KEEP: list = []  # what the native timers point at lives as long as they do


def _native_timer(libc: Any, function: Any, value: int, seconds: float) -> Any:
    """A one-shot timer whose expiry calls ``function(value)`` on a thread of its own
    (POSIX timer_create with SIGEV_THREAD): it runs while this thread holds the GIL."""
    import ctypes

    class SigEvent(ctypes.Structure):  # struct sigevent (Linux: 64 bytes)
        _fields_ = [("value", ctypes.c_void_p), ("signo", ctypes.c_int),
                    ("notify", ctypes.c_int), ("function", ctypes.c_void_p),
                    ("attributes", ctypes.c_void_p), ("pad", ctypes.c_byte * 32)]

    class TimeSpec(ctypes.Structure):
        _fields_ = [("sec", ctypes.c_long), ("nsec", ctypes.c_long)]

    ev = SigEvent(value=value, notify=_SIGEV_THREAD,
                  function=ctypes.cast(function, ctypes.c_void_p).value)
    timer = ctypes.c_void_p()
    if libc.timer_create(_CLOCK_MONOTONIC, ctypes.byref(ev), ctypes.byref(timer)) != 0:
        raise OSError(ctypes.get_errno(), "timer_create")
    when = (TimeSpec(0, 0), TimeSpec(int(seconds), int(seconds % 1 * 1e9)))
    if libc.timer_settime(timer, 0, ctypes.byref((TimeSpec * 2)(*when)), None) != 0:
        libc.timer_delete(timer)
        raise OSError(ctypes.get_errno(), "timer_settime")
    _KEEP.append(ev)
    return timer


def _exit_timers(text: str, code: int, seconds: float) -> tuple[list, Any]:
    """Native timers that, ``seconds`` from now, write ``text`` (one line, on stderr,
    after the program's name) and exit with ``code``; ([], None) without POSIX timers
    (not Linux)."""
    timers: list = []
    if not sys.platform.startswith("linux"):
        return timers, None
    libc = None
    try:
        import ctypes
        libc = ctypes.CDLL(None, use_errno=True)
        line = ctypes.create_string_buffer(text.replace("%", "%%").encode())
        _KEEP.append(line)
        timers.append(_native_timer(libc, libc.warnx, ctypes.addressof(line),
                                    seconds + 0.05))
        timers.append(_native_timer(libc, libc._exit, int(code) & 0xFF, seconds + 0.1))
    except (OSError, AttributeError, ValueError):
        for t in timers:
            if libc is not None:
                libc.timer_delete(t)
        return [], None
    return timers, libc


@contextmanager
def bounded_teardown(code: int, seconds: float = MIDDLEWARE_TEARDOWN_S) -> Iterator[None]:
    """The middleware's part of a teardown (see the module docstring): if the block has
    not ended within ``seconds``, every thread's stack and one line go to stderr and the
    process exits with ``code``. Without POSIX timers (not Linux) only the stop watch
    (:func:`watch`) applies."""
    timers, libc = _exit_timers(
        f"{_name()}: the middleware's teardown did not end within {seconds:g} s; exited "
        f"without it, with the code of its stop ({code})", code, seconds)
    if timers:
        faulthandler.dump_traceback_later(seconds, exit=False, file=sys.stderr)
    try:
        yield
    finally:
        for t in timers:
            libc.timer_delete(t)
        if timers:  # the stop watch again, for what is left (the interpreter's exit)
            faulthandler.cancel_dump_traceback_later()
            STATE.watching = False
            watch()


@contextmanager
def exit_if_hung(code: int, text: str,
                 seconds: float = MIDDLEWARE_TEARDOWN_S) -> Iterator[None]:
    """A command's last teardown, its outcome said already: if the block has not ended
    within ``seconds``, ``text`` goes to stderr as one line and the process exits with
    ``code``, the command's own (no stacks, no stop watch after it)."""
    timers, libc = _exit_timers(text, code, seconds)
    try:
        yield
    finally:
        for t in timers:
            libc.timer_delete(t)


@contextmanager
def deferred(on: bool = True) -> Iterator[None]:
    """A node's construction that does not block and must not be cut short (the
    recorder's: its bag is open and its readers take messages before the constructor
    returns): a stop signal inside it is only noted, as while running, so the node is
    built whole and its spin's first pass ends it (what had arrived handed over, the
    node's ``close`` finishing the bag). ``on`` False: nothing changes."""
    was = STATE.deferring
    STATE.deferring = was or bool(on)
    try:
        yield
    finally:
        STATE.deferring = was


@contextmanager
def interruptible() -> Iterator[None]:
    """A long computation in a callback (an identification): a stop signal raises
    :class:`Stopped` inside it instead of waiting for it to end."""
    if STATE.signum is not None:
        raise Stopped(STATE.signum)
    STATE.raise_depth += 1
    try:
        yield
    finally:
        STATE.raise_depth -= 1


install()
