"""NI-DAQ backend through the official ``nidaqmx`` package (imported only when used).

Two analog outputs drive the amplifier inputs and two analog inputs read the
displacement sensor, hardware-timed single point (HWTSP) on one sample clock: the
outputs are clocked by the inputs' sample clock, so each step writes one sample per
channel (``AnalogMultiChannelWriter.write_one_sample``) and reads the sample of the
next clock (``AnalogMultiChannelReader.read_one_sample`` blocks until it): the loop is
paced by the hardware, as NI documents for control loops.

Late samples: when the loop misses a sample clock, DAQmx reports it, as a warning
(``DaqWarning`` 209800-209803) or, unless late errors are converted to warnings, as an
error (``DaqError`` -209800..-209803, after which the read is repeated). Both are
counted; the sample index comes from the task's own count of acquired samples
(``in_stream.total_samp_per_chan_acquired``), so the driver's stamps show each miss.

Safety: ``close`` ramps the outputs to the safe voltage at the safe ramp rate on the
hardware clock and leaves them there. A SIGKILL of the whole process cannot run any
code: for that the backend arms the device's watchdog timer (``WatchdogTask``, when
``watchdog_timeout_s`` > 0) whose expiration state is the safe voltage; every step
resets it, so if the process dies or hangs the hardware drives the outputs to the safe
voltage by itself (devices without a watchdog refuse it; the backend then says so).
The sample clock and the watchdog start at the first step, not when the backend is
built, so the time a driver spends waiting for its readers is neither counted as
missed samples nor long enough to expire the watchdog.

Per axis (x, y) parameters: physical channels, AI terminal configuration and range,
amplifier gain [V/V], sensor scale [um/V] and offset [um], output limits [V] and slew
limit [V/s].
"""

from __future__ import annotations

import warnings
from collections.abc import Callable, Sequence
from typing import Any

from piezo_stage.core.errors import ConfigError
from piezo_stage.core.loop.backend import StepResult
from piezo_stage.core.params import Param, Schema
from piezo_stage.core.types import Params, PerAxis

LATE_CODES = {209800, 209801, 209802, 209803}  # |code|: read/write not complete before
# the sample clock, missed sample clock, three or more missed sample clocks

DAQ_PARAMS: Schema = (  # the driver node declares them read-only (core/params.py)
    Param("ao_channels", ["Dev1/ao0", "Dev1/ao1"], "NI-DAQ output channels [x, y]"),
    Param("ai_channels", ["Dev1/ai0", "Dev1/ai1"], "NI-DAQ input channels [x, y]"),
    Param("ai_terminal_config", "DEFAULT", "AI terminal configuration: DEFAULT | RSE | NRSE "
          "| DIFF | PSEUDO_DIFF"),
    Param("ai_range_V", [-10.0, 10.0], "AI input range [V]"),
    Param("amplifier_gain", [15.0, 15.0], "amplifier gain per axis [V out / V in]"),
    Param("sensor_um_per_V", [10.0, 10.0], "sensor scale per axis [um/V]"),
    Param("sensor_offset_um", [0.0, 0.0], "sensor offset per axis [um]"),
    Param("output_limits_V", [0.0, 150.0, 0.0, 150.0], "stage voltage limits [x_lo, x_hi, "
          "y_lo, y_hi] [V]"),
    Param("slew_V_per_s", [1.0e5, 1.0e5], "stage voltage slew limit per axis [V/s]"),
    Param("watchdog_timeout_s", 0.0, "hardware watchdog: outputs go to the safe voltage when "
          "the driver stops for this long (0: off)"),
)


def _pair(params: Params, name: str, n: int = 2) -> list[float]:
    val = [float(x) for x in params[name]]
    if len(val) != n:
        raise ConfigError(f"{name} needs {n} values, got {len(val)}")
    return val


