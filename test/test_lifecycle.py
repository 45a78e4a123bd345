"""The stage driver as a managed (lifecycle) node, driven from outside with lifecycle_msgs
only, as a lab's own manager or `ros2 lifecycle set` would: every transition, in
lockstep and in real time, a deactivate while tracking, an activate after a fault; and
`piezo-stage lifecycle`, our stand-in for the ros2 CLI."""

import os
import subprocess
import sys
import time

import numpy as np
import pytest

pytest.importorskip("rclpy")
from test_realtime import assert_never_beyond_slew  # noqa: E402

from conftest import CONFIG, realtime_twice  # noqa: E402
from piezo_stage.io.run_bag import read_run  # noqa: E402
from piezo_stage.launcher.launcher import Launch, LaunchOptions  # noqa: E402
from piezo_stage.launcher.lifecycle import GRAPH, plan  # noqa: E402

MODEL = os.path.join(CONFIG, "stage_model.yaml")
NS = "/stage/stage_driver"


def test_a_state_is_reached_by_the_shortest_chain_of_standard_transitions():
    assert plan("unconfigured", "active") == ["configure", "activate"]
    assert plan("active", "unconfigured") == ["deactivate", "cleanup"]
    assert plan("active", "finalized") == ["shutdown"]
    assert plan("inactive", "inactive") == []
    assert plan("inactive", "cleanup") == ["cleanup"]
    with pytest.raises(Exception, match="not a transition from active"):
        plan("active", "configure")
    with pytest.raises(Exception, match="not reachable from finalized"):
        plan("finalized", "active")
    with pytest.raises(Exception, match="give a transition"):
        plan("active", "armed")
    assert all(goal in GRAPH for edges in GRAPH.values() for goal in edges.values())


def test_lifecycle_refuses_an_unknown_target_and_a_node_that_is_not_there(ros_env):
    for argv, said in ((["stage_driver", "armed"], "give a transition"),
                       (["nobody", "--timeout", "1"], "/stage/nobody: no lifecycle node")):
        r = subprocess.run([sys.executable, "-m", "piezo_stage", "lifecycle", *argv],
                           env=ros_env, capture_output=True, text=True, timeout=60)
        assert r.returncode == 2, r
        assert len(r.stderr.strip().splitlines()) == 1 and said in r.stderr, r.stderr


