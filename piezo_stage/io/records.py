"""Read a record from a CSV file or a recorded bag (directory or .mcap)."""

from __future__ import annotations

import os

from piezo_stage.core.errors import DataError
from piezo_stage.core.estimation.record import Record, on_grid
from piezo_stage.io.csv_table import read_record


def is_bag(path) -> bool:
    p = os.fspath(path)
    return os.path.isdir(p) or p.endswith(".mcap")


def load_record(path, need_w=True) -> Record:
    """A Record from ``path``: CSV (t,vx,vy,wx,wy or one axis's subset) or a bag, on a
    uniform grid (``core.estimation.record.on_grid``: a real-time bag's skipped ticks,
    a logger's jitter, lost samples; its ``notes`` say how)."""
    if not os.path.exists(path):
        raise DataError(f"{path}: no such file or directory")
    if is_bag(path):
        from piezo_stage.io.bag import read_bag_record
        return on_grid(read_bag_record(path))
    return on_grid(read_record(path, need_w=need_w))
