"""`piezo-stage refit`: a lab's archive of runs re-identified, and how the stage changed.

Each axis of a bag is fitted where its voltage moves (a protocol such as ``excite``'s
drives the axes in turn), that span split in two halves: the Duhem model is identified
on the first and scored on the second (its own later part, held out); an axis at rest
is left out with a note. A bag not on one sample clock (a real-time run's skipped
ticks) is put on one first (``core.estimation.record.on_grid``). Bags run in parallel
worker processes. Then, over the bags in date order: the model's gain and errors, how
far each earlier model's response lies from the newest one's on the newest bag's own
input ("change"),
and with a reference model (``--against``) the gap diagnosis of each bag against it:
which unmodelled effect each shows and how large (creep's gamma, a delay, a
resonance's frequency, else the held-out gap it explains), its change since the first
bag and the date it first changed by ``GROWTH_PCT`` or more.

A bag's date: the run's start the recorder stores (MCAP metadata ``piezo_stage_run``),
else its first sample's stamp when that is wall time (real-time runs), else a
``YYYYMMDD-HHMMSS`` folder name on its path, else the file's modification time; the
table says which.
"""

from __future__ import annotations

import math
import os
import re
from datetime import datetime, timezone
from typing import TYPE_CHECKING

import numpy as np

from piezo_stage.core.errors import DataError
from piezo_stage.core.types import Doc, PerAxis

if TYPE_CHECKING:
    from piezo_stage.core.estimation.record import Record

SPLIT = 0.5          # the share of each bag identified on; the rest is held out
GROWTH_PCT = 30.0    # an effect's change worth a date
# an effect's size: its parameter where it has one that scales with it (else the
# held-out gap it explains, um)
SIZE_OF = {"creep": "gamma", "delay": "delay_s", "dynamics": "fn_hz"}
WALL_NS = 10**17     # a stamp past 1973: wall time, not a simulated clock from 0


def find_bags(paths) -> list[str]:
    """The bags named or held in ``paths``: a bag folder (an .mcap file in it) or an
    .mcap file is itself; any other folder is searched two levels down (a run folder
    of bags, a folder of run folders). DataError when a path is missing or holds none."""
    out = []
    for p in paths:
        if not os.path.exists(p):
            raise DataError(f"{p}: no such file or directory")
        if _is_bag(p):
            out.append(os.path.normpath(p))
            continue
        found = []
        if os.path.isdir(p):
            for d1 in sorted(os.listdir(p)):
                q = os.path.join(p, d1)
                if _is_bag(q):
                    found.append(q)
                elif os.path.isdir(q):
                    found += [os.path.join(q, d2) for d2 in sorted(os.listdir(q))
                              if _is_bag(os.path.join(q, d2))]
        if not found:
            raise DataError(f"{p}: no bag in it (a bag is a folder with an .mcap file)")
        out += [os.path.normpath(f) for f in found]
    return list(dict.fromkeys(out))  # in order, each once


def _is_bag(p) -> bool:
    if os.path.isfile(p):
        return p.endswith(".mcap")
    return os.path.isdir(p) and any(f.endswith(".mcap") for f in os.listdir(p))


def run_date(path) -> tuple[datetime, str]:
    """When a bag's run started (UTC) and how that is known (see the module docstring)."""
    from piezo_stage.io.bag import iter_messages, read_metadata
    try:
        meta = read_metadata(path).get("piezo_stage_run", {})
        if meta.get("started_utc"):
            return datetime.fromisoformat(meta["started_utc"]), "recorded start"
    except (ValueError, OSError, DataError):
        pass
    try:
        for topic, _, log_ns, _ in iter_messages(path):
            if topic.endswith("/joint_states"):
                if log_ns > WALL_NS:
                    return datetime.fromtimestamp(log_ns * 1e-9, timezone.utc), "first stamp"
                break
    except (OSError, DataError):
        pass
    for part in reversed(os.path.abspath(path).split(os.sep)):
        m = re.fullmatch(r"(\d{8}-\d{6})", part)
        if m:
            return datetime.strptime(m.group(1), "%Y%m%d-%H%M%S").replace(
                tzinfo=timezone.utc), "folder name"
    return datetime.fromtimestamp(os.path.getmtime(path), timezone.utc), "file time"


