"""Stage backends behind the driver node: simulated, NI-DAQ, replay of a bag.

Each backend has ``rate_hz``, ``limits`` (V), ``slew_V_per_s`` and
``step(vx, vy) -> (measured {axis: um}, true {axis: um} or None, applied {axis: V})``,
advancing one control period with the voltages held, and ``close()``.
"""

from __future__ import annotations

from piezo_stage.core.errors import ConfigError


RO = {"read_only": True}
# The driver node's parameters: (key, name, default, description with unit, limits)
DRIVER_PARAMS = (
    ("backend", "backend", "sim", "sim | daq | replay", {**RO, "choices": ("sim", "daq", "replay")}),
    ("mode", "mode", "lockstep", "lockstep (sim) | realtime",
     {**RO, "choices": ("lockstep", "realtime")}),
    ("rate", "control_rate_hz", 1000.0, "control rate [Hz]", {**RO, "lo": 1.0, "hi": 1e5}),
    ("plant_config", "plant_config", "", "sim plant YAML ('' = default)", RO),
    ("seed", "seed", -1, "sim noise seed (-1: the config's)", RO),
    ("replay_bag", "replay_bag", "", "bag for the replay backend", RO),
    ("stale", "stale_timeout_s", 0.05, "real time: command age that counts as stale [s]",
     {"lo": 0.001, "hi": 10.0}),
    ("safe", "safe_voltage_V", 0.0, "output after a stale command [V]", {"lo": -200.0, "hi": 200.0}),
    ("ramp", "safe_ramp_V_per_s", 500.0, "ramp rate to the safe voltage [V/s]",
     {"lo": 1.0, "hi": 1e6}),
    ("max_steps", "max_steps", 0, "stop after this many steps (0: never)", {}),
    ("min_subs", "min_subscribers", 0, "lockstep: joint_states subscribers to wait for", {}),
    ("min_rec", "min_record_subscribers", 0, "lockstep: true_position subscribers to wait "
     "for (recorders)", {}),
    ("exit_done", "exit_after_max_steps", False, "exit (code 0) once max_steps are done "
     "and delivered", {}),
    ("ao_channels", "ao_channels", "Dev1/ao0,Dev1/ao1", "NI-DAQ output channels x,y", RO),
    ("ai_channels", "ai_channels", "Dev1/ai0,Dev1/ai1", "NI-DAQ input channels x,y", RO),
    ("amplifier_gain", "amplifier_gain", 15.0, "NI-DAQ: amplifier gain [V/V]", RO),
    ("sensor_um_per_V", "sensor_um_per_V", 10.0, "NI-DAQ: sensor scale [um/V]", RO),
    ("sensor_offset_um", "sensor_offset_um", 0.0, "NI-DAQ: sensor offset [um]", RO),
)


def step_period_summary(times) -> str:
    """Steps/s, median and p99 step period of a list of step times [s]."""
    import numpy as np
    d = np.diff(times)
    if d.size == 0:
        return "no steps timed"
    return (f"{1 / d.mean():.0f} steps/s, step period median {1e3 * np.median(d):.3f} ms, "
            f"p99 {1e3 * np.percentile(d, 99):.3f} ms")


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
        mx, my = self.plant.step(vx, vy)
        true = {a: float(x[0]) for a, x in self.plant.last_true.items()}
        return {"x": mx, "y": my}, true, {"x": vx, "y": vy}

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
