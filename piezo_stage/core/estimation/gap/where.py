"""Where a residual lives: holds (voltages held still), and the residual by band,
branch, turning points, holds, amplitude and the other axis's input."""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike
from scipy import signal

from piezo_stage.core.errors import DataError
from piezo_stage.core.estimation.identify.segmentation import segment
from piezo_stage.core.estimation.record import Record
from piezo_stage.core.metrics import rms
from piezo_stage.core.model.duhem import OTHER
from piezo_stage.core.types import Doc

MIN_HOLD_S = 1.0
RATE_PARTS = 4  # a record's main tone, read in this many parts (one rate: all alike)


def main_tones(v: ArrayLike, fs: float, parts: int = RATE_PARTS) -> list[float]:
    """The main tone [Hz] of each of ``parts`` equal parts of ``v`` (the largest
    spectral line above 0.5 Hz and one cycle of the part; 0 for a part that does not
    move)."""
    v = np.asarray(v, dtype=float)
    n = v.size // parts
    out = []
    for k in range(parts):
        seg = v[k * n:(k + 1) * n]
        if seg.size < 8 or np.ptp(seg) <= 0:
            out.append(0.0)
            continue
        m = 8 * seg.size  # zero-padded: the peak read finer than 1 / the part's length
        spec = np.abs(np.fft.rfft((seg - seg.mean()) * np.hanning(seg.size), m))
        f = np.fft.rfftfreq(m, 1.0 / fs)
        spec[f < max(0.5, fs / seg.size)] = 0.0
        out.append(float(f[int(np.argmax(spec))]) if spec.any() else 0.0)
    return out


SEVERAL_RATES = 2.0  # peak rates this far apart (max / min) are several rates


def several_rates(v: ArrayLike, fs: float, parts: int = RATE_PARTS) -> bool:
    """Whether ``v`` moves at several rates: the peak |dv/dt| (its 95th percentile) of
    the parts of ``v`` that move (``parts`` equal parts) at least ``SEVERAL_RATES``
    apart: a calibration at 2 Hz then 5 Hz, or rising-amplitude triangles (their slope
    grows), and not one sine or the gap protocol's 0.5 and 0.8 Hz sines alike."""
    v = np.asarray(v, dtype=float)
    n = v.size // parts
    span = float(np.ptp(v)) if v.size else 0.0
    peaks = []
    for k in range(parts):
        seg = v[k * n:(k + 1) * n]
        if seg.size < 8 or np.ptp(seg) < 0.05 * span:
            continue  # a hold (or nearly): no rate of its own
        peaks.append(float(np.percentile(np.abs(np.diff(seg)), 95)) * fs)
    return len(peaks) >= 2 and min(peaks) > 0 and max(peaks) >= SEVERAL_RATES * min(peaks)


def one_rate_note(fit: Record, holdout: Record, axis: str) -> str | None:
    """When FIT runs at one rate (every part's main tone alike) and HOLDOUT at another
    (its main tone at least twice or at most half FIT's): what the diagnosis cannot
    tell from such a FIT, and the calibration that would (None otherwise)."""
    f_fit = main_tones(fit.v[axis], fit.fs_hz)
    f_hold = main_tones(holdout.v[axis], holdout.fs_hz, 1)[0]
    if min(f_fit) <= 0 or f_hold <= 0 or max(f_fit) > 1.25 * min(f_fit):
        return None
    f0 = float(np.median(f_fit))
    if 0.5 * f0 < f_hold < 2.0 * f0:
        return None
    return (f"FIT runs at one rate ({f0:.3g} Hz) and HOLDOUT at another ({f_hold:.3g} Hz): "
            "an effect that grows with the rate (a loop that widens, a lag) cannot be "
            "identified from one rate; calibrate at two rates at least (e.g. "
            f"{f0:.3g} and {2.5 * f0:.3g} Hz, each for a few cycles)")


