"""The model document: one YAML schema (what the simulator, the inverse, identification
and the model message share), parsed bounded and checked, to and from the model.

Schema (version 1)::

    piezo_stage_model: 1
    convention: seed-eq6        # w_k (1 + alpha|dv|) = w_{k-1} + |dv| f(v_k) + dv g(v_k)
    units: {voltage: V, displacement: um, alpha: 1/V, f: um/V, g: um/V}
    voltage_limits_V: [0.0, 150.0]
    axes:
      x:
        structure: whole | segmented
        initial_state: {v_V: 0.0, w_um: 0.0}
        fitted_range_V: [lo, hi]  # optional: the input range the branches were fitted
                                  #   on; well past it each branch polynomial continues
                                  #   straight from its end (duhem.branch_values)
        continued_past_fit: level # optional: past it the branches go on at their
                                  #   end's value instead (a law fitted on a small part
                                  #   of the voltage limits: bounded_past_fit)
        # whole:      alpha, f, g at this level
        # segmented:  ascending: {alpha, f, g} and descending: {alpha, f, g}
        #             or, when only the identifiable combination is known,
        #             ascending: {alpha, h} (h = f + g), descending: {alpha, h} (h = g - f)
        coupling:               # optional: displacement on x caused by the y voltage
          structure: whole
          alpha: ...
          f: [...]
          g: [...]
        play_operators:         # optional: return-point memory, sum_j p_j z_j added to
          thresholds_V: [...]   #   the Duhem output (core/model/play.py); r_j >= 0
          weights_um_per_V: [...]
          initial_V: [...]      #   z_j at the start (default: at rest at initial_state)
          rate_widening_s: 0.0  #   optional beta [s], < 1.9 ms: thresholds r_j + beta
                                #   |dv/dt| (low-passed over 2 ms): a loop that widens
                                #   with the input's rate (the gap diagnosis's `rate`)
          bands_V: [[lo, hi], ...]  # optional: operator j's output is z_j clipped to
                                #   [lo, hi] (a discretized Preisach law, --class preisach)
      y: ...
    effects: {}                 # optional unmodelled effects (see core/model/effects.py)

Coefficients are lowest power first. Unknown keys are rejected so a typo is not
silently ignored.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np
from numpy.typing import ArrayLike

from piezo_stage.core.errors import ConfigError, ModelError
from piezo_stage.core.model.duhem import (
    AXES,
    CONTINUATIONS,
    AxisParts,
    DuhemBranch,
    DuhemModel,
    DuhemState,
    StageModel,
    polynomial_range,
)
from piezo_stage.core.model.effects import validate_effects
from piezo_stage.core.model.play import MAX_OPERATORS, PlayOperators
from piezo_stage.core.types import Doc, EffectsBlock, PerAxis
from piezo_stage.core.yaml_text import (  # noqa: F401 - the document's names, as before
    MAX_YAML_BYTES,
    MAX_YAML_DEPTH,
    parse_yaml,
)

SCHEMA_KEY = "piezo_stage_model"


SCHEMA_VERSION = 1


def as_number(x: object, where: str, error: type = ModelError) -> float:
    """A finite real number. Booleans are not numbers here; a string is one only when
    it reads as a number (YAML 1.1 reads ``1e-3`` and ``1.0e6`` as strings)."""
    if isinstance(x, bool) or not isinstance(x, (int, float, str)):
        raise error(f"{where}: expected a number, got {x!r}")
    try:
        v = float(x)
    except ValueError:
        raise error(f"{where}: expected a number, got {x!r}") from None
    if not np.isfinite(v):
        raise error(f"{where}: not finite")
    return v


_number = as_number


def _numbers(xs: Any, where: str) -> list[float]:
    if not isinstance(xs, (list, tuple)) or not xs:
        raise ModelError(f"{where}: expected a list of numbers")
    return [_number(x, f"{where}[{i}]") for i, x in enumerate(xs)]


def _check_keys(d: Any, allowed: Sequence[str], where: str) -> None:
    if not isinstance(d, dict):
        raise ModelError(f"{where}: expected a mapping")
    extra = sorted(str(k) for k in set(d) - set(allowed))
    if extra:
        import difflib
        near = difflib.get_close_matches(extra[0], [str(a) for a in allowed], n=1,
                                         cutoff=0.6)
        hint = f" (did you mean {near[0]!r}?)" if near else ""
        raise ModelError(f"{where}: unknown key(s) {extra}{hint}")


def _branch(d: Any, where: str) -> DuhemBranch:
    _check_keys(d, ("alpha", "f", "g", "h"), where)
    if "alpha" not in d:
        raise ModelError(f"{where}: missing alpha")
    if "h" in d and ("f" in d or "g" in d):
        raise ModelError(f"{where}: give either h or f and g, not both")
    if "h" not in d and ("f" not in d or "g" not in d):
        raise ModelError(f"{where}: needs f and g (or h)")
    alpha = _number(d["alpha"], f"{where}.alpha")
    try:
        if "h" in d:
            return DuhemBranch.from_h(alpha, _numbers(d["h"], f"{where}.h"))
        return DuhemBranch(alpha, np.array(_numbers(d["f"], f"{where}.f")),
                           np.array(_numbers(d["g"], f"{where}.g")))
    except (TypeError, ValueError) as e:  # ModelError is a ValueError
        raise ModelError(f"{where}: {e}") from None


def _duhem(d: Any, where: str) -> DuhemModel:
    if not isinstance(d, dict):
        raise ModelError(f"{where}: expected a mapping")
    structure = d.get("structure", "whole")
    init = d.get("initial_state", {}) or {}
    _check_keys(init, ("v_V", "w_um"), f"{where}.initial_state")
    state = DuhemState(_number(init.get("v_V", 0.0), f"{where}.initial_state.v_V"),
                       _number(init.get("w_um", 0.0), f"{where}.initial_state.w_um"))
    fr = d.get("fitted_range_V")
    if fr is not None:
        if not isinstance(fr, (list, tuple)) or len(fr) != 2:
            raise ModelError(f"{where}.fitted_range_V must be [lo, hi]")
        fr = tuple(_numbers(list(fr), f"{where}.fitted_range_V"))
        if not fr[0] < fr[1]:
            raise ModelError(f"{where}.fitted_range_V {list(fr)} must have lo < hi")
    cont = d.get("continued_past_fit", "straight")
    if cont not in CONTINUATIONS:
        raise ModelError(f"{where}.continued_past_fit: one of {', '.join(CONTINUATIONS)}, "
                         f"got {cont!r}")
    if structure == "whole":
        _check_keys(d, ("structure", "initial_state", "fitted_range_V", "continued_past_fit",
                        "alpha", "f", "g", "h", "coupling", "play_operators", "note"), where)
        b = _branch({k: d[k] for k in ("alpha", "f", "g", "h") if k in d}, where)
        return DuhemModel(b, b, state, fr, cont)
    if structure == "segmented":
        _check_keys(d, ("structure", "initial_state", "fitted_range_V", "continued_past_fit",
                        "ascending", "descending", "coupling", "play_operators", "note"),
                    where)
        for k in ("ascending", "descending"):
            if k not in d:
                raise ModelError(f"{where}: segmented model needs '{k}'")
        return DuhemModel(_branch(d["ascending"], f"{where}.ascending"),
                          _branch(d["descending"], f"{where}.descending"), state, fr, cont)
    raise ModelError(f"{where}: structure must be 'whole' or 'segmented', got {structure!r}")


def _plays(d: Any, v0: float, where: str) -> PlayOperators:
    _check_keys(d, ("thresholds_V", "weights_um_per_V", "initial_V", "rate_widening_s",
                    "bands_V"), where)
    for k in ("thresholds_V", "weights_um_per_V"):
        if k not in d:
            raise ModelError(f"{where}: missing {k}")
    if isinstance(d["thresholds_V"], list) and len(d["thresholds_V"]) > MAX_OPERATORS:
        raise ModelError(f"{where}: more than {MAX_OPERATORS} operators")
    r = _numbers(d["thresholds_V"], f"{where}.thresholds_V")
    p = _numbers(d["weights_um_per_V"], f"{where}.weights_um_per_V")
    z = (_numbers(d["initial_V"], f"{where}.initial_V") if "initial_V" in d
         else [v0] * len(r))
    beta = d.get("rate_widening_s", 0.0)
    bands = None
    if "bands_V" in d:
        rows = d["bands_V"]
        if not isinstance(rows, list) or len(rows) != len(r):
            raise ModelError(f"{where}.bands_V: one [low, high] pair per operator "
                             f"({len(r)})")
        bands = np.array([_numbers(b, f"{where}.bands_V[{i}]") for i, b in enumerate(rows)],
                         dtype=object)
        if bands.ndim != 2 or bands.shape[1] != 2:
            raise ModelError(f"{where}.bands_V: one [low, high] pair per operator")
        bands = bands.astype(float)
    try:
        return PlayOperators(np.asarray(r, float), np.asarray(p, float), np.asarray(z, float),
                             beta, bands)
    except ModelError as e:
        raise ModelError(f"{where}: {e}") from None


def model_from_dict(doc: object, source: str = "model") -> tuple[StageModel, Doc]:
    """Parse a model document; returns (StageModel, effects dict)."""
    if not isinstance(doc, dict) or SCHEMA_KEY not in doc:
        raise ModelError(f"{source}: not a piezo_stage model file (no '{SCHEMA_KEY}' key)")
    if doc[SCHEMA_KEY] != SCHEMA_VERSION:
        raise ModelError(f"{source}: unsupported model version {doc[SCHEMA_KEY]!r}")
    _check_keys(doc, (SCHEMA_KEY, "convention", "units", "voltage_limits_V", "axes",
                      "effects", "identification", "note"), source)
    if doc.get("convention", "seed-eq6") != "seed-eq6":
        raise ModelError(f"{source}: unknown convention {doc['convention']!r}")
    axes_doc = doc.get("axes")
    if not isinstance(axes_doc, dict) or not axes_doc:
        raise ModelError(f"{source}: 'axes' must map x and/or y to a model")
    parts: dict[str, AxisParts] = {}
    for a, d in axes_doc.items():
        if a not in AXES:
            raise ModelError(f"{source}: unknown axis {a!r}")
        law = _duhem(d, f"{source}: axes.{a}")
        doc_a = d if isinstance(d, dict) else {}
        parts[a] = AxisParts(
            law,
            _duhem(doc_a["coupling"], f"{source}: axes.{a}.coupling")
            if doc_a.get("coupling") is not None else None,
            _plays(doc_a["play_operators"], law.initial.v, f"{source}: axes.{a}.play_operators")
            if doc_a.get("play_operators") is not None else None)
    lim = doc.get("voltage_limits_V", [0.0, 150.0])
    if not isinstance(lim, (list, tuple)) or len(lim) != 2:
        raise ModelError(f"{source}: voltage_limits_V must be [min, max]")
    lim = tuple(_numbers(list(lim), f"{source}: voltage_limits_V"))
    if not lim[0] < lim[1] or max(abs(lim[0]), abs(lim[1])) > MAX_VOLTS:
        raise ModelError(f"{source}: voltage_limits_V {list(lim)} must have min < max "
                         f"within +-{MAX_VOLTS:g} V")
    model = StageModel.from_fits(parts, lim)
    problem = magnitude_problem(model)
    if problem:
        raise ModelError(f"{source}: {problem}")
    try:  # every effect key known, every value in a physical range (core/model/effects.py)
        effects = validate_effects(doc.get("effects"), f"{source}: effects")
    except ConfigError as e:
        raise ModelError(str(e)) from None
    return model, effects


MAX_VOLTS = 1000.0      # no piezo amplifier here drives more


MAX_SLOPE = 1.0e4       # um/V: h(v) beyond this anywhere in the limits is not a stage


def magnitude_problem(model: StageModel) -> str | None:
    """What makes ``model`` no stage (None: nothing): a branch polynomial not finite or
    beyond ``MAX_SLOPE`` anywhere over the voltage limits as the model runs there (past
    its fitted range a branch continues from its end), the play operators' summed slope
    likewise. The loader's check (1e300 coefficients, or 2,000 terms that overflow, are
    refused), and every writer's before it writes (``bounded_past_fit``)."""
    for a, p in model.plays.items():
        slope = float(np.abs(p.weights_um_per_V).sum())
        if slope > MAX_SLOPE:
            return (f"axes.{a}.play_operators: weights sum to {slope:.3g} um/V in "
                    f"magnitude (<= {MAX_SLOPE:g})")
    lim = model.voltage_limits
    v = np.linspace(lim[0], lim[1], 201)
    for kind, models in (("axes", model.axes), ("coupling", model.coupling)):
        for a, m in models.items():
            bad = _branch_problem(m, v)
            if bad:
                return f"{kind}.{a} {bad}"
    return None


