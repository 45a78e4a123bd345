"""Disturbances: a narrow line in the residual that the input does not cause (a floor
vibration), with the feedback bandwidth that rejects it."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from scipy import signal

from piezo_stage.core.estimation.gap.where import held
from piezo_stage.core.estimation.record import Record
from piezo_stage.core.model.duhem import OTHER
from piezo_stage.core.types import Doc

PEAK_RATIO = 20.0   # a narrowband line: this many times the residual's median PSD


def disturbance(rec: Record, axis: str, resid: np.ndarray, nf: float) -> Doc | None:
    """Motion the input does not cause: the strongest narrow line in the residual's
    spectrum away from where the inputs have power (their tones, harmonics and step
    edges), when it stands clear of the residual's own floor. No model can remove it
    on held-out data, so it is reported with its size and band and the feedback
    bandwidth that would reject it (10x its frequency: |S| ~ f / f_bw, 20 dB).
    -> {freq_hz, band_hz, rms_um, feedback_bandwidth_hz} or None."""
    fs = rec.fs_hz
    r = resid - resid.mean()
    nper = int(min(len(r), 2 ** int(np.ceil(np.log2(max(fs * 4, 256))))))
    f, P = signal.welch(r, fs=fs, nperseg=nper)
    df = f[1] - f[0]
    quiet = np.ones(len(f), bool)
    for key in (axis, OTHER[axis]):
        u = rec.v.get(key)
        if u is None or np.ptp(u) <= 0:
            continue
        _, Pu = signal.welch(u - u.mean(), fs=fs, nperseg=nper)
        quiet &= Pu < 1e-4 * Pu.max()  # where the input has (next to) no power
        # and away from the harmonics of its tones (a hysteresis mismatch puts lines
        # there, caused by the input though the input has no power at them)
        # the input's tones, found at 1 Hz resolution (a tone played for a second or
        # two is spread over many fine bins), then placed on the fine ones: +-5 %
        # around each (the sidebands of a tone switched on and off) and +-1 % around
        # its harmonics, where a hysteresis mismatch puts lines
        fc, Pc = signal.welch(u - u.mean(), fs=fs, nperseg=int(min(len(u), fs)))
        peaks, _ = signal.find_peaks(Pc, prominence=1e-3 * Pc.max())
        for coarse in fc[peaks][fc[peaks] >= 0.5]:
            near = np.abs(f - coarse) <= 1.0      # the tone, to the fine resolution
            tone = float(f[near][np.argmax(Pu[near])])
            quiet &= np.abs(f - tone) > max(0.05 * tone, 1.0)
            for h in range(2, 11):
                quiet &= np.abs(f - h * tone) > 3 * df + 0.01 * h * tone
    quiet[f < 2.0] = False             # drift and creep live there
    if quiet.sum() < 20:
        return None
    floor = float(np.median(P[quiet]))
    low = f >= 2.0
    # where both inputs are held the input causes no line at all: a line that is
    # there too is a disturbance, whatever its frequency (so a vibration on a
    # harmonic of the excitation is still found); without such holds, only lines
    # away from the input's tones and harmonics are judged
    segs = _joint_holds(rec, axis)
    if segs:
        cand = signal.find_peaks(np.where(low, P, 0.0), height=PEAK_RATIO * floor)[0]
        cand = cand[np.argsort(P[cand])[::-1][:5]]
    else:
        cand = np.flatnonzero(quiet & (P > PEAK_RATIO * floor))
        cand = cand[np.argsort(P[cand])[::-1][:1]]
    for k in cand:
        lo, hi = max(k - 3, 0), min(k + 4, len(f))
        size = float(np.sqrt(np.sum(np.clip(P[lo:hi] - floor, 0, None)) * df))
        if size < 0.1 * nf:
            continue
        if segs and _line_rms(r, fs, f[k], segs) < 0.5 * size:
            continue  # absent while the inputs hold still: the input causes it
        return {"freq_hz": float(f[k]), "band_hz": [float(f[lo]), float(f[hi - 1])],
                "rms_um": size, "feedback_bandwidth_hz": 10.0 * float(f[k])}
    return None


def _joint_holds(rec: Record, axis: str, min_s: float = 0.25,
                 total_s: float = 1.0) -> list[tuple[int, int]]:
    """Sample ranges where both inputs are held (>= min_s each, >= total_s in all)."""
    mask = held(rec.v[axis], rec.fs_hz, min_s)
    vo = rec.v.get(OTHER[axis])
    if vo is not None and np.ptp(vo) > 0:
        mask &= held(vo, rec.fs_hz, min_s)
    edges = np.flatnonzero(np.diff(np.concatenate([[0], mask.astype(np.int8), [0]])))
    segs = [(a, b) for a, b in zip(edges[::2], edges[1::2]) if b - a >= min_s * rec.fs_hz]
    return segs if sum(b - a for a, b in segs) >= total_s * rec.fs_hz else []


def _line_rms(r: np.ndarray, fs: float, freq: float, segs: Sequence[tuple[int, int]]) -> float:
    """RMS of the sinusoid at freq in r over the segments (each fitted on its own:
    the line's phase need not carry across)."""
    power, n = 0.0, 0
    for a, b in segs:
        t = np.arange(b - a) / fs
        A = np.column_stack([np.sin(2 * np.pi * freq * t), np.cos(2 * np.pi * freq * t),
                             np.ones(b - a)])
        c, *_ = np.linalg.lstsq(A, r[a:b], rcond=None)
        power += (c[0] ** 2 + c[1] ** 2) / 2 * (b - a)
        n += b - a
    return float(np.sqrt(power / n))