def halves(rec, share: float = SPLIT):
    """(first part, the rest) of a record, each from t = 0."""
    k = int(len(rec) * share)
    if k < 100 or len(rec) - k < 100:
        raise DataError(f"{rec.source}: {len(rec)} samples, too few to fit on one part "
                        "and score on the other")

    def part(a, b):
        piece = rec.slice(a, b)
        piece.t = piece.t - piece.t[0]
        return piece
    return part(0, k), part(k, len(rec))


def moving_span(v: np.ndarray) -> tuple[int, int] | None:
    """The samples [start, stop) from an axis's voltage's first move to its last (a
    protocol drives the axes in turn: x first, then y), None when it never moves."""
    v = np.asarray(v, float)
    moves = np.flatnonzero(np.abs(np.diff(v)) > 1e-6)
    if np.ptp(v) <= 1e-6 or moves.size == 0:
        return None
    return int(moves[0]), int(moves[-1]) + 2


def axis_parts(rec, spans: PerAxis[Record] | None = None
               ) -> tuple[PerAxis[tuple[Record, Record]], list[str]]:
    """Each axis's (FIT, HOLD): the halves of the span where its voltage moves, and a
    note for each axis left out (at rest, or moving too briefly to fit and score);
    ``spans`` gets each axis's whole span (from t = 0). -> ({axis: (fit, hold)},
    notes)."""
    parts, notes = {}, []
    for a in ("x", "y"):
        if a not in rec.v or a not in rec.w:
            continue
        span = moving_span(rec.v[a])
        if span is None:
            notes.append(f"axis {a} is at rest (its voltage is constant): not refitted")
            continue
        whole = rec.slice(*span)
        whole.t = whole.t - whole.t[0]
        try:
            parts[a] = halves(whole)
            if spans is not None:
                spans[a] = whole
        except DataError as e:
            notes.append(f"axis {a}: {str(e).split(': ', 1)[-1]} where it moves: not "
                         "refitted")
    return parts, notes


