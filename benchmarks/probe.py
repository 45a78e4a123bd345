"""An outside node (its own rclpy context and domain) for tests and benchmarks: watches
the driver's state and joint_states, calls its services, publishes commands and sets
parameters the way a lab's own node or `ros2 param set` would."""

from __future__ import annotations

import time
from typing import Any

import rclpy
from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import Vector3Stamped
from rclpy.context import Context
from rclpy.executors import SingleThreadedExecutor
from rclpy.qos import QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import JointState
from std_srvs.srv import SetBool, Trigger

from piezo_stage.nodes._common import QOS_DATA, QOS_EVENTS


class Probe:
    def __init__(self, domain_id: int, ns: str = "/stage"):
        self.ctx = Context()
        rclpy.init(context=self.ctx, domain_id=int(domain_id))
        self.node = rclpy.create_node("probe", context=self.ctx)
        self.ex = SingleThreadedExecutor(context=self.ctx)
        self.ex.add_node(self.node)
        self.states: list[tuple[str, str, float]] = []
        self.effort: list | None = None
        self.samples, self.values = 0, {}  # type: int, dict
        self.node.create_subscription(DiagnosticArray, f"{ns}/state", self._on_state, QOS_EVENTS)
        # only the newest sample matters here: no backlog to lag behind under load
        newest = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE)
        self.node.create_subscription(JointState, f"{ns}/joint_states", self._on_js, newest)
        self.arm_cli = self.node.create_client(SetBool, f"{ns}/arm")
        self.estop_cli = self.node.create_client(Trigger, f"{ns}/estop")
        self.ns = ns
        self.cmd_pub: Any = None  # made on first use: it would look like a controller

    def _on_state(self, msg):
        kv = {k.key: k.value for k in msg.status[0].values}
        self.values = kv
        if not self.states or self.states[-1][:2] != (kv["state"], kv.get("reason", "")):
            # (the driver also republishes its state to relay the feedforward's phase)
            self.states.append((kv["state"], kv.get("reason", ""), time.monotonic()))

    def _on_js(self, msg):
        self.effort, self.samples = list(msg.effort), self.samples + 1

    @property
    def state(self):
        return self.states[-1][0] if self.states else None

    def spin(self, seconds: float):
        t_end = time.monotonic() + seconds
        while time.monotonic() < t_end:
            self.ex.spin_once(timeout_sec=min(0.01, max(0.0, t_end - time.monotonic())))

    def wait(self, cond, timeout: float) -> bool:
        t_end = time.monotonic() + timeout
        while time.monotonic() < t_end:
            if cond():
                return True
            self.ex.spin_once(timeout_sec=0.01)
        return cond()

    def wait_state(self, name: str, timeout: float = 30.0, after: int = 0) -> bool:
        return self.wait(lambda: any(s[0] == name for s in self.states[after:]), timeout)

    def wait_steady(self, name: str = "armed", hold: float = 0.5,
                    timeout: float = 30.0) -> bool:
        """``name`` is the state now and has been, unchanged, for ``hold`` s: a fault
        injected then meets that state (a set still settling after its last re-arm can
        be faulted again, and a fault injected into a faulted set shows no new state)."""
        return self.wait(lambda: bool(self.states) and self.states[-1][0] == name
                         and time.monotonic() - self.states[-1][2] >= hold, timeout)

    def seen(self, after: int = 0, since: float | None = None) -> str:
        """The states seen from index ``after`` on, in one line: each with its reason
        and its time in s from ``since`` (a ``time.monotonic()``; the first one's by
        default) -> what a failed wait for a state can say of the set."""
        rows = self.states[max(after, 0):]
        if not rows:
            return f"no state seen after the first {after} (now {self.state})"
        t0 = rows[0][2] if since is None else since
        return "; ".join(f"{s} ({r}) {t - t0:+.3f} s" for s, r, t in rows)

    def call(self, client, request, timeout: float = 10.0):
        assert client.wait_for_service(timeout_sec=timeout), client.srv_name
        fut = client.call_async(request)
        assert self.wait(fut.done, timeout), f"{client.srv_name}: no answer"
        return fut.result()

    def arm(self, on: bool = True):
        return self.call(self.arm_cli, SetBool.Request(data=on))

    def estop(self):
        return self.call(self.estop_cli, Trigger.Request())

    def command(self, x: float, y: float, stamp_ns: int = 0):
        m = Vector3Stamped()
        m.header.stamp.sec, m.header.stamp.nanosec = divmod(int(stamp_ns), 1_000_000_000)
        m.vector.x, m.vector.y = x, y
        pub = self.cmd_pub
        if pub is None:
            pub = self.cmd_pub = self.node.create_publisher(Vector3Stamped,
                                                            f"{self.ns}/command", QOS_DATA)
            self.wait(lambda: pub.get_subscription_count() > 0, 5)
        pub.publish(m)

    def close(self):
        self.node.destroy_node()
        rclpy.try_shutdown(context=self.ctx)


def _param_call(probe: Probe, node: str, call, *args, attempts: int = 5):
    """A parameter service call; a reply dropped because the new client was not yet
    discovered by the server (rmw: 'failed to send response') is asked again."""
    from rclpy.parameter_client import AsyncParameterClient
    cli = AsyncParameterClient(probe.node, node)
    assert cli.wait_for_services(10.0), node
    for _ in range(attempts):
        fut = getattr(cli, call)(*args)
        if probe.wait(fut.done, 5.0):
            return fut.result()
    raise TimeoutError(f"{node}: no answer to {call} after {attempts} attempts")


def _param_call_raw(probe: Probe, node: str, service: str, srv_type, attempts: int = 5,
                    **fields):
    """A parameter service (``list_parameters``, ``describe_parameters``) called
    directly, as `ros2 param list/describe` does -> its response."""
    cli = probe.node.create_client(srv_type, f"{node}/{service}")
    try:
        assert cli.wait_for_service(10.0), node
        for _ in range(attempts):
            fut = cli.call_async(srv_type.Request(**fields))
            if probe.wait(fut.done, 10.0):  # a busy host starves normal-priority nodes
                return fut.result()
        raise TimeoutError(f"{node}: no answer from {service} after {attempts} attempts")
    finally:
        probe.node.destroy_client(cli)


def set_params(probe: Probe, node: str, **values):
    """Set parameters on another node as `ros2 param set` does -> [(ok, reason)]."""
    from rclpy.parameter import Parameter
    res = _param_call(probe, node, "set_parameters",
                      [Parameter(k, value=v) for k, v in values.items()])
    return [(r.successful, r.reason) for r in res.results]


def get_params(probe: Probe, node: str, *names):
    from rclpy.parameter import parameter_value_to_python
    res = _param_call(probe, node, "get_parameters", list(names))
    return [parameter_value_to_python(v) for v in res.values]
