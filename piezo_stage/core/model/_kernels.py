"""The model's compiled kernels (core/_jit.py compiles them): one per formula,
``horner`` (polynomials), ``branch_step`` / ``duhem_step`` (the paper's eq. 6),
``amplifier_step`` (clamp, then slew); the batch runs, the plant (``plant_run``), the
play operators, the sensor, the exact inverse (``inverse_one``, ``stage_inverse_step``)
and the effects' column filters call them."""

import numpy as np
from numpy.typing import NDArray

from piezo_stage.core._jit import F64, PREFIX, njit


@njit
def horner(c: F64, x: float) -> float:
    """A branch polynomial at x, ``c`` a branch row (PREFIX): the polynomial
    sum_i c[PREFIX + i] x**i over [lo, hi] (the fitted range and its margin:
    duhem.polynomial_range), and outside it the straight continuation from the nearer
    end with the end's slope, precomputed: the polynomial's own tail past the data is
    no physics, and a degree-5 tail reached 1e11 um/V a few tens of volts beyond a
    record's range."""
    if x > c[1]:
        return c[4] + c[5] * (x - c[1])
    if x < c[0]:
        return c[2] + c[3] * (x - c[0])
    p = c[PREFIX:]  # (a loop to index -1 over the slice compiles 3.4 x faster than a
    acc = 0.0       # loop that stops at PREFIX - 1: measured on 2M Duhem steps)
    for i in range(p.shape[0] - 1, -1, -1):
        acc = acc * x + p[i]
    return acc


@njit
def branch_step(v_prev: float, w_prev: float, vk: float, alpha_b: float, h: F64) -> float:
    """One step of the paper's eq. 6 on one branch, the one formula of the Duhem step:
    w_k = (w_{k-1} + dv h(v_k)) / (1 + alpha |dv|), h's coefficients lowest power first."""
    dv = vk - v_prev
    return (w_prev + dv * horner(h, vk)) / (1.0 + alpha_b * abs(dv))


@njit
def duhem_step(v_prev: float, w_prev: float, vk: float, alpha: F64, H: F64) -> float:
    """One step of the paper's eq. 6 from (v_prev, w_prev) to voltage vk, on the branch the
    step's sign picks (H is (2, D): ascending, descending)."""
    b = 0 if vk >= v_prev else 1
    return branch_step(v_prev, w_prev, vk, alpha[b], H[b])


@njit
def duhem_run(v: F64, v_prev: float, w_prev: float, alpha: F64, H: F64,
              out: F64) -> tuple[float, float]:
    """Run the discrete Duhem recursion (the paper's eq. 6) over ``v``.

    w_k = (w_{k-1} + dv_k * H_b(v_k)) / (1 + alpha_b |dv_k|),  dv_k = v_k - v_{k-1},
    with branch b = 0 (ascending, dv >= 0) or 1 (descending). ``H[0] = f + g`` and
    ``H[1] = g - f`` (see duhem.py). Writes ``out`` and returns the final (v, w).
    """
    for k in range(v.shape[0]):
        w_prev = duhem_step(v_prev, w_prev, v[k], alpha, H)
        out[k] = w_prev
        v_prev = v[k]
    return v_prev, w_prev


@njit
def slew_clamp_run(v: F64, v_prev: float, v_min: float, v_max: float, max_step: float,
                   out: F64) -> tuple[float, int]:
    """Amplifier: clamp to [v_min, v_max], then limit |v_k - v_{k-1}| to max_step.

    Returns (final voltage, number of samples that hit a limit).
    """
    hits = 0
    for k in range(v.shape[0]):
        x, hit = amplifier_step(v[k], v_prev, v_min, v_max, max_step)
        if hit:
            hits += 1
        out[k] = x
        v_prev = x
    return v_prev, hits


