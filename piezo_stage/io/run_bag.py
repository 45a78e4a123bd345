"""A recorded run of the node set, read back as arrays: what the benchmarks, the
experiments and the tests judge a run by.

``read_run(bag)`` -> ``Run`` with, per sample of joint_states (stamp order): stamps [ns],
measured position [um], applied voltage [V], receive time at the recorder [ns] (its log
time in real time); the true positions and the references (desired [um]) by stamp; the
driver's state changes and the reason of each fault; the driver's diagnostics (key ->
value string), its last and all of them in order.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from piezo_stage.core.errors import DataError
from piezo_stage.core.types import Doc
from piezo_stage.io.bag import deserialize, iter_messages
from piezo_stage_msgs_adapters.wire import (
    announcement_of,
    joint_state_um,
    point_um,
    reference_um,
    trajectory_header,
)


def _ns(m) -> int:
    return m.header.stamp.sec * 1_000_000_000 + m.header.stamp.nanosec


@dataclass
class Run:
    t_ns: np.ndarray                       # joint_states stamps
    w_um: np.ndarray                       # (n, 2) measured x, y
    v_V: np.ndarray                        # (n, 2) applied x, y
    recv_ns: np.ndarray                    # recorder's log time of each sample
    true_um: dict[int, np.ndarray] = field(default_factory=dict) # stamp -> (2,)
    desired_um: dict[int, np.ndarray] = field(default_factory=dict) # reference stamp -> (2,)
    states: list = field(default_factory=list)        # (since ns, state)
    fault_reasons: list = field(default_factory=list)  # each fault's reason, in order
    driver: Doc = field(default_factory=dict)        # last driver diagnostics
    driver_reports: list = field(default_factory=list)  # all of them, in order
    diagnostics: Doc = field(default_factory=dict)   # node name -> its last ones
    models: int = 0                                   # models handed over (on model)
    skipped: int = 0                                  # joint states not the driver's
    accepted: list = field(default_factory=list)      # trajectories run: frame_ids

    def state_times(self, name: str) -> list:
        return [s for s, n in self.states if n == name]

    def errors_t_ns(self, t_from_ns: int, t_to_ns: int) -> list[int]:
        """The stamps in [t_from, t_to] that have both a true and a desired position."""
        return [k for k in sorted(self.desired_um) if t_from_ns <= k <= t_to_ns
                and k in self.true_um]

    def errors_um(self, t_from_ns: int, t_to_ns: int) -> np.ndarray:
        """(n, 2) true - desired at every stamp in [t_from, t_to] that has both."""
        ks = self.errors_t_ns(t_from_ns, t_to_ns)
        return np.array([self.true_um[k] - self.desired_um[k] for k in ks]).reshape(-1, 2)


def status_node(name: str) -> str:
    """The node of a DiagnosticStatus name ``"<namespace>/<node>: <task>"``."""
    return name.split(":", 1)[0].rsplit("/", 1)[-1].strip()


def read_run(bag) -> Run:
    t: list[int] = []
    w: list = []
    v: list = []
    recv: list[int] = []
    true: dict[int, np.ndarray] = {}
    ref: dict[int, np.ndarray] = {}
    states: list[tuple[int, str]] = []
    diags: Doc = {}
    reports: list[dict] = []
    reasons: list[str] = []
    models = skipped = 0
    accepted: list[str] = []
    for topic, msgtype, log_ns, data in iter_messages(bag):
        if topic.endswith("/joint_states"):
            try:  # an outside node's malformed or foreign joint state is not a sample
                ns, w_um, v_V = joint_state_um(data)
            except DataError:
                skipped += 1
                continue
            if not {"x", "y"} <= set(w_um):
                skipped += 1
                continue
            t.append(ns)
            recv.append(log_ns)
            w.append([w_um.get("x", np.nan), w_um.get("y", np.nan)])
            v.append([v_V["x"], v_V["y"]] if v_V and len(v_V) == 2 else [np.nan, np.nan])
        elif topic.endswith("/sim/true_position"):
            ns, p_um = point_um(data)
            true[ns] = np.array([p_um["x"], p_um["y"]])
        elif topic.endswith("/reference"):  # desired x, y: the first two joints
            try:
                r = reference_um(data)  # the controller's decoder (wire.reference_of)
            except DataError:  # an outside node's malformed reference: no target
                continue
            ref[r.ns] = np.array([r.desired_um["x"], r.desired_um["y"]])
        elif topic.endswith("/state") and msgtype.endswith("DiagnosticArray"):
            try:
                a = announcement_of(deserialize(data, msgtype))  # the loop nodes' reader
            except DataError:  # a foreign or malformed state: no change of the driver's
                continue
            if not states or states[-1][1] != a.state:
                states.append((a.since_ns, a.state))
                if a.state == "faulted":
                    reasons.append(a.reason)  # changes (not the relays of the
                # feedforward's phase, which repeat the state)
        elif topic.endswith("/model"):
            models += 1
        elif topic.endswith("/trajectory/accepted"):
            accepted.append(trajectory_header(data)[0])
        elif topic == "/diagnostics":
            m = deserialize(data, msgtype)
            for st in m.status:
                kv = {k.key: k.value for k in st.values}
                kv["hardware_id"] = st.hardware_id
                diags[status_node(st.name)] = kv
                if status_node(st.name) == "stage_driver":
                    reports.append(kv)
    order = np.argsort(t, kind="stable")
    arr = lambda x, shape: np.array(x).reshape(shape)[order]  # noqa: E731
    return Run(arr(t, -1), arr(w, (-1, 2)), arr(v, (-1, 2)), arr(recv, -1), true, ref,
               states, reasons, diags.get("stage_driver", {}), reports, diags, models,
               skipped, accepted)