def _branch_problem(m: DuhemModel, v: np.ndarray) -> str | None:
    vv = np.unique(np.concatenate([v, polynomial_range(m.fit_range_V)]))
    vv = vv[np.isfinite(vv)]
    for name, asc_branch in (("ascending", True), ("descending", False)):
        for asc in (True, False):
            y = m.branch_values(asc_branch, asc, vv)
            if not np.all(np.isfinite(y)) or np.abs(y).max() > MAX_SLOPE:
                return (f"{name} branch reaches {np.nanmax(np.abs(y)):.3g} um/V within "
                        f"the voltage limits (finite and <= {MAX_SLOPE:g})")
    return None


def bounded_past_fit(model: StageModel) -> tuple[StageModel, list[str]]:
    """``model`` as a writer may write it: where a Duhem law's straight continuation
    past its fitted range would leave ``magnitude_problem``'s bounds inside the voltage
    limits (a law fitted on 0-3.6 V of a 0-150 V amplifier's range: its branch's slope
    at 4 V carried on to 150 V), its branches go on level past that range instead
    (``continued_past_fit: level`` in the file), one note each. ModelError when even
    that is no stage: nothing is written then."""
    notes: list[str] = []
    v = np.linspace(model.voltage_limits[0], model.voltage_limits[1], 201)
    parts: Doc = {"axes": dict(model.axes), "coupling": dict(model.coupling)}
    for kind, models in parts.items():
        for a, m in models.items():
            bad = _branch_problem(m, v)
            if not bad or m.fit_range_V is None or m.continuation == "level":
                continue
            lvl = m.with_continuation("level")
            if _branch_problem(lvl, v) is None:
                models[a] = lvl
                lo, hi = polynomial_range(m.fit_range_V)
                notes.append(f"{kind}.{a}: its branches go on level past {lo:.4g}..{hi:.4g} "
                             f"V (continued_past_fit: level); straight, the {bad}")
    out = model.replace(axes=parts["axes"], coupling=parts["coupling"])
    problem = magnitude_problem(out)
    if problem:
        raise ModelError(f"the model is no stage: {problem}")
    return out, notes


