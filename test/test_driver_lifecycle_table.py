"""The driver's lifecycle decisions as data (core/loop/lifecycle.py), the loop's options
from the driver's parameters, and the capacity figures a refusal writes."""

import pytest

from piezo_stage.core.loop import lifecycle as lc
from piezo_stage.core.loop.arming import ArmingParams
from piezo_stage.core.loop.sample_loop import PARAMETERS, LoopOptions, SampleLoop
from piezo_stage.drivers import SimBackend


@pytest.mark.parametrize("event, managed, label, step", [
    (lc.HARDWARE_FAULT, True, "active", lc.DEACTIVATE),
    (lc.HARDWARE_FAULT, True, "inactive", lc.CLEANUP),
    (lc.HARDWARE_FAULT, True, "unconfigured", lc.EXIT),
    (lc.HARDWARE_FAULT, False, "active", lc.EXIT),
    (lc.FAULTED_AT_SAFE, True, "active", lc.DEACTIVATE),
    (lc.FAULTED_AT_SAFE, True, "inactive", lc.STAY),
    (lc.FAULTED_AT_SAFE, False, "active", lc.STAY),
])
def test_a_fault_escalates_as_the_table_says(event, managed, label, step):
    """Managed and active: the error transition by a deactivate; inactive (no error
    edge): cleanup; unmanaged: a hardware fault ends the node, a loop fault at safe
    stays for its own recovery."""
    assert lc.escalation(event, managed, label) == step


def test_an_unknown_event_is_refused_and_transitions_settle_where_ros_says():
    with pytest.raises(ValueError, match="unknown event"):
        lc.escalation("meltdown", True, "active")
    assert lc.settled("deactivating") == "inactive"
    assert lc.settled("errorprocessing") == "unconfigured"
    assert lc.settled("active") == "active"
    level, message, values = lc.closed_status("unconfigured")
    assert level == 0 and values["state"] == "disarmed" and "closed" in message


def test_loop_options_come_from_the_drivers_parameters_by_name():
    p = {q.name: q.default for q in PARAMETERS}
    p.update(control_rate_hz=2000.0, mode="lockstep", max_steps=7, min_margin=1.5)
    o = LoopOptions.from_params(p, first_j=42, arm_on_start=False)
    assert (o.rate_hz, o.lockstep, o.max_steps, o.first_j, o.min_margin,
            o.arm_on_start) == (2000.0, True, 7, 42, 1.5, False)
    assert LoopOptions.from_params({**p, "mode": "realtime"}).lockstep is False


def test_a_refusal_has_no_figures_before_a_measurement():
    s = SampleLoop(SimBackend("", 1000.0, 0), ArmingParams(), LoopOptions(
        rate_hz=1000.0, lockstep=True), lambda *a: None)
    assert s.refusal_figures() is None


def test_a_backend_opened_for_a_block_is_closed_however_the_block_ends():
    """``opened`` closes the backend with the block's safe voltage and ramp, on an
    error too (as mcap's Writer finishes its file)."""
    from piezo_stage.core.loop.backend import opened
    closes = []

    class Stage(SimBackend):
        def close(self, safe_V=0.0, ramp_V_per_s=0.0):
            closes.append((safe_V, ramp_V_per_s))

    with opened(Stage("", 1000.0, 0), 5.0, 100.0) as b:
        assert b.step(1.0, 1.0).applied["x"] == pytest.approx(1.0)
    with pytest.raises(RuntimeError), opened(Stage("", 1000.0, 0), 2.0) as b:
        raise RuntimeError("a lost link")
    assert closes == [(5.0, 100.0), (2.0, 0.0)]