@njit
def amplifier_step(x: float, v_prev: float, v_min: float, v_max: float,
                   max_step: float) -> tuple[float, bool]:
    """One amplifier sample: clamp to [v_min, v_max], then limit the step from v_prev.
    Returns (output, whether a limit was hit)."""
    hit = False
    if x > v_max:
        x = v_max
        hit = True
    elif x < v_min:
        x = v_min
        hit = True
    d = x - v_prev
    if d > max_step:
        x = v_prev + max_step
        hit = True
    elif d < -max_step:
        x = v_prev - max_step
        hit = True
    return x, hit


@njit
def plant_run(vx: F64, vy: F64, substeps: int, vstate: F64, dstate: F64, alpha: F64, H: F64,
              present: NDArray[np.bool_], v_min: float, v_max: float, max_step: float,
              applied: F64, w: F64) -> int:
    """The plant's hysteresis path over the commands ``vx``, ``vy`` [V] (zero-order
    hold, ``substeps`` samples per command): per sample the amplifier (clamp, then
    slew) and the Duhem steps of the models x, y, coupling into x (driven by y),
    coupling into y (driven by x). The one arithmetic of ``Plant.run`` and
    ``Plant.step``.

    State, updated in place: ``vstate[2]`` amplifier outputs, ``dstate[4, 2]`` (v, w)
    per model; ``alpha[4, 2]``, ``H[4, 2, D]``, ``present[4]``. Writes
    ``applied[2, n * substeps]`` [V] and ``w[2, n * substeps]`` [um] (0 on an axis
    without a model); returns the number of samples that hit a limit.
    """
    hits = 0
    k = 0
    for i in range(vx.shape[0]):
        for _ in range(substeps):
            for a in range(2):
                x, hit = amplifier_step(vx[i] if a == 0 else vy[i], vstate[a], v_min, v_max,
                                        max_step)
                if hit:
                    hits += 1
                vstate[a] = x
                applied[a, k] = x
            for a in range(2):
                wa = 0.0
                if present[a]:
                    wa = duhem_step(dstate[a, 0], dstate[a, 1], vstate[a], alpha[a], H[a])
                    dstate[a, 0] = vstate[a]
                    dstate[a, 1] = wa
                c = 2 + a
                if present[c]:  # (also under another law on the axis: Plant adds it)
                    wc = duhem_step(dstate[c, 0], dstate[c, 1], vstate[1 - a], alpha[c],
                                    H[c])
                    dstate[c, 0] = vstate[1 - a]
                    dstate[c, 1] = wc
                    wa = wa + wc
                w[a, k] = wa
            k += 1
    return hits


@njit
def play_clamp(vk: float, r: float, z: float) -> float:
    """One play operator (threshold ``r``) from state ``z`` at voltage ``vk``: its new
    state, the one formula of every play path."""
    lo, hi = vk - r, vk + r
    return lo if z < lo else (hi if z > hi else z)


@njit
def band(z: float, lo: float, hi: float) -> float:
    """A play operator's output: its state ``z`` clipped to its band [lo, hi] (a
    discretized Preisach law's cell; +-inf for a plain play operator)."""
    return lo if z < lo else (hi if z > hi else z)


@njit
def play_sum(vk: float, r: F64, p: F64, z: F64, widen: float = 0.0) -> float:
    """The operators' sum_j p_j band_j(z_j) [um] after voltage ``vk`` from state ``z``
    (left as it is); ``r`` the operators' table (3, n): thresholds, band lows, band
    highs (core/model/play.py's ``table``); every threshold widened by ``widen`` [V]
    (a rate-dependent law)."""
    s = 0.0
    for j in range(r.shape[1]):
        s += p[j] * band(play_clamp(vk, r[0, j] + widen, z[j]), r[1, j], r[2, j])
    return s


@njit
def play_advance(vk: float, r: F64, p: F64, z: F64, widen: float = 0.0) -> float:
    """``play_sum``, with the state ``z`` moved to voltage ``vk``."""
    s = 0.0
    for j in range(r.shape[1]):
        z[j] = play_clamp(vk, r[0, j] + widen, z[j])
        s += p[j] * band(z[j], r[1, j], r[2, j])
    return s


