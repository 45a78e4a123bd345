"""One node set per namespace: before a launch starts any node, it looks on its domain
for a set already running in its namespace. Two sets on one namespace would share
topics: the running set would take the newcomer's trajectory and its bag would hold
both sets' commands.

The look is a short-lived outside node: the graph's node names in the namespace (what
`ros2 node list` shows), and, to say whose set it is, the driver's latched ``state``,
whose values name the host and the launcher's pid."""

from __future__ import annotations

import time


def running_set(namespace: str, domain_id: int, wait_s: float = 2.0) -> str | None:
    """None when nothing runs in ``namespace`` on ``domain_id``; else who runs there
    ("host, pid N", or the node names when no driver announced itself). Up to
    ``wait_s`` for the graph to show the namespace's nodes: on a loaded host their
    names took longer than 0.5 s to arrive, and the second launch went ahead (a fresh
    clone's suite, 2026-11-25); a clean start pays the whole wait once."""
    import rclpy
    from diagnostic_msgs.msg import DiagnosticArray
    from rclpy.context import Context
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.signals import SignalHandlerOptions

    from piezo_stage.nodes._common import QOS_EVENTS
    ns = "/" + namespace.strip("/")
    ctx = Context()
    rclpy.init(context=ctx, domain_id=int(domain_id),
               signal_handler_options=SignalHandlerOptions.NO)
    node = rclpy.create_node("launch_check", context=ctx, start_parameter_services=False,
                             enable_rosout=False)
    ex = SingleThreadedExecutor(context=ctx)
    ex.add_node(node)
    who = {}
    node.create_subscription(DiagnosticArray, f"{ns}/state", lambda m: who.update(
        {kv.key: kv.value for kv in m.status[0].values} if m.status else {}), QOS_EVENTS)
    try:
        end = time.monotonic() + wait_s
        names = []
        while time.monotonic() < end and not names:
            ex.spin_once(timeout_sec=0.05)
            names = sorted(n for n, s in node.get_node_names_and_namespaces() if s == ns)
        if not names:
            return None
        end = time.monotonic() + 3.0  # its driver's latched state, if it has one
        while time.monotonic() < end and "host" not in who:
            ex.spin_once(timeout_sec=0.05)
        if "host" in who:
            return f"{who['host']}, pid {who.get('pid', '?')}"
        return "nodes " + ", ".join(names)
    finally:
        node.destroy_node()
        rclpy.try_shutdown(context=ctx)
