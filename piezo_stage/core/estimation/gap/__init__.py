"""Sim-to-real gap diagnosis: where the simulator and the stage disagree, which
unmodelled effects cause it, and how far the gap shrinks once they are added.

Base model ("the sim"): the segmented Duhem model per axis, identified on FIT (or
given: then what it has is not a candidate). Candidates, each a small physical
operator from core/model/effects.py added to the sim and fitted on FIT *together with* the
Duhem coefficients (the effect operator is linear, so E(X theta) = E(X) theta: for
fixed alphas and effect parameters it is one least-squares problem; the effect's own
parameters are searched):

    creep      w = E_creep(H(v)), log-like relaxation bank, gamma searched
    dynamics   w = G(s) H(v), resonance (fn, zeta) or lag (tau), the better of the two
    delay      w(t) = H(v)(t - d), d searched
    drift      w = H(v) + a t + b (1 - exp(-t / tau)), input independent
    coupling   w = H(v) + H_c(v_other), a Duhem term driven by the other axis
    structure  H with richer branch polynomials (the hysteresis's own shape)
    memory     structure with play operators beside it (return-point memory the Duhem
               law lacks); the structure candidate's other form, named so where the
               operators are what paid on HOLDOUT
    none       the base model alone

Every candidate is scored on HOLDOUT (a different record): the initial Duhem state
and a constant sensor offset are re-estimated there, the same for all. The gap is the
part of the residual above the floor (the noise, and a disturbance line if any),
sqrt(max(rms^2 - floor^2, 0)); shrink = 100 (1 - gap_after / gap_before). Effects join
one at a time (forward selection, each refitted with those before it) while the
held-out gap keeps shrinking clearly. The budget splits the held-out residual into
noise, input-locked and not input-locked parts, and the gap into what each kept
effect explains and what is left; a disturbance (a line the input does not cause) is
reported with the feedback bandwidth that rejects it.
"""

from __future__ import annotations

import contextlib
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

from piezo_stage.core.errors import DataError

# the package's public names, here as before it was split by concern
from piezo_stage.core.estimation.gap.budget import gap_budget, input_period  # noqa: F401
from piezo_stage.core.estimation.gap.candidates import (  # noqa: F401
    EFFECTS,
    TRANSFORMS,
    Candidate,
    ClassCandidate,
    broadband,
    fit_candidate,
    play_columns,
)
from piezo_stage.core.estimation.gap.selection import AxisDiagnosis, diagnose_axis  # noqa: F401
from piezo_stage.core.estimation.gap.where import held, holds  # noqa: F401
from piezo_stage.core.estimation.record import Record
from piezo_stage.core.model.duhem import StageModel, voltage_limits_for
from piezo_stage.core.types import Doc, EffectsBlock, PerAxis
from piezo_stage.core.workers import forking, quiet_worker

# The other speed-up (see candidates.ONE_COLUMN_SEARCH): the axes in processes
# (False: threads), switchable so that ``bench gap`` measures the path without it
AXES_IN_PROCESSES = True


@dataclass
class Diagnosis:
    """What ``diagnose`` found: ``json``, the --json contract (see the module docstring
    and docs/gap.md; ``diagnosis["verdict"]`` reads it), ``per_axis``, each axis's full
    diagnosis (its kept model and candidates: for reports and ``model``), and
    ``limits_V``, the voltage limits of every model it wrote and scored."""

    json: Doc
    per_axis: PerAxis[Any]
    limits_V: tuple = (0.0, 150.0)

    def __getitem__(self, key: str) -> Any:  # the JSON contract's values
        return self.json[key]

    def __contains__(self, key: str) -> bool:
        return key in self.json

    def document(self) -> tuple[dict, list[str]]:
        """The model document ``gap --out-model`` writes -> (document, notes): each
        axis's kept model (the sim's where none was kept) as the diagnosis scored it
        on HOLDOUT (``gap/written.py``), the effects with each axis's own parameters."""
        from piezo_stage.core.estimation.gap.written import document
        return document({a: d.written.written() for a, d in self.per_axis.items()},
                        self.limits_V)

    def model(self) -> tuple[StageModel, Doc]:
        """The written model read back as a model file is read: (StageModel, effects)."""
        from piezo_stage.core.model.model_doc import model_from_dict
        return model_from_dict(self.document()[0], "the model to write")


def _holes_filled(fit: Record, axes: Sequence[str]) -> Record:
    """FIT with the displacement in its long holes (``measured`` False) filled with the
    base Duhem law's prediction, fitted without them (``identify_axis``): the
    candidates, fitted on it, take nearly nothing from the holes (the record module's
    ``fitted_together``, one step of it for all candidates)."""
    from piezo_stage.core.estimation.identify.api import identify_axis, predict_axis
    from piezo_stage.core.estimation.record import fill_unmeasured
    pred = {}
    for a in axes:
        try:
            pred[a] = predict_axis(identify_axis(fit, a), fit)[2]
        except DataError:  # an axis with nothing to identify: its holes interpolated
            pass
    return fill_unmeasured(fit, pred)


def _axis_child(conn: Any, fit: Record, holdout: Record, axis: str, args: tuple) -> None:
    quiet_worker()  # the parent decides about stops (core/workers.py)
    effects, base_model, base_effects, limits_V, history, live = args
    try:
        d = diagnose_axis(fit, holdout, axis, effects, base_model,
                          lambda what: conn.send(("progress", what)), base_effects, limits_V,
                          history, live)
        conn.send(("done", d))
    except BaseException as e:  # noqa: BLE001 -- re-raised in the parent
        conn.send(("error", e))
    finally:
        conn.close()


