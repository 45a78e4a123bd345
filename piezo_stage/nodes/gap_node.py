"""gap: a simulated twin beside the real stage, on the same voltages, live.

Runs the model file (hysteresis, coupling and any effects it lists) on the applied
voltages carried by joint_states (effort, V) and publishes the residual measured -
twin on ``gap/residual`` (geometry_msgs/PointStamped, metres) and its rolling RMS on
/diagnostics, so a lab user sees the sim-to-real gap while running.

With ``watch`` (``piezo-stage launch --watch``), the gap's level after arming is watched
(core/estimation/gap/watch.py): where it rises clearly, the newest data are diagnosed as
``gap`` diagnoses offline, in a process of its own (nodes/_watch.py); a refit with the
effect named that shrinks the gap on the newest held-out data is published on ``model``
(the feedforward takes it, bumplessly) and becomes the twin's. Each diagnosis is on
/diagnostics (``watch_*`` values) at once; docs/watch.md. With ``watch_hold`` (a lockstep
set: ``launch --watch`` sets it there), the node tells the driver on ``watch/hold``, as soon
as a rise is found, the last sample of the window, and the set waits there until the
diagnosis is decided: the model comes at the window's end whatever the host's pace.
"""

# first, before the heavy imports: stop signals work from here on (see process/signals.py)
import piezo_stage.process.signals  # noqa: F401, I001

# isort: split
import yaml
from geometry_msgs.msg import PointStamped
from rclpy.node import Node
from sensor_msgs.msg import JointState
from std_msgs.msg import Header, String

from piezo_stage.core.errors import PiezoStageError
from piezo_stage.core.estimation.gap.monitor import ResidualMonitor
from piezo_stage.core.estimation.gap.watch import (
    LiveWatch,
    WatchEvent,
    WatchOptions,
    effects_of,
    model_in_use,
    settle_samples,
)
from piezo_stage.core.model.model_doc import model_from_dict
from piezo_stage.io.model_file import load_model
from piezo_stage.io.plant_file import default_config_dir
from piezo_stage.nodes._common import QOS_DATA, QOS_EVENTS, QOS_LATCHED, Status, steady_timer
from piezo_stage.nodes._executor import LeanNode, hot_subscription, run_node
from piezo_stage.nodes._loop import Diagnostics, Gate
from piezo_stage.nodes._params import declare_schema
from piezo_stage.nodes.declared import GAP
from piezo_stage_msgs_adapters import hold_msg, joint_state_to_um, model_msg, point_cdr


