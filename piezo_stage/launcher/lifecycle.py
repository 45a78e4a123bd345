"""A managed node's lifecycle from outside, the way `ros2 lifecycle get|set` works (no
ros2 CLI here): a short-lived node that calls the node's standard services
(``<node>/get_state``, ``get_available_transitions``, ``change_state``) with
lifecycle_msgs only, so it drives our stage driver or any other lifecycle node.

A target may be a transition (configure, activate, deactivate, cleanup, shutdown) or a
primary state (unconfigured, inactive, active, finalized): a state is reached through
the shortest chain of transitions of the standard lifecycle graph, one call each."""

from __future__ import annotations

import time
from collections import deque

from piezo_stage.core.errors import ConfigError, RunError

TRANSITIONS = ("configure", "activate", "deactivate", "cleanup", "shutdown")
STATES = ("unconfigured", "inactive", "active", "finalized")
# the standard graph between primary states (rcl_lifecycle's default state machine)
GRAPH = {"unconfigured": {"configure": "inactive", "shutdown": "finalized"},
         "inactive": {"activate": "active", "cleanup": "unconfigured",
                      "shutdown": "finalized"},
         "active": {"deactivate": "inactive", "shutdown": "finalized"},
         "finalized": {}}


def plan(current: str, target: str) -> list[str]:
    """The transitions from ``current`` to reach ``target`` (a state or a transition's
    label). ConfigError for an unknown target or one not reachable from here."""
    if target in TRANSITIONS:
        if target not in GRAPH.get(current, {}):
            allowed = ", ".join(GRAPH.get(current, {})) or "none"
            raise ConfigError(f"{target}: not a transition from {current} (from there: "
                              f"{allowed})")
        return [target]
    if target not in STATES:
        raise ConfigError(f"{target!r}: give a transition ({', '.join(TRANSITIONS)}) or a "
                          f"state ({', '.join(STATES)})")
    seen: dict[str, list[str]] = {current: []}
    todo = deque([current])
    while todo:
        s = todo.popleft()
        for label, nxt in GRAPH.get(s, {}).items():
            if nxt not in seen:
                seen[nxt] = seen[s] + [label]
                todo.append(nxt)
    if target not in seen:
        raise ConfigError(f"{target}: not reachable from {current}")
    return seen[target]


def full_name(node: str, namespace: str) -> str:
    """``stage_driver`` -> ``/stage/stage_driver``; an absolute name stays."""
    if node.startswith("/"):
        return node.rstrip("/")
    return f"/{namespace.strip('/')}/{node}".replace("//", "/")