def _axes_apart(fit: Record, holdout: Record, axes: Sequence[str], args: tuple,
                progress: Callable[[str], None]) -> PerAxis[AxisDiagnosis]:
    """Each axis's diagnosis in a process of its own (forked: the records are not
    copied), progress relayed from them. Processes, not threads: the many small steps
    of the parameter searches hold the GIL, so two axes in two threads take longer than
    in two processes (`bench gap`). One axis, or no fork (not Linux): in this process /
    in threads."""
    import multiprocessing as mp
    import sys
    if len(axes) == 1 or not (AXES_IN_PROCESSES and sys.platform.startswith("linux")):
        from concurrent.futures import ThreadPoolExecutor
        with ThreadPoolExecutor(max_workers=min(2, len(axes))) as pool:
            futures = {a: pool.submit(diagnose_axis, fit, holdout, a, args[0], args[1],
                                      progress, args[2], args[3], args[4], args[5])
                       for a in axes}
            return {a: f.result() for a, f in futures.items()}
    from multiprocessing.connection import wait
    ctx = mp.get_context("fork")
    procs: dict[str, Any] = {}
    conns: dict[Any, str] = {}  # a pipe's reading end -> its axis
    r: Any
    per: dict[str, Any] = {}
    try:
        for a in axes:
            r, w = ctx.Pipe(duplex=False)
            p = ctx.Process(target=_axis_child, args=(w, fit, holdout, a, args), daemon=True)
            with forking():
                p.start()
            w.close()
            procs[a], conns[r] = p, a
        while conns:
            for r in wait(list(conns)):
                a = conns[r]
                try:
                    kind, val = r.recv()
                except EOFError:
                    procs[a].join(5)
                    raise RuntimeError(f"axis {a}: its diagnosis process ended without a "
                                       f"result (exit code {procs[a].exitcode})") from None
                if kind == "progress":
                    progress(val)
                    continue
                del conns[r]
                r.close()
                if kind == "error":
                    raise val
                per[a] = val
    finally:
        for p in procs.values():
            if p.is_alive() and p.pid is not None and conns:
                p.terminate()
            p.join(5)
    return {a: per[a] for a in axes}


def diagnose(fit: Record, holdout: Record | None = None, effects: Sequence[str] = EFFECTS,
             axes: Sequence[str] | None = None, base_model: StageModel | None = None,
             progress: Callable[[str], None] | None = None,
             base_effects: EffectsBlock | None = None, limits_V: tuple | None = None,
             history: int = 0, live: bool = False) -> Diagnosis:
    """Diagnose the gap on every axis (see the module docstring). ``progress(what)`` is
    called after each candidate fit (in this thread: relayed from the axes' processes);
    ``limits_V`` are the amplifier's, the written models' (None: 0-150 V widened to
    both records' voltages); HOLDOUT's first ``history`` samples are run
    but not scored (``diagnose_axis``: a record's later part held out with its
    history, as ``refit`` holds out each bag's second half). ``live``: the live watch's reading (a
    running trajectory that holds still nowhere): creep and drift told apart by HOLDOUT
    alone, and of two effects that explain the gap alike the one forward selection kept
    is named (the other said alike), not called inconclusive."""
    t0 = time.perf_counter()
    holdout = holdout or fit
    axes = axes or [a for a in ("x", "y") if a in fit.w and a in holdout.w]
    if not axes:
        raise DataError("no axis with voltage and displacement in both records")
    for a in axes:
        if (a in fit.w) != (a in holdout.w):
            raise DataError(f"FIT and HOLDOUT have different channels (axis {a})")
    if len(fit.t) < 200 or len(holdout.t) - history < 200:
        raise DataError("records too short for a gap diagnosis (need >= 200 samples)")
    if fit.measured is not None:  # FIT's long holes: left out of every candidate's fit
        fit = _holes_filled(fit, axes)
    # the amplifier's limits, or 0-150 V widened to take both records' voltages: the
    # limits of every model written and scored (one for all axes, as the file has one)
    limits_V = voltage_limits_for([r.v[a] for a in axes for r in (fit, holdout)], limits_V)
    # the axes are independent problems, one per core; one BLAS thread each (two of
    # each on two cores fight, ~20 % slower). threadpoolctl is optional (rosdep has no
    # key for it): without it the diagnosis is the same, only slower on two axes.
    try:
        from threadpoolctl import threadpool_limits
    except ImportError:
        def threadpool_limits(_n: int | None) -> contextlib.AbstractContextManager:  # type: ignore[misc]
            return contextlib.nullcontext()
    args = (effects, base_model, base_effects, limits_V, history, live)
    with threadpool_limits(1 if len(axes) > 1 else None):
        per = _axes_apart(fit, holdout, axes, args, progress or (lambda what: None))
    worst = max(per.values(), key=lambda d: d.ranking[0]["gap_before_um"])
    out = {"verdict": worst.verdict, "reason": worst.reason, "ranking": worst.ranking,
           "where": worst.where, "noise_floor_um": worst.noise_floor_um,
           "effects": worst.effects, "budget": worst.budget,
           "axes": {a: {"verdict": d.verdict, "reason": d.reason, "ranking": d.ranking,
                        "where": d.where, "noise_floor_um": d.noise_floor_um,
                        "effects": d.effects, "budget": d.budget,
                        "written": {"model": d.written_as, "rms_after_um": d.written_rms_um,
                                    "gap_after_um": d.written_gap_um}}
                    for a, d in per.items()},
           "holdout_is_fit": holdout is fit,
           "scored": {"start_up_s": worst.skip / holdout.fs_hz, "offset": "removed",
                      "from": "the written model's initial state (FIT's start)"},
           "seconds": time.perf_counter() - t0}
    return Diagnosis(out, per, limits_V)
