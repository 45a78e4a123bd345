"""stage_driver: the stage (sim, NI-DAQ or replay) on topics; the last line of defence.

Lockstep (sim): one control period per command whose stamp is the next step, stamps in
simulated time from 0, so two runs with the same seed give identical data.
Real time: its own timer at the control rate, zero-order hold of the last command; a
stale command (older than stale_timeout_s) ramps the output to safe_voltage_V.
Commands are clamped to the voltage and slew limits; NaN/inf commands are rejected
(the last good value is held) and counted; ~/estop (std_srvs/Trigger) drives to 0 V.
"""

import time
from collections import deque

from geometry_msgs.msg import PointStamped, Vector3Stamped
from sensor_msgs.msg import JointState
from std_srvs.srv import Trigger

from piezo_stage.core.errors import DataError
from piezo_stage.drivers import DRIVER_PARAMS, clamp_slew, make_backend, step_period_summary
from piezo_stage.nodes._common import (QOS_DATA, Diagnostics, Gate, declare, hot_subscription,
                                       run, validate_choices)
from piezo_stage_msgs_adapters import joint_state_cdr, point_cdr, voltage_from_msg
import rclpy
from rclpy.duration import Duration
from rclpy.node import Node


class StageDriver(Node):
    def __init__(self):
        super().__init__("stage_driver")
        p = {key: declare(self, name, default, desc, **kw)
             for key, name, default, desc, kw in DRIVER_PARAMS}
        validate_choices(self)
        self.p = p
        self.backend = make_backend(p["backend"], p["rate"], p)
        self.dt = 1.0 / p["rate"]
        self.lo_hi = self.backend.limits
        self.max_step = self.backend.slew_V_per_s * self.dt
        self.v = {"x": max(self.lo_hi[0], 0.0), "y": max(self.lo_hi[0], 0.0)}
        self.cmd, self.cmd_time = dict(self.v), time.monotonic()
        self.k, self.t0_ns = 0, 0 if p["mode"] == "lockstep" else time.time_ns()
        self.stats = {"steps": 0, "rejected": 0, "limit_hits": 0, "stale": 0,
                      "unexpected_stamp": 0, "deadline_misses": 0, "estop": False}
        self.jpub = self.create_publisher(JointState, "joint_states", QOS_DATA)
        self.tpub = self.create_publisher(PointStamped, "sim/true_position", QOS_DATA)
        lock = p["mode"] == "lockstep"
        self.gate = Gate(self, [(self.jpub, p["min_subs"] * lock),
                                (self.tpub, p["min_rec"] * lock * (p["backend"] == "sim"))])
        if lock:  # one command per step: served by the lean loop
            hot_subscription(self, Vector3Stamped, "command", self.on_command, QOS_DATA,
                             raw=True)
        else:
            self.create_subscription(Vector3Stamped, "command", self.on_command, QOS_DATA,
                                     raw=True)
        self.create_service(Trigger, "estop", self.on_estop)
        Diagnostics(self, self.status, hardware_id=p["backend"])
        self._last_tick = time.monotonic()
        self.step_times = deque(maxlen=1_000_000)  # bounded: real-time runs go on
        if p["mode"] == "realtime":
            self.create_timer(self.dt, self.on_tick)
        self.advance(self.v)  # sample 0: the stage at rest

    def stamp(self, k):
        return self.t0_ns + int(round(k * self.dt * 1e9))

    def advance(self, v):
        done = (self.p["max_steps"] and self.k > self.p["max_steps"]) or \
            getattr(self.backend, "exhausted", False)
        if done:
            if self.p["exit_done"] and not hasattr(self, "_exit_timer"):
                self._exit_timer = self.create_timer(0.2, self.finish)
            return
        if self.stats["estop"]:
            v = {"x": 0.0, "y": 0.0}
        v, hit = clamp_slew(v, self.v, self.lo_hi, self.max_step)
        self.stats["limit_hits"] += hit
        w, true, applied = self.backend.step(v["x"], v["y"])
        self.v = v
        ns = self.stamp(self.k)
        self.gate.publish(self.jpub, joint_state_cdr(ns, w, applied))
        if true is not None:
            self.gate.publish(self.tpub, point_cdr(ns, true))
        self.k += 1
        self.stats["steps"] = self.k
        self.step_times.append(time.perf_counter())

    def on_command(self, msg):
        try:
            ns, v = voltage_from_msg(msg)
        except DataError:
            self.stats["rejected"] += 1
            v, ns = dict(self.cmd), None  # hold the last good value
        else:
            self.cmd = v
        self.cmd_time = time.monotonic()
        if self.p["mode"] == "lockstep":
            self.advance_on_command(ns)

    def advance_on_command(self, ns):
        if ns is not None and ns != self.stamp(self.k):
            self.stats["unexpected_stamp"] += 1
            return
        self.advance(self.cmd)

    def on_tick(self):
        now = time.monotonic()
        if now - self._last_tick > 1.5 * self.dt:
            self.stats["deadline_misses"] += 1
        self._last_tick = now
        target = self.cmd
        if now - self.cmd_time > self.p["stale"]:
            self.stats["stale"] += 1
            step = self.p["ramp"] * self.dt
            target = {a: min(max(self.p["safe"], x - step), x + step) for a, x in self.v.items()}
        self.advance(target)

    def finish(self):
        """All steps done: make sure every subscriber has them, then exit cleanly."""
        if self.gate.open and all(pub.wait_for_all_acked(Duration(seconds=5))
                                  for pub in (self.jpub, self.tpub)):
            self.get_logger().info(f"done after {self.k} samples: "
                                   f"{step_period_summary(list(self.step_times)[1:])}")
            rclpy.try_shutdown()

    def on_estop(self, request, response):
        self.stats["estop"] = True
        self.get_logger().warning("E-STOP: driving the stage to 0 V")
        if self.p["mode"] == "lockstep":
            self.advance({"x": 0.0, "y": 0.0})
        response.success, response.message = True, "driving to 0 V; restart to clear"
        return response

    def status(self):
        s = self.stats
        level = 2 if s["estop"] else 1 if (s["rejected"] or s["stale"]) else 0
        return level, "e-stop" if s["estop"] else "ok", {**s, "backend": self.p["backend"],
                                                          "mode": self.p["mode"],
                                                          "v_x_V": self.v["x"],
                                                          "v_y_V": self.v["y"]}

    def close(self):
        self.backend.close()


def main(args=None):
    return run(StageDriver, args)


if __name__ == "__main__":
    raise SystemExit(main())