class Manager:
    """An outside lifecycle manager: rclpy with lifecycle_msgs (and std_srvs for the
    e-stop, std/diagnostic messages to watch), nothing of ours."""

    def __init__(self, domain_id):
        import rclpy
        from diagnostic_msgs.msg import DiagnosticArray
        from lifecycle_msgs.msg import TransitionEvent
        from lifecycle_msgs.srv import (
            ChangeState,
            GetAvailableStates,
            GetAvailableTransitions,
            GetState,
        )
        from rclpy.context import Context
        from rclpy.executors import SingleThreadedExecutor
        from rclpy.qos import QoSProfile, ReliabilityPolicy
        from sensor_msgs.msg import JointState
        from std_srvs.srv import Trigger
        self.ctx = Context()
        rclpy.init(context=self.ctx, domain_id=int(domain_id))
        self.node = rclpy.create_node("lab_manager", context=self.ctx)
        self.ex = SingleThreadedExecutor(context=self.ctx)
        self.ex.add_node(self.node)
        self.srv = {name: self.node.create_client(t, f"{NS}/{name}") for name, t in (
            ("change_state", ChangeState), ("get_state", GetState),
            ("get_available_states", GetAvailableStates),
            ("get_available_transitions", GetAvailableTransitions))}
        self.estop_cli = self.node.create_client(Trigger, "/stage/estop")
        self.events, self.samples, self.effort, self.armed = [], 0, None, []
        self.node.create_subscription(TransitionEvent, f"{NS}/transition_event",
                                      lambda m: self.events.append(
                                          (m.start_state.label, m.goal_state.label)), 10)
        self.node.create_subscription(
            JointState, "/stage/joint_states", self._on_js,
            QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE))
        from piezo_stage.nodes._common import QOS_EVENTS
        self.node.create_subscription(DiagnosticArray, "/stage/state", self._on_state,
                                      QOS_EVENTS)
        self.state_values = {}

    def _on_js(self, m):
        self.samples, self.effort = self.samples + 1, list(m.effort)

    def _on_state(self, m):
        self.state_values = {kv.key: kv.value for kv in m.status[0].values}
        self.armed.append(self.state_values.get("state"))

    def wait(self, cond, timeout):
        t_end = time.monotonic() + timeout
        while time.monotonic() < t_end and not cond():
            self.ex.spin_once(timeout_sec=0.01)
        return cond()

    def spin(self, s):
        self.wait(lambda: False, s)

    def call(self, name, request, timeout=20.0):
        cli = self.srv.get(name) or self.estop_cli
        assert cli.wait_for_service(timeout_sec=timeout), name
        fut = cli.call_async(request)
        assert self.wait(fut.done, timeout), f"{name}: no answer"
        return fut.result()

    def state(self):
        from lifecycle_msgs.srv import GetState
        return self.call("get_state", GetState.Request()).current_state.label

    def transitions(self):
        from lifecycle_msgs.srv import GetAvailableTransitions
        r = self.call("get_available_transitions", GetAvailableTransitions.Request())
        return {t.transition.label for t in r.available_transitions}

    def change(self, label):
        from lifecycle_msgs.msg import Transition
        from lifecycle_msgs.srv import ChangeState
        ids = {"configure": Transition.TRANSITION_CONFIGURE,
               "activate": Transition.TRANSITION_ACTIVATE,
               "deactivate": Transition.TRANSITION_DEACTIVATE,
               "cleanup": Transition.TRANSITION_CLEANUP}
        if label == "shutdown":
            ids["shutdown"] = {"unconfigured": Transition.TRANSITION_UNCONFIGURED_SHUTDOWN,
                               "inactive": Transition.TRANSITION_INACTIVE_SHUTDOWN,
                               "active": Transition.TRANSITION_ACTIVE_SHUTDOWN}[self.state()]
        return self.call("change_state", ChangeState.Request(
            transition=Transition(id=ids[label]))).success

    def close(self):
        import rclpy
        self.node.destroy_node()
        rclpy.try_shutdown(context=self.ctx)


def _config(tmp_path, mode):
    # (the transitions are what is judged here, not the loop's pace: a 0.5 s stale
    # timeout, so that a host pause in real time is not an error transition the test did
    # not ask for; a loaded host can pause 56 ms while a second suite runs)
    cfg = tmp_path / "lifecycle.yaml"
    cfg.write_text(
        f"/**/stage_driver:\n  ros__parameters:\n    mode: {mode}\n"
        "    stale_timeout_s: 0.5\n    safe_ramp_V_per_s: 500.0\n"
        "    min_margin: 0.0\n"  # the rate is the capacity run's (conftest)
        "/**/feedforward:\n  ros__parameters:\n    model_file: " + MODEL + "\n"
        "/**/controller:\n  ros__parameters:\n    kp: 0.2\n"
        "/**/trajectory:\n  ros__parameters:\n    kind: seed\n    duration_s: 120.0\n")
    return str(cfg)


@pytest.mark.slow
@pytest.mark.parametrize("mode", ["lockstep",
                                  pytest.param("realtime", marks=pytest.mark.realtime)])
def test_every_transition_from_an_outside_manager(tmp_path, ros_env, ros_domains, mode):
    """launch --managed: the driver waits unconfigured, publishing nothing, until told;
    configure (the loop runs at the safe voltage), activate (arms through the approach),
    deactivate while tracking (a ramp to safe within the slew limit, still publishing),
    activate again, an e-stop while active (the error transition: unconfigured, the
    backend closed), configure and activate after it (armed again), deactivate,
    cleanup, and shutdown (the driver exits 0). The bag is the judge of the voltages.
    Real time at the host's rate (skips where it holds none; a run that fails, once more
    at the rate the host holds then: conftest.realtime_twice); lockstep at its own."""
    if mode == "lockstep":
        _transitions(tmp_path, ros_env, mode, None)
    else:
        realtime_twice(lambda e, rate, which: _transitions(tmp_path / which, e, mode, rate),
                       ros_env, ros_domains)


