"""The simulated stage's configuration file (config/sim_stage.yaml).

Schema (version 1)::

    piezo_stage_plant: 1
    model: stage_model.yaml          # model file, relative to this file
    internal_rate_hz: 10000
    amplifier: {slew_V_per_s: 1.0e5} # voltage limits come from the model file
    sensor: {noise_rms_um: 0.1, quantization_um: 0.005}
    seed: 0
    effects:                         # each off unless enabled: true
      creep: {enabled: false, gamma: 0.03, tau_s: [0.05, 0.5, 5, 50]}
      dynamics: {enabled: false, kind: resonance, fn_hz: 800, zeta: 0.05}
      delay: {enabled: false, delay_s: 0.0005}
      drift: {enabled: false, rate_um_per_s: 0.01, amplitude_um: 0.5, tau_s: 60}
    changes:                         # optional: the stage changing during a run
      - {at_s: 20, effects: {creep: {enabled: true, gamma: 0.06}}}
"""

from __future__ import annotations

import math
import os

from piezo_stage.core.errors import ConfigError, ModelError
from piezo_stage.core.model.effects import enabled_effects
from piezo_stage.core.model.plant import PlantConfig
from piezo_stage.io.model_file import as_number, load_model, load_yaml

SCHEMA_KEY = "piezo_stage_plant"
_TOP = (SCHEMA_KEY, "model", "internal_rate_hz", "amplifier", "sensor", "seed", "effects",
        "hysteresis", "changes", "note")


def _num(d, key, default, where, lo=-math.inf, hi=math.inf):
    """A number within [lo, hi] (booleans and strings are not numbers here)."""
    x = as_number(d.get(key, default), f"{where}.{key}", ConfigError)
    if not lo <= x <= hi:
        raise ConfigError(f"{where}.{key} = {x:g} is outside [{lo:g}, {hi:g}]")
    return float(x)


def plant_config_from_dict(doc, base_dir=".", source="plant config") -> PlantConfig:
    if not isinstance(doc, dict) or SCHEMA_KEY not in doc:
        raise ConfigError(f"{source}: not a plant config (no '{SCHEMA_KEY}' key)")
    extra = set(doc) - set(_TOP)
    if extra:
        raise ConfigError(f"{source}: unknown key(s) {sorted(extra)}")
    if "model" not in doc:
        raise ConfigError(f"{source}: 'model' (path to the model file) is required")
    mpath = doc["model"]
    if not os.path.isabs(mpath):
        mpath = os.path.join(base_dir, mpath)
    try:
        model, model_effects = load_model(mpath)
    except ModelError as e:
        raise ConfigError(str(e)) from None
    amp = doc.get("amplifier") or {}
    sensor = doc.get("sensor") or {}
    if not isinstance(amp, dict) or not isinstance(sensor, dict):
        raise ConfigError(f"{source}: amplifier and sensor must be mappings")
    effects = enabled_effects(model_effects, "model effects")
    effects.update(enabled_effects(doc.get("effects") or {}, f"{source}: effects"))
    try:
        seed = int(doc.get("seed", 0))
    except (TypeError, ValueError):
        raise ConfigError(f"{source}: seed must be an integer") from None
    hyst = doc.get("hysteresis") or {}
    if not isinstance(hyst, dict):
        raise ConfigError(f"{source}: hysteresis must be a mapping")
    if hyst:  # checked here, so a bad block fails when the file is read
        from piezo_stage.core.model.play import PlayHysteresis
        PlayHysteresis.from_params({k: v for k, v in hyst.items() if k != "axes"},
                                   f"{source}: hysteresis")
    changes = _changes(doc.get("changes"), source)
    return PlantConfig(
        changes=changes,
        model=model,
        hysteresis=dict(hyst),
        internal_rate_hz=_num(doc, "internal_rate_hz", 10_000.0, source, 1.0, 1.0e6),
        slew_V_per_s=_num(amp, "slew_V_per_s", 1.0e5, "amplifier", 1e-3, 1e9),
        noise_rms_um=_num(sensor, "noise_rms_um", 0.1, "sensor", 0.0, 1e3),
        quantization_um=_num(sensor, "quantization_um", 0.005, "sensor", 0.0, 1e3),
        effects=effects,
        seed=seed,
    )


def _changes(doc, source) -> list:
    """The ``changes`` block: a list of {at_s: seconds from the run's first sample,
    effects: an effects block whose entries replace the effect's parameters from then
    on (``enabled: false`` switches one off)}, checked, in time order."""
    if doc is None:
        return []
    if not isinstance(doc, list):
        raise ConfigError(f"{source}: changes must be a list of {{at_s, effects}}")
    out = []
    for i, c in enumerate(doc):
        where = f"{source}: changes[{i}]"
        if not isinstance(c, dict) or set(c) - {"at_s", "effects"} or "at_s" not in c:
            raise ConfigError(f"{where}: give at_s and effects (nothing else)")
        at = _num(c, "at_s", 0.0, where, 0.0, 1e7)
        from piezo_stage.core.model.effects import validate_effects
        out.append({"at_s": at, "effects": validate_effects(c.get("effects") or {},
                                                             f"{where}.effects")})
    return sorted(out, key=lambda c: c["at_s"])


def load_plant_config(path) -> PlantConfig:
    try:
        doc = load_yaml(path, "plant config")
    except ModelError as e:
        raise ConfigError(str(e)) from None
    return plant_config_from_dict(doc, os.path.dirname(os.path.abspath(path)), str(path))


def default_config_dir() -> str:
    """config/ of this package (see piezo_stage.paths)."""
    from piezo_stage.paths import config_dir
    return config_dir()


def default_plant_config_path() -> str:
    return os.path.join(default_config_dir(), "sim_stage.yaml")
