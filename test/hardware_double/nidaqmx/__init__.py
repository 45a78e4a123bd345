"""TEST DOUBLE of the NI-DAQmx Python API (the hardware boundary; the only double the
project allows). Put ``test/hardware_double`` first on PYTHONPATH and ``import nidaqmx``
gets this instead of NI's package.

It models a USB-6259-like device wired to a simulated stage: the two analog outputs
drive the amplifier (gain 15 V/V) of the project's simulated plant, and the two analog
inputs read its displacement through a sensor of 10 um/V. Hardware-timed single-point
semantics: ``write`` sets the outputs, ``wait_for_next_sample_clock`` advances the
stage one sample period, ``read`` returns the inputs of that sample. It records every
call so a test can check what the driver asked of the hardware.
"""

from types import SimpleNamespace

CALLS = []
_DEVICE = {}


class AcquisitionType:
    HW_TIMED_SINGLE_POINT = "HW_TIMED_SINGLE_POINT"
    CONTINUOUS = "CONTINUOUS"


constants = SimpleNamespace(AcquisitionType=AcquisitionType)


def _device(rate):
    if "plant" not in _DEVICE:
        from piezo_stage.core.plant import Plant
        from piezo_stage.io.plant_file import default_plant_config_path, load_plant_config
        _DEVICE["plant"] = Plant(load_plant_config(default_plant_config_path()), rate)
        _DEVICE["ao"] = [0.0, 0.0]
        _DEVICE["ai"] = [0.0, 0.0]
    return _DEVICE


class _Channels(list):
    def __init__(self, kind):
        super().__init__()
        self.kind = kind

    def add_ao_voltage_chan(self, name, min_val=-10.0, max_val=10.0):
        CALLS.append(("add_ao", name, min_val, max_val))
        self.append((name, min_val, max_val))

    def add_ai_voltage_chan(self, name, min_val=-10.0, max_val=10.0):
        CALLS.append(("add_ai", name, min_val, max_val))
        self.append((name, min_val, max_val))


class _Timing:
    def __init__(self, task):
        self.task = task

    def cfg_samp_clk_timing(self, rate, source="", sample_mode=None, **kw):
        CALLS.append(("timing", rate, source, sample_mode))
        self.task.rate = rate
        self.task.mode = sample_mode


class Task:
    def __init__(self):
        self.ao_channels = _Channels("ao")
        self.ai_channels = _Channels("ai")
        self.timing = _Timing(self)
        self.rate = None
        self.mode = None

    def start(self):
        CALLS.append(("start",))
        _device(self.rate)

    def write(self, data):
        for (name, lo, hi), x in zip(self.ao_channels, data):
            if not lo - 1e-9 <= x <= hi + 1e-9:
                raise ValueError(f"{name}: {x} V outside the channel range [{lo}, {hi}]")
        CALLS.append(("write", tuple(data)))
        _DEVICE["ao"] = list(data)

    def wait_for_next_sample_clock(self):
        d = _DEVICE
        w = d["plant"].run([d["ao"][0] * 15.0], [d["ao"][1] * 15.0])
        d["ai"] = [w["x"][0] / 10.0, w["y"][0] / 10.0]

    def read(self):
        return list(_DEVICE["ai"])

    def stop(self):
        CALLS.append(("stop",))

    def close(self):
        CALLS.append(("close",))
