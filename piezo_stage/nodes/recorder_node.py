"""recorder: every topic, as raw serialized messages, into a rosbag2-layout MCAP bag.

Subscribes to the topic contract at start (so nothing of a lockstep run is missed)
and to any other topic it discovers. Messages are written as the CDR bytes received
(no deserialize/serialize round trip); stamped messages are logged at their header
stamp, others at receive time. Chunks are flushed every ``flush_period_s`` so a
SIGKILL loses at most that much; SIGINT finalises a complete bag. The run's config and
model files go in as MCAP metadata.
"""

# first, before the heavy imports: stop signals work from here on (see process/signals.py)
import piezo_stage.process.signals  # noqa: F401, I001

# isort: split
import os
import sys

from rclpy.node import Node
from rclpy.qos import DurabilityPolicy

from piezo_stage.core.loop.stamps import MAX_STAMP_NS
from piezo_stage.io.bag import BagWriter, new_bag_dir
from piezo_stage.nodes._common import MessageInfo, steady_timer
from piezo_stage.nodes._executor import LeanNode, run_node
from piezo_stage.nodes._loop import Diagnostics, set_realtime_priority
from piezo_stage.nodes._params import declare_schema
from piezo_stage.nodes._tap import TopicTap
from piezo_stage.nodes.declared import RECORDER


class Recorder(LeanNode, Node):
    # a stop while it is built is noted, not raised (run_node): its readers acknowledge
    # messages before the constructor returns, and a stop raised there left a bag
    # without its summary and those messages untaken (seen once, on a loaded host)
    DEFERS_STOPS = True

    def __init__(self) -> None:
        super().__init__("recorder")
        p = declare_schema(self, RECORDER, {
            "batch_period_s": lambda v: setattr(self, "lean_batch_s", v)})
        out = p["output"] or new_bag_dir("bags")
        meta = {}
        for key in ("config_file", "model_file"):
            path = p[key]
            if path and os.path.isfile(path):
                meta["piezo_stage_" + key.split("_")[0]] = {"path": path,
                                                            "yaml": open(path).read()}
        # when the run started, on the wall clock (a lockstep bag's stamps start at 0):
        # what `refit` dates the run by
        from datetime import datetime, timezone
        meta["piezo_stage_run"] = {"started_utc": datetime.now(timezone.utc).isoformat()}
        self.bag = BagWriter(out, metadata=meta)
        # off the loop's critical path: take what arrived every few ms, not per message
        self.lean_batch_s = p["batch_period_s"]
        self.log_received = p["log_time"] == "receive"
        if self.log_received:
            set_realtime_priority(p["thread_priority"], self.get_logger(), main_thread=False)
        self.get_logger().info(f"recording to {out}")
        self.bad_stamps = 0
        # the device is the driver's: learnt from its state as the tap records it
        self.state_topic = f"{self.get_namespace().rstrip('/')}/state"
        self.diag: Diagnostics | None = None
        self.tap = TopicTap(self, self.add_topic, self.write)
        steady_timer(self, p["flush_period_s"], self.bag.flush)
        self.diag = Diagnostics(self, lambda: (
            0, f"recording to {out}: {sum(self.bag.counts.values())} messages on "
               f"{len(self.bag.counts)} topics",
            {"bag": out, "batch_period_s": self.lean_batch_s, "bad_stamps": self.bad_stamps,
             **self.bag.counts}), "recording")

    def add_topic(self, topic: str, msgtype: str, kind: str) -> None:
        self.bag.add_topic(topic, msgtype, self.offered(topic, kind))

    def offered(self, topic: str, kind: str) -> str:
        """The QoS the topic's publishers offer (as ``ros2 bag record`` stores it): asked
        of the graph when a publisher is there (topics found by discovery), else what
        our nodes offer for that kind."""
        from piezo_stage.io.bag import QOS_KINDS
        if kind not in QOS_KINDS:
            infos = self.get_publishers_info_by_topic(topic)
            if infos:
                q = infos[0].qos_profile
                latched = q.durability == DurabilityPolicy.TRANSIENT_LOCAL
                return "latched" if latched and q.depth <= 1 else \
                    "events" if latched else "data"
            return "data"
        return kind

    def write(self, topic: str, data: bytes, stamp_ns: int | None, info: MessageInfo) -> None:
        if stamp_ns is not None and not 0 <= stamp_ns <= MAX_STAMP_NS:
            # a negative stamp (sec = -1) cannot be an MCAP time: the message is kept,
            # logged at its arrival, and counted
            self.bad_stamps += 1
            stamp_ns = None
        if self.log_received:
            received = info.get("received_timestamp") or self.get_clock().now().nanoseconds
        if stamp_ns is not None:
            t = stamp_ns
        else:  # lockstep: the set's clock (simulated time under use_sim_time)
            t = received if self.log_received else self.get_clock().now().nanoseconds
        # log time: when it arrived (real time), or its stamp (lockstep's simulated
        # time, so reruns are identical); publish time: its stamp
        self.bag.write(topic, data, received if self.log_received else t, t)
        if topic == self.state_topic and self.diag is not None:
            self.diag.learn_from_state(data)

    def stop_summary(self) -> str:
        """What a stop left (run_node prints it)."""
        return f"bag {self.bag.path} finished, {sum(self.bag.counts.values())} messages"

    def close(self) -> None:
        """The bag is finished (its summary and index written) before the node goes
        (run_node calls this, then destroys the node). Its own last report goes into
        it first: a lockstep run shorter than the 1 s cadence had only the recorder's
        first report in its bag, made before the driver's state had named the device
        ("stage /stage")."""
        self._record_final_report()
        self.bag.finish()
        # the ROS context may already be shut down here: plain stderr, not the logger
        sys.stderr.write(f"[recorder] bag complete: {dict(self.bag.counts)}\n")


    def _record_final_report(self) -> None:
        topic = "/diagnostics"
        if self.diag is None or topic not in self.bag.counts:
            return
        try:
            from rclpy.serialization import serialize_message
            ns, msg = self.diag.report()
            self.write(topic, serialize_message(msg), ns, {})
        except Exception as e:  # noqa: BLE001 - the bag still finishes; said, not raised
            sys.stderr.write(f"[recorder] its last report was not recorded: {e}\n")


def main(args: list[str] | None = None) -> int:
    """Run the recorder (the Jazzy form)."""
    return run_node(Recorder, args)


if __name__ == "__main__":
    from piezo_stage.process.stopping import exit_now
    exit_now(main())  # flushed, at-exit work done, no finalization (stopping.py)