class Gap(LeanNode, Node):
    USES_KERNELS = True  # the model's twin (LeanNode)

    def __init__(self) -> None:
        super().__init__("gap")
        p = declare_schema(self, GAP)
        path = p["model_file"] or f"{default_config_dir()}/stage_model.yaml"
        model, effects = load_model(path)
        # the residual against the model's twin (core/estimation/gap/monitor.py)
        self.monitor = ResidualMonitor(model, effects, p["control_rate_hz"], p["window"])
        self.model_name = path
        self.pub = self.create_publisher(PointStamped, "gap/residual", QOS_DATA)
        self.gate = Gate(self, [(self.pub, p["min_subscribers"])])
        self.watch: LiveWatch | None = None
        self.events: list[WatchEvent] = []
        if p["watch"]:
            from piezo_stage.nodes._watch import WatchWorker
            self.watch = LiveWatch(p["control_rate_hz"], model_in_use(model, effects),
                                   WatchOptions(effects=tuple(p["watch_effects"])),
                                   have=effects_of(effects))
            self.worker = WatchWorker()
            self.model_pub = self.create_publisher(String, "model", QOS_LATCHED)
            steady_timer(self, 0.1, self.on_watch)
        # lockstep: the set waits at a window's last sample while it is diagnosed
        self.hold_pub = self.create_publisher(Header, "watch/hold", QOS_EVENTS) \
            if self.watch is not None and p["watch_hold"] else None
        self.holding = False
        self.period_ns = 1e9 / p["control_rate_hz"]
        hot_subscription(self, JointState, "joint_states", self.on_state, QOS_DATA,
                         raw=True)
        self.diag = Diagnostics(self, self.status, "sim-to-real residual")

    def on_state(self, msg: bytes) -> None:
        try:
            ns, w, v = joint_state_to_um(msg, with_effort=True)
        except PiezoStageError:
            return
        if v is None:
            return
        r = self.monitor.sample(w, v)
        self.gate.publish(self.pub, point_cdr(ns, r))  # raw CDR: no message object
        if self.watch is not None:
            req = self.watch.sample(v, w, r)
            end = self.watch.window_end()
            if self.hold_pub is not None and end is not None and not self.holding:
                # the window's last sample, 6 s of samples ahead of it: the set waits
                # there (announced ahead, the wait's sample does not depend on the host)
                self.holding = True
                self.hold_pub.publish(hold_msg(ns + round((end - self.watch.n)
                                                          * self.period_ns)))
            if req is not None:
                self.get_logger().info(
                    f"the live gap rose on {', '.join(req.rising)} at "
                    f"{req.start_index / self.watch.fs:.1f} s: diagnosing the window")
                self.worker.submit(req)

    def on_watch(self) -> None:
        """A diagnosis that ended: its event said, its model handed on where it is."""
        assert self.watch is not None
        got = self.worker.done()
        if got is None:
            return
        req, res = got
        ev = self.watch.decide(req, res)
        if ev.handed_on and ev.model_doc is not None:
            history = self.watch.since(req.start_index)
            if history is None:
                ev.handed_on = False
                ev.reason += "; not handed on: the diagnosis took longer than the samples kept"
            else:
                model, effects = model_from_dict(ev.model_doc, "the watch's model")
                self.monitor.switch(model, effects, history, settle=settle_samples(req))
                self.watch.adopted(ev.model_doc, effects_of(effects))
                self.model_pub.publish(model_msg(yaml.safe_dump(ev.model_doc,
                                                                sort_keys=False)))
                self.model_name = f"the watch's refit with {ev.effect} at {ev.at_s:.1f} s"
        self.events.append(ev)
        self.get_logger().info(f"watch: {ev.reason} (diagnosed in {res.seconds:.1f} s)")
        self.diag.publish()  # each diagnosis a message of its own
        self.go_on()

    def go_on(self) -> None:
        """A lockstep set held at a window's end goes on (the model, if any, sent)."""
        if self.hold_pub is not None and self.holding:
            self.holding = False
            self.hold_pub.publish(hold_msg(None))

    def status(self) -> Status:
        vals: dict = {f"rms_{a}_um": x for a, x in self.monitor.rms_um().items()}
        n = self.monitor.n
        msg = (f"residual rms x/y {vals['rms_x_um']:.4g}/{vals['rms_y_um']:.4g} um against "
               f"{self.model_name}") if n else "waiting for samples"
        if self.watch is not None:
            vals["watch_diagnoses"] = len(self.events)
            vals["watch_models"] = sum(e.handed_on for e in self.events)
            vals["watch_level_um"] = ",".join(f"{self.watch.level.get(a, float('nan')):.4f}"
                                              for a in ("x", "y"))
            if self.events:
                vals.update(self.events[-1].values())
        return 0, msg, {**vals, "model": self.model_name, "samples": n}

    def close(self) -> None:
        """The watch's worker ended before the node goes (run_node calls this), then
        the node's last report."""
        if self.watch is not None:
            self.worker.close()
            self.go_on()
        super().close()


def main(args: list[str] | None = None) -> int:
    """Run the gap monitor (the Jazzy form)."""
    return run_node(Gap, args)


if __name__ == "__main__":
    from piezo_stage.process.stopping import exit_now
    exit_now(main())  # flushed, at-exit work done, no finalization (stopping.py)
