"""TEST DOUBLE of the NI-DAQmx *driver* (the hardware boundary; the only double the
project allows).

Everything above the driver is NI's real ``nidaqmx`` package (Task, channel
collections, timing, stream readers and writers, WatchdogTask, errors and warnings):
only the layer that calls NI's C library, ``nidaqmx._library_interpreter.
LibraryInterpreter``, is replaced by ``SimulatedDriver``, a subclass of the package's
own ``BaseInterpreter``. So every call the backend makes goes through the real package
with its real signatures, and any driver function the double does not model fails
loudly (NotImplementedError naming it).

The simulated device ("Dev1"): two analog outputs drive the amplifier (15 V/V) of the
project's simulated plant, two analog inputs read its displacement through a sensor of
10 um/V. Hardware-timed single point: a write sets the outputs for the next sample
clock; a read waits for that clock (the stage advances one period) and returns its
sample. The sample clock runs on the wall clock from the AI task's start ("wall"), or
advances one period per read without waiting ("virtual", for fast unit tests). Late
samples: a read that comes after its clock has passed reports DAQmx's late warning
209802 (or raises error -209802 with ``late="error"``, NI's default) and the missed
clocks count in total_samp_per_chan_acquired. ``lag_every=N`` makes every Nth read
arrive two periods late, the way a host that misses deadlines would. A watchdog task
drives the outputs to its expiration state when not reset within its timeout.

``install(**options)`` puts it under the real package; ``CALLS`` records what the
driver layer was asked; ``DEVICE`` holds the device's state.
"""

from __future__ import annotations

import os
import time
import warnings

import numpy as np
from nidaqmx._base_interpreter import BaseInterpreter
from nidaqmx.constants import AcquisitionType, ChannelType, UsageTypeAI
from nidaqmx.errors import DaqError, DaqReadError, DaqWarning

CALLS = []
DEVICE = {}
DEFAULTS = {"clock": "wall", "late": "warning", "lag_every": 0, "gain": 15.0,
            "um_per_V": 10.0, "start_latency_s": 0.0}
OPTIONS = dict(DEFAULTS)

TASK_CHANNELS = 0x1273          # task: channel names
READ_CHANNELS_TO_READ = 0x1823  # read: channels to read
READ_TOTAL_ACQUIRED = 0x192A    # read: total samples per channel acquired
CHAN_TYPE = 0x187F              # channel: type
CHAN_AI_MEAS_TYPE = 0x0695      # channel: AI measurement type
TASK_NUM_CHANS = 0x2181         # task: number of channels
TASK_NAME = 0x1276              # task: name
WRITE_NUM_CHANS = 0x217E        # write: number of channels
READ_NUM_CHANS = 0x217B         # read: number of channels
MISSED_CLOCK = 209802


class _Task:
    def __init__(self, name):
        self.name, self.channels, self.kind = name, [], None
        self.rate, self.mode, self.source = None, None, ""
        self.running, self.t0, self.k, self.ao = False, None, -1, None
        self.reads = 0
        self.watchdog = None


def _plant():
    if "plant" not in DEVICE:
        import sys
        sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.dirname(
            os.path.abspath(__file__)))))
        from piezo_stage.core.model.plant import Plant
        from piezo_stage.io.plant_file import default_plant_config_path, load_plant_config
        cfg, rate = load_plant_config(default_plant_config_path()), DEVICE.get("rate", 1000.0)
        Plant(cfg, rate).run([0.0], [0.0])  # compile the kernels now, not at a clock edge
        DEVICE["plant"] = Plant(cfg, rate)
        DEVICE.setdefault("ao", [0.0, 0.0])
    return DEVICE["plant"]


