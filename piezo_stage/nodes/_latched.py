"""Taking latched messages without offending volatile publishers.

A topic like ``trajectory`` has publishers of both kinds: latched ones (reliable,
transient local, depth 1: our trajectory node, the recommended outside publisher) and
default-QoS ones (volatile). A subscriber that asks for transient local gets the
latched message a publisher sent before the two matched (a restarted feedforward gets
the running trajectory), but it is incompatible with every volatile publisher: both
sides then log "incompatible QoS" warnings, and a lab user reads "No messages will be
sent" as a failure. A volatile subscriber matches everyone but never gets history.

So the node keeps one volatile subscription for everything live, and ``LatchedFetch``
opens a transient-local one only for a moment (``open_s``), when the graph shows a
latched publisher it has not fetched from yet and no volatile publisher is on the
topic; it closes the moment each of those publishers' message has come (or after
``open_s``). Our own trajectory node is left out: it sends its trajectory again when
the feedforward holds with none (trajectory_node.py), so the set's start opens no
fetch, and a default-QoS publisher already on the graph sees no warning then. What is
left: with an outside latched publisher, a default-QoS publisher that joins in that
moment may see the fetch and log one incompatible-QoS warning; it is still matched by
the volatile subscription and its messages are taken.
The callback may then see one publication twice (live and fetched): it gets the
message info with the bytes, and callers take a publication once by its identity
(core/loop/stamps.py ``Publications``), never by its content: the same bytes published
again are another request.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Iterable, Sequence
from typing import TYPE_CHECKING, Any

from rclpy.qos import DurabilityPolicy

from piezo_stage.nodes._common import QOS_LATCHED, UNKNOWN_NODE, MessageInfo, steady_timer

if TYPE_CHECKING:
    from rclpy.node import Node
    from rclpy.subscription import Subscription

# our nodes (in the same namespace) whose latched publishers send their message again
# to a consumer that lacks it: no fetch is needed from them
RESENDING = ("trajectory",)


def fetchable(infos: Sequence[Any], ns: str, resending: Iterable[str] = RESENDING
              ) -> tuple[set, bool]:
    """(the endpoint gids of the latched publishers in ``infos`` (a topic's publishers,
    as the graph gives them) a fetch is for, whether a volatile publisher is among
    them). Left out: our own nodes in namespace ``ns`` that resend (``resending``), and
    a latched publisher whose node the graph cannot name yet, which may be one of
    those: decided at a later poll, once named (a fetch opened for our own trajectory
    node would meet a lab's volatile publisher discovered a moment later, and both
    would log incompatible QoS, as a fresh clone's CI once saw)."""
    durable = [i for i in infos if i.qos_profile.durability == DurabilityPolicy.TRANSIENT_LOCAL]
    latched = {bytes(i.endpoint_gid) for i in durable if i.node_name != UNKNOWN_NODE
               and not (i.node_name in resending and i.node_namespace == ns)}
    return latched, len(durable) < len(infos)


class LatchedFetch:
    """See the module docstring. ``callback(data, info)`` gets the raw CDR bytes and
    rclpy's message info (the publication's source timestamp and sequence number)."""

    def __init__(self, node: Node, msg_type: type, topic: str,
                 callback: Callable[[bytes, MessageInfo], None], poll_s: float = 0.25,
                 open_s: float = 1.0, resending: Iterable[str] = RESENDING) -> None:
        self.node, self.msg_type, self.topic, self.callback = node, msg_type, topic, callback
        self.resending = frozenset(resending)
        self.open_s = open_s
        self.fetched: set[bytes] = set()   # gids of the latched publishers fetched from
        self.sub: Subscription | None = None
        self.opened_at = 0.0
        self.fetches, self.expected, self.got = 0, 0, 0
        steady_timer(node, poll_s, self.poll)

    def _take(self, data: bytes, info: MessageInfo) -> None:
        self.got += 1
        self.callback(data, info)
        if self.got >= self.expected:  # the history it opened for: close at once
            self._close()

    def _close(self) -> None:
        if self.sub is not None:
            self.node.destroy_subscription(self.sub)
            self.sub = None

    def poll(self) -> None:
        """Open a fetch for new latched publishers; close it when its time is up or a
        volatile publisher appears."""
        infos = self.node.get_publishers_info_by_topic(self.topic)
        latched, volatile = fetchable(infos, self.node.get_namespace(), self.resending)
        if volatile or time.monotonic() - self.opened_at > self.open_s:
            self._close()
        new = latched - self.fetched
        if new and not volatile and self.sub is None:
            self.fetched |= new
            self.expected, self.got = len(new), 0
            # (rclpy's hints name only the one-argument callback; it takes both)
            self.sub = self.node.create_subscription(
                self.msg_type, self.topic, self._take, QOS_LATCHED, raw=True)  # type: ignore[arg-type]
            self.opened_at = time.monotonic()
            self.fetches += 1
