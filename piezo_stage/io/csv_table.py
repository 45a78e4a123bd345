"""CSV tables with a header row: read named float columns, write atomically."""

from __future__ import annotations

import numpy as np

from piezo_stage.core.errors import DataError, printable
from piezo_stage.core.estimation.record import Record
from piezo_stage.core.types import Doc
from piezo_stage.io.files import atomic_write, check_input


def read_table(path, required, optional=()) -> Doc:
    """Read columns by header name.

    Raises DataError (one line) for a missing file, missing or misnamed columns,
    non-numeric cells, ragged rows, NaN or inf.
    """
    header, body = _read_text(path)
    # comma-separated; a semicolon-separated file (a spreadsheet's export in locales
    # with a decimal comma) is read the same way when its header has no comma
    sep = ";" if ";" in header and "," not in header else ","
    names = [h.strip() for h in header.strip().split(sep)]
    shown = printable(", ".join(names))  # a header is echoed escaped and cut
    path = printable(path)
    if not header.strip():
        raise DataError(f"{path}: empty file (expected a header row)")
    missing = [c for c in required if c not in names]
    if missing:
        raise DataError(f"{path}: missing column(s) {', '.join(missing)}; header has "
                        f"{shown} (expected {', '.join(required)})")
    if len(set(names)) != len(names):
        raise DataError(f"{path}: duplicate column names in header")
    rows = [r for r in body.splitlines() if r.strip()]
    if not rows:
        raise DataError(f"{path}: no data rows")
    data = np.empty((len(rows), len(names)))
    for i, r in enumerate(rows):
        cells = r.split(sep)
        if len(cells) != len(names):
            raise DataError(f"{path}: line {i + 2} has {len(cells)} fields, header has "
                            f"{len(names)}")
        try:
            data[i] = [float(c) for c in cells]
        except ValueError:
            raise DataError(f"{path}: line {i + 2} has a non-numeric value") from None
    bad = ~np.isfinite(data)
    if bad.any():
        i, j = np.argwhere(bad)[0]
        raise DataError(f"{path}: line {i + 2}, column {names[j]} is NaN or inf")
    cols = {n: data[:, k] for k, n in enumerate(names) if n in required or n in optional}
    return cols


MAX_HEADER_CHARS = 65536


def _read_text(path) -> tuple[str, str]:
    """(header line, the rest) of a regular, bounded UTF-8 file; DataError otherwise."""
    check_input(path, what="CSV")
    try:
        with open(path, newline="", encoding="utf-8-sig") as fh:  # a BOM is not a name
            header = fh.readline(MAX_HEADER_CHARS + 1)
            if len(header) > MAX_HEADER_CHARS:
                raise DataError(f"{printable(path)}: no header line in the first "
                                f"{MAX_HEADER_CHARS} characters: not a CSV")
            body = fh.read()
    except (UnicodeDecodeError, PermissionError) as e:
        raise DataError(f"{printable(path)}: cannot read as UTF-8 text "
                        f"({type(e).__name__})") from None
    return header, body


def _near(name: str, candidates: list[str]) -> str | None:
    """The candidate ``name`` most likely misspells (any case, one slip), else None."""
    import difflib
    low = {c.lower(): c for c in candidates}
    if name.lower() in low:
        return low[name.lower()]
    hit = difflib.get_close_matches(name.lower(), list(low), n=1, cutoff=0.75)
    return low[hit[0]] if hit else None


def write_table(path, columns: Doc, fmt="%.10g"):
    """Write named columns (equal length) with a header row, atomically."""
    names = list(columns)
    data = np.column_stack([np.asarray(columns[n], float) for n in names])
    with atomic_write(path) as fh:
        fh.write(",".join(names) + "\n")
        np.savetxt(fh, data, delimiter=",", fmt=fmt)


def read_record(path, axes=("x", "y"), need_w=True) -> Record:
    """Read t, v<axis>, w<axis> columns of a record CSV (seconds, volts, micrometres).

    Axes whose columns are absent are skipped; at least one complete axis is needed.
    """
    header, _ = _read_text(path)
    names = [h.strip() for h in header.strip().split(";" if ";" in header and
                                                      "," not in header else ",")]
    expected = ["t"] + [f"{c}{a}" for a in axes for c in ("v", "w")]
    for n in names:  # a misnamed column is named, not passed over for the other axis
        near = _near(n, [e for e in expected if e not in names])
        if near and n not in expected:
            raise DataError(f"{printable(path)}: column {printable(n, 40)!r} is not one "
                            f"of t, vx, vy, wx, wy (did you mean {near!r}?)")
        if len(n) == 2 and n[0] in "vw" and n not in expected:  # another axis's name
            raise DataError(f"{printable(path)}: column {printable(n, 40)!r} is not one "
                            "of t, vx, vy, wx, wy (the axes are x and y)")
    if need_w:
        for a in axes:  # half an axis: its voltage without its displacement, or back
            got = [c for c in (f"v{a}", f"w{a}") if c in names]
            if len(got) == 1:
                lack = f"w{a}" if got[0].startswith("v") else f"v{a}"
                raise DataError(f"{printable(path)}: column {lack} is missing ({got[0]} is "
                                f"there); header has {printable(', '.join(names))}")
    present = [a for a in axes if f"v{a}" in names and (not need_w or f"w{a}" in names)]
    if "t" not in names or not present:
        want = "t,vx,vy,wx,wy" if need_w else "t,vx,vy"
        raise DataError(f"{path}: missing columns: need t and, for at least one axis, "
                        f"v<axis>{',w<axis>' if need_w else ''} (e.g. {want}); header has "
                        f"{printable(', '.join(names))}")
    req = ["t"] + [f"v{a}" for a in present] + ([f"w{a}" for a in present] if need_w else [])
    cols = read_table(path, req)
    return Record(cols["t"], {a: cols[f"v{a}"] for a in present},
                  {a: cols[f"w{a}"] for a in present} if need_w else {}, source=str(path))
