"""One node set per namespace: before a launch starts any node, it looks on its domain
for a set already running in its namespace. Two sets on one namespace would share
topics: the running set would take the newcomer's trajectory and its bag would hold
both sets' commands.

The look is a short-lived outside node: the graph's node names in the namespace (what
`ros2 node list` shows), and, to say whose set it is, the driver's latched ``state``,
whose values name the host and the launcher's pid."""

from __future__ import annotations

import threading
import time
from contextlib import contextmanager

STATE_WAIT_S = 10.0  # for a running set's driver to say whose it is
BUSY_WAIT_S = 6.0    # for its node names, when the domain shows other nodes


def running_set(namespace: str, domain_id: int, wait_s: float = 2.0,
                cancel: threading.Event | None = None, report=None,
                looking: threading.Event | None = None) -> str | None:
    """None when nothing runs in ``namespace`` on ``domain_id``; else who runs there
    ("host, pid N", or the node names when no driver announced itself). Up to
    ``wait_s`` for the graph to show the namespace's nodes (``BUSY_WAIT_S`` when it
    shows other nodes, whose discovery is going on): on a loaded host their names took
    longer than 0.5 s to arrive, and after ten outside nodes joined and left, over
    2 s; a shorter wait let a second launch go ahead beside a running set. A
    clean start pays the whole wait once (on a lab's busy domain up to 6 s): ``Look``
    spends it beside the start-up. ``cancel`` set: it ends within 50 ms, with None.
    ``report``: called with the answer before the look's node is torn down (its
    participant leaves the graph properly, a little after the answer is out).
    ``looking``: set once the look's node is on the graph (its wait counts from then)."""
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

    def answer() -> str | None:
        if looking is not None:
            looking.set()
        t0 = time.monotonic()
        names: list = []
        limit = wait_s
        while not names:
            if cancel is not None and cancel.is_set():
                return None
            # (up to the wait's end, not past it: the answer is in within milliseconds)
            left = limit - (time.monotonic() - t0)
            ex.spin_once(timeout_sec=min(0.05, max(left, 0.001)))
            seen = [(n, s) for n, s in node.get_node_names_and_namespaces()
                    if (n, s) != ("launch_check", "/")]
            names = sorted(n for n, s in seen if s == ns)
            # a graph with other nodes in it is being discovered: give ours longer
            # (right after many nodes joined and left, the set's names came late)
            limit = BUSY_WAIT_S if seen else wait_s
            if time.monotonic() - t0 >= limit:
                break
        if not names:
            return None
        # its driver's latched state, if it has one: on a loaded host, with other nodes
        # just gone, it can take seconds to arrive, and a refusal sooner names only the
        # nodes seen by then
        end = time.monotonic() + STATE_WAIT_S
        while time.monotonic() < end and "host" not in who:
            if cancel is not None and cancel.is_set():
                return None
            ex.spin_once(timeout_sec=0.05)
        if "host" in who:
            return f"{who['host']}, pid {who.get('pid', '?')}"
        names = sorted(n for n, s in node.get_node_names_and_namespaces() if s == ns)
        return "nodes " + ", ".join(names)
    try:
        found = answer()
        if report is not None and not (cancel is not None and cancel.is_set()):
            report(found)
        return found
    finally:
        node.destroy_node()
        rclpy.try_shutdown(context=ctx)


# how long a command waits for its look's node to be on the graph before it goes on
# with its own imports [s]: a bound, the node takes about 0.2 s
LOOKING_WAIT_S = 1.0


class Look:
    """``running_set`` in a thread of its own, begun as soon as the namespace and the
    domain are known: its wait (2 s on a clean start) then runs while the command
    imports and reads its config, and while the nodes import, instead of after them
    (launch to armed, `bench startup`). The command waits (``LOOKING_WAIT_S`` at most)
    for the look's node to be on the graph first: the node's imports and creation would
    otherwise share the interpreter with the command's, and the wait, which counts from
    the node, would end later by as long as those took. ``result()`` waits
    for the answer (raising what the look raised), which is in before the look's node
    is torn down; ``cancel()`` ends a look whose answer is no longer wanted (a config
    refused, a stop while starting): within 50 ms, with nothing left behind."""

    def __init__(self, namespace: str, domain_id: int, wait_s: float = 2.0) -> None:
        self.namespace, self.domain_id, self.wait_s = namespace, int(domain_id), wait_s
        self._cancel = threading.Event()
        self._answered = threading.Event()
        self._answer: tuple[str | None, BaseException | None] = (None, None)
        self._looking = threading.Event()
        self._thread = threading.Thread(target=self._look, name="running-set look",
                                        daemon=True)
        self._thread.start()
        # (or its answer, an error included)
        end = time.monotonic() + LOOKING_WAIT_S
        while not (self._looking.is_set() or self._answered.is_set()) and \
                time.monotonic() < end:
            self._looking.wait(0.01)

    def _report(self, who: str | None) -> None:
        self._answer = (who, None)
        self._answered.set()

    def _look(self) -> None:
        try:
            running_set(self.namespace, self.domain_id, self.wait_s, cancel=self._cancel,
                        report=self._report, looking=self._looking)
        except BaseException as e:  # noqa: BLE001 - raised in result(), in the caller
            if not self._answered.is_set():
                self._answer = (None, e)
        finally:
            self._answered.set()

    def done(self) -> bool:
        return self._answered.is_set()

    def wait(self, timeout: float) -> bool:
        """Up to ``timeout`` seconds for the answer: whether it is in."""
        return self._answered.wait(timeout)

    def result(self) -> str | None:
        """None: nothing runs in the namespace; else who runs there."""
        self._answered.wait()
        who, error = self._answer
        if error is not None:
            raise error
        return who

    def cancel(self) -> None:
        self._cancel.set()
        self._thread.join()


@contextmanager
def begin_look(namespace: str, env=None):
    """A ``Look`` for ``namespace`` on the domain ``env`` (default os.environ) names, for
    a command to hand to its ``Launch`` (None where the domain is no number); cancelled
    on leaving (a no-op once answered)."""
    import os
    env = os.environ if env is None else env
    try:
        domain = int(env.get("ROS_DOMAIN_ID") or 0)
    except ValueError:  # not a domain: the launch says so where it looks itself
        yield None
        return
    look = Look(namespace, domain)
    try:
        yield look
    finally:
        look.cancel()

