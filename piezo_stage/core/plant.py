"""Simulated 2-axis piezo stage.

Signal path per axis, at the internal rate (10 kHz by default)::

    command (zero-order hold) -> amplifier (clamp, slew) -> Duhem hysteresis
    + coupling from the other axis -> creep -> dynamics -> drift -> delay
    -> sensor (noise, quantisation) -> sampled at the command rate

Every unmodelled effect is off unless configured. A run is deterministic for a given
seed, and running a record in one batch or in any chunking (down to one command at a
time, as the lockstep driver does) gives identical output.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from piezo_stage.core._jit import as_f64, plant_step, slew_clamp_run
from piezo_stage.core.duhem import AXES, DuhemState, StageModel
from piezo_stage.core.effects import EFFECTS, make_effect
from piezo_stage.core.errors import ConfigError

# Order in which effects act on the displacement (see module docstring).
EFFECT_ORDER = ("creep", "dynamics", "drift", "delay")
assert set(EFFECT_ORDER) == set(EFFECTS)


@dataclass
class PlantConfig:
    """Everything that defines a simulated stage.

    Attributes
    ----------
    model : StageModel
        Hysteresis and coupling per axis; its voltage limits are the amplifier's.
    internal_rate_hz : float
        Rate of the plant's own integration [Hz].
    slew_V_per_s : float
        Amplifier slew-rate limit [V/s] (inf for none).
    noise_rms_um, quantization_um : float
        Sensor white noise RMS and resolution [um] (0 for none).
    effects : dict
        effect name -> parameter dict (plus optional 'axes': ['x', 'y']); only the
        effects listed here are on.
    seed : int
        Seed of the sensor-noise generator.
    """

    model: StageModel
    internal_rate_hz: float = 10_000.0
    slew_V_per_s: float = 1.0e5
    noise_rms_um: float = 0.1
    quantization_um: float = 0.005
    effects: dict = field(default_factory=dict)
    seed: int = 0

    def __post_init__(self):
        if not self.internal_rate_hz > 0:
            raise ConfigError("internal_rate_hz must be > 0")
        if not self.slew_V_per_s > 0:
            raise ConfigError("slew_V_per_s must be > 0")
        if self.noise_rms_um < 0 or self.quantization_um < 0:
            raise ConfigError("noise_rms_um and quantization_um must be >= 0")
        for name in self.effects:
            if name not in EFFECTS:
                raise ConfigError(f"unknown effect {name!r}; known: {', '.join(EFFECTS)}")

    @classmethod
    def exact(cls, model: StageModel, rate_hz: float) -> "PlantConfig":
        """The model and nothing else: no noise, slew, quantisation or effects."""
        return cls(model, internal_rate_hz=rate_hz, slew_V_per_s=np.inf,
                   noise_rms_um=0.0, quantization_um=0.0)


class Plant:
    """A simulated stage driven at ``command_rate_hz`` (zero-order hold).

    ``run(vx, vy)`` advances one command per element; ``step(vx, vy)`` advances one.
    Both return measured displacement [um] per axis; ``last_true`` holds the
    noise-free displacement of the last call.
    """

    def __init__(self, config: PlantConfig, command_rate_hz: float):
        if not command_rate_hz > 0:
            raise ConfigError("command rate must be > 0")
        self.config = config
        self.command_rate_hz = float(command_rate_hz)
        self.substeps = max(1, int(round(config.internal_rate_hz / command_rate_hz)))
        self.fs_hz = self.command_rate_hz * self.substeps
        lo, hi = config.model.voltage_limits
        self.v_limits = (float(lo), float(hi))
        self._max_step = config.slew_V_per_s / self.fs_hz
        self._effects = {a: [] for a in AXES}
        unknown = set(config.effects) - set(EFFECT_ORDER)
        if unknown:
            raise ConfigError(f"unknown effect(s) {sorted(unknown)}; known: "
                              f"{', '.join(EFFECTS)}")
        for name in EFFECT_ORDER:
            if name not in config.effects:
                continue
            params = dict(config.effects[name] or {})
            axes = params.pop("axes", list(AXES))
            for a in axes:
                if a not in AXES:
                    raise ConfigError(f"effect {name}: unknown axis {a!r}")
                self._effects[a].append(make_effect(name, self.fs_hz, params))
        self.reset()

    def reset(self):
        """Back to rest: initial hysteresis states, 0 V applied, effects at rest."""
        model = self.config.model
        self._states = {}
        for a, m in model.axes.items():
            self._states[a] = m.initial
            if a in model.coupling:
                self._states["c" + a] = model.coupling[a].initial
        self._v = {a: max(self.v_limits[0], min(self.v_limits[1], 0.0)) for a in AXES}
        for a in AXES:
            x0 = model.axes[a].initial.w if a in model.axes else 0.0
            for e in self._effects[a]:
                e.reset(x0)
        self._rng = np.random.default_rng(self.config.seed)
        self.limit_hits = 0
        self.samples = 0
        self._live = False  # True while the compiled step's arrays hold the state
        self.last_true = {a: np.zeros(0) for a in AXES}
        self.last_applied = {a: np.zeros(0) for a in AXES}

    def run(self, vx, vy):
        """Apply command arrays [V] (one element per command period).

        Returns
        -------
        dict axis -> ndarray [um]
            Measured displacement at the end of each command period.
        """
        if self._live:
            self._from_arrays()
        vx = np.atleast_1d(as_f64(vx))
        vy = np.atleast_1d(as_f64(vy))
        if vx.shape != vy.shape:
            raise ConfigError("vx and vy must have the same length")
        n = vx.size
        R = self.substeps
        applied = {}
        for a, v in (("x", vx), ("y", vy)):
            up = np.repeat(v, R) if R > 1 else v
            out = np.empty_like(up)
            self._v[a], hits = slew_clamp_run(up, self._v[a], self.v_limits[0],
                                              self.v_limits[1], self._max_step, out)
            self.limit_hits += hits
            applied[a] = out
        w, self._states = self.config.model.simulate(applied["x"], applied["y"],
                                                     self._states)
        cfg = self.config
        noise = self._rng.standard_normal((n, 2)) if cfg.noise_rms_um > 0 else None
        meas, true = {}, {}
        for i, a in enumerate(AXES):
            y = w.get(a, np.zeros(n * R))
            for e in self._effects[a]:
                y = e.process(y)
            y = y[R - 1::R]
            true[a] = y
            m = y + cfg.noise_rms_um * noise[:, i] if noise is not None else y.copy()
            if cfg.quantization_um > 0:
                m = np.round(m / cfg.quantization_um) * cfg.quantization_um
            meas[a] = m
        self.samples += n
        self.last_true = true
        self.last_applied = {a: applied[a][R - 1::R] for a in AXES}
        return meas

    def step(self, vx: float, vy: float):
        """One command period; returns (wx, wy) measured [um]. Without effects this
        runs one compiled kernel (a few us, what the lockstep driver needs per
        sample) with exactly the arithmetic of ``run``; with effects it is ``run``."""
        k = self._kernel()
        if k is None:
            m = self.run([vx], [vy])
            return float(m["x"][0]), float(m["y"][0])
        if not self._live:
            self._to_arrays()
        cfg = self.config
        noise = self._rng.standard_normal(2) if cfg.noise_rms_um > 0 else k["zero"]
        out = k["out"]
        self.limit_hits += plant_step(float(vx), float(vy), k["v"], k["d"], k["alpha"],
                                      k["H"], k["present"], self.substeps,
                                      self.v_limits[0], self.v_limits[1], self._max_step,
                                      noise, cfg.noise_rms_um, cfg.quantization_um, out)
        self.samples += 1
        self.last_true = {"x": out[2:3].copy(), "y": out[3:4].copy()}
        self.last_applied = {"x": out[4:5].copy(), "y": out[5:6].copy()}
        return float(out[0]), float(out[1])

    _MODELS = (("x", "axis"), ("y", "axis"), ("cx", "coupling"), ("cy", "coupling"))

    def _kernel(self):
        """Parameters of the compiled step (None when an effect is on), built once."""
        k = self.__dict__.get("_k", False)
        if k is not False:
            return k
        k = None
        if not any(self._effects[a] for a in AXES):
            model = self.config.model
            ms = [model.axes.get(n) if kind == "axis" else
                  (model.coupling.get(n[1]) if n[1] in model.axes else None)
                  for n, kind in self._MODELS]
            kp = [m.kernel_params() if m is not None else None for m in ms]
            d = max([p[1].shape[1] for p in kp if p is not None] or [1])
            k = {"alpha": np.zeros((4, 2)), "H": np.zeros((4, 2, d)),
                 "present": np.array([p is not None for p in kp]), "v": np.zeros(2),
                 "d": np.zeros((4, 2)), "out": np.zeros(6), "zero": np.zeros(2)}
            for i, p in enumerate(kp):
                if p is not None:  # zero high-order padding leaves Horner's sums exact
                    k["alpha"][i] = p[0]
                    k["H"][i, :, :p[1].shape[1]] = p[1]
        self._k = k
        return k

    def _to_arrays(self):
        k = self._k
        for i, a in enumerate(AXES):
            k["v"][i] = self._v[a]
        for i, (n, _) in enumerate(self._MODELS):
            st = self._states.get(n)
            if st is not None:
                k["d"][i] = (st.v, st.w)
        self._live = True

    def _from_arrays(self):
        k = self._k
        for i, a in enumerate(AXES):
            self._v[a] = float(k["v"][i])
        for i, (n, _) in enumerate(self._MODELS):
            if n in self._states:
                self._states[n] = DuhemState(float(k["d"][i, 0]), float(k["d"][i, 1]))
        self._live = False