@njit
def rate_widen(vk: float, vp: float, rate: F64) -> float:
    """The thresholds' widening [V] at voltage ``vk`` after ``vp``, for a rate-dependent
    law's ``rate`` = [decay, gain, widening before] (a rate-independent law: zeros):
    beta times the low-passed |dv/dt|, which is decay x the widening before plus
    gain x |vk - vp| (decay = 1 - s, gain = beta s / dt for the filter's coefficient s
    per sample). The operators' sum is monotone in vk while gain < 1."""
    return rate[0] * rate[2] + rate[1] * abs(vk - vp)


@njit
def play_run(v: F64, r: F64, p: F64, z: F64, out: F64) -> None:
    """Play operators (table ``r``: see ``play_sum``; weights ``p``, state ``z``,
    updated in place) over ``v`` [V]; writes their sum [um] per sample into ``out``."""
    for k in range(v.shape[0]):
        out[k] = play_advance(v[k], r, p, z)


@njit
def play_run_rate(v: F64, state: F64, dt: float, beta: float, smooth: float, r: F64,
                  p: F64, z: F64, out: F64) -> None:
    """Rate-dependent play operators (thresholds r_j + beta |dv/dt|: the loop widens
    with the input's rate, as the rate-dependent Prandtl-Ishlinskii law of Al Janaideh
    et al. has it) over ``v`` [V], ``dt`` [s] apart; |dv/dt| low-passed (``smooth``:
    the filter's coefficient per sample; an amplifier's held steps are one rate, not a
    spike and zeros); ``state`` = [the voltage before, the filtered rate], updated, as
    ``z``; ``r`` the operators' table (see ``play_sum``); writes their sum [um] per
    sample into ``out``."""
    v_prev, rate = state[0], state[1]
    for k in range(v.shape[0]):
        rate += smooth * (abs(v[k] - v_prev) / dt - rate)
        v_prev = v[k]
        out[k] = play_advance(v[k], r, p, z, beta * rate)
    state[0], state[1] = v_prev, rate


@njit
def sensor_run(true: F64, noise: F64, noise_rms: float, quant: float, out: F64) -> None:
    """The sensor on ``true[2, n]`` [um]: white noise (``noise[n, 2]`` standard normal,
    times ``noise_rms``), then quantisation to ``quant`` (0: none). Writes ``out``."""
    for i in range(true.shape[1]):
        for a in range(2):
            m = true[a, i] + noise_rms * noise[i, a]
            if quant > 0.0:
                m = np.round(m / quant) * quant
            out[a, i] = m


@njit
def _branch_residual(dv: float, vp: float, wp: float, wt: float, alpha: float,
                     H: F64, r: F64, p: F64, z: F64, q: F64) -> float:
    # r(dv) = (w_prev + dv H(v_prev+dv)) - (1 + alpha |dv|) (w_target - P(v_prev+dv)):
    # zero where the forward step from (v_prev, w_prev), plus the play operators' sum P
    # from their state z (thresholds widened as ``q`` says), lands exactly on w_target
    # (P is 0 without operators)
    vk = vp + dv
    return wp + dv * horner(H, vk) - (1.0 + alpha * abs(dv)) * (
        wt - play_sum(vk, r, p, z, q[0] * q[2] + q[1] * abs(dv)))


