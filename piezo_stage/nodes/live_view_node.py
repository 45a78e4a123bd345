"""live_view: the running set's topics served to Foxglove over its WebSocket protocol.

Every topic the recorder would take (the contract, plus whatever discovery finds) is
offered as a Foxglove channel with its ros2msg schema and CDR encoding, so Foxglove
(or any client of the foxglove.websocket.v1 protocol) decodes sensor_msgs/JointState
and the rest as it does from a bag: no ROS install is needed on the viewing side, and
the bytes go out as received (no deserialize/serialize round trip). Data topics are
taken best-effort, so a slow viewer never holds up the loop's publishers; a topic
nobody subscribes to costs only the take, and ``max_rate_hz`` thins what is sent per
topic per wall-clock second (a 1 kHz loop is more than a plot needs). Messages carry
their header stamp as log time (the set's one clock: simulated time in lockstep, wall
clock in real time).
"""

# first, before the heavy imports: stop signals work from here on (see process/signals.py)
import piezo_stage.process.signals  # noqa: F401, I001

# isort: split
import time
from typing import Any

from foxglove import Channel, Schema, start_server
from foxglove.websocket import ServerListener
from rclpy.node import Node

from piezo_stage.io.bag import msgdef
from piezo_stage.nodes._common import MessageInfo, Status
from piezo_stage.nodes._executor import LeanNode, run_node
from piezo_stage.nodes._loop import Diagnostics
from piezo_stage.nodes._params import declare_schema
from piezo_stage.nodes._tap import TopicTap
from piezo_stage.nodes.declared import LIVE_VIEW


class _Subscriptions(ServerListener):
    """Which channels clients subscribe to (for /diagnostics)."""

    def __init__(self) -> None:
        self.active: dict[tuple[int, int], str] = {}  # (client, channel) -> topic

    def on_subscribe(self, client: Any, channel: Any) -> None:
        self.active[(client.id, channel.id)] = channel.topic

    def on_unsubscribe(self, client: Any, channel: Any) -> None:
        self.active.pop((client.id, channel.id), None)


class LiveView(LeanNode, Node):
    def __init__(self) -> None:
        super().__init__("live_view")
        self.min_gap_ns = 0
        p = declare_schema(self, LIVE_VIEW, {
            "max_rate_hz": self.set_rate,
            "batch_period_s": lambda v: setattr(self, "lean_batch_s", v)})
        host, port = p["host"], p["port"]
        self.set_rate(p["max_rate_hz"])
        self.lean_batch_s = p["batch_period_s"]
        self.channels: dict[str, Any] = {}  # topic -> foxglove Channel
        self.last_ns: dict[str, int] = {}  # topic -> when last sent
        self.sent = 0
        # the contract's channels exist before the server listens: a client's first
        # subscription then never races a channel's registration (the SDK advertises a
        # channel made while a client is connected a moment before it accepts it)
        self.tap = TopicTap(self, self.add_topic, self.forward, best_effort=True)
        self.listener = _Subscriptions()
        self.server = start_server(name=f"piezo_stage {self.get_namespace()}", host=host,
                                   port=port, server_listener=self.listener)
        self.url = f"ws://{host}:{self.server.port}"
        self.get_logger().info(f"live view on {self.url} (Foxglove: Open connection, "
                               "Foxglove WebSocket)")
        Diagnostics(self, self.status, "live view")

    def set_rate(self, hz: float) -> None:
        self.min_gap_ns = int(1e9 / hz) if hz > 0 else 0

    def add_topic(self, topic: str, msgtype: str, kind: str) -> None:
        self.channels[topic] = Channel(topic, message_encoding="cdr", schema=Schema(
            name=msgtype, encoding="ros2msg", data=msgdef(msgtype).encode()))

    def forward(self, topic: str, data: bytes, stamp_ns: int | None, info: MessageInfo) -> None:
        ch = self.channels[topic]
        if not ch.has_sinks():
            return  # nobody watches this topic
        # thinned on the wall clock (the viewer's), whatever the set's clock runs at: by
        # arrival time, since the messages of one batch are taken together
        now = info.get("received_timestamp") or time.time_ns()
        if self.min_gap_ns and now - self.last_ns.get(topic, -(2 ** 62)) < self.min_gap_ns:
            return
        self.last_ns[topic] = now
        t = stamp_ns if stamp_ns is not None else self.get_clock().now().nanoseconds
        ch.log(bytes(data), log_time=t)
        self.sent += 1

    def status(self) -> Status:
        watched = sorted(set(self.listener.active.values()))
        return 0, (f"serving {len(self.channels)} topics on {self.url}; "
                   f"{len(watched)} watched"), {
            "url": self.url, "messages_sent": self.sent, "topics": len(self.channels),
            "watched": ", ".join(watched)}

    def close(self) -> None:
        """The WebSocket server stops before the node goes (run_node calls this, then
        destroys the node)."""
        self.server.stop()


def main(args: list[str] | None = None) -> int:
    """Run the live view (the Jazzy form)."""
    return run_node(LiveView, args)


if __name__ == "__main__":
    from piezo_stage.process.stopping import exit_now
    exit_now(main())  # flushed, at-exit work done, no finalization (stopping.py)
