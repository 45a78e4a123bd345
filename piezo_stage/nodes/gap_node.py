"""gap: a simulated twin beside the real stage, on the same voltages, live.

Runs the model file (hysteresis, coupling and any effects it lists) on the applied
voltages carried by joint_states (effort, V) and publishes the residual measured -
twin on ``gap/residual`` (geometry_msgs/PointStamped, metres) and its rolling RMS on
/diagnostics, so a lab user sees the sim-to-real gap while running.
"""

# first, before the heavy imports: stop signals work from here on (see process/signals.py)
import piezo_stage.process.signals  # noqa: F401, I001

# isort: split
from geometry_msgs.msg import PointStamped
from rclpy.node import Node
from sensor_msgs.msg import JointState

from piezo_stage.core.errors import PiezoStageError
from piezo_stage.core.estimation.gap.monitor import ResidualMonitor
from piezo_stage.io.model_file import load_model
from piezo_stage.io.plant_file import default_config_dir
from piezo_stage.nodes._common import QOS_DATA, Status
from piezo_stage.nodes._executor import LeanNode, hot_subscription, run_node
from piezo_stage.nodes._loop import Diagnostics, Gate
from piezo_stage.nodes._params import declare_schema
from piezo_stage.nodes.declared import GAP
from piezo_stage_msgs_adapters import joint_state_to_um, point_cdr


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
        hot_subscription(self, JointState, "joint_states", self.on_state, QOS_DATA,
                         raw=True)
        Diagnostics(self, self.status, "sim-to-real residual")

    def on_state(self, msg: bytes) -> None:
        try:
            ns, w, v = joint_state_to_um(msg, with_effort=True)
        except PiezoStageError:
            return
        if v is None:
            return
        r = self.monitor.sample(w, v)
        self.gate.publish(self.pub, point_cdr(ns, r))  # raw CDR: no message object

    def status(self) -> Status:
        vals = {f"rms_{a}_um": x for a, x in self.monitor.rms_um().items()}
        n = self.monitor.n
        msg = (f"residual rms x/y {vals['rms_x_um']:.4g}/{vals['rms_y_um']:.4g} um against "
               f"{self.model_name}") if n else "waiting for samples"
        return 0, msg, {**vals, "model": self.model_name, "samples": n}


def main(args: list[str] | None = None) -> int:
    """Run the gap monitor (the Jazzy form)."""
    return run_node(Gap, args)


if __name__ == "__main__":
    from piezo_stage.process.stopping import exit_now
    exit_now(main())  # flushed, at-exit work done, no finalization (stopping.py)
