"""Physics of the discrete Duhem model (the paper's eqs. 1-6)."""

import numpy as np
import pytest

from conftest import sine_v
from piezo_stage.core.model.duhem import DuhemBranch, DuhemHysteresis, DuhemModel, DuhemState


@pytest.fixture
def seg(stage_model):
    return stage_model.axes["x"]


def test_step_matches_batch_and_reset(seg):
    _, v = sine_v(1.0, 2000, 2)
    w_batch, final = seg.simulate(v)
    h = DuhemHysteresis(seg)
    w_step = np.array([h.step(x) for x in v])
    np.testing.assert_allclose(w_step, w_batch, rtol=0, atol=1e-12)
    assert h.state == final
    h.reset()
    assert h.state == seg.initial
    # batch in two pieces with the state carried equals one batch
    w1, s1 = seg.simulate(v[:1234])
    w2, _ = seg.simulate(v[1234:], s1)
    np.testing.assert_array_equal(np.concatenate([w1, w2]), w_batch)


def test_recursion_is_seed_eq6():
    # hand-computed two steps of eq. 6 with f, g quadratic
    m = DuhemModel(DuhemBranch(0.1, [1.0, 0.5], [0.2, 0.0, 0.01]),
                   DuhemBranch(0.2, [0.3], [0.4, 0.1]), DuhemState(0.0, 0.0))
    w, _ = m.simulate([2.0, 1.0])
    v1, v0 = 2.0, 0.0
    F = 1.0 + 0.5 * v1
    G = 0.2 + 0.01 * v1 ** 2
    w1 = (0 + (v1 - v0) * (F + G)) / (1 + 0.1 * abs(v1 - v0))
    F2, G2 = 0.3, 0.4 + 0.1 * 1.0
    w2 = (w1 + (1.0 - 2.0) * (G2 - F2)) / (1 + 0.2 * abs(1.0 - 2.0))
    np.testing.assert_allclose(w, [w1, w2], rtol=1e-14)


def test_loop_closes_on_periodic_input(seg):
    fs, f = 10_000, 1.0
    _, v = sine_v(f, fs, 6)
    w, _ = seg.simulate(v)
    per = int(fs / f)
    gaps = [np.max(np.abs(w[(k + 1) * per:(k + 2) * per] - w[k * per:(k + 1) * per]))
            for k in range(5)]
    # the transient from the virgin state dies out geometrically; the loop closes
    assert gaps[-1] < 1e-6
    assert gaps[0] > 1e-3          # there was a transient to die out
    assert all(b < a for a, b in zip(gaps, gaps[1:]) if a > 1e-12)
    # it is a real loop: the branches differ by several um at mid-stroke
    last = slice(-per, None)
    up = np.diff(v[last], prepend=v[last][0]) > 0
    i_up = np.argmin(np.abs(v[last] - 75) + 1e3 * ~up)
    i_dn = np.argmin(np.abs(v[last] - 75) + 1e3 * up)
    assert w[last][i_dn] - w[last][i_up] > 5.0


def test_discrete_result_converges_as_sampling_gets_finer(seg):
    ref_fs = 256_000
    _, vref = sine_v(1.0, ref_fs, 1)
    wref, _ = seg.simulate(vref)
    errs = []
    for fs in (1000, 2000, 4000, 8000, 16000):
        _, v = sine_v(1.0, fs, 1)
        w, _ = seg.simulate(v)
        step = ref_fs // fs
        errs.append(np.max(np.abs(w - wref[::step])))
    errs = np.array(errs)
    assert np.all(np.diff(errs) < 0)
    # implicit Euler is first order: halving the step halves the error
    np.testing.assert_allclose(errs[:-1] / errs[1:], 2.0, rtol=0.15)
    assert errs[-1] < 0.01