def _transitions(tmp_path, ros_env, mode, rate):
    from lifecycle_msgs.srv import GetAvailableStates
    from std_srvs.srv import Trigger
    tmp_path.mkdir(exist_ok=True)
    d = int(ros_env["ROS_DOMAIN_ID"])
    bag = str(tmp_path / "bag")
    launch = Launch(_config(tmp_path, mode), LaunchOptions(record=bag, managed=True, rate=rate,
        nodes=["stage_driver", "feedforward", "controller", "trajectory"],
        exclusive=False), env=ros_env)
    m = Manager(d)
    marks = {}
    try:
        launch.start()
        assert m.state() == "unconfigured"
        states = m.call("get_available_states", GetAvailableStates.Request())
        assert {"unconfigured", "inactive", "active", "finalized", "errorprocessing"} <= {
            s.label for s in states.available_states}
        assert m.transitions() == {"configure", "shutdown"}
        m.spin(2.0)
        assert m.samples == 0  # managed: nothing opened, nothing published until told

        assert m.change("configure") and m.state() == "inactive"
        assert m.wait(lambda: m.samples > 50 and m.effort == [0.0, 0.0], 30)
        assert m.state_values.get("lifecycle") == "inactive"
        m.spin(1.0)
        assert m.armed[-1] == "disarmed"  # inactive never arms, whatever the loop does
        assert m.transitions() == {"activate", "cleanup", "shutdown"}

        n = len(m.armed)  # (arming may end while the state is asked)
        assert m.change("activate") and m.state() == "active"
        assert m.wait(lambda: "armed" in m.armed[n:], 60)
        m.spin(1.5)  # tracking
        marks["deactivate"] = m.samples
        assert m.change("deactivate") and m.state() == "inactive"
        assert m.wait(lambda: m.effort == [0.0, 0.0], 20)  # ramped to safe
        n0 = m.samples  # still publishing (within 5 s: a host that starves this
        assert m.wait(lambda: m.samples > n0 + 10, 5)  # process may pause its reads)
        n = len(m.armed)
        assert m.change("activate")
        assert m.wait(lambda: "armed" in m.armed[n:], 60)
        m.spin(1.0)

        n_events = len(m.events)
        assert m.call("estop", Trigger.Request()).success
        assert m.wait(lambda: ("active", "deactivating") in m.events[n_events:]
                      and m.events[-1][1] == "unconfigured", 20), m.events[n_events:]
        assert "errorprocessing" in {g for _, g in m.events[n_events:]}
        assert m.state() == "unconfigured"
        # the last samples, ramped to safe, may come after the transition's events
        assert m.wait(lambda: m.effort == [0.0, 0.0], 10), m.effort

        n = len(m.armed)
        assert m.change("configure") and m.change("activate")  # after the fault
        assert m.wait(lambda: "armed" in m.armed[n:], 60), m.armed[n:]
        m.spin(1.0)

        # the CLI stand-in for `ros2 lifecycle`: read, then a state two steps away
        cli = [sys.executable, "-m", "piezo_stage", "lifecycle", "stage_driver"]
        r = subprocess.run(cli, env=ros_env, capture_output=True, text=True, timeout=60)
        assert r.returncode == 0 and r.stdout.startswith(f"{NS}: active"), r
        r = subprocess.run(cli + ["unconfigured"], env=ros_env, capture_output=True,
                           text=True, timeout=60)
        assert r.returncode == 0, r
        assert r.stdout.splitlines() == [f"{NS}: active -> inactive (deactivate)",
                                         f"{NS}: inactive -> unconfigured (cleanup)"]
        assert m.state() == "unconfigured"
        assert m.change("shutdown")
        launch.procs["stage_driver"].wait(20)
    finally:
        m.close()
        launch.stop()
    assert launch.procs["stage_driver"].returncode == 0  # finalized: exits by itself
    run = read_run(bag)
    ok = np.all(np.isfinite(run.v_V), axis=1)
    t, v = run.t_ns[ok], run.v_V[ok]
    assert np.all(np.diff(t) > 0)  # one time base across every configure
    assert_never_beyond_slew(t, v)
    assert np.abs(v).max() > 1.0  # it did track, and ramped from there
    states = [s for _, s in run.states]
    assert states.count("armed") >= 3 and "faulted" in states