def refit_bag(path: str, out_dir: str, limits_V=None, against=None) -> Doc:
    """One bag: each axis identified on the first half of the span where its voltage
    moves and scored on the second (``axis_parts``), the model written to ``out_dir``;
    with ``against`` (a model file) the gap diagnosis of each axis's second half
    against that model, fitted on the first. Returns the bag's row (``notes``: the
    axes left out and how the record was read)."""
    import time

    from piezo_stage.core.estimation.identify.api import identify_axis, validate_axis
    from piezo_stage.core.model.duhem import StageModel, stroke_um, voltage_limits_for
    from piezo_stage.io.model_file import load_model, save_model
    from piezo_stage.io.records import load_record
    t0 = time.perf_counter()
    rec = load_record(path)
    rec.voltage_exact = True  # a bag holds the voltage the driver applied
    lim = voltage_limits_for(list(rec.v.values()), limits_V)
    spans: PerAxis[Record] = {}
    parts, notes = axis_parts(rec, spans)
    results = {}
    for a, (fit, _) in parts.items():
        try:
            results[a] = identify_axis(fit, a)
        except DataError as e:
            notes.append(f"axis {a}: {str(e).split(': ', 1)[-1]}: not refitted")
    if not results:
        raise DataError(f"{path}: no axis could be refitted ({'; '.join(notes)})")
    model = StageModel.from_fits({a: r.parts() for a, r in results.items()}, lim)
    started, dated_by = run_date(path)
    name = _bag_name(path)
    model_path = os.path.join(out_dir, "models", f"{name}.yaml")
    save_model(model_path, model, extra={"identification": {
        "bag": os.path.abspath(path), "started_utc": started.isoformat(),
        "fitted_on": f"the first {SPLIT:.0%} of the span where each axis moves"}})
    per_axis: PerAxis[Doc] = {}
    row: Doc = {"bag": os.path.abspath(path), "name": name,
                 "started_utc": started.isoformat(), "dated_by": dated_by,
                 "model": model_path, "axes": per_axis,
                 "notes": list(rec.notes) + [f"{path}: {n}" for n in notes]}
    for a, r in results.items():
        fit, hold = parts[a]
        span = (float(fit.v[a].min()), float(fit.v[a].max()))
        per_axis[a] = {
            "gain_um_per_V": stroke_um(r.model, span) / max(span[1] - span[0], 1e-12),
            "fit_rms_um": float(r.fit["rms_um"]),
            "held_out_rms_um": float(validate_axis(r, hold)["validate_rms_um"])}
    if against:
        from piezo_stage.core.estimation.gap import diagnose
        ref, ref_effects = load_model(against)
        for a in results:
            if a not in ref.axes:
                continue
            fit, hold = parts[a]
            # the second half held out with its history (the first half run, not
            # scored): the stage's state where it starts, a creep still relaxing from
            # the first half's steps, follows from what came before and is no drift
            both = spans[a]
            d = diagnose(fit, both, axes=[a], base_model=ref, base_effects=ref_effects,
                         limits_V=limits_V, history=len(fit))
            per_axis[a]["against"] = _against_row(d.json["axes"][a])
    row["seconds"] = time.perf_counter() - t0
    return row


def _against_row(j: Doc) -> Doc:
    """One axis's diagnosis against the reference as a row's: the verdict and each
    named effect's size (its parameter that scales with it, else the held-out gap it
    explains)."""
    explained = j.get("budget", {}).get("explained_um", {})
    effects: dict[str, Doc] = {}  # effect -> its size
    for st in j["effects"]:
        key = SIZE_OF.get(st["effect"])
        val = st["params"].get(key) if key else None
        if not isinstance(val, (int, float)):
            key, val = "explained_um", explained.get(st["effect"], 0.0)
        effects[st["effect"]] = {"size": float(val), "size_of": key,
                                 "explained_um": float(explained.get(st["effect"], 0.0))}
    return {"verdict": j["verdict"], "effects": effects}


def _bag_name(path) -> str:
    """A file name for a bag's model: its folder names from the run folder on."""
    parts = os.path.normpath(os.path.abspath(path)).split(os.sep)[-2:]
    name = "_".join(p.removesuffix(".mcap") for p in parts)
    return re.sub(r"[^A-Za-z0-9_.-]", "_", name)


def _worker_init():
    from piezo_stage.core.workers import quiet_worker
    quiet_worker()  # the parent decides about stops
    _one_thread_each()


def _one_thread_each():
    """A worker of many: its gap axes in threads, one BLAS thread (a cluster's worker
    keeps its own signals: its nanny stops it)."""
    import piezo_stage.core.estimation.gap as gap
    gap.AXES_IN_PROCESSES = False  # a worker per bag already: its axes in threads
    try:  # and one BLAS thread each: workers x BLAS threads beyond the cores fight
        from threadpoolctl import threadpool_limits
        threadpool_limits(1)
    except ImportError:
        pass


def _refit_or_skip(path, out_dir, limits_V, against):
    """``refit_bag``, or {"skipped": path, "why": ...} for a bag that cannot be refitted
    (no axis moves, too short, unreadable): an archive holds such runs too."""
    try:
        return refit_bag(path, out_dir, limits_V, against)
    except DataError as e:
        return {"skipped": os.path.abspath(path), "why": str(e)}