class SimulatedDriver(BaseInterpreter):
    """The NI-DAQmx C driver, simulated: see the module docstring."""

    tasks = {}
    _next = [1]

    def __init__(self, *args, **kwargs):
        pass

    # -- tasks and channels --------------------------------------------------------------
    def _new(self, name):
        h = self._next[0]
        self._next[0] += 1
        self.tasks[h] = _Task(name or f"_unnamedTask<{h}>")
        return h

    def create_task(self, session_name):
        CALLS.append(("create_task", session_name))
        return self._new(session_name), True

    def create_ai_voltage_chan(self, task, physical_channel, name_to_assign_to_channel,
                               terminal_config, min_val, max_val, units, custom_scale_name):
        CALLS.append(("add_ai", physical_channel, terminal_config, min_val, max_val))
        t = self.tasks[task]
        t.kind = "ai"
        t.channels.append((physical_channel, min_val, max_val))

    def create_ao_voltage_chan(self, task, physical_channel, name_to_assign_to_channel,
                               min_val, max_val, units, custom_scale_name):
        CALLS.append(("add_ao", physical_channel, min_val, max_val))
        t = self.tasks[task]
        t.kind = "ao"
        t.channels.append((physical_channel, min_val, max_val))

    def cfg_samp_clk_timing(self, task, rate, source, active_edge, sample_mode,
                            samps_per_chan):
        CALLS.append(("timing", rate, source, AcquisitionType(sample_mode).name))
        t = self.tasks[task]
        t.rate, t.mode, t.source = rate, sample_mode, source
        DEVICE["rate"] = rate
        if t.kind == "ai":
            _plant()  # the device exists before its clock starts

    def start_task(self, task):
        t = self.tasks[task]
        CALLS.append(("start", t.kind or "watchdog"))
        t.running = True
        if t.kind == "ai":
            _plant()
            time.sleep(OPTIONS["start_latency_s"])  # a device that takes a while to start
            t.t0 = time.monotonic()
        if t.watchdog is not None:
            t.watchdog["last"] = time.monotonic()

    def stop_task(self, task):
        CALLS.append(("stop", self.tasks[task].kind or "watchdog"))
        self.tasks[task].running = False

    def clear_task(self, task):
        t = self.tasks.pop(task)
        CALLS.append(("clear", t.kind or "watchdog"))

    def task_control(self, task, action):
        CALLS.append(("control", action))

    # -- attributes -------------------------------------------------------------------
    def get_task_attribute_string(self, task, attribute):
        t = self.tasks[task]
        if attribute == TASK_CHANNELS:
            return ",".join(c[0] for c in t.channels)
        if attribute == TASK_NAME:
            return t.name
        raise NotImplementedError(f"task attribute 0x{attribute:X}")

    def get_task_attribute_uint32(self, task, attribute):
        if attribute == TASK_NUM_CHANS:
            return len(self.tasks[task].channels)
        raise NotImplementedError(f"task attribute 0x{attribute:X}")

    def get_read_attribute_string(self, task, attribute, size_hint=0):
        if attribute == READ_CHANNELS_TO_READ:
            return ",".join(c[0] for c in self.tasks[task].channels)
        raise NotImplementedError(f"read attribute 0x{attribute:X}")

    def get_write_attribute_uint32(self, task, attribute):
        if attribute == WRITE_NUM_CHANS:
            return len(self.tasks[task].channels)
        raise NotImplementedError(f"write attribute 0x{attribute:X}")

    def get_read_attribute_uint32(self, task, attribute):
        if attribute == READ_NUM_CHANS:
            return len(self.tasks[task].channels)
        raise NotImplementedError(f"read attribute 0x{attribute:X}")

    def get_read_attribute_uint64(self, task, attribute):
        if attribute == READ_TOTAL_ACQUIRED:
            return self.tasks[task].k + 1
        raise NotImplementedError(f"read attribute 0x{attribute:X}")

    def get_chan_attribute_int32(self, task, channel, attribute):
        t = self.tasks[task]
        if attribute == CHAN_TYPE:
            return (ChannelType.ANALOG_INPUT if t.kind == "ai" else
                    ChannelType.ANALOG_OUTPUT).value
        if attribute == CHAN_AI_MEAS_TYPE:
            return UsageTypeAI.VOLTAGE.value
        raise NotImplementedError(f"channel attribute 0x{attribute:X}")

    # -- data ---------------------------------------------------------------------------
    def write_analog_f64(self, task, num_samps_per_chan, auto_start, timeout, data_layout,
                         write_array):
        t = self.tasks[task]
        data = [float(x) for x in np.ravel(write_array)]
        for (name, lo, hi), x in zip(t.channels, data):
            if not lo - 1e-9 <= x <= hi + 1e-9:
                raise DaqError(f"{name}: {x} V is outside the channel's range [{lo}, {hi}]",
                               -200561)
        CALLS.append(("write", tuple(data)))
        DEVICE["ao"] = data
        self._watchdog_check()
        return 1

    def read_analog_f64(self, task, num_samps_per_chan, timeout, fill_mode, read_array):
        t = self.tasks[task]
        if t.mode != AcquisitionType.HW_TIMED_SINGLE_POINT.value or not t.running:
            raise NotImplementedError("the double models running HW-timed single-point reads")
        t.reads += 1
        period = 1.0 / t.rate
        late = False
        if OPTIONS["clock"] == "virtual":
            step = 3 if OPTIONS["lag_every"] and t.reads % OPTIONS["lag_every"] == 0 else 1
            late = step > 1
        else:
            if OPTIONS["lag_every"] and t.reads % OPTIONS["lag_every"] == 0:
                time.sleep(2.2 * period)  # the host misses its deadline
            due = t.t0 + (t.k + 1) * period        # the next clock edge
            now = time.monotonic()
            if now > due + period:                 # that edge has passed: late
                late = True
                step = int((now - t.t0) / period) - t.k
            else:
                if now < due:
                    time.sleep(due - now)
                step = 1
        self._watchdog_check()
        plant, ao = _plant(), DEVICE["ao"]
        for _ in range(step):  # the stage ran on at the outputs' values
            w = plant.run([ao[0] * OPTIONS["gain"]], [ao[1] * OPTIONS["gain"]])
        t.k += step
        read_array[0] = w["x"][0] / OPTIONS["um_per_V"]
        read_array[1] = w["y"][0] / OPTIONS["um_per_V"]
        CALLS.append(("read", t.k))
        if late:
            if OPTIONS["late"] == "error":
                raise DaqReadError("Wait for next sample clock detected a missed sample "
                                   "clock.", -MISSED_CLOCK, 0)
            warnings.warn(DaqWarning("Wait for next sample clock detected a missed sample "
                                     "clock.", MISSED_CLOCK))
        return read_array, 1

    # -- watchdog -------------------------------------------------------------------------
    def create_watchdog_timer_task_ex(self, device_name, session_name, timeout):
        CALLS.append(("watchdog", device_name, timeout))
        h = self._new(session_name)
        self.tasks[h].watchdog = {"timeout": timeout, "states": {}, "last": None}
        return h, True

    def cfg_watchdog_ao_expir_states(self, task, channel_names, expir_state_array,
                                     output_type_array):
        from nidaqmx.utils import unflatten_channel_string
        names = unflatten_channel_string(channel_names)
        CALLS.append(("watchdog_states", tuple(names), tuple(float(x) for x in expir_state_array)))
        self.tasks[task].watchdog["states"] = dict(zip(names, expir_state_array))

    def _watchdog_check(self):
        for t in self.tasks.values():
            wd = t.watchdog
            if wd and t.running and wd["last"] is not None and \
                    time.monotonic() - wd["last"] > wd["timeout"]:
                DEVICE["ao"] = list(wd["states"].values())
                DEVICE["watchdog_expired"] = True


