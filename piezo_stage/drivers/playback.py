"""Playing a voltage waveform on a backend's own clock and recording what the stage did:
the ``play`` command's engine.

One function, ``play_record``, for every backend: the record that comes back has the
columns ``simulate`` writes (t, vx, vy, wx, wy), so ``identify``, ``gap`` and
``experiment`` take it whatever played it.

- ``sim``: the simulated stage (a plant config), sample-exact: what ``simulate`` does.
- ``pi``: the PI controller's wave generator and data recorder (drivers/pi.py): the
  controller's servo clock plays and records, the host only loads and reads.
- ``nv200``: each NV200's generator (1024 points) and recorder (drivers/nv200.py);
  longer waveforms are refused.
- ``daq``: NI-DAQ hardware-timed single point (drivers/daq.py): one write and one read
  per sample clock, paced by the device; a sample the host misses is counted (DAQmx's
  late-sample report) and the play fails, since the record would not be the waveform.

Hardware starts and ends at the safe voltage: the outputs ramp to the waveform's first
value at the safe ramp rate before it plays, and back after.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from piezo_stage.core.errors import BackendFault, ConfigError, DataError
from piezo_stage.core.estimation.record import Record
from piezo_stage.core.loop.backend import opened
from piezo_stage.core.types import Params, PerAxis

if TYPE_CHECKING:
    from piezo_stage.core.model.plant import PlantConfig

PLAY_BACKENDS = ("sim", "pi", "nv200", "daq")


def _check_limits(rec: Record, limits: PerAxis[tuple[float, float]]) -> None:
    for a, (lo, hi) in limits.items():
        v = rec.v[a]
        bad = np.flatnonzero((v < lo) | (v > hi))
        if bad.size:
            i = int(bad[0])
            raise DataError(f"{rec.source}: v{a} = {v[i]:g} V at line {i + 2} is outside "
                            f"the output limits [{lo:g}, {hi:g}] V")


def _check_slew(rec: Record, slew: PerAxis[float]) -> None:
    for a, s in slew.items():
        step = np.abs(np.diff(rec.v[a]))
        bad = np.flatnonzero(step > s / rec.fs_hz * (1 + 1e-9))
        if bad.size:
            i = int(bad[0])
            raise DataError(f"{rec.source}: v{a} steps {step[i]:g} V at line {i + 3}, "
                            f"beyond the slew limit {s:g} V/s at {rec.fs_hz:g} Hz")


def play_record(kind: str, rec: Record, params: Params | None = None,
                plant_config: PlantConfig | None = None,
                safe_V: float = 0.0, ramp_V_per_s: float = 500.0) -> Record:
    """Play ``rec.v`` (both axes, V) on backend ``kind`` and return the record of it:
    the voltage each sample got and the displacement measured [um].

    ``params``: the driver's backend parameters (drivers.BACKEND_PARAMS by name; the
    defaults where absent); ``plant_config``: the PlantConfig ``sim`` plays on.
    DataError when the waveform leaves the backend's output or slew limits (nothing
    played), ConfigError for a backend that cannot be set up, BackendFault when the
    hardware fails during the play.
    """
    if set(rec.v) != {"x", "y"}:
        raise DataError(f"{rec.source}: a waveform needs both vx and vy")
    if kind == "sim":
        from piezo_stage.core.model.plant import Plant
        if plant_config is None:
            raise ConfigError("backend sim needs a plant config")
        _check_limits(rec, {a: (float(plant_config.model.voltage_limits[0]),
                                float(plant_config.model.voltage_limits[1])) for a in "xy"})
        plant = Plant(plant_config, rec.fs_hz)
        w = plant.run(rec.v["x"], rec.v["y"])
        applied = {a: np.array(x) for a, x in plant.last_applied.items()}
        return Record(rec.t, applied, w, f"{rec.source} played on sim", voltage_exact=True)
    from piezo_stage.core.params import defaults
    from piezo_stage.drivers import BACKEND_PARAMS
    p = defaults(BACKEND_PARAMS)
    p.update(params or {})
    if kind in ("pi", "nv200"):
        from piezo_stage.drivers.nv200 import Nv200Backend
        from piezo_stage.drivers.pi import PiBackend
        made: PiBackend | Nv200Backend = (PiBackend if kind == "pi" else Nv200Backend)(
            rec.fs_hz, p, safe_V)
        with opened(made, safe_V) as backend:  # (play ramped to safe already)
            _check_limits(rec, backend.limits)
            _check_slew(rec, backend.slew_V_per_s)
            applied, w = backend.play(rec.v["x"], rec.v["y"], rec.fs_hz, ramp_V_per_s)
        return Record(rec.t, applied, w, f"{rec.source} played on {backend.hardware_id}",
                      voltage_exact=True)
    if kind == "daq":
        from piezo_stage.drivers.daq import DaqBackend
        with opened(DaqBackend(rec.fs_hz, p, safe_V), safe_V, ramp_V_per_s) as daq:
            _check_limits(rec, daq.limits)
            _check_slew(rec, daq.slew_V_per_s)
            step = ramp_V_per_s / rec.fs_hz
            v = {"x": safe_V, "y": safe_V}
            first = {a: float(rec.v[a][0]) for a in "xy"}
            while any(abs(v[a] - first[a]) > 1e-12 for a in v):
                v = {a: min(max(first[a], x - step), x + step) for a, x in v.items()}
                daq.step(v["x"], v["y"])
            late0 = daq.late
            n = len(rec)
            w = {a: np.empty(n) for a in "xy"}
            for k in range(n):
                m = daq.step(float(rec.v["x"][k]), float(rec.v["y"][k])).measured
                w["x"][k], w["y"][k] = m["x"], m["y"]
            if daq.late > late0:
                raise BackendFault(f"the host missed {daq.late - late0} sample clocks "
                                   f"of {n}: the record is not the waveform (play it at a "
                                   "lower rate)")
        return Record(rec.t, dict(rec.v), w, f"{rec.source} played on {daq.hardware_id}",
                      voltage_exact=True)
    raise ConfigError(f"unknown backend {kind!r}; use {', '.join(PLAY_BACKENDS)}")