def test_rate_independent_loop_at_1_and_40_hz(seg):
    # same samples per cycle: the law only sees the voltage sequence -> identical loop
    n = 4000
    _, v1 = sine_v(1.0, 1.0 * n, 3)
    _, v40 = sine_v(40.0, 40.0 * n, 3)
    np.testing.assert_allclose(v1, v40, atol=1e-9)
    w1, _ = seg.simulate(v1)
    w40, _ = seg.simulate(v40)
    np.testing.assert_allclose(w1, w40, atol=1e-8)
    # same sample rate: 40 Hz takes 40x coarser voltage steps, so the loops differ by
    # the (first-order) discretisation error only, which vanishes as fs grows
    def loop_diff(fs):
        _, va = sine_v(1.0, fs, 3)
        _, vb = sine_v(40.0, fs, 3)
        wa, _ = seg.simulate(va)
        wb, _ = seg.simulate(vb)
        na, nb = int(fs), int(fs / 40)
        ph = np.linspace(0, 1, 401)[:-1]
        ga = np.interp(ph, np.arange(na) / na, wa[-na:])
        gb = np.interp(ph, np.arange(nb) / nb, wb[-nb:])
        return np.max(np.abs(ga - gb)) / np.ptp(wa)

    d10k, d160k = loop_diff(10_000), loop_diff(160_000)
    assert d10k < 0.015
    assert d160k < d10k / 10


def test_segmented_state_is_continuous_at_reversals(seg):
    fs = 10_000
    t = np.arange(3 * fs) / fs
    # variable-amplitude triangle with many reversals
    v = 75 + 70 * np.sin(2 * np.pi * 1.0 * t) * np.sin(2 * np.pi * 0.37 * t)
    w, _ = seg.simulate(v)
    dw = np.abs(np.diff(w))
    dv = np.abs(np.diff(v))
    slope = dw / np.maximum(dv, 1e-12)
    rev = np.flatnonzero(np.diff(np.sign(np.diff(v))) != 0) + 1
    assert rev.size > 4
    # no jump: at a reversal the output moves like anywhere else, |dw| <= max slope |dv|
    assert np.max(dw[rev]) <= np.max(slope[dv > 1e-6]) * np.max(dv[rev]) + 1e-12
    # and each branch's own parameters are in force: rising samples follow the
    # ascending set from the carried state, falling ones the descending set
    asc = DuhemModel(seg.ascending, seg.ascending)
    desc = DuhemModel(seg.descending, seg.descending)
    for k in rev[:5]:
        st = DuhemState(v[k - 1], w[k - 1])
        branch = asc if v[k] >= v[k - 1] else desc
        np.testing.assert_allclose(branch.simulate([v[k]], st)[0][0], w[k], atol=1e-12)


def test_segmented_differs_from_whole(seg):
    _, v = sine_v(1.0, 5000, 3)
    w_seg, _ = seg.simulate(v)
    w_whole, _ = DuhemModel(seg.ascending, seg.ascending).simulate(v)
    assert np.max(np.abs(w_seg - w_whole)) > 1.0
    assert seg.structure == "segmented"
    assert DuhemModel(seg.ascending, seg.ascending).structure == "whole"


def test_reduced_branch_identifiable_combination():
    full = DuhemBranch(0.05, [0.1, 0.02], [0.3, 0.01])
    asc = DuhemBranch.from_h(0.05, full.h(True))
    desc = DuhemBranch.from_h(0.05, full.h(False))
    _, v = sine_v(1.0, 2000, 2)
    a, _ = DuhemModel(full, full).simulate(v)
    b, _ = DuhemModel(asc, desc).simulate(v)
    np.testing.assert_allclose(a, b, atol=1e-12)


@pytest.mark.parametrize("alpha", [0.0, -1.0, float("nan")])
def test_bad_alpha_rejected(alpha):
    from piezo_stage.core.errors import ModelError
    with pytest.raises(ModelError):
        DuhemBranch(alpha, [0.0], [1.0])
