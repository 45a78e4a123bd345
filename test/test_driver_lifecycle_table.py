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


class ClosingSim(SimBackend):
    """The simulated stage, counting its closes."""

    closes: list = []

    def close(self, safe_V=0.0, ramp_V_per_s=0.0):
        ClosingSim.closes.append(safe_V)
        super().close(safe_V, ramp_V_per_s)


def _driver(announced, **params):
    from piezo_stage.core.loop.driver import DriverCore
    p = {q.name: q.default for q in PARAMETERS}
    p.update({"mode": "lockstep", "backend": "sim", **params})
    ClosingSim.closes = []
    return DriverCore(p, ArmingParams(safe_V=5.0), lambda: ClosingSim("", 1000.0, 0),
                      lambda *a: announced.append(a))


def test_the_driver_core_keeps_its_state_across_configures():
    """A configure opens a loop and announces it; a close announces disarmed, closes
    the backend once and the next loop starts after the last sample; the arm service
    answers only while active; a fault's reason is reported once by the error
    transition."""
    announced = []
    d = _driver(announced)
    d.configure(lambda loop: loop.on_start())
    assert d.loop is not None and announced[-1][0] == d.loop.state
    assert "configured" in announced[-1][1] and d.hardware_id() != "sim stage (closed)"
    last_j = d.running.j
    assert d.arm(True, "inactive") == (False, "inactive: the driver arms only when "
                                       "active (lifecycle: configure, then activate)")
    assert d.close("cleaned up") == ""
    assert d.loop is None and d.next_j == last_j + 1 and ClosingSim.closes == [5.0]
    assert announced[-1] == ("disarmed", "cleaned up: the backend is closed", True)
    assert d.hardware_id() == "sim stage (closed)" and d.estop().startswith("unconfigured")
    assert d.status("unconfigured", 0)[2]["lifecycle"] == "unconfigured"
    with pytest.raises(RuntimeError, match="no sample loop"):
        d.running  # noqa: B018 - the property raises
    d.configure(lambda loop: None)
    assert d.running.j == last_j  # counted on from the last loop (the sample before it)
    assert d.escalate(lc.HARDWARE_FAULT, True, "active", "faulted: hardware: x") == \
        lc.DEACTIVATE
    assert d.error_reason("deactivating", None) == "faulted: hardware: x"
    assert d.error_reason("configuring", ValueError("bad")) == "configuring: bad"


def test_a_configure_that_fails_leaves_nothing_open():
    from piezo_stage.core.errors import ConfigError
    from piezo_stage.core.loop.driver import fixable
    d = _driver([])

    def start(loop):
        raise ConfigError("the host cannot hold the rate")
    with pytest.raises(ConfigError):
        d.configure(start)
    assert d.loop is None and d.backend is None and ClosingSim.closes == [5.0]
    assert fixable(ConfigError("x")) and not fixable(RuntimeError("x"))


def test_the_end_of_a_run_ramps_in_real_time_and_ends_at_once_in_lockstep():
    d = _driver([])
    assert d.ramp_down(realtime=True) is None  # nothing open: at once
    d.configure(lambda loop: None)
    assert d.ramp_down(realtime=False) is None and d.running.shutdown_requested
    d2 = _driver([], mode="realtime")
    d2.configure(lambda loop: None)
    ramp_s = d2.ramp_down(realtime=True)
    assert ramp_s is not None and ramp_s >= 0 and d2.shutdown_requested