@njit
def _first_root(vp: float, wp: float, wt: float, alpha: float, H: F64, span: float,
                n_scan: int, r: F64, p: F64, z: F64, q: F64) -> tuple[float, bool]:
    # Smallest |dv| in (0, span] (span signed) where the residual changes sign: scan,
    # then bisect-polish the first bracket to machine precision. Returns (dv, found).
    r0 = _branch_residual(0.0, vp, wp, wt, alpha, H, r, p, z, q)
    lo = 0.0
    rlo = r0
    for j in range(1, n_scan + 1):
        hi = span * j / n_scan
        rhi = _branch_residual(hi, vp, wp, wt, alpha, H, r, p, z, q)
        if rlo == 0.0:
            return lo, True
        if (rlo < 0.0) != (rhi < 0.0) or rhi == 0.0:
            # Illinois-modified regula falsi: superlinear, always bracketed
            a, fa, b, fb = lo, rlo, hi, rhi
            side = 0
            for _ in range(200):
                c = (a * fb - b * fa) / (fb - fa)
                fc = _branch_residual(c, vp, wp, wt, alpha, H, r, p, z, q)
                if fc == 0.0 or abs(b - a) < 1e-13 * (1.0 + abs(c)):
                    return c, True
                if (fc < 0.0) == (fb < 0.0):
                    b, fb = c, fc
                    if side == -1:
                        fa *= 0.5
                    side = -1
                else:
                    a, fa = c, fc
                    if side == 1:
                        fb *= 0.5
                    side = 1
            return c, True
        lo, rlo = hi, rhi
    # no sign change: the target is beyond the limit, unless it sits on the limit
    # itself within rounding (residual at the end ~ 1e-12 of the displacement scale)
    return span, abs(rlo) <= 1e-9 * (1.0 + abs(wt))


@njit
def inverse_one(wt: float, v_prev: float, w_prev: float, alpha: F64, H: F64, v_min: float,
                v_max: float, n_scan: int, r: F64, p: F64,
                z: F64, q: F64) -> tuple[float, float, bool]:
    """Exact inverse for one sample: (v, Duhem w after v, saturated) from (v_prev,
    w_prev) and the play operators' state ``z`` (table ``r``, see ``play_sum``; weights
    ``p``; empty for none; ``q`` their rate widening, see ``rate_widen``), which is left as it is:
    the caller advances it with the voltage used.

    Picks the branch by the sign of the requested change, finds the voltage nearest to
    v_prev that makes the forward step hit ``wt`` (the Duhem output plus the operators'
    sum), clamps to [v_min, v_max]. Saturated means exactly: the target was not met
    (the root search can fail on rounding right at a limit, where the target is in fact
    reached, which is why the flag is decided on the result).
    """
    now = w_prev + play_sum(v_prev, r, p, z, q[0] * q[2])
    if wt > now and v_max > v_prev:
        dv = _first_root(v_prev, w_prev, wt, alpha[0], H[0], v_max - v_prev, n_scan,
                         r, p, z, q)[0]
    elif wt < now and v_min < v_prev:
        dv = _first_root(v_prev, w_prev, wt, alpha[1], H[1], v_min - v_prev, n_scan,
                         r, p, z, q)[0]
    else:
        dv = 0.0
    vk = min(max(v_prev + dv, v_min), v_max)
    w = duhem_step(v_prev, w_prev, vk, alpha, H)
    total = w + play_sum(vk, r, p, z, rate_widen(vk, v_prev, q))
    return vk, w, abs(total - wt) > 1e-9 * (1.0 + abs(wt))


@njit
def play_commit(vk: float, vp: float, r: F64, p: F64, z: F64, q: F64) -> float:
    """Move the operators' state ``z`` (and ``q``'s widening) to voltage ``vk`` after
    ``vp``; returns their sum [um]."""
    widen = rate_widen(vk, vp, q)
    q[2] = widen
    return play_advance(vk, r, p, z, widen)


