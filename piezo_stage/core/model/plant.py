"""Simulated 2-axis piezo stage.

Signal path per axis, at the internal rate (10 kHz by default)::

    command (zero-order hold) -> amplifier (clamp, slew) -> Duhem hysteresis
    (+ the model's play operators) + coupling from the other axis -> creep
    -> dynamics -> drift -> delay -> sensor (noise, quantisation) -> sampled at the command rate

``hysteresis`` (a plant option) replaces the Duhem law on the axes it names with a
law that is not our model class (core/model/play.py: play operators with return-point
memory and a tanh envelope); the coupling and everything after stay.

Every unmodelled effect is off unless configured. A run is deterministic for a given
seed, and running a record in one batch or in any chunking (down to one command at a
time, as the lockstep driver does) gives identical output.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike

from piezo_stage.core._jit import as_f64
from piezo_stage.core.errors import ConfigError
from piezo_stage.core.model._kernels import plant_run, sensor_run
from piezo_stage.core.model.duhem import AXES, StageModel
from piezo_stage.core.model.effects import (
    EFFECTS,
    effects_on,
    enabled_effects,
    make_effect,
    sampled_pair,
)
from piezo_stage.core.model.play import PlayHysteresis
from piezo_stage.core.types import EffectsBlock, Params, PerAxis

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
    hysteresis : dict
        {} for the model file's Duhem law; else core/model/play.py's parameters (plus
        'axes'): that law replaces the Duhem one on those axes.
    seed : int
        Seed of the sensor-noise generator.
    changes : list
        The stage changing during a run: [{at_s, effects}] in time order, each
        effects block replacing the named effects' parameters from the first command
        at or after ``at_s`` seconds of the run (``enabled: false`` switches one
        off); an effect switched on or changed starts at rest at the hysteresis's
        output then.
    """

    model: StageModel
    internal_rate_hz: float = 10_000.0
    slew_V_per_s: float = 1.0e5
    noise_rms_um: float = 0.1
    quantization_um: float = 0.005
    effects: EffectsBlock = field(default_factory=dict)
    seed: int = 0
    hysteresis: Params = field(default_factory=dict)
    changes: list = field(default_factory=list)

    def __post_init__(self) -> None:
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
    def exact(cls, model: StageModel, rate_hz: float,
              effects: EffectsBlock | None = None) -> "PlantConfig":
        """The model and nothing else: no noise, slew or quantisation; with
        ``effects`` (a model file's block) the enabled ones."""
        return cls(model, internal_rate_hz=rate_hz, slew_V_per_s=np.inf,
                   noise_rms_um=0.0, quantization_um=0.0,
                   effects=enabled_effects(effects) if effects else {})


