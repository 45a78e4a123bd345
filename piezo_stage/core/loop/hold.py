"""The live watch's wait in a lockstep set (docs/watch.md, step 7): the gap node names
the last sample the set takes before it waits while a window is diagnosed; the command
for the tick after it is kept until the watch says go on. Pure bookkeeping: the driver
node feeds it the hold messages and the commands, and takes back the one that waited.
"""

from __future__ import annotations

from typing import Any


class LockstepHold:
    """``hold(last_ns)`` (None: go on) and ``take(ns, v)`` for each command, stamped for
    the tick it applies at: False where it must wait (kept); ``go_on()`` returns the
    command that waited, if any, and ends the hold."""

    def __init__(self) -> None:
        self.last_ns: int | None = None
        self.waiting: tuple[int, Any] | None = None

    @property
    def held(self) -> bool:
        """A hold is announced or under way."""
        return self.last_ns is not None

    def hold(self, last_ns: int | None) -> tuple[int, Any] | None:
        """The watch's message: the last sample's stamp before the wait, or None: go on
        (-> the command that waited, to be taken now)."""
        if last_ns is None:
            return self.go_on()
        self.last_ns = int(last_ns)
        return None

    def take(self, ns: int, v: Any) -> bool:
        """Whether the command for tick ``ns`` is taken now (else it waits, kept: the
        one for the tick after the window's last sample)."""
        if self.last_ns is None or ns <= self.last_ns:
            return True
        self.waiting = (ns, v)
        return False

    def go_on(self) -> tuple[int, Any] | None:
        """The hold ended; -> the command that waited (None: none did)."""
        self.last_ns = None
        out, self.waiting = self.waiting, None
        return out