def hold_runs(v: ArrayLike, fs: float, min_s: float = 0.2,
              tol_frac: float = 1e-3) -> list[tuple[int, int]]:
    """The holds of ``v``: [(start, stop)] sample ranges of at least ``min_s`` seconds
    over which the voltage stays within ``tol_frac`` of its span (the whole stretch,
    not sample to sample: a slow sine's turning points and a staircase DAC output move
    on, and are not holds)."""
    from piezo_stage.core.estimation._kernels import hold_runs_kernel
    v = np.ascontiguousarray(v, dtype=float)
    if v.size == 0:
        return []
    tol = tol_frac * max(float(np.ptp(v)), 1e-12)
    need = max(int(round(min_s * fs)), 1)
    out = np.empty((v.size // need + 1, 2), np.int64)
    n = hold_runs_kernel(v, tol, need, out)
    return [(int(a), int(b)) for a, b in out[:n]]


def held(v: ArrayLike, fs: float, min_s: float = 0.2, tol_frac: float = 1e-3) -> np.ndarray:
    """Mask of the samples inside holds (see ``hold_runs``)."""
    mask = np.zeros(np.size(v), dtype=np.bool_)
    for a, b in hold_runs(v, fs, min_s, tol_frac):
        mask[a:b] = True
    return mask


def holds(v: ArrayLike, fs: float, min_s: float = MIN_HOLD_S) -> list[float]:
    """Lengths [s] of the holds of at least ``min_s`` seconds (see ``hold_runs``)."""
    return [(b - a) / fs for a, b in hold_runs(v, fs, min_s)]


def where(rec: Record, axis: str, resid: np.ndarray, nf: float) -> Doc:
    """Localise the residual: band, segment, amplitude, correlation with the other axis."""
    v = rec.v[axis]
    fs = rec.fs_hz
    out = {"axis": axis, "rms_um": rms(resid), "noise_floor_um": nf}
    f, P = signal.welch(resid - resid.mean(), fs=fs, nperseg=min(len(resid), 4096))
    white = nf ** 2 / (fs / 2)  # one-sided PSD of white noise of variance nf^2
    edges = [0.0, 0.3, 3.0, 30.0, 300.0, fs / 2]
    bands = []
    for lo, hi in zip(edges[:-1], edges[1:]):
        m = (f >= lo) & (f < hi) if hi < fs / 2 else (f >= lo)
        if m.sum() == 0 or lo >= fs / 2:
            continue
        excess = float(np.sum(np.clip(P[m] - white, 0, None)) * (f[1] - f[0]))
        bands.append(((lo, min(hi, fs / 2)), excess))
    (blo, bhi), _ = max(bands, key=lambda b: b[1])
    out["band_hz"] = [blo, bhi]
    out["band_excess_um2"] = {f"{lo:g}-{hi:g}": e for (lo, hi), e in bands}
    dv = np.diff(v, prepend=v[0])
    try:
        seg = segment(v)
        turn = np.zeros(len(v), bool)
        wdt = max(1, int(0.02 * fs))
        for i in seg.turning_points:
            turn[max(i - wdt, 0):i + wdt] = True
        labels = seg.labels
    except DataError:
        turn = np.zeros(len(v), bool)
        labels = np.sign(dv)
    still = held(v, fs)
    parts = {"ascending": (labels > 0) & ~turn & ~still,
             "descending": (labels < 0) & ~turn & ~still,
             "turning_points": turn & ~still, "holds": still}
    seg_rms = {k: rms(resid[m]) for k, m in parts.items() if m.sum() > 10}
    out["segment_rms_um"] = seg_rms
    out["segment"] = max(seg_rms, key=lambda k: seg_rms[k])
    q = np.quantile(v, [1 / 3, 2 / 3])
    amp = {"low": v <= q[0], "mid": (v > q[0]) & (v <= q[1]), "high": v > q[1]}
    out["amplitude_rms_um"] = {k: rms(resid[m]) for k, m in amp.items() if m.sum() > 10}
    vo = rec.v.get(OTHER[axis])
    if vo is not None and np.ptp(vo) > 0:
        out["corr_other_input"] = float(np.corrcoef(resid, vo)[0, 1])
    return out
