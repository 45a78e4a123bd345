"""Stage backends behind the driver node: simulated, NI-DAQ, PI controller, NV200
amplifiers, replay of a bag.

Each is a core.loop.backend.Backend (what the sample loop asks of a stage) whose
``step(vx, vy)`` returns a StepResult.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import TYPE_CHECKING

from piezo_stage.core.errors import ConfigError
from piezo_stage.core.loop.backend import Backend, StepResult
from piezo_stage.core.params import Param, Schema
from piezo_stage.core.types import Params
from piezo_stage.drivers.daq import DAQ_PARAMS
from piezo_stage.drivers.nv200 import NV200_PARAMS
from piezo_stage.drivers.pi import PI_PARAMS

if TYPE_CHECKING:
    from piezo_stage.core.loop.sample_loop import SampleLoop

# The backends' configuration (core/params.py): the driver declares it read-only.
BACKEND_PARAMS: Schema = (
    Param("plant_config", "", "sim: plant YAML ('' = the package's config/sim_stage.yaml)"),
    Param("seed", -1, "sim: noise seed (-1: the plant config's)"),
    Param("replay_bag", "", "replay: the bag to play"),
) + DAQ_PARAMS + PI_PARAMS + NV200_PARAMS


def step_period_summary(times: Sequence[float]) -> str:
    """Steps/s, median and p99 step period of a list of step times [s]."""
    import numpy as np
    d = np.diff(times)
    if d.size == 0:
        return "no steps timed"
    return (f"{1 / d.mean():.0f} steps/s, step period median {1e3 * np.median(d):.3f} ms, "
            f"p99 {1e3 * np.percentile(d, 99):.3f} ms")


def done_line(loop: SampleLoop, acked_s: float) -> str:
    """A lockstep run's last line: the samples of ``loop`` (a core SampleLoop), their
    step period, and how long its readers took to acknowledge the last of them."""
    return (f"done after {loop.j + 1} samples: "
            f"{step_period_summary(list(loop.step_times)[1:])}; "
            f"acknowledged in {acked_s * 1e3:.0f} ms")


class SimBackend:
    paced = False  # the driver paces it (lockstep: by commands; real time: wall clock)
    exhausted = False  # never runs out

    def __init__(self, config_path: str, rate_hz: float, seed: int | None = None) -> None:
        from piezo_stage.core.model.plant import Plant
        from piezo_stage.io.plant_file import default_plant_config_path, load_plant_config
        cfg = load_plant_config(config_path or default_plant_config_path())
        if seed is not None and seed >= 0:
            cfg.seed = int(seed)
        self.config = cfg
        self.plant = Plant(cfg, rate_hz)
        self.plant.warm()  # the kernels compiled now, not at the first tick or a change
        self.rate_hz = rate_hz
        self.limits = {a: tuple(cfg.model.voltage_limits) for a in ("x", "y")}
        self.slew_V_per_s = {a: cfg.slew_V_per_s for a in ("x", "y")}
        self.hardware_id = f"sim seed {cfg.seed} ({config_path or 'sim_stage.yaml'})"

    def step(self, vx: float, vy: float) -> StepResult:
        mx, my = self.plant.step(vx, vy)
        true = {a: float(x[0]) for a, x in self.plant.last_true.items()}
        return StepResult({"x": mx, "y": my}, {"x": vx, "y": vy}, true)

    def start(self) -> None:
        pass  # the driver paces the simulation

    def close(self, safe_V: float = 0.0, ramp_V_per_s: float = 0.0) -> None:
        pass  # nothing stays energised


class ReplayBackend:
    """Plays a recorded bag's measurements (and applied voltages) as if live."""
    paced = False

    def __init__(self, bag_path: str, rate_hz: float) -> None:
        from piezo_stage.io.bag import read_bag_record
        self.rec = read_bag_record(bag_path)
        self.k = 0
        self.rate_hz = rate_hz
        self.limits = {a: (-1e9, 1e9) for a in ("x", "y")}
        self.slew_V_per_s = {a: float("inf") for a in ("x", "y")}
        self.hardware_id = f"replay of {bag_path}"

    @property
    def exhausted(self) -> bool:
        return self.k >= len(self.rec)

    def step(self, vx: float, vy: float) -> StepResult:
        k = min(self.k, len(self.rec) - 1)
        self.k += 1
        w = {a: float(x[k]) for a, x in self.rec.w.items()}
        v = {a: float(self.rec.v.get(a, [0.0] * len(self.rec))[k]) for a in ("x", "y")}
        return StepResult({"x": w.get("x", 0.0), "y": w.get("y", 0.0)}, v)

    def start(self) -> None:
        pass

    def close(self, safe_V: float = 0.0, ramp_V_per_s: float = 0.0) -> None:
        pass


def make_backend(kind: str, rate_hz: float, params: Params, safe_V: float = 0.0) -> Backend:
    if kind == "sim":
        return SimBackend(params.get("plant_config", ""), rate_hz, params.get("seed"))
    if kind == "replay":
        if not params.get("replay_bag"):
            raise ConfigError("backend replay needs the replay_bag parameter")
        return ReplayBackend(params["replay_bag"], rate_hz)
    if kind == "daq":
        from piezo_stage.drivers.daq import DaqBackend
        return DaqBackend(rate_hz, params, safe_V)
    if kind == "pi":
        from piezo_stage.drivers.pi import PiBackend
        return PiBackend(rate_hz, params, safe_V)
    if kind == "nv200":
        from piezo_stage.drivers.nv200 import Nv200Backend
        return Nv200Backend(rate_hz, params, safe_V)
    raise ConfigError(f"unknown backend {kind!r}; use sim, daq, pi, nv200 or replay")
