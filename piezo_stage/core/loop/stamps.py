"""Sample stamps from the graph, checked against the stream they claim to belong to.

Every loop node keeps the newest stamp it has taken and drops what is not newer (a
duplicate changes nothing). One message stamped far from the stream (10^15 ns ahead,
or negative), sent by anyone on the graph, would then become "the newest" and every
real sample after it would be dropped as old: the feedforward stopped answering, the
driver faulted on stale commands and arming was refused for good.

``StampGuard`` takes a stamp only within ``window_ns`` after the last one it took. A
stream that really moved (a driver restarted, a clock re-based) is recognised by
``rebase_after`` stamps in a row that are consistent with each other (increasing, each
within the window of the one before) but not with the old stream: the guard then
follows it. A lone stray stamp never forms such a run, so it is counted and dropped,
never taken. Times are integers in ns.
"""

from __future__ import annotations

MAX_STAMP_NS = 2 ** 63 - 1


class StampGuard:
    """See the module docstring.

    Parameters
    ----------
    window_ns : int
        How far past the last taken stamp a new one may be [ns].
    rebase_after : int
        Consistent stamps in a row, away from the stream, that re-base it.
    """

    def __init__(self, window_ns: int = 10 * 10 ** 9, rebase_after: int = 50):
        self.window_ns = int(window_ns)
        self.rebase_after = int(rebase_after)
        self.last: int | None = None
        self.dropped = 0       # stamps not taken (strays, before a re-base)
        self.rebased = 0
        self._run: list[int] = []

    def accept(self, ns: int) -> bool:
        """True to take a message stamped ``ns`` (then it is the newest); False for a
        duplicate, an old stamp or a stray one (counted in ``dropped``)."""
        if not 0 <= ns <= MAX_STAMP_NS:
            self.dropped += 1
            return False
        if self.last is None or self.last < ns <= self.last + self.window_ns:
            self.last, self._run = ns, []
            return True
        if ns <= self.last and ns > self.last - self.window_ns:
            return False  # a duplicate or a late one of this stream: nothing new
        run = self._run
        if run and not run[-1] < ns <= run[-1] + self.window_ns:
            run.clear()
        run.append(ns)
        if len(run) >= self.rebase_after:
            self.last, self._run = ns, []
            self.rebased += 1
            return True
        self.dropped += 1
        return False
