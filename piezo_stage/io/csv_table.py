"""CSV tables with a header row: read named float columns, write atomically."""

from __future__ import annotations

import numpy as np

from piezo_stage.core.errors import DataError
from piezo_stage.core.record import Record
from piezo_stage.io.files import atomic_write


def read_table(path, required, optional=()) -> dict:
    """Read columns by header name.

    Raises DataError (one line) for a missing file, missing or misnamed columns,
    non-numeric cells, ragged rows, NaN or inf.
    """
    try:
        with open(path, newline="", encoding="utf-8-sig") as fh:  # a BOM is not a name
            header = fh.readline()
            body = fh.read()
    except FileNotFoundError:
        raise DataError(f"{path}: no such file") from None
    except (IsADirectoryError, UnicodeDecodeError, PermissionError) as e:
        raise DataError(f"{path}: cannot read ({type(e).__name__})") from None
    # comma-separated; a semicolon-separated file (a spreadsheet's export in locales
    # with a decimal comma) is read the same way when its header has no comma
    sep = ";" if ";" in header and "," not in header else ","
    names = [h.strip() for h in header.strip().split(sep)]
    if not header.strip():
        raise DataError(f"{path}: empty file (expected a header row)")
    missing = [c for c in required if c not in names]
    if missing:
        raise DataError(f"{path}: missing column(s) {', '.join(missing)}; header has "
                        f"{', '.join(names)} (expected {', '.join(required)})")
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


def write_table(path, columns: dict, fmt="%.10g"):
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
    try:
        with open(path) as fh:
            names = [h.strip() for h in fh.readline().strip().split(",")]
    except (FileNotFoundError, IsADirectoryError, UnicodeDecodeError, PermissionError):
        raise DataError(f"{path}: no such file or not a readable CSV") from None
    present = [a for a in axes if f"v{a}" in names and (not need_w or f"w{a}" in names)]
    if "t" not in names or not present:
        want = "t,vx,vy,wx,wy" if need_w else "t,vx,vy"
        raise DataError(f"{path}: missing columns: need t and, for at least one axis, "
                        f"v<axis>{',w<axis>' if need_w else ''} (e.g. {want}); header has "
                        f"{', '.join(names)}")
    req = ["t"] + [f"v{a}" for a in present] + ([f"w{a}" for a in present] if need_w else [])
    cols = read_table(path, req)
    return Record(cols["t"], {a: cols[f"v{a}"] for a in present},
                  {a: cols[f"w{a}"] for a in present} if need_w else {}, source=str(path))
