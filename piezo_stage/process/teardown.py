"""A command's middleware participants, torn down after the command's outcome is said,
and bounded.

Fast DDS (2.14, Jazzy's) can deadlock while it destroys a participant that is
discovering another one's endpoints (launcher/running.py's ``Look`` has the mechanism),
and rclpy holds the GIL through it: no Python code runs again in that process. A
command that talks to a set (``move``, ``scan``, ``lifecycle``, ``replay``) asks for
:func:`at_end`; its client's teardown (:func:`leave`) then waits for the command's end,
after its last line, where ``piezo-stage``'s entry runs it (:func:`finish`) under a
native timer: if it hangs, one line says so and the process exits with the command's
own code within ``MIDDLEWARE_TEARDOWN_S``, instead of never, at a whole CPU, beside the
set it talked to. Elsewhere (a lab's own program using :class:`piezo_stage.client.Stage`)
a teardown runs where it is asked for, as it always did.
"""

from __future__ import annotations

import os
import sys
import threading
from collections.abc import Callable
from typing import NoReturn

from piezo_stage.process import signals, stopping

# set (to anything): the command's teardown hangs, as it does when Fast DDS deadlocks
# (the suite checks the bound)
HANG_ENV = "PIEZO_STAGE_TEARDOWN_HANGS"


class _State:
    at_end = False
    pending: list[Callable[[], None]] = []


STATE = _State()


def at_end() -> None:
    """This command's participants are torn down at its end (:func:`finish`)."""
    STATE.at_end = True


def leave(teardown: Callable[[], None]) -> None:
    """Run ``teardown`` (a participant's: destroy the node, shut its context down) now,
    or at the command's end where it asked for :func:`at_end`."""
    if STATE.at_end:
        STATE.pending.append(teardown)
    else:
        teardown()


def finish(code: int) -> None:
    """The command's end, its lines written: the teardowns left to it, last first,
    bounded (the module docstring)."""
    pending, STATE.pending = STATE.pending, []
    if not pending:
        return
    for stream in (sys.stdout, sys.stderr):  # what the command said, out before a kill
        try:
            stream.flush()
        except (OSError, ValueError):
            pass
    text = (f"piezo-stage: the middleware's teardown did not end within "
            f"{signals.MIDDLEWARE_TEARDOWN_S:g} s (Fast DDS); exited without it, with the "
            f"command's code ({code})")
    with signals.exit_if_hung(code, text):
        if os.environ.get(HANG_ENV):
            threading.Event().wait()
        for teardown in reversed(pending):
            try:
                teardown()
            except Exception:  # noqa: BLE001 - the outcome is said; the rest still ends
                pass


def end(code) -> NoReturn:
    """A ``piezo-stage`` command's end (its entries: ``python -m piezo_stage`` and
    ``python -m piezo_stage.cli``), its outcome said: a stop arriving now is ignored
    (the interpreter's exit would give the default handlers back and end a finished
    command by the signal, with no word), the teardowns left to it run, bounded, and
    the process exits with the command's own code."""
    stopping.hold()
    finish(code if isinstance(code, int) else 0 if code is None else 1)
    stopping.exit_now(code)
