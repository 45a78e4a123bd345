"""identifier: buffers live voltage and displacement, identifies the Duhem model.

Identifies on request (~/identify, std_srvs/Trigger) or by itself after ``auto_cycles``
complete voltage cycles (on the data up to the turning point that completes them), and
hands the model to the feedforward on ``model``
(std_msgs/String holding the model file's YAML, transient local: late joiners get it).
"""

# first, before the heavy imports: stop signals work from here on (see process/signals.py)
import piezo_stage.process.signals  # noqa: F401, I001

# isort: split
from collections import deque
from typing import Any

import numpy as np
import yaml
from rclpy.node import Node
from sensor_msgs.msg import JointState
from std_msgs.msg import String
from std_srvs.srv import Trigger

from piezo_stage.core.errors import PiezoStageError
from piezo_stage.core.estimation.identify.segmentation import segment
from piezo_stage.core.estimation.record import Record, on_grid
from piezo_stage.core.loop.stamps import StampGuard
from piezo_stage.nodes._common import QOS_DATA, QOS_LATCHED, Status, steady_timer
from piezo_stage.nodes._executor import LeanNode, hot_subscription, run_node
from piezo_stage.nodes._loop import Diagnostics
from piezo_stage.nodes._params import declare_schema
from piezo_stage.nodes.declared import IDENTIFIER
from piezo_stage.process.signals import interruptible
from piezo_stage_msgs_adapters import joint_state_to_um, model_msg

BATCH_S = 0.05


class Identifier(LeanNode, Node):
    USES_KERNELS = True  # the identification's (LeanNode)

    def __init__(self) -> None:
        super().__init__("identifier")
        # the live ones as attributes the next fit reads
        p = declare_schema(self, IDENTIFIER, {q.name: lambda v, name=q.name: setattr(
            self, name, v) for q in IDENTIFIER if q.live})
        self.method, self.structure = p["method"], p["structure"]
        self.auto_cycles, self.max_samples = p["auto_cycles"], p["max_samples"]
        # samples in stamp order, bounded: the oldest fall off the front (no re-sort)
        self.buf: deque[tuple] = deque(maxlen=self.max_samples)
        self.done_auto = False
        self.stamps = StampGuard()  # one stray stamp must not make every later sample old
        self.stats: dict[str, Any] = {
            "samples": 0, "identifications": 0, "last_fit_rms_um": float("nan"),
            "last_error": "", "bad_messages": 0, "out_of_order": 0}
        self.pub = self.create_publisher(String, "model", QOS_LATCHED)
        # off the loop's path: what arrived is taken every BATCH_S in one pass (a wake
        # a sample costs a real-time set's host CPU the loop needs)
        self.lean_batch_s = BATCH_S
        hot_subscription(self, JointState, "joint_states", self.on_state, QOS_DATA,
                         raw=True)
        self.create_service(Trigger, "~/identify", self.on_identify)
        steady_timer(self, 0.5, self.on_timer)
        Diagnostics(self, self.status, "identification",
                    rates=[("bad_messages", "malformed joint_states", 0),
                           ("out_of_order", "out-of-order samples", 0)])

    def status(self) -> Status:
        err = self.stats["last_error"]
        return ((1, f"last identification failed: {err}") if err else
                (0, f"{len(self.buf)} samples buffered")) + ({
                    **self.stats, "buffered": len(self.buf), "method": self.method,
                    "structure": self.structure, "auto_cycles": self.auto_cycles},)

    def on_state(self, msg: bytes) -> None:
        try:
            ns, w, v = joint_state_to_um(msg, with_effort=True)
        except PiezoStageError:  # a malformed or foreign JointState: count it, go on
            self.stats["bad_messages"] += 1
            return
        if v is None:  # a driver that does not report the applied voltage
            return
        if not self.stamps.accept(ns):  # old, repeated, or a stray stamp
            self.stats["out_of_order"] += 1
            return
        self.buf.append((ns, w["x"], w["y"], v["x"], v["y"]))

    def record(self, n: int | None = None) -> Record:
        """The buffer as a Record (its first n samples when n is given)."""
        a = np.array(list(self.buf)[:n], dtype=float).reshape(-1, 5)
        stamps = a[:, 0].astype(np.int64) if len(a) else np.zeros(0, np.int64)
        t = (stamps - stamps[0]) * 1e-9 if len(a) else np.zeros(0)
        return Record(t, {"x": a[:, 3], "y": a[:, 4]}, {"x": a[:, 1], "y": a[:, 2]},
                      source="live buffer", voltage_exact=True)

    def identify(self, n: int | None = None) -> str:
        # the identification's numerics at the first fit (the node starts sooner)
        from piezo_stage.core.estimation.identify import IdentifyOptions
        from piezo_stage.core.estimation.identify.api import identify_stage
        from piezo_stage.core.model.model_doc import checked_doc
        rec = on_grid(self.record(n))  # a real-time run's skipped ticks: one grid
        for note in rec.notes:
            self.get_logger().info(f"note: {note}")
        self.stats["samples"] = len(rec)
        opts = IdentifyOptions(method=self.method, structure=self.structure)
        with interruptible():  # a long swarm search still stops in time
            fitted = identify_stage(rec, ("x", "y"), opts, skip_unusable=True)
        doc, notes = checked_doc(fitted.model)  # as a file of it would be checked
        for note in notes:
            self.get_logger().info(f"note: {note}")
        self.pub.publish(model_msg(yaml.safe_dump(doc, sort_keys=False)))
        res = fitted.results
        self.stats["identifications"] += 1
        self.stats["last_fit_rms_um"] = max(r.fit["rms_um"] for r in res.values())
        return (f"identified on {len(rec)} samples: fit rms " +
                ", ".join(f"{a} {r.fit['rms_um']:.4f} um" for a, r in res.items()))

    def on_timer(self) -> None:
        if self.auto_cycles <= 0 or self.done_auto or len(self.buf) < 100:
            return
        vx = np.array([b[3] for b in self.buf])
        try:
            tp = segment(vx).turning_points
        except PiezoStageError:
            return
        if len(tp) // 2 >= self.auto_cycles:
            self.done_auto = True
            # on the data up to the turning point that completes the cycles, not on
            # whatever arrived by this timer tick: the same run gives the same model
            self.identify_and_report(int(tp[2 * self.auto_cycles - 1]) + 1)

    def identify_and_report(self, n: int | None = None) -> tuple[bool, str]:
        """-> (success, message); the outcome also goes to the log and diagnostics."""
        try:
            ok, message = True, self.identify(n)
            self.stats["last_error"] = ""
        except (PiezoStageError, IndexError) as e:
            ok, message = False, f"identification failed: {e}"
            self.stats["last_error"] = str(e)
        self.get_logger().info(message)
        return ok, message

    def on_identify(self, request: Trigger.Request, response: Trigger.Response
                    ) -> Trigger.Response:
        response.success, response.message = self.identify_and_report()
        return response


def main(args: list[str] | None = None) -> int:
    """Run the identifier (the Jazzy form)."""
    return run_node(Identifier, args)


if __name__ == "__main__":
    from piezo_stage.process.stopping import exit_now
    exit_now(main())  # flushed, at-exit work done, no finalization (stopping.py)
