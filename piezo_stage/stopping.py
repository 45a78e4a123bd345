"""How the ``piezo-stage`` command stops: SIGINT, SIGTERM and SIGHUP alike, from the
first moment. Imported before anything heavy (this package's ``__init__`` is light):
before the command runs nothing is open, so a stop says so and exits at once, with no
traceback from an import; while it runs the signal is raised as KeyboardInterrupt, so
``finally`` blocks run and a temporary output is removed (nothing half-written is
left). The nodes have their own, nodes/_signals.py."""

from __future__ import annotations

import os
import signal
import sys

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
    raise KeyboardInterrupt


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


def stopped_line() -> tuple[str, int]:
    """The one line a stopped command prints, and its exit code (128 + the signal)."""
    return (f"piezo-stage: stopped by {signal.Signals(STATE.signum).name}",
            128 + STATE.signum)
