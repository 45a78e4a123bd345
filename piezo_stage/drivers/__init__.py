"""Stage backends behind the driver node: simulated, NI-DAQ, replay of a bag.

Each backend has ``rate_hz``, ``limits`` (V), ``slew_V_per_s`` and
``step(vx, vy) -> (measured {axis: um}, true {axis: um} or None, applied {axis: V})``,
advancing one control period with the voltages held, and ``close()``.
"""

from __future__ import annotations

from piezo_stage.core.errors import ConfigError


def clamp_slew(v: dict, prev: dict, limits, max_step) -> tuple[dict, bool]:
    """The driver's last line of defence: clamp to limits, then limit the step."""
    lo, hi = limits
    out, hit = {}, False
    for a, x in v.items():
        y = min(max(x, lo), hi)
        y = min(max(y, prev[a] - max_step), prev[a] + max_step)
        hit |= y != x
        out[a] = y
    return out, hit


class SimBackend:
    def __init__(self, config_path: str, rate_hz: float, seed=None):
        from piezo_stage.core.plant import Plant
        from piezo_stage.io.plant_file import default_plant_config_path, load_plant_config
        cfg = load_plant_config(config_path or default_plant_config_path())
        if seed is not None and seed >= 0:
            cfg.seed = int(seed)
        self.config = cfg
        self.plant = Plant(cfg, rate_hz)
        self.rate_hz = rate_hz
        self.limits = cfg.model.voltage_limits
        self.slew_V_per_s = cfg.slew_V_per_s

    def step(self, vx, vy):
        m = self.plant.run([vx], [vy])
        true = {a: float(x[0]) for a, x in self.plant.last_true.items()}
        return {a: float(x[0]) for a, x in m.items()}, true, {"x": vx, "y": vy}

    def close(self):
        pass


class ReplayBackend:
    """Plays a recorded bag's measurements (and applied voltages) as if live."""

    def __init__(self, bag_path: str, rate_hz: float):
        from piezo_stage.io.bag import read_bag_record
        self.rec = read_bag_record(bag_path)
        self.k = 0
        self.rate_hz = rate_hz
        self.limits = (-1e9, 1e9)
        self.slew_V_per_s = float("inf")

    @property
    def exhausted(self):
        return self.k >= len(self.rec)

    def step(self, vx, vy):
        k = min(self.k, len(self.rec) - 1)
        self.k += 1
        w = {a: float(x[k]) for a, x in self.rec.w.items()}
        v = {a: float(self.rec.v.get(a, [0.0] * len(self.rec))[k]) for a in ("x", "y")}
        return {"x": w.get("x", 0.0), "y": w.get("y", 0.0)}, None, v

    def close(self):
        pass


def make_backend(kind: str, rate_hz: float, params: dict):
    if kind == "sim":
        return SimBackend(params.get("plant_config", ""), rate_hz, params.get("seed"))
    if kind == "replay":
        if not params.get("replay_bag"):
            raise ConfigError("backend replay needs the replay_bag parameter")
        return ReplayBackend(params["replay_bag"], rate_hz)
    if kind == "daq":
        from piezo_stage.drivers.daq import DaqBackend
        return DaqBackend(rate_hz, params)
    raise ConfigError(f"unknown backend {kind!r}; use sim, daq or replay")