def _floats(a: ArrayLike) -> list[float]:
    return [float(x) for x in np.asarray(a, float)]


def _branch_doc(b: DuhemBranch, ascending: bool) -> Doc:
    if b.reduced:
        return {"alpha": b.alpha, "h": _floats(b.h(ascending))}
    return {"alpha": b.alpha, "f": _floats(b.f), "g": _floats(b.g)}


def _duhem_doc(m: DuhemModel) -> Doc:
    d: dict[str, object] = {"structure": m.structure,
                            "initial_state": {"v_V": float(m.initial.v),
                                              "w_um": float(m.initial.w)}}
    if m.fit_range_V is not None:
        d["fitted_range_V"] = [float(x) for x in m.fit_range_V]
        if m.continuation != "straight":
            d["continued_past_fit"] = m.continuation
    if m.structure == "whole":
        d.update(_branch_doc(m.ascending, True))
    else:
        d["ascending"] = _branch_doc(m.ascending, True)
        d["descending"] = _branch_doc(m.descending, False)
        if m.ascending.reduced or m.descending.reduced:
            d["note"] = ("within one branch only h = f + g (ascending) and h = g - f "
                         "(descending) are identifiable; f and g are not given separately")
    return d


def model_to_dict(model: StageModel, effects: EffectsBlock | None = None,
                  extra: Doc | None = None) -> Doc:
    """The model document (the schema above) of ``model``, its ``effects`` and any
    ``extra`` top-level keys (identification figures)."""
    axes: PerAxis[Doc] = {}
    doc: dict[str, object] = {
        SCHEMA_KEY: SCHEMA_VERSION,
        "convention": "seed-eq6",
        "units": {"voltage": "V", "displacement": "um", "alpha": "1/V",
                  "f": "um/V per V^i", "g": "um/V per V^i"},
        "voltage_limits_V": [float(x) for x in model.voltage_limits],
        "axes": axes,
    }
    for a, m in model.axes.items():
        d = _duhem_doc(m)
        if a in model.coupling:
            d["coupling"] = _duhem_doc(model.coupling[a])
        if a in model.plays:
            p = model.plays[a]
            d["play_operators"] = {"thresholds_V": _floats(p.thresholds_V),
                                   "weights_um_per_V": _floats(p.weights_um_per_V),
                                   "initial_V": _floats(p.initial_V)}
            if p.rate_dependent:
                d["play_operators"]["rate_widening_s"] = p.rate_widening_s
            if p.bands_V is not None:
                d["play_operators"]["bands_V"] = [_floats(b) for b in p.bands_V]
        axes[a] = d
    if effects:
        doc["effects"] = effects
    if extra:
        doc.update(extra)
    return doc


def checked_doc(model: StageModel, effects: EffectsBlock | None = None,
                extra: Doc | None = None) -> tuple[dict, list[str]]:
    """The model document a writer writes (a file, the model message): ``model``
    bounded past its fitted range where it must be (``bounded_past_fit``), then read
    back by the loader's own parser and checks, so no writer of ours writes a model our
    own tools refuse (ModelError before anything is written). -> (document, notes)."""
    model, notes = bounded_past_fit(model)
    doc = model_to_dict(model, effects, extra)
    model_from_dict(doc, "the model to write")
    return doc, notes