@njit
def duhem_inverse_run(w_target: F64, v_prev: float, w_prev: float, alpha: F64, H: F64,
                      v_min: float, v_max: float, n_scan: int, r: F64, p: F64, z: F64,
                      q: F64, out_v: F64, out_w: F64,
                      out_sat: NDArray[np.int8]) -> tuple[float, float]:
    """Exact per-sample inverse of :func:`duhem_run` plus play operators (``z`` their
    state, ``q`` their rate widening, both advanced in place) over a target sequence;
    the state follows what the model really does at the chosen (possibly saturated)
    voltage. ``out_w`` is the total."""
    for k in range(w_target.shape[0]):
        vk, wk, sat = inverse_one(w_target[k], v_prev, w_prev, alpha, H, v_min,
                                  v_max, n_scan, r, p, z, q)
        out_w[k] = wk + play_commit(vk, v_prev, r, p, z, q)
        v_prev, w_prev = vk, wk
        out_v[k] = vk
        out_sat[k] = 1 if sat else 0
    return v_prev, w_prev


@njit
def stage_sync(vx: float, vy: float, vp: F64, wp: F64, alpha: F64, H: F64, cvp: F64,
               cwp: F64, calpha: F64, cH: F64, pr: F64, pp: F64, pz: F64,
               pq: F64) -> None:
    """Advance a 2-axis model (direct part, play operators, coupling) by the applied
    voltages (``pr``, ``pp``, ``pz``: the operators' tables (2, 3, P), weights and state
    (2, P) per axis, zero weights as padding; ``pq``: their rate widening per axis,
    shape (2, 3), see ``rate_widen``)."""
    for a in range(2):
        va = vx if a == 0 else vy
        vo = vy if a == 0 else vx
        wp[a] = duhem_step(vp[a], wp[a], va, alpha[a], H[a])
        play_commit(va, vp[a], pr[a], pp[a], pz[a], pq[a])
        cwp[a] = duhem_step(cvp[a], cwp[a], vo, calpha[a], cH[a])
        vp[a] = va
        cvp[a] = vo


@njit
def stage_inverse_step(target: F64, vp: F64, wp: F64, alpha: F64, H: F64, cvp: F64,
                       cwp: F64, calpha: F64, cH: F64, pr: F64, pp: F64, pz: F64,
                       pq: F64, use_c: bool, v_min: float, v_max: float, sweeps: int,
                       n_scan: int, out: F64) -> F64:
    """Joint inverse of a 2-axis model with coupling for one sample (axis 0 = x, 1 = y).

    w_a = H_aa(v_a) + P_a(v_a) + H_ab(v_b): Gauss-Seidel sweeps, each solving one axis
    exactly for its target minus the coupling produced by the other axis's current
    voltage. ``out`` rows: v, w (direct part with its play operators), coupling output,
    saturated flag (per axis). The state is left as it is (``stage_sync`` advances it).
    """
    v0 = vp[0]
    v1 = vp[1]
    # without coupling the axes are independent: one sweep solves both; with it, the
    # sweeps stop once neither voltage moves by more than 1e-9 V (the fixed point)
    for s in range(sweeps if use_c else 1):
        last0, last1 = v0, v1
        for a in range(2):
            vo = v1 if a == 0 else v0
            wc = duhem_step(cvp[a], cwp[a], vo, calpha[a], cH[a]) if use_c else 0.0
            va, wa, sat = inverse_one(target[a] - wc, vp[a], wp[a], alpha[a], H[a],
                                      v_min, v_max, n_scan, pr[a], pp[a], pz[a], pq[a])
            if a == 0:
                v0 = va
            else:
                v1 = va
            out[0, a] = va
            out[1, a] = wa + play_sum(va, pr[a], pp[a], pz[a],
                                      rate_widen(va, vp[a], pq[a]))
            out[2, a] = wc
            out[3, a] = 1.0 if sat else 0.0
        if s > 0 and abs(v0 - last0) <= 1e-9 and abs(v1 - last1) <= 1e-9:
            break
    return out


