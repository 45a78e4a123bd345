"""The feedforward's per-sample work without ROS (core/loop/feedforward.py): bumpless while
the driver does not apply commands, the model's inverse once it does, a new model eased
in while armed, missed ticks answered, a bad model refused with the old one kept."""

import os

import pytest

from conftest import CONFIG
from piezo_stage.core.errors import PiezoStageError
from piezo_stage.core.loop.feedforward import HANDOVER_V_PER_TICK, InverseFeedforward
from piezo_stage.core.loop.planner import ReferencePlanner
from piezo_stage.core.model.duhem import AXES
from piezo_stage.io.model_file import load_model

DT = 1_000_000  # 1 kHz


@pytest.fixture
def model():
    return load_model(os.path.join(CONFIG, "stage_model.yaml"))[0]


def _core(model=None):
    core = InverseFeedforward(ReferencePlanner(), DT)
    if model is not None:
        core.set_model(model, None, "test model")
    return core


def test_disabled_it_holds_the_applied_voltage_and_where_the_stage_is(model):
    core = _core(model)
    applied, w = {"x": 12.0, "y": 34.0}, {"x": 5.0, "y": 9.0}
    core.measured(0, w, applied)
    desired, err = core.answer(0, DT, w, applied, enabled=False)
    assert err is None and core.ff == applied and core.ff is not applied
    assert desired == pytest.approx(w)


def test_enabled_it_answers_with_the_models_inverse(model):
    core = _core(model)
    applied, w = {"x": 0.0, "y": 0.0}, {"x": 0.0, "y": 0.0}
    core.measured(0, w, applied)
    core.answer(0, DT, w, applied, enabled=False)
    core.planner.set_setpoint({"x": 0.5, "y": 0.5})
    for k in range(1, 400):  # the approach, then the setpoint held
        desired, err = core.answer((k - 1) * DT, k * DT, w, applied, enabled=True)
        assert err is None
        applied = dict(core.ff)
        core.measured(k * DT, w, applied)
    assert desired == pytest.approx({"x": 0.5, "y": 0.5})
    # the inverse's own model puts the stage where it was asked (coupling included)
    assert core.inv.w["x"] == pytest.approx(0.5, abs=1e-6)
    assert core.inv.w["y"] == pytest.approx(0.5, abs=1e-6)
    assert all(0.0 < core.ff[a] < 150.0 for a in AXES)


def test_without_a_model_the_nominal_gain_within_the_limits():
    core = _core()
    core.planner.set_setpoint({"x": 10.0, "y": -4.0})
    core.planner.hold({"x": 10.0, "y": -4.0})
    w = {"x": 10.0, "y": -4.0}
    core.answer(0, DT, w, {"x": 0.0, "y": 0.0}, enabled=True)
    assert core.ff == {"x": 20.0, "y": 0.0}  # 10 um / 0.5 um/V; -8 V clamped to 0


def test_a_new_model_while_armed_never_jumps(model):
    """While armed at a setpoint, the model is replaced by one without its coupling
    (which would answer the same target with other voltages): the new inverse starts
    where the stage is, the offset to the old answer is eased out a volt a tick at
    most, and the feedforward then settles on the new model's answer."""
    assert model.coupling
    core = _core(model)
    applied, w = {"x": 0.0, "y": 0.0}, {"x": 0.0, "y": 0.0}
    core.measured(0, w, applied)
    core.answer(0, DT, w, applied, enabled=False)  # disarmed first: holds where it is
    core.planner.set_setpoint({"x": 20.0, "y": 20.0})

    def run(k0, n):
        nonlocal applied
        out = []
        for k in range(k0, k0 + n):
            core.answer((k - 1) * DT, k * DT, w, applied, enabled=True)
            applied = dict(core.ff)
            core.measured(k * DT, w, applied)
            out.append(dict(core.ff))
        return out

    before = run(1, 400)[-1]
    core.set_model(model.replace(coupling={}), None, "no coupling", armed=True)
    after = run(401, 400)
    steps = [before] + after
    assert max(abs(b[a] - c[a]) for b, c in zip(steps, steps[1:]) for a in AXES) \
        <= HANDOVER_V_PER_TICK + 1e-9
    assert core.model.coupling == {}
    assert core.handover is None and after[-1] == pytest.approx(after[-2], abs=1e-9)


