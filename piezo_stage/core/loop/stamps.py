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

``SampleGuard`` is the one guard every loop core puts before its per-sample work: a
malformed message counted, the stamp taken by a ``StampGuard``, and in real time a
sample whose answer could only reach the driver after its tick dropped; each counted
in the core's own counters.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

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

    def __init__(self, window_ns: int = 10 * 10 ** 9, rebase_after: int = 50) -> None:
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




class SampleGuard:
    """The guard before a loop core's per-sample work (the feedforward's, the
    controller's): what it drops, counted in ``stats`` (the core's counters:
    ``bad_messages``, ``stray_stamps``, ``late_dropped``)."""

    def __init__(self, stats: dict[str, int]) -> None:
        self.stats = stats
        self.stamps = StampGuard()  # a stray stamp from the graph never poisons the loop

    def malformed(self) -> None:
        """A message that did not decode: counted, nothing else changes."""
        self.stats["bad_messages"] += 1

    def admit(self, ns: int, now_ns: int | None = None) -> bool:
        """Whether to work on the sample stamped ``ns``: not a duplicate, an old or a
        stray stamp (``StampGuard``), and in real time (``now_ns``, the wall clock)
        not already past, so its answer could still reach the driver on time."""
        if not self.stamps.accept(ns):
            self.stats["stray_stamps"] = self.stamps.dropped
            return False
        return self.on_time(ns, now_ns)

    def on_time(self, target_ns: int, now_ns: int | None = None, late: bool = False) -> bool:
        """Whether an answer for ``target_ns`` can still reach the driver: not ``late``
        by the core's own judgement and, in real time, not past ``now_ns``; a late one
        is counted and dropped."""
        if late or (now_ns is not None and target_ns < now_ns):
            self.stats["late_dropped"] += 1
            return False
        return True
class Publications:
    """Which publications a node has taken. A request (a trajectory) is identified by its
    publication, not by its content: the same bytes published again are a new request
    and run again; one publication delivered twice (a volatile subscription and a
    latched fetch both hand it over) is taken once. The identity is what the
    middleware stamps on a publication (``publication_key``: its writer's source
    timestamp and sequence number); a delivery without one is always new.

    Parameters
    ----------
    remember : int
        How many of the newest publications are remembered (a latched fetch delivers
        only the one its publisher holds, soon after the live copy).
    """

    def __init__(self, remember: int = 64) -> None:
        self.remember = int(remember)
        self._order: list = []
        self._seen: set = set()
        self.repeated = 0  # deliveries of a publication taken already

    def first(self, key: tuple | None) -> bool:
        """True the first time publication ``key`` is seen (then remembered); False for
        a delivery of one taken already (counted in ``repeated``). None: no identity,
        always True."""
        if key is None:
            return True
        if key in self._seen:
            self.repeated += 1
            return False
        self._seen.add(key)
        self._order.append(key)
        if len(self._order) > self.remember:
            self._seen.discard(self._order.pop(0))
        return True

    def admit(self, key: tuple | None, request: tuple | None = None) -> bool:
        """Whether a delivery is a new request to run: a publication not taken already
        (``key``), of a request not taken already (``request``, ``request_key``: a
        resend of one is not new). Both are remembered; a delivery turned away is
        counted in ``repeated``."""
        if not self.first(key):
            return False
        if request is not None and request in self._seen:
            self.repeated += 1
            return False
        return self.first(request)


REQUEST_PREFIX = "request:"


def request_key(frame_id: str) -> tuple | None:
    """A request's identity, where its sender gave it one: a ``header.frame_id`` that
    begins with ``request:`` names one request however often it is sent (a sender
    that resends until it hears an answer: our trajectory node), so it is taken once;
    any other frame_id (or none) names nothing, and every publication of it runs."""
    if frame_id.startswith(REQUEST_PREFIX) and len(frame_id) > len(REQUEST_PREFIX):
        return ("request", frame_id)
    return None


def publication_key(info: Mapping[str, Any] | None) -> tuple | None:
    """A publication's identity from the message info rclpy hands a two-argument
    subscription callback: (source timestamp [ns], publication sequence number);
    None where the middleware gives no source timestamp."""
    if not info or not info.get("source_timestamp"):
        return None
    return int(info["source_timestamp"]), info.get("publication_sequence_number")