@njit
def stage_inverse_ahead(ahead: F64, target: F64, vp: F64, wp: F64, alpha: F64, H: F64,
                        cvp: F64, cwp: F64, calpha: F64, cH: F64, pr: F64, pp: F64,
                        pz: F64, pq: F64, present: F64, use_c: bool, v_min: float,
                        v_max: float, sweeps: int, n_scan: int, out: F64) -> F64:
    """``stage_inverse_step`` for ``target`` after the targets still in flight
    (``ahead``, shape (k, 2), oldest first: each inverted and committed in turn, an axis
    the model lacks at ``v_min``), on a copy of the state, which is left as it was.
    ``out`` as ``stage_inverse_step``'s, its row 3 the saturations counted over every
    step (per axis). One compiled call where the loop's look-ahead asks for several
    (a 5 ms look-ahead at 1 kHz: six)."""
    vp2, wp2, cvp2, cwp2 = vp.copy(), wp.copy(), cvp.copy(), cwp.copy()
    pz2, pq2 = pz.copy(), pq.copy()
    sat0 = 0.0
    sat1 = 0.0
    for i in range(ahead.shape[0]):
        stage_inverse_step(ahead[i], vp2, wp2, alpha, H, cvp2, cwp2, calpha, cH, pr, pp,
                           pz2, pq2, use_c, v_min, v_max, sweeps, n_scan, out)
        vx = out[0, 0] if present[0] > 0.0 else v_min
        vy = out[0, 1] if present[1] > 0.0 else v_min
        sat0 += out[3, 0] * present[0]
        sat1 += out[3, 1] * present[1]
        stage_sync(vx, vy, vp2, wp2, alpha, H, cvp2, cwp2, calpha, cH, pr, pp, pz2, pq2)
    stage_inverse_step(target, vp2, wp2, alpha, H, cvp2, cwp2, calpha, cH, pr, pp, pz2,
                       pq2, use_c, v_min, v_max, sweeps, n_scan, out)
    out[3, 0] = out[3, 0] * present[0] + sat0
    out[3, 1] = out[3, 1] * present[1] + sat1
    return out


@njit
def iir_columns(b: F64, a: F64, X: F64, out: F64) -> F64:
    """Filter every column of X (N, p) from rest by b/a (a[0] = 1; direct form II
    transposed, any low order): the effect operators on the regressors. scipy's
    lfilter along axis 0 walks a row-major array with a stride; this walks it once."""
    n, p = X.shape
    order = max(b.shape[0], a.shape[0]) - 1
    bb = np.zeros(order + 1)
    aa = np.zeros(order + 1)
    bb[:b.shape[0]] = b
    aa[:a.shape[0]] = a
    z = np.zeros((order + 1, p))
    for k in range(n):
        for j in range(p):
            x = X[k, j]
            y = bb[0] * x + z[0, j]
            for i in range(1, order + 1):
                z[i - 1, j] = bb[i] * x - aa[i] * y + z[i, j]
            out[k, j] = y
    return out


@njit
def delay_columns(X: F64, n: int, fr: float, out: F64) -> F64:
    """The fractional delay y_k = (1 - fr) x_{k-n} + fr x_{k-n-1} of every column of
    X (N, p), zeros before the start: the delay effect's one formula (its streaming
    form runs it over the delay line's state followed by the new samples)."""
    for k in range(X.shape[0]):
        for j in range(X.shape[1]):
            a = X[k - n, j] if k >= n else 0.0
            b = X[k - n - 1, j] if k >= n + 1 else 0.0
            out[k, j] = (1.0 - fr) * a + fr * b
    return out


@njit
def lowpass_mean_columns(poles: F64, X: F64, out: F64) -> F64:
    """The mean of first-order low-passes y = (1 - p) x + p y_prev over ``poles``, of
    every column of X from rest, in one pass (the creep operator's slow part)."""
    n, p = X.shape
    m = poles.shape[0]
    y = np.zeros((m, p))
    for k in range(n):
        for j in range(p):
            x = X[k, j]
            acc = 0.0
            for i in range(m):
                y[i, j] = (1.0 - poles[i]) * x + poles[i] * y[i, j]
                acc += y[i, j]
            out[k, j] = acc / m
    return out