def test_missed_ticks_are_answered_up_to_twenty():
    core = _core()
    assert list(core.targets(10 * DT)) == [10 * DT]
    assert list(core.targets(13 * DT)) == [11 * DT, 12 * DT, 13 * DT]
    assert len(core.targets(100 * DT)) == 20


def test_a_model_missing_an_axis_or_outside_the_drivers_limits_is_refused(model):
    core = _core(model)
    with pytest.raises(PiezoStageError, match="no model for axis y"):
        core.set_model(model.replace(axes={"x": model.axes["x"]}), None, "x only")
    with pytest.raises(PiezoStageError, match="outside the driver's"):
        core.set_model(model, None, "far", driver_limits=(200.0, 300.0))
    assert core.model is not None and core.limits == model.voltage_limits


def test_a_trajectorys_stamp_sets_its_start_and_an_old_one_is_refused():
    from piezo_stage.core.errors import DataError
    from piezo_stage.core.loop.feedforward import PAST_TRAJECTORY_NS, trajectory_start
    now = 10**18
    assert trajectory_start(0, now) is None  # zero: now
    assert trajectory_start(now - PAST_TRAJECTORY_NS + 1, now) is None  # just sent: now
    assert trajectory_start(now + 5 * 10**9, now) == now + 5 * 10**9  # the future: then
    with pytest.raises(DataError, match="stamped 5.000 s in the past"):
        trajectory_start(now - 5 * 10**9, now)


def test_the_phase_says_which_trajectory_runs(model):
    import numpy as np
    core = _core(model)
    assert core.phase() == (core.planner.phase, "")  # nothing to follow: the phase alone
    core.planner.hold({"x": 1.0, "y": 1.0})
    t = np.arange(0.0, 0.01, 0.001)
    core.planner.set_trajectory(t, {"x": np.full(t.size, 2.0), "y": np.full(t.size, 2.0)})
    core.traj_text = "trajectory of 10 points stamped 0"
    assert core.phase() == (core.planner.phase, "trajectory of 10 points stamped 0")


def test_every_kernel_a_tracked_sample_calls_is_ready_once_the_model_is():
    """Real time: once a model is prepared (at the node's start, or off the loop's thread
    for a refit), tracking with commands in flight (the look-ahead) loads no compiled
    kernel on the loop's thread. A fresh process: the kernels compiled so far in it are
    counted after ``set_model`` and after 200 tracked samples, 5 ticks ahead."""
    import subprocess
    import sys
    code = f"""
import os
from piezo_stage.core.loop.feedforward import InverseFeedforward
from piezo_stage.core.loop.planner import ReferencePlanner
from piezo_stage.io.model_file import load_model
import sys
def compiled():  # every compiled function of the package's modules loaded so far
    return {{f"{{m}}.{{n}}": len(d.signatures) for m, mod in list(sys.modules.items())
            if m.startswith("piezo_stage") for n, d in vars(mod).items()
            if hasattr(d, "signatures") and hasattr(d, "py_func")}}
core = InverseFeedforward(ReferencePlanner(), {DT})
core.set_model(load_model(os.path.join({CONFIG!r}, "stage_model.yaml"))[0], None, "m")
before = compiled()
applied, w = {{"x": 0.0, "y": 0.0}}, {{"x": 0.0, "y": 0.0}}
core.measured(0, w, applied)
core.answer(0, 5 * {DT}, w, applied, enabled=False)
core.planner.set_setpoint({{"x": 5.0, "y": 3.0}})
for k in range(1, 200):
    core.answer(k * {DT}, (k + 5) * {DT}, w, applied, enabled=True)
    applied = dict(core.ff)
    core.measured(k * {DT}, w, applied)
after = compiled()
print(sorted(n for n in after if after[n] != before[n]) or "none")
"""
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                       timeout=300)
    assert r.returncode == 0, r.stderr[-2000:]
    assert r.stdout.strip().splitlines()[-1] == "none", r.stdout
