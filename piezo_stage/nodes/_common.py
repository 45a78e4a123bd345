"""What every node shares: the QoS profiles and housekeeping timers on the steady clock.
The executor and the pieces of main() are in _executor.py, parameters in _params.py,
the control loop's shared pieces in _loop.py."""

from __future__ import annotations

from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

# Loop and record topics: reliable with a deep queue, so a briefly slow subscriber (the
# recorder) catches up instead of losing samples.
QOS_DATA = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=5000,
                      reliability=ReliabilityPolicy.RELIABLE,
                      durability=DurabilityPolicy.VOLATILE)


def data_out_qos() -> QoSProfile:
    """QOS_DATA for a loop node's publisher of a per-sample topic (joint_states,
    true_position, reference, command, gap/residual): with the writer history that
    ``PIEZO_STAGE_WRITER_DEPTH`` names, where it is set (`piezo-stage launch` sets 250 for
    a real-time set), else QOS_DATA itself.

    A reader's queue is its own (QOS_DATA's 5000: the recorder catching up); a writer's
    history is only what it can send again to a reader whose acknowledgement is late.
    Fast DDS does work that grows with that history, under the lock a publish takes,
    each time a reader of the topic matches or leaves: at 5000, a node joining the graph
    held the driver's and the controller's publishes 10-20 ms, and a 500 Hz set faulted
    on stale commands 1-5 times in 20 joins; at 250, none in 20 (2026-12-01, a 2-core VM,
    docs/realtime.md). Lockstep keeps 5000: its loop runs unpaced over shared memory, and
    a reader's acknowledgements there fall more than 250 samples behind.
    Raises ConfigError for a value that is no whole number of samples in [1, 5000]."""
    import os

    from piezo_stage.core.errors import ConfigError
    from piezo_stage.nodes import WRITER_DEPTH_ENV
    raw = os.environ.get(WRITER_DEPTH_ENV, "").strip()
    if not raw:
        return QOS_DATA
    try:
        depth = int(raw)
    except ValueError:
        depth = 0
    if not 1 <= depth <= QOS_DATA.depth:
        raise ConfigError(f"{WRITER_DEPTH_ENV}={raw[:40]!r}: a whole number of samples in "
                          f"[1, {QOS_DATA.depth}]")
    return QoSProfile(history=QOS_DATA.history, depth=depth,
                      reliability=QOS_DATA.reliability, durability=QOS_DATA.durability)


# Model and whole trajectories: the last one is kept for late joiners.
QOS_LATCHED = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=1,
                         reliability=ReliabilityPolicy.RELIABLE,
                         durability=DurabilityPolicy.TRANSIENT_LOCAL)
# State changes (the driver's arming state, the feedforward's phase): latched, and
# every change delivered in order, so a reader that takes them in batches misses none.
QOS_EVENTS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=20,
                        reliability=ReliabilityPolicy.RELIABLE,
                        durability=DurabilityPolicy.TRANSIENT_LOCAL)
QOS_DIAG = QoSProfile(depth=50, reliability=ReliabilityPolicy.RELIABLE)


def steady_timer(node, period_s, callback):
    """A housekeeping timer (polls, flushes, links, diagnostics cadence) on the steady
    clock: it runs while simulated time stands still (before the first sample, after the
    last), where a ROS-time timer under use_sim_time would never fire."""
    from rclpy.clock import Clock, ClockType
    return node.create_timer(period_s, callback, clock=Clock(clock_type=ClockType.STEADY_TIME))
