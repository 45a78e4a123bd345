"""NI-DAQ backend through the official ``nidaqmx`` package (imported only when used).

Two analog outputs drive the amplifier inputs and two analog inputs read the
displacement sensor, both hardware-timed single point at the control rate on the
same sample clock: each step writes one sample per channel, waits for the next
sample clock and reads one sample per channel, which is what a control loop needs.

Scaling (from parameters): amplifier gain [V out per V in] (the DAQ writes v /
gain), sensor scale [um per V] and offset [um].
"""

from __future__ import annotations

from piezo_stage.core.errors import ConfigError


class DaqBackend:
    def __init__(self, rate_hz: float, params: dict, nidaqmx=None):
        if nidaqmx is None:
            try:
                import nidaqmx  # noqa: F811 - the optional dependency, loaded on demand
            except ImportError:
                raise ConfigError("backend daq needs the nidaqmx package "
                                  "(pip install nidaqmx) and NI-DAQmx drivers") from None
        self.nidaqmx = nidaqmx
        self.rate_hz = float(rate_hz)
        self.gain = float(params.get("amplifier_gain", 15.0))
        self.um_per_V = float(params.get("sensor_um_per_V", 10.0))
        self.offset_um = float(params.get("sensor_offset_um", 0.0))
        self.limits = (float(params.get("v_min", 0.0)), float(params.get("v_max", 150.0)))
        self.slew_V_per_s = float(params.get("slew_V_per_s", 1.0e5))
        ao = [c.strip() for c in str(params.get("ao_channels", "Dev1/ao0,Dev1/ao1")).split(",")]
        ai = [c.strip() for c in str(params.get("ai_channels", "Dev1/ai0,Dev1/ai1")).split(",")]
        if len(ao) != 2 or len(ai) != 2:
            raise ConfigError("ao_channels and ai_channels need two channels each (x,y)")
        consts = nidaqmx.constants
        self.ao = nidaqmx.Task()
        self.ai = nidaqmx.Task()
        for ch in ao:
            self.ao.ao_channels.add_ao_voltage_chan(ch, min_val=self.limits[0] / self.gain,
                                                    max_val=self.limits[1] / self.gain)
        for ch in ai:
            self.ai.ai_channels.add_ai_voltage_chan(ch, min_val=-10.0, max_val=10.0)
        hwtsp = consts.AcquisitionType.HW_TIMED_SINGLE_POINT
        self.ai.timing.cfg_samp_clk_timing(self.rate_hz, sample_mode=hwtsp)
        # the outputs share the inputs' sample clock, so write and read stay aligned
        clock = "/" + ai[0].split("/")[0] + "/ai/SampleClock"
        self.ao.timing.cfg_samp_clk_timing(self.rate_hz, source=clock, sample_mode=hwtsp)
        self.ao.write([self.limits[0] / self.gain] * 2)
        self.ao.start()
        self.ai.start()

    def step(self, vx, vy):
        self.ao.write([vx / self.gain, vy / self.gain])
        self.ai.wait_for_next_sample_clock()
        raw = self.ai.read()
        w = {"x": raw[0] * self.um_per_V + self.offset_um,
             "y": raw[1] * self.um_per_V + self.offset_um}
        return w, None, {"x": vx, "y": vy}

    def close(self):
        for t in (self.ao, self.ai):
            try:
                t.stop()
            finally:
                t.close()