class LifecycleClient:
    """An outside client of one lifecycle node (its own context on ``domain_id``)."""

    def __init__(self, node: str, domain_id: int, timeout_s: float = 10.0):
        import rclpy
        from lifecycle_msgs.srv import ChangeState, GetAvailableTransitions, GetState
        from rclpy.context import Context
        from rclpy.executors import SingleThreadedExecutor
        from rclpy.signals import SignalHandlerOptions
        self.name, self.timeout_s = node, float(timeout_s)
        self.ctx = Context()
        rclpy.init(context=self.ctx, domain_id=int(domain_id),
                   signal_handler_options=SignalHandlerOptions.NO)
        self.node = rclpy.create_node("lifecycle_client", context=self.ctx,
                                      start_parameter_services=False, enable_rosout=False)
        self.ex = SingleThreadedExecutor(context=self.ctx)
        self.ex.add_node(self.node)
        self.get_cli = self.node.create_client(GetState, f"{node}/get_state")
        self.list_cli = self.node.create_client(GetAvailableTransitions,
                                                f"{node}/get_available_transitions")
        self.change_cli = self.node.create_client(ChangeState, f"{node}/change_state")
        self.types = (GetState, GetAvailableTransitions, ChangeState)

    def close(self) -> None:
        """Leave the graph (at the command's end, bounded: process/teardown.py)."""
        import rclpy

        from piezo_stage.process import teardown
        node, ctx = self.node, self.ctx

        def leave() -> None:
            try:
                node.destroy_node()
            finally:
                rclpy.try_shutdown(context=ctx)
        teardown.leave(leave)

    def _ready(self, client, what: str, t_end: float, timeout: float) -> None:
        """Wait for ``client``'s service (the graph is kept by DDS's own threads: a
        short spin each time, so a service found early is called early)."""
        while not client.service_is_ready():
            if time.monotonic() > t_end:
                raise ConfigError(f"{self.name}: no lifecycle node answers there ({what} "
                                  f"not available within {timeout:g} s; is the set running "
                                  "on this ROS_DOMAIN_ID?)")
            self.ex.spin_once(timeout_sec=0.01)

    def _calls(self, *calls, timeout_s: float | None = None) -> list:
        """Each (client, request, what) called at once, their answers in order."""
        timeout = self.timeout_s if timeout_s is None else timeout_s
        t_end = time.monotonic() + timeout
        for client, _, what in calls:
            self._ready(client, what, t_end, timeout)
        futs = [(client.call_async(req), what) for client, req, what in calls]
        for fut, what in futs:
            while not fut.done():
                if time.monotonic() > t_end + timeout:
                    raise RunError(f"{self.name}: {what} did not answer within {timeout:g} s")
                self.ex.spin_once(timeout_sec=0.05)
        return [fut.result() for fut, _ in futs]

    def _call(self, client, request, what: str, timeout_s: float | None = None):
        return self._calls((client, request, what), timeout_s=timeout_s)[0]

    def state_and_transitions(self) -> tuple[str, list[tuple[int, str, str]]]:
        """The node's state label and the transitions available now, asked together."""
        got, listed = self._calls(
            (self.get_cli, self.types[0].Request(), "get_state"),
            (self.list_cli, self.types[1].Request(), "get_available_transitions"))
        return got.current_state.label, self._listed(listed)

    @staticmethod
    def _listed(r) -> list[tuple[int, str, str]]:
        return [(t.transition.id, t.transition.label, t.goal_state.label)
                for t in r.available_transitions]

    def state(self) -> str:
        """The node's state label."""
        return self._call(self.get_cli, self.types[0].Request(), "get_state").current_state.label

    def transitions(self) -> list[tuple[int, str, str]]:
        """(id, label, goal state) of each transition available now."""
        return self._listed(self._call(self.list_cli, self.types[1].Request(),
                                       "get_available_transitions"))

    def change(self, label: str) -> bool:
        """One transition by its label (a lifecycle node, rclpy's or rclcpp's, looks a
        labelled transition up itself: no listing first, one call less)."""
        from lifecycle_msgs.msg import Transition
        req = self.types[2].Request(transition=Transition(label=label))
        return bool(self._call(self.change_cli, req, "change_state").success)


def drive(node: str, target: str | None, domain_id: int, timeout_s: float = 10.0,
          say=print) -> str:
    """Read ``node``'s state (no target) or take it to ``target``; each step said in
    one line. Returns the final state. ConfigError: no such node or target; RunError:
    a transition the node refused (it stays where the refusal left it)."""
    cli = LifecycleClient(node, domain_id, timeout_s)
    try:
        if target is None:
            now, available = cli.state_and_transitions()
            listed = ", ".join(dict.fromkeys(lab for _, lab, _ in available))
            say(f"{node}: {now}" + (f" (transitions: {listed})" if listed else ""))
            return now
        now = cli.state()
        for label in plan(now, target):
            if not cli.change(label):
                try:
                    after = cli.state()
                except (ConfigError, RunError):
                    after = "no answer"
                raise RunError(f"{node}: {label} refused ({now} -> {after}; the node's "
                               "log says why)")
            # (its goal, not asked again: after shutdown the node is gone)
            after = GRAPH[now][label]
            say(f"{node}: {now} -> {after} ({label})")
            now = after
        return now
    finally:
        cli.close()
