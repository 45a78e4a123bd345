"""How the ``piezo-stage`` command stops: SIGINT, SIGTERM and SIGHUP alike, from the
first moment. Imported before anything heavy (this package's ``__init__`` is light):
before the command runs nothing is open, so a stop says so and exits at once, with no
traceback from an import; while it runs the signal is raised as KeyboardInterrupt, so
``finally`` blocks run and a temporary output is removed (nothing half-written is
left). The nodes have their own, process/signals.py."""

from __future__ import annotations

import os
import signal
import sys
import threading  # here, whole: a stop landing in its own first import found it half-made
from typing import NoReturn

SIGNALS = (signal.SIGINT, signal.SIGTERM, signal.SIGHUP)


class _State:
    signum = signal.SIGINT  # the signal that stopped the command
    running = False


STATE = _State()


def _on_signal(signum, frame):
    STATE.signum = signum
    if not STATE.running:
        sys.stderr.write(f"piezo-stage: stopped by {signal.Signals(signum).name} during "
                         "start-up\n")
        sys.stderr.flush()
        os._exit(128 + signum)
    if cannot_raise_here(frame):  # raised there it would be dropped or break an import
        again_soon(signum)        # lock: the same stop again in a moment, once back in
        return                    # the command's own code
    raise KeyboardInterrupt


def again_soon(signum: int) -> None:
    """Send ``signum`` to this process again in 5 ms (a stop that could not be raised
    where it landed). ``threading`` is this module's, imported whole before any
    handler was installed: imported here, a stop that landed in the command's own first
    import of it got the half-initialized module (no ``Timer`` yet) and a traceback."""
    t = threading.Timer(0.005, os.kill, (os.getpid(), signum))
    t.daemon = True
    t.start()


def in_ctypes_callback(frame) -> bool:
    """Whether ``frame`` runs inside a function C calls back through ctypes, where an
    exception is printed with its traceback and dropped: numba's compiler hands LLVM's
    object cache to Python so (llvmlite's ``_raw_object_cache_*``); a Ctrl-C there was
    printed as "Exception ignored on calling ctypes callback function" and lost."""
    while frame is not None:
        code = frame.f_code
        if code.co_name.startswith("_raw_object_cache") and "llvmlite" in code.co_filename:
            return True
        frame = frame.f_back
    return False


def in_finalizer(frame) -> bool:
    """Whether ``frame`` runs inside an object's finalizer (``__del__``), where an
    exception is printed as "Exception ignored in ... __del__" with its traceback and
    dropped: a Ctrl-C landing in llvmlite's ``ObjectRef.__del__`` while numba compiled
    was printed so, and the stop lost (`test_cli`'s Ctrl-C at a random moment)."""
    while frame is not None:
        if frame.f_code.co_name == "__del__":
            return True
        frame = frame.f_back
    return False


def cannot_raise_here(frame) -> bool:
    """Whether an exception raised at ``frame`` would be printed and dropped (a ctypes
    callback, a finalizer) or break an import's lock: a stop is sent again instead."""
    return in_ctypes_callback(frame) or in_import_machinery(frame) or in_finalizer(frame)


def in_import_machinery(frame) -> bool:
    """Whether ``frame`` is importlib's own code (its module locks, their weakref
    callbacks), not a module's top level being imported: a KeyboardInterrupt raised
    there was printed and dropped ("Exception ignored in _get_module_lock.cb") and the
    launcher ran on (`bench signals`: stops soon after the start)."""
    return frame is not None and frame.f_code.co_filename.startswith("<frozen importlib")


def forget_interrupt() -> None:
    """CPython marks a KeyboardInterrupt that leaves code run by ``exec`` of a string
    as unhandled for good (the mark is cleared only by the next such ``exec``), and
    the interpreter then ends by SIGINT at its exit even though the command caught the
    stop and said so: a stop during an import that builds a dataclass (numba's) exited
    -2 after "stopped by SIGTERM" (`bench signals`).
    An ``exec`` that completes clears the mark."""
    exec("None")


def install() -> None:
    """Take the three signals (from the command's entry, before its imports)."""
    for s in SIGNALS:
        signal.signal(s, _on_signal)


def running() -> None:
    """The command has started: a signal now unwinds it (KeyboardInterrupt)."""
    install()
    STATE.running = True


def hold() -> None:
    """The command has ended: the stop signals are ignored from here to the exit, in
    every thread (blocking them in this one was not enough: a signal then reached a
    BLAS or progress-bar thread while the interpreter's exit had given the handlers
    back to the default action, which killed a finished command; an ignored signal
    stays ignored through the exit)."""
    for s in SIGNALS:
        signal.signal(s, signal.SIG_IGN)
    forget_interrupt()


def stopped_line() -> tuple[str, int]:
    """The one line a stopped command prints, and its exit code (128 + the signal)."""
    return (f"piezo-stage: stopped by {signal.Signals(STATE.signum).name}",
            128 + STATE.signum)


def exit_now(code) -> NoReturn:
    """End the process with ``code`` (``sys.exit``'s: None 0, an int itself) once a
    command or a node is done: its output flushed and its at-exit work done (atexit
    handlers, the temporary directories they remove, worker processes ended), then
    ``os._exit``, which leaves out the interpreter's finalization: tearing down every
    module and numba's compiled kernels costs CPU per process, paid at every command's
    end and at every stop of a set, node after node. A thread still running that is
    no daemon gets the ordinary exit, which waits for it."""
    import atexit
    import threading
    code = 0 if code is None else code
    if not isinstance(code, int) or any(
            t.is_alive() and not t.daemon for t in threading.enumerate()
            if t is not threading.main_thread()):
        sys.exit(code)
    atexit._run_exitfuncs()
    for stream in (sys.stdout, sys.stderr):
        try:
            stream.flush()
        except (OSError, ValueError):  # a closed pipe: nothing more to say
            pass
    os._exit(code)