def refit(paths, out_dir: str, jobs: int | None = None, limits_V=None, against=None,
          progress=None, skipped: list | None = None,
          scheduler: str | None = None) -> list[dict]:
    """Every bag in ``paths`` refitted (``refit_bag``) on ``jobs`` local worker
    processes (the CPU count by default), or on the Dask distributed cluster whose
    scheduler is at ``scheduler`` (its workers need this package; ``jobs`` unused);
    rows in date order; ``progress(name)`` after each bag. A bag that cannot be
    refitted is left out and listed in ``skipped`` [(path, why)]; DataError naming
    every bag and why when none can."""
    from concurrent.futures import ProcessPoolExecutor, as_completed
    bags = find_bags(paths)
    os.makedirs(os.path.join(out_dir, "models"), exist_ok=True)
    jobs = max(1, min(jobs or os.cpu_count() or 1, len(bags)))
    rows = []
    skipped = [] if skipped is None else skipped
    out_dir = os.path.abspath(out_dir)  # (a cluster's workers run elsewhere)

    def take(row):
        if "skipped" in row:
            skipped.append((row["skipped"], row["why"]))
        else:
            rows.append(row)
        if progress:
            progress(os.path.basename(row.get("skipped", row.get("name", ""))))
    if scheduler:
        for row in _on_cluster(scheduler, bags, out_dir, limits_V, against):
            take(row)
    elif jobs == 1:
        for b in bags:
            take(_refit_or_skip(b, out_dir, limits_V, against))
    else:
        from piezo_stage.core.workers import forking
        with ProcessPoolExecutor(max_workers=jobs, initializer=_worker_init) as pool:
            with forking():  # (the workers are forked as the first bags are submitted)
                futures = [pool.submit(_refit_or_skip, b, out_dir, limits_V, against)
                           for b in bags]
            try:
                for f in as_completed(futures):
                    take(f.result())
            except BaseException:
                for f in futures:
                    f.cancel()
                raise
    if not rows:
        raise DataError("no bag could be refitted: " + "; ".join(
            f"{_bag_name(p)}: {why.replace(p + ': ', '')}" for p, why in skipped))
    rows.sort(key=lambda r: (r["started_utc"], r["name"]))
    _changes(rows)
    return rows


def _on_cluster(address: str, bags: list, out_dir: str, limits_V, against):
    """``_refit_or_skip`` of each bag on a Dask distributed cluster (``dask`` extra),
    rows as they finish. DataError when the package is missing or the scheduler does
    not answer."""
    try:
        from distributed import Client, as_completed
    except ImportError:
        raise DataError("--scheduler needs Dask's distributed package: pip install "
                        "'piezo_stage[dask]'") from None
    try:
        client = Client(address, timeout=10)
    except (OSError, TimeoutError) as e:
        raise DataError(f"--scheduler {address}: no Dask scheduler answers there "
                        f"({type(e).__name__}: {e})") from None
    try:
        client.run(_one_thread_each)
        futures = [client.submit(_refit_or_skip, b, out_dir, limits_V, against,
                                 pure=False, key=f"refit-{_bag_name(b)}") for b in bags]
        for f in as_completed(futures):
            yield f.result()
    finally:
        client.close()


def _changes(rows) -> None:
    """Each row's model against the newest: the RMS difference of their responses to
    the newest bag's own voltages [um], per axis (``change_um``)."""
    from piezo_stage.io.model_file import load_model
    from piezo_stage.io.records import load_record
    newest = rows[-1]
    rec = load_record(newest["bag"])
    v = {a: rec.v.get(a, np.zeros(len(rec))) for a in ("x", "y")}
    dt = 1.0 / rec.fs_hz
    ref = load_model(newest["model"])[0].simulate(v["x"], v["y"], dt_s=dt)[0]
    for r in rows:
        w = load_model(r["model"])[0].simulate(v["x"], v["y"], dt_s=dt)[0]
        for a, ax in r["axes"].items():
            if a in w and a in ref:
                d = w[a] - ref[a]
                ax["change_um"] = float(np.sqrt(np.mean((d - d.mean()) ** 2)))


