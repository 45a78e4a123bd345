"""The NI-DAQ backend against the NI-DAQmx TEST DOUBLE (test/hardware_double)."""

import os
import sys

import numpy as np
import pytest

from conftest import ROOT

DOUBLE = os.path.join(ROOT, "test", "hardware_double")


@pytest.fixture
def nidaqmx_double():
    sys.path.insert(0, DOUBLE)
    sys.modules.pop("nidaqmx", None)
    import nidaqmx
    assert "TEST DOUBLE" in nidaqmx.__doc__
    nidaqmx.CALLS.clear()
    nidaqmx._DEVICE.clear()
    yield nidaqmx
    sys.path.remove(DOUBLE)
    sys.modules.pop("nidaqmx", None)


def test_daq_backend_hardware_timed_single_point_and_scaling(nidaqmx_double):
    from piezo_stage.drivers.daq import DaqBackend
    b = DaqBackend(1000.0, {"ao_channels": "Dev1/ao0, Dev1/ao1",
                            "ai_channels": "Dev1/ai0,Dev1/ai1",
                            "amplifier_gain": 15.0, "sensor_um_per_V": 10.0})
    calls = nidaqmx_double.CALLS
    assert ("add_ao", "Dev1/ao0", 0.0, 10.0) in calls          # 0-150 V at gain 15
    timing = [c for c in calls if c[0] == "timing"]
    assert all(c[1] == 1000.0 and c[3] == "HW_TIMED_SINGLE_POINT" for c in timing)
    assert timing[1][2] == "/Dev1/ai/SampleClock"               # outputs on the AI clock
    w = [b.step(100.0, 0.0)[0] for _ in range(50)]
    assert ("write", (100.0 / 15.0, 0.0)) in calls              # volts / amplifier gain
    assert 40 < w[-1]["x"] < 80                                 # um through 10 um/V
    b.close()
    assert calls[-1] == ("close",)


def test_driver_node_with_daq_backend(tmp_path, nidaqmx_double):
    pytest.importorskip("rclpy")
    import random
    import subprocess
    env = dict(os.environ, ROS_DOMAIN_ID=str(random.randint(1, 100)),
               ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST",
               PYTHONPATH=os.pathsep.join([DOUBLE, ROOT]))
    from piezo_stage.launch.launcher import Launch
    cfg = tmp_path / "daq.yaml"
    cfg.write_text("/**/stage_driver:\n  ros__parameters:\n    backend: daq\n"
                   "    mode: lockstep\n/**/feedforward:\n  ros__parameters:\n"
                   "    model_file: " + os.path.join(ROOT, "config", "stage_model.yaml") +
                   "\n/**/controller:\n  ros__parameters:\n    kp: 0.2\n")
    bag = tmp_path / "daq_run"
    rc = Launch(str(cfg), record=str(bag), env=env, overrides={
        "stage_driver": {"max_steps": 300, "exit_after_max_steps": True}}).run(120)
    assert rc == 0
    from piezo_stage.io.bag import read_bag_record
    rec = read_bag_record(bag)
    assert len(rec) == 301
    assert np.all(np.isfinite(rec.w["x"]))
