"""What the diagnosis writes is what it scores.

Every figure the diagnosis gives on HOLDOUT (a candidate's residual, a kept effect's
shrink, the budget) is the figure of the model ``gap --out-model`` would write for it,
run as ``simulate --model`` runs that file: the model document built and checked as a
writer builds it (``model_doc.checked_doc``: a law bounded past its fitted range where it
must be), read back by the loader's own parser, and run by the model's exact plant
(``Plant.of_model``) over HOLDOUT's voltages from the file's initial state (FIT's
start). Nothing is fitted to HOLDOUT but one constant, the record's mean offset (a
sensor's zero belongs to the record, not the model), and the first second of HOLDOUT is
run but not scored (the state at HOLDOUT's start is not FIT's when HOLDOUT was cut from
a run): ``held_out``, as ``identify``'s held-out figure (``prandtl.held_out_rms``).
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np

from piezo_stage.core.estimation.gap.candidates import AxisWritten
from piezo_stage.core.estimation.record import Record
from piezo_stage.core.model.duhem import AXES, StageModel
from piezo_stage.core.model.effects import effects_block
from piezo_stage.core.model.model_doc import checked_doc, model_from_dict
from piezo_stage.core.model.plant import Plant
from piezo_stage.core.types import Doc

START_UP_S = 1.0   # HOLDOUT's first second: run, not scored


MIN_SCORED = 200   # samples a held-out figure needs at least (diagnose's minimum)


def start_up_samples(n: int, fs_hz: float, history: int = 0) -> int:
    """The samples of a held-out record of ``n`` samples at ``fs_hz`` that are run but
    not scored: its ``history`` where it has one (a record's later part held out with
    the part before it), else its first START_UP_S (or as much of it as leaves
    MIN_SCORED samples)."""
    if history:
        return int(history)
    return int(max(0, min(round(START_UP_S * fs_hz), n - MIN_SCORED)))


def document(per_axis: Mapping[str, AxisWritten], limits_V: tuple) -> tuple[dict, list[str]]:
    """The model document of these axes, as a writer writes it (``checked_doc``) ->
    (document, notes on what was bounded past its fitted range)."""
    model = StageModel.from_fits({a: w.parts for a, w in per_axis.items()}, limits_V)
    effects = effects_block({a: w.effects for a, w in per_axis.items()})
    return checked_doc(model, effects or None)


def run_document(doc: Doc, rec: Record) -> dict[str, np.ndarray]:
    """The document read back as a model file is read and run over ``rec``'s voltages
    by its exact plant, as ``simulate --model`` runs it -> {axis: displacement [um]}
    for the axes it models. An axis ``rec`` has no voltage for rests at 0 V."""
    model, effects = model_from_dict(doc, "the model to write")
    plant = Plant.of_model(model, effects, rec.fs_hz)
    n = len(rec.t)
    lo, hi = model.voltage_limits
    rest = np.full(n, min(max(0.0, lo), hi))
    out = plant.run(rec.v.get("x", rest), rec.v.get("y", rest))
    return {a: out[a] for a in AXES if a in model.axes}


def predicted(w: AxisWritten, axis: str, rec: Record, limits_V: tuple) -> np.ndarray:
    """One axis's written model run over ``rec`` [um] (``run_document``)."""
    return run_document(document({axis: w}, limits_V)[0], rec)[axis]


def held_out(pred: np.ndarray, w: np.ndarray, skip: int) -> np.ndarray:
    """The held-out residual: ``pred - w`` after the first ``skip`` samples, its mean
    removed (the record's offset)."""
    r = (np.asarray(pred, float) - np.asarray(w, float))[skip:]
    return r - r.mean() if r.size else r