def growth(rows) -> list[dict]:
    """Per axis and effect named against the reference: its size in the first bag and
    the last, the change [%], and the first date it had changed by GROWTH_PCT or more
    (an effect absent at first: the date it first appeared)."""
    out = []
    for a in ("x", "y"):
        named = sorted({e for r in rows for e in r["axes"].get(a, {}).get("against", {})
                        .get("effects", {})})
        for e in named:
            series = [(r["started_utc"], r["axes"].get(a, {}).get("against", {})
                       .get("effects", {}).get(e)) for r in rows]
            first = next(s[1] for s in series if s[1] is not None)
            size_of = first["size_of"]
            vals = [(d, x["size"] if x is not None and x["size_of"] == size_of else 0.0)
                    for d, x in series]
            v0 = vals[0][1]
            crossed = None
            for d, x in vals:
                if (v0 == 0.0 and x != 0.0) or (v0 != 0.0 and
                                                abs(x / v0 - 1.0) * 100.0 >= GROWTH_PCT):
                    crossed = d
                    break
            change = (vals[-1][1] / v0 - 1.0) * 100.0 if v0 != 0.0 else math.inf
            out.append({"axis": a, "effect": e, "size_of": size_of, "first": v0,
                        "first_utc": vals[0][0], "last": vals[-1][1],
                        "last_utc": vals[-1][0], "change_pct": change,
                        "crossed_utc": crossed, "bags_named": sum(x is not None
                                                                  for _, x in series)})
    return out


def _when(iso: str) -> str:
    """A run's start to the second, UTC ("YYYY-MM-DD hh:mm:ss"): runs of one day are
    told apart."""
    return iso[:19].replace("T", " ")


def growth_lines(g: list[dict]) -> list[str]:
    """What changed, one line each ("x: creep +45 % since <first run> (gamma 0.0300 ->
    0.0435); changed by 30 % on <that run>")."""
    lines = []
    for e in g:
        since = _when(e["first_utc"])
        if math.isinf(e["change_pct"]):
            lines.append(f"{e['axis']}: {e['effect']} appeared on "
                         f"{_when(e['crossed_utc'] or e['first_utc'])} (absent on {since}; "
                         f"{e['size_of']} {e['last']:.4g} on {_when(e['last_utc'])})")
            continue
        when = (f"; changed by {GROWTH_PCT:.0f} % on {_when(e['crossed_utc'])}"
                if e["crossed_utc"] else f"; never by {GROWTH_PCT:.0f} %")
        lines.append(f"{e['axis']}: {e['effect']} {e['change_pct']:+.0f} % since {since} "
                     f"({e['size_of']} {e['first']:.4g} -> {e['last']:.4g}){when}")
    return lines


def table_columns(rows) -> Doc:
    """The CSV's columns: bag, date and per axis the figures (and the effect sizes)."""
    cols = {"bag": [r["name"] for r in rows], "started_utc": [r["started_utc"] for r in rows],
            "dated_by": [r["dated_by"] for r in rows]}
    axes = [a for a in ("x", "y") if any(a in r["axes"] for r in rows)]
    for a in axes:
        for k in ("gain_um_per_V", "fit_rms_um", "held_out_rms_um", "change_um"):
            cols[f"{a}_{k}"] = [r["axes"].get(a, {}).get(k, float("nan")) for r in rows]
        named = sorted({e for r in rows for e in r["axes"].get(a, {}).get("against", {})
                        .get("effects", {})})
        if any("against" in r["axes"].get(a, {}) for r in rows):
            cols[f"{a}_verdict"] = [r["axes"].get(a, {}).get("against", {})
                                    .get("verdict", "") for r in rows]
        for e in named:
            cols[f"{a}_{e}"] = [r["axes"].get(a, {}).get("against", {}).get("effects", {})
                                .get(e, {}).get("size", 0.0) for r in rows]
    return cols