class Plant:
    """A simulated stage driven at ``command_rate_hz`` (zero-order hold).

    ``run(vx, vy)`` advances one command per element; ``step(vx, vy)`` advances one.
    Both return measured displacement [um] per axis; ``last_true`` holds the
    noise-free displacement of the last call, and with ``keep_fine`` set
    ``last_true_fine`` the same at the internal rate (between the command samples).
    """

    @classmethod
    def of_model(cls, model: StageModel, effects: EffectsBlock | None,
                 rate_hz: float) -> "Plant":
        """The exact plant of a model (its twin: the model and its enabled ``effects``,
        no noise, slew or quantisation) driven at ``rate_hz``: the one way a model is
        simulated as a stage (simulate --model, the gap node, the studies)."""
        return cls(PlantConfig.exact(model, rate_hz, effects), rate_hz)

    def __init__(self, config: PlantConfig, command_rate_hz: float) -> None:
        if not command_rate_hz > 0:
            raise ConfigError("command rate must be > 0")
        self.config = config
        self.command_rate_hz = float(command_rate_hz)
        self.substeps = max(1, int(round(config.internal_rate_hz / command_rate_hz)))
        self.fs_hz = self.command_rate_hz * self.substeps
        lo, hi = config.model.voltage_limits
        self.v_limits = (float(lo), float(hi))
        self._max_step = config.slew_V_per_s / self.fs_hz
        self._effects: dict[str, list] = {a: [] for a in AXES}
        unknown = set(config.effects) - set(EFFECT_ORDER)
        if unknown:
            raise ConfigError(f"unknown effect(s) {sorted(unknown)}; known: "
                              f"{', '.join(EFFECTS)}")
        for name, p in config.effects.items():
            for e in p if isinstance(p, list) else [p]:
                bad = [a for a in (e or {}).get("axes", ()) if a not in AXES]
                if bad:
                    raise ConfigError(f"effect {name}: unknown axis {bad[0]!r}")
        self._effect_params = dict(config.effects)  # as they stand (``changes``)
        self._build_effects(None)
        self._play = {}
        if config.hysteresis:
            params = dict(config.hysteresis)
            for a in params.pop("axes", list(AXES)):
                if a not in AXES:
                    raise ConfigError(f"hysteresis: unknown axis {a!r}")
                self._play[a] = PlayHysteresis.from_params(params)
        self._kernel_params()
        self.reset()

    # the compiled plant's models, in its order: axis x, axis y, coupling into x (driven
    # by y), coupling into y (driven by x)
    _MODELS = (("x", "axis"), ("y", "axis"), ("x", "coupling"), ("y", "coupling"))

    def _kernel_params(self) -> None:
        """The models as ``plant_run`` takes them, and the plant's state arrays."""
        model = self.config.model
        self._models = [model.axes.get(a) if kind == "axis" else
                        (model.coupling.get(a) if a in model.axes else None)
                        for a, kind in self._MODELS]
        kp = [m.kernel_params() if m is not None else None for m in self._models]
        d = max([p[1].shape[1] for p in kp if p is not None] or [1])
        self._alpha, self._H = np.zeros((4, 2)), np.zeros((4, 2, d))
        self._present = np.array([p is not None for p in kp])
        for i, a in enumerate(AXES):  # another law in place of the Duhem one
            if a in self._play:
                self._present[i] = False
        for i, p in enumerate(kp):
            if p is not None:  # zero high-order padding leaves Horner's sums exact
                self._alpha[i] = p[0]
                self._H[i, :, :p[1].shape[1]] = p[1]
        self._vstate, self._dstate = np.zeros(2), np.zeros((4, 2))
        self._has_effects = any(self._effects[a] for a in AXES)
        self._one = np.zeros((2, 1))  # step's command buffer

    def _build_effects(self, at_rest: PerAxis[float] | None) -> None:
        """Each axis's effects from the parameters as they stand (the one reading of
        the block per axis: effects_on); with ``at_rest`` ({axis: um}), only those
        whose parameters changed are built again, at rest there."""
        old = getattr(self, "_on", {})
        self._on = {}
        for a in AXES:
            on = sampled_pair(effects_on(self._effect_params, a), self.fs_hz)
            self._on[a] = on
            kept = {type(e).__name__.lower(): e for e in self._effects.get(a, [])}
            built = []
            for n in EFFECT_ORDER:
                if n not in on:
                    continue
                if at_rest is not None and old.get(a, {}).get(n) == on[n] and n in kept:
                    built.append(kept[n])
                    continue
                e = make_effect(n, self.fs_hz, on[n])
                if at_rest is not None:
                    e.reset(at_rest[a])
                built.append(e)
            self._effects[a] = built
        self._has_effects = any(self._effects[a] for a in AXES)

    def warm(self) -> None:
        """Compile (or load from the cache) every kernel this plant will run, its
        scheduled changes' too, on a copy: a change's first use otherwise stalls the
        sample it comes at (0.5 s here: a real-time driver faulted on stale commands).
        The plant itself is not stepped."""
        import dataclasses
        now = [dict(c, at_s=0.0) for c in self.config.changes]
        Plant(dataclasses.replace(self.config, changes=now), self.command_rate_hz).step(
            0.0, 0.0)

    def _apply_change(self, change: Params) -> None:
        """A scheduled change (PlantConfig.changes) from now on."""
        for name, p in change["effects"].items():
            if isinstance(p, dict) and not p.get("enabled", True):
                self._effect_params.pop(name, None)
            else:
                self._effect_params[name] = p
        self._build_effects(dict(self._h_last))

    def reset(self) -> None:
        """Back to rest: initial hysteresis states, 0 V applied, effects at rest."""
        model = self.config.model
        self._vstate[:] = max(self.v_limits[0], min(self.v_limits[1], 0.0))
        for i, m in enumerate(self._models):
            self._dstate[i] = (m.initial.v, m.initial.w) if m is not None else (0.0, 0.0)
        for a in AXES:  # at rest at the hysteresis's initial output (its plays' and
            x0 = model.axes[a].initial.w if a in model.axes else 0.0  # coupling's too)
            if a in model.plays:
                x0 += model.plays[a].output(model.plays[a].state())
            if a in model.axes and a in model.coupling:
                x0 += model.coupling[a].initial.w
            for e in self._effects[a]:
                e.reset(x0)
        self._z = {a: law.rest(self._vstate[i]) for i, a in enumerate(AXES)
                   if (law := self._play.get(a)) is not None}
        self._rate = {a: law.rate_state(self._vstate[i]) for i, a in enumerate(AXES)
                      if (law := self._play.get(a)) is not None}
        self._mz = {a: p.state() for a, p in model.plays.items()}
        # (the operators' rate filter at rest at the law's initial voltage, as its state:
        # play_columns' start, where a model's operators were fitted from)
        self._mq = {a: np.array([model.axes[a].initial.v if a in model.axes else
                                 self._vstate[AXES.index(a)], 0.0]) for a in model.plays}
        self._rng = np.random.default_rng(self.config.seed)
        if self.config.changes:  # back to the effects before any change
            self._effect_params = dict(self.config.effects)
            self._build_effects(None)
        self._pending = [(int(np.ceil(c["at_s"] * self.command_rate_hz - 1e-9)), c)
                         for c in self.config.changes]
        self._h_last = {a: 0.0 for a in AXES}  # the hysteresis's last output [um]
        self.limit_hits = 0
        self.samples = 0
        self.last_true = {a: np.zeros(0) for a in AXES}
        self.keep_fine = False
        self.last_true_fine = {a: np.zeros(0) for a in AXES}
        self.last_applied = {a: np.zeros(0) for a in AXES}

    def run(self, vx: ArrayLike, vy: ArrayLike) -> dict[str, np.ndarray]:
        """Apply command arrays [V] (one element per command period).

        Returns
        -------
        dict axis -> ndarray [um]
            Measured displacement at the end of each command period.
        """
        vx = np.atleast_1d(as_f64(vx))
        vy = np.atleast_1d(as_f64(vy))
        if vx.shape != vy.shape:
            raise ConfigError("vx and vy must have the same length")
        meas = self._advance(vx, vy)
        return {a: meas[i] for i, a in enumerate(AXES)}

    def step(self, vx: float, vy: float) -> tuple[float, float]:
        """One command period; returns (wx, wy) measured [um]: ``run`` on one command,
        through buffers kept for it (the lockstep driver calls this per sample)."""
        c = self._one
        c[0, 0], c[1, 0] = vx, vy
        meas = self._advance(c[0], c[1])
        return float(meas[0, 0]), float(meas[1, 0])

    def _advance(self, vx: np.ndarray, vy: np.ndarray) -> np.ndarray:
        """The plant over commands vx, vy (a scheduled change splits them where it
        comes): hysteresis path, effects, sensor; returns the measured (2, n) [um] and
        keeps the true and applied values of the call."""
        if self._pending and self._pending[0][0] < self.samples + vx.size:
            k = max(0, self._pending[0][0] - self.samples)
            parts, trues, fines, applied = [], [], [], []
            if k:
                parts.append(self._advance(vx[:k], vy[:k]))
                trues.append(self.last_true)
                fines.append(self.last_true_fine)
                applied.append(self.last_applied)
            self._apply_change(self._pending.pop(0)[1])
            parts.append(self._advance(vx[k:], vy[k:]))
            trues.append(self.last_true)
            fines.append(self.last_true_fine)
            applied.append(self.last_applied)
            self.last_true = {a: np.concatenate([t[a] for t in trues]) for a in AXES}
            self.last_applied = {a: np.concatenate([t[a] for t in applied]) for a in AXES}
            if self.keep_fine:
                self.last_true_fine = {a: np.concatenate([t[a] for t in fines])
                                       for a in AXES}
            return np.concatenate(parts, axis=1)
        return self._advance_plain(vx, vy)

    def _advance_plain(self, vx: np.ndarray, vy: np.ndarray) -> np.ndarray:
        """``_advance`` with no change within the commands."""
        n, R = vx.size, self.substeps
        applied, w = np.empty((2, n * R)), np.empty((2, n * R))
        self.limit_hits += plant_run(vx, vy, R, self._vstate, self._dstate, self._alpha,
                                     self._H, self._present, self.v_limits[0],
                                     self.v_limits[1], self._max_step, applied, w)
        for i, a in enumerate(AXES):
            if a in self._play:  # (a rate-dependent law: the voltage before, and dt)
                w[i] += self._play[a].run(applied[i], self._z[a], 1.0 / self.fs_hz,
                                          self._rate[a])
            elif a in self._mz:  # the model's own play operators, beside its Duhem law
                w[i] += self.config.model.plays[a].run(applied[i], self._mz[a],
                                                       1.0 / self.fs_hz, self._mq[a])
        if w.shape[1]:
            self._h_last = {"x": float(w[0, -1]), "y": float(w[1, -1])}
        fine = w
        if self._has_effects:
            fine = np.empty_like(w)
            for i, a in enumerate(AXES):
                y = w[i]
                for e in self._effects[a]:
                    y = e.process(y)
                fine[i] = y
        true = fine[:, R - 1::R]
        if self.keep_fine:
            self.last_true_fine = {"x": fine[0].copy(), "y": fine[1].copy()}
        cfg = self.config
        noise = (self._rng.standard_normal((n, 2)) if cfg.noise_rms_um > 0 else
                 np.zeros((n, 2)))
        meas = np.empty((2, n))
        sensor_run(true, noise, cfg.noise_rms_um, cfg.quantization_um, meas)
        self.samples += n
        self.last_true = {"x": true[0], "y": true[1]}
        self.last_applied = {"x": applied[0, R - 1::R], "y": applied[1, R - 1::R]}
        return meas