class DaqBackend:
    paced = True  # step() blocks until the hardware's next sample clock
    exhausted = False

    def __init__(self, rate_hz: float, params: Params, safe_V: float) -> None:
        try:
            import nidaqmx  # the optional dependency, loaded on demand
            from nidaqmx.constants import AcquisitionType, TerminalConfiguration
            from nidaqmx.stream_readers import AnalogMultiChannelReader
            from nidaqmx.stream_writers import AnalogMultiChannelWriter
        except ImportError:
            raise ConfigError("backend daq needs the nidaqmx package (pip install "
                              "nidaqmx) and the NI-DAQmx driver") from None
        import numpy as np
        self.np, self.nidaqmx = np, nidaqmx
        self.rate_hz = float(rate_hz)
        ao, ai = list(params["ao_channels"]), list(params["ai_channels"])
        if len(ao) != 2 or len(ai) != 2:
            raise ConfigError("ao_channels and ai_channels need two channels each [x, y]")
        self.gain = _pair(params, "amplifier_gain")
        self.um_per_V = _pair(params, "sensor_um_per_V")
        self.offset_um = _pair(params, "sensor_offset_um")
        lim = _pair(params, "output_limits_V", 4)
        self.limits = {"x": (lim[0], lim[1]), "y": (lim[2], lim[3])}
        slew = _pair(params, "slew_V_per_s")
        self.slew_V_per_s = {"x": slew[0], "y": slew[1]}
        if any(g <= 0 for g in self.gain) or any(lo >= hi for lo, hi in self.limits.values()):
            raise ConfigError("amplifier_gain must be > 0 and output limits lo < hi")
        if not all(lo <= safe_V <= hi for lo, hi in self.limits.values()):
            raise ConfigError(f"safe_voltage_V {safe_V:g} is outside the output limits")
        term = str(params["ai_terminal_config"]).upper()
        if term not in TerminalConfiguration.__members__:
            raise ConfigError(f"ai_terminal_config {term!r}: one of "
                              f"{', '.join(TerminalConfiguration.__members__)}")
        ai_lo, ai_hi = _pair(params, "ai_range_V")
        self.device = ai[0].split("/")[0]
        self.hardware_id = f"NI-DAQ {self.device} ({', '.join(ao + ai)})"
        self.late = 0
        from nidaqmx.errors import DaqNotFoundError
        try:
            self.ao = nidaqmx.Task()
        except DaqNotFoundError:  # the package is there, NI's driver library is not
            raise ConfigError("backend daq: the nidaqmx package is installed but NI's "
                              "NI-DAQmx driver is not (install NI-DAQmx on this "
                              "machine, e.g. `python -m nidaqmx installdriver`)") from None
        self.ai = nidaqmx.Task()
        self.wd: Any = None  # nidaqmx's WatchdogTask where the device has one
        try:
            for ch, (lo, hi), g in zip(ao, self.limits.values(), self.gain):
                self.ao.ao_channels.add_ao_voltage_chan(ch, min_val=lo / g, max_val=hi / g)
            for ch in ai:
                self.ai.ai_channels.add_ai_voltage_chan(
                    ch, terminal_config=TerminalConfiguration[term], min_val=ai_lo,
                    max_val=ai_hi)
            hwtsp = AcquisitionType.HW_TIMED_SINGLE_POINT
            self.ai.timing.cfg_samp_clk_timing(self.rate_hz, sample_mode=hwtsp)
            # the outputs run on the inputs' sample clock, so write and read stay aligned
            self.ao.timing.cfg_samp_clk_timing(self.rate_hz,
                                               source=f"/{self.device}/ai/SampleClock",
                                               sample_mode=hwtsp)
            self.reader = AnalogMultiChannelReader(self.ai.in_stream)
            self.writer = AnalogMultiChannelWriter(self.ao.out_stream, auto_start=False)
            self.raw_in = np.zeros(2)
            self.raw_out = np.zeros(2)
            self.v = {"x": float(safe_V), "y": float(safe_V)}
            timeout = float(params["watchdog_timeout_s"])
            if timeout > 0:
                self._make_watchdog(ao, safe_V, timeout)
        except Exception:
            self._close_tasks()
            raise
        self.started = False

    def start(self) -> None:
        """Start the sample clock and the watchdog at the first step, not when built: a
        driver may wait seconds for its readers, and a clock started then would count
        those seconds as missed samples and the watchdog would expire before the loop."""
        self.started = True
        self._write(self.v)                      # HWTSP: the first sample before start
        self.ao.start()                          # waits for the AI sample clock
        self.ai.start()
        if self.wd is not None:
            self.wd.start()

    def _make_watchdog(self, ao: Sequence[str], safe_V: float, timeout: float) -> None:
        from nidaqmx.constants import WatchdogAOExpirState
        from nidaqmx.errors import DaqError
        from nidaqmx.system.watchdog import AOExpirationState, WatchdogTask
        try:
            self.wd = WatchdogTask(self.device, timeout=timeout)
            self.wd.cfg_watchdog_ao_expir_states([
                AOExpirationState(ch, safe_V / g, WatchdogAOExpirState.VOLTAGE)
                for ch, g in zip(ao, self.gain)])
        except DaqError as e:
            raise ConfigError(f"{self.device}: hardware watchdog unavailable ({e.error_code}); "
                              "set watchdog_timeout_s: 0 to run without it") from None

    def _write(self, v: PerAxis[float]) -> None:
        self.raw_out[0] = v["x"] / self.gain[0]
        self.raw_out[1] = v["y"] / self.gain[1]
        self.writer.write_one_sample(self.raw_out)

    def _late_call(self, fn: Callable[..., Any], *args: Any) -> bool:
        """Call fn, counting DAQmx's late-sample warnings and errors; True if it
        completed, False if a late error interrupted it."""
        from nidaqmx.errors import DaqError, DaqWarning
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always", DaqWarning)
            try:
                fn(*args)
                ok = True
            except DaqError as e:
                if abs(e.error_code) not in LATE_CODES:
                    raise
                self.late += 1
                ok = False
        for w in caught:
            if isinstance(w.message, DaqWarning) and abs(w.message.error_code) in LATE_CODES:
                self.late += 1
            else:
                warnings.warn_explicit(w.message, w.category, w.filename, w.lineno)
        return ok

    def step(self, vx: float, vy: float) -> StepResult:
        """Write the voltages for the next sample clock, read that clock's sample (its
        index: the device's count of clocks)."""
        if not self.started:
            self.start()
        self.v = {"x": vx, "y": vy}
        self._late_call(self._write, self.v)
        while not self._late_call(self.reader.read_one_sample, self.raw_in):
            pass  # late error: that clock is gone; the next read takes the next one
        # shapes are checked on the first call; then no per-sample attribute queries
        self.reader.verify_array_shape = self.writer.verify_array_shape = False
        if self.wd is not None:
            self.wd.reset_timer()
        index = int(self.ai.in_stream.total_samp_per_chan_acquired) - 1
        w = {a: float(self.raw_in[i]) * self.um_per_V[i] + self.offset_um[i]
             for i, a in enumerate(("x", "y"))}
        return StepResult(w, dict(self.v), None, index)

    def close(self, safe_V: float = 0.0, ramp_V_per_s: float = 0.0) -> None:
        """Ramp to the safe voltage on the hardware clock, leave it there, release.
        Safe to call twice."""
        if self.ai is None:
            return
        if not self.started:  # never started: nothing was written, nothing to ramp
            return self._close_tasks()
        try:
            step = ramp_V_per_s / self.rate_hz
            v = dict(self.v)
            while any(abs(x - safe_V) > 1e-12 for x in v.values()):
                v = {a: min(max(safe_V, x - step), x + step) for a, x in v.items()}
                self.step(v["x"], v["y"])
        finally:
            self._close_tasks()

    def _close_tasks(self) -> None:
        for t in (self.ao, self.ai, self.wd):
            if t is None:
                continue
            try:
                t.stop()
            except Exception:  # noqa: BLE001 - closing must go on whatever stop said
                pass
            finally:
                t.close()
        self.ao = self.ai = self.wd = None
