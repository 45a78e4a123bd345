"""Worker processes that leave stops to their parent: a terminal's Ctrl-C reaches the
whole process group, and a worker that raised it too printed a traceback. The parent
forks with the stop signals blocked (``forking``); each worker, first thing, ignores
SIGINT and takes SIGTERM and SIGHUP by their default action (quiet), then unblocks them
(``quiet_worker``), so a stop that came in between is never raised in it. The parent
ends its workers when it stops."""

from __future__ import annotations

import contextlib
import signal
from collections.abc import Iterator

STOPS = (signal.SIGINT, signal.SIGTERM, signal.SIGHUP)


@contextlib.contextmanager
def forking() -> Iterator[None]:
    """The stop signals blocked in this thread while its body forks workers (they start
    with them blocked); a stop that came meanwhile is raised here after it."""
    held = signal.pthread_sigmask(signal.SIG_BLOCK, STOPS)
    try:
        yield
    finally:
        signal.pthread_sigmask(signal.SIG_SETMASK, held)


def quiet_worker() -> None:
    """In a worker, first: SIGINT ignored, SIGTERM and SIGHUP by default (quiet), then
    the stops unblocked (pending ones now take these dispositions)."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    for s in (signal.SIGTERM, signal.SIGHUP):
        signal.signal(s, signal.SIG_DFL)
    signal.pthread_sigmask(signal.SIG_UNBLOCK, STOPS)
