"""One node set per namespace: before a launch starts any node, it looks on its domain
for a set already running in its namespace. Two sets on one namespace would share
topics: the running set would take the newcomer's trajectory and its bag would hold
both sets' commands.

The look is a short-lived outside node: the graph's node names in the namespace (what
`ros2 node list` shows), and, to say whose set it is, the driver's latched ``state``,
whose values name the host and the launcher's pid."""

from __future__ import annotations

import time

STATE_WAIT_S = 10.0  # for a running set's driver to say whose it is
BUSY_WAIT_S = 6.0    # for its node names, when the domain shows other nodes


def running_set(namespace: str, domain_id: int, wait_s: float = 2.0) -> str | None:
    """None when nothing runs in ``namespace`` on ``domain_id``; else who runs there
    ("host, pid N", or the node names when no driver announced itself). Up to
    ``wait_s`` for the graph to show the namespace's nodes (``BUSY_WAIT_S`` when it
    shows other nodes, whose discovery is going on): on a loaded host their names took
    longer than 0.5 s to arrive, and after ten outside nodes joined and left, over
    2 s; each time the second launch went ahead (fresh clones' suites, 2026-11-25). A
    clean start pays the whole wait once (on a lab's busy domain up to 6 s)."""
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
    who: dict[str, str] = {}

    def on_state(m: DiagnosticArray) -> None:
        who.update({kv.key: kv.value for kv in m.status[0].values} if m.status else {})
    node.create_subscription(DiagnosticArray, f"{ns}/state", on_state, QOS_EVENTS)
    try:
        t0 = time.monotonic()
        names: list = []
        while not names:
            ex.spin_once(timeout_sec=0.05)
            seen = [(n, s) for n, s in node.get_node_names_and_namespaces()
                    if (n, s) != ("launch_check", "/")]
            names = sorted(n for n, s in seen if s == ns)
            # a graph with other nodes in it is being discovered: give ours longer
            # (right after ten nodes joined and left, the set's names took over 2 s)
            if time.monotonic() - t0 >= (BUSY_WAIT_S if seen else wait_s):
                break
        if not names:
            return None
        # its driver's latched state, if it has one: on a loaded 2-core host, with ten
        # other nodes just gone, it took longer than 3 s to arrive (a fresh clone's
        # suite, 2026-11-25), and the refusal named only the nodes seen by then
        end = time.monotonic() + STATE_WAIT_S
        while time.monotonic() < end and "host" not in who:
            ex.spin_once(timeout_sec=0.05)
        if "host" in who:
            return f"{who['host']}, pid {who.get('pid', '?')}"
        names = sorted(n for n, s in node.get_node_names_and_namespaces() if s == ns)
        return "nodes " + ", ".join(names)
    finally:
        node.destroy_node()
        rclpy.try_shutdown(context=ctx)
