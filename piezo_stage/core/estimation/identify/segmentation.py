"""Split a record into ascending and descending branches.

The branch of a sample is the direction of the voltage since the last *turning point*.
A turning point is confirmed only once the voltage has moved back from the running
extremum by more than a threshold (a Schmitt trigger), so sensor noise on a measured
voltage, holds and tiny reversals do not split a branch. The threshold defaults to the
larger of 1 % of the voltage span and 5 x a robust estimate of the voltage noise.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike

from piezo_stage.core.errors import DataError


@dataclass
class Segmentation:
    """A record split by branch: labels[k] = +1 (ascending) or -1 (descending); segments
    as (start, stop, sign)."""

    labels: np.ndarray
    segments: list
    turning_points: np.ndarray
    threshold_V: float

    def mask(self, ascending: bool) -> np.ndarray:
        """Boolean mask of the samples on branch ``asc``."""
        return self.labels == (1 if ascending else -1)

    def count(self, ascending: bool) -> int:
        """How many samples are on branch ``asc``."""
        return int(np.count_nonzero(self.mask(ascending)))


def voltage_noise(v: ArrayLike) -> float:
    """Robust white-noise RMS of a voltage record [V] (third differences, MAD)."""
    d3 = np.diff(np.asarray(v, float), 3)
    if d3.size == 0:
        return 0.0
    return float(1.4826 * np.median(np.abs(d3 - np.median(d3))) / np.sqrt(20.0))


def segment(v: ArrayLike, threshold_V: float | None = None) -> Segmentation:
    """Label each sample of ``v`` [V] by branch; see the module docstring."""
    v = np.asarray(v, float)
    if v.size < 3:
        raise DataError("record too short to segment (need at least 3 samples)")
    span = float(np.ptp(v))
    if span == 0.0:
        raise DataError("voltage is constant: nothing to identify")
    thr = threshold_V if threshold_V is not None else max(0.01 * span, 5 * voltage_noise(v))
    labels = np.zeros(v.size, dtype=np.int8)
    turning = []
    # initial direction: the first move larger than the threshold
    moved = np.flatnonzero(np.abs(v - v[0]) > thr)
    if moved.size == 0:
        raise DataError(f"voltage never moves more than {thr:.3g} V: nothing to identify")
    direction = 1 if v[moved[0]] > v[0] else -1
    ext_i = 0
    start = 0
    segments = []
    for k in range(1, v.size):
        if direction > 0:
            if v[k] >= v[ext_i]:
                ext_i = k
            elif v[ext_i] - v[k] > thr:
                segments.append((start, ext_i + 1, 1))
                turning.append(ext_i)
                start, direction, ext_i = ext_i + 1, -1, k
        else:
            if v[k] <= v[ext_i]:
                ext_i = k
            elif v[k] - v[ext_i] > thr:
                segments.append((start, ext_i + 1, -1))
                turning.append(ext_i)
                start, direction, ext_i = ext_i + 1, 1, k
    segments.append((start, v.size, direction))
    for a, b, s in segments:
        labels[a:b] = s
    return Segmentation(labels, segments, np.asarray(turning, int), float(thr))


def branch_monotone(v: ArrayLike, seg: Segmentation | None = None) -> np.ndarray:
    """The voltage with noise-driven micro-reversals removed inside each branch.

    The discrete Duhem law accumulates |dv|: sensor noise on a *measured* voltage adds
    path length (and branch flips) the actuator never saw. Within each segment the
    voltage is replaced by its running maximum (ascending) or minimum (descending).
    A clean commanded voltage is returned unchanged.
    """
    v = np.asarray(v, float)
    seg = seg or segment(v)
    out = v.copy()
    for a, b, sign in seg.segments:
        out[a:b] = np.maximum.accumulate(v[a:b]) if sign > 0 else np.minimum.accumulate(v[a:b])
    return out


MINOR_LOOP_DEPTH = 0.1  # of the span: a reversal this far inside the record's range


def inner_reversals(v: ArrayLike) -> int:
    """How many of the voltage's reversals lie inside its range by more than
    ``MINOR_LOOP_DEPTH`` of its span (a maximum below the top, a minimum above the
    bottom): the minor loops a record holds. A calibration of constant amplitude has
    none, and there every class with memory fits its major loop alike: they differ
    only in the minor loops the record never showed."""
    v = np.asarray(v, float)
    seg = segment(v)
    tp = seg.turning_points
    if tp.size == 0:
        return 0
    lo, hi = float(v.min()), float(v.max())
    depth = MINOR_LOOP_DEPTH * (hi - lo)
    top = np.array([seg.labels[i] > 0 for i in tp])  # a maximum ends a rising branch
    inner = np.where(top, v[tp] < hi - depth, v[tp] > lo + depth)
    return int(np.count_nonzero(inner))