def _reset_timer(self, task, action):  # WatchdogTask.reset_timer -> DAQmxControlWatchdogTask
    CALLS.append(("watchdog_reset",))
    wd = self.tasks[task].watchdog
    wd["last"] = time.monotonic()


SimulatedDriver.control_watchdog_task = _reset_timer


def _unmodelled(name):
    def call(self, *args, **kwargs):
        raise NotImplementedError(f"the NI-DAQmx double does not model {name}")
    call.__name__ = name
    return call


for _name in BaseInterpreter.__abstractmethods__:
    if _name not in vars(SimulatedDriver):
        _fill = _unmodelled(_name)
        if isinstance(vars(BaseInterpreter).get(_name), property):
            _fill = property(_fill)  # NI's interface has it as a property
        setattr(SimulatedDriver, _name, _fill)
SimulatedDriver.__abstractmethods__ = frozenset()


def device_outputs():
    """The analog outputs as the hardware holds them now (after any watchdog expiry)."""
    SimulatedDriver()._watchdog_check()
    return list(DEVICE.get("ao", [0.0, 0.0]))


def install(**options):
    """Put the simulated driver under the real nidaqmx package (fresh device)."""
    import nidaqmx._library_interpreter as li
    OPTIONS.clear()
    OPTIONS.update(DEFAULTS, **options)
    CALLS.clear()
    DEVICE.clear()
    SimulatedDriver.tasks = {}
    li.LibraryInterpreter = SimulatedDriver
