"""piezosystem jena NV200 backend: two NV200 amplifiers (one per axis: an NV200 drives
one actuator) through the vendor's official ``nv200`` package (imported only when used).

Each amplifier runs open loop (``cl,0``: the actuator gets the setpoint in volts; its
sensor reads the position in um) from the set command (``modsrc,0``). ``nv200`` is an
asyncio package: this backend owns one event loop and runs each call on it to the end
(both amplifiers concurrently), so to the driver it is as synchronous as the others.

- **streamed** (the driver node's real-time loop): each sample sets both setpoints and
  reads both positions, the two amplifiers at once. The package clears its input for
  10 ms before every write (``TelnetProtocol.write``), so a sample takes about 20 ms
  over Ethernet whatever the link: some 50 samples/s (docs/hardware.md).
- **played** (``play``): the waveform goes into each amplifier's generator table
  (1024 points, in percent of its voltage range; the output period a whole number of
  its 50 us cycles), both generators start (one command each: the host sets their
  relative start, a few ms), and each amplifier's data recorder, started by its own
  generator, takes position and voltage (6144 samples a channel). Waveforms longer
  than the table are refused: the gap protocol (tens of thousands of points) does not
  fit an NV200's table; play it on a PI controller or an NI-DAQ card.

Safety as for the other backends: outputs clamped to the output limits (and to the
amplifier's own voltage range, read at start), ramps to and from the safe voltage, a
lost link or an amplifier error raises BackendFault (the driver faults and exits 1).
The NV200 keeps its last output when the link is lost.
"""

from __future__ import annotations

import asyncio
from collections.abc import Awaitable, Callable
from typing import Any, TypeVar

import numpy as np

from piezo_stage.core.errors import BackendFault, ConfigError
from piezo_stage.core.loop.backend import StepResult
from piezo_stage.core.params import Param, Schema
from piezo_stage.core.types import Params, PerAxis

NV200_PARAMS: Schema = (  # the driver node declares them read-only (core/params.py)
    Param("nv200_addresses", ["tcp:192.168.0.20", "tcp:192.168.0.21"], "NV200 amplifiers "
          "[x, y]: tcp:HOST[:PORT] (the Ethernet model's telnet port, 23) | serial:DEVICE"),
    Param("nv200_timeout_s", 1.0, "NV200: answer timeout [s] (a lost link faults after this)"),
)
T = TypeVar("T")  # what a coroutine gives

TICK_S = 50e-6           # the amplifier's cycle
WAVE_POINTS = 1024       # its generator table
RECORDER_POINTS = 6144   # its recorder, per channel
LINK_HZ = 50.0           # the samples a second the package's telnet link keeps (20 ms)


def parse_address(address: str) -> tuple[str, str, int | None]:
    """``tcp:HOST[:PORT]`` | ``serial:DEVICE`` -> (kind, host or device, port or None)."""
    kind, _, rest = str(address).partition(":")
    if kind == "tcp" and rest:
        host, _, port = rest.partition(":")
        try:
            return kind, host, int(port) if port else 23
        except ValueError:
            pass
    elif kind == "serial" and rest:
        return kind, rest, None
    raise ConfigError(f"NV200 address {address!r}: use tcp:HOST[:PORT] or serial:DEVICE")


class Nv200Backend:
    """See the module docstring."""
    paced = False
    exhausted = False

    def __init__(self, rate_hz: float, params: Params, safe_V: float) -> None:
        try:
            from nv200.nv200_device import NV200Device
        except ImportError:
            raise ConfigError("backend nv200 needs piezosystem jena's nv200 package (pip "
                              "install --ignore-requires-python nv200: it says Python "
                              ">= 3.12 and runs on 3.11)") from None
        self.rate_hz = float(rate_hz)
        addrs = [str(a) for a in params["nv200_addresses"]]
        if len(addrs) != 2 or addrs[0] == addrs[1]:
            raise ConfigError("nv200_addresses needs two different amplifiers [x, y]")
        self.targets = {a: parse_address(s) for a, s in zip(("x", "y"), addrs)}
        self.addresses = dict(zip(("x", "y"), addrs))
        lim = [float(x) for x in params["output_limits_V"]]
        slew = [float(x) for x in params["slew_V_per_s"]]
        if len(lim) != 4 or len(slew) != 2 or lim[0] >= lim[1] or lim[2] >= lim[3]:
            raise ConfigError("output_limits_V needs [x_lo, x_hi, y_lo, y_hi] with lo < hi, "
                              "slew_V_per_s two values")
        self.limits = {"x": (lim[0], lim[1]), "y": (lim[2], lim[3])}
        self.slew_V_per_s = {"x": slew[0], "y": slew[1]}
        self.timeout_s = float(params["nv200_timeout_s"])
        self.safe_V = float(safe_V)
        self.loop = asyncio.new_event_loop()
        self.devs = {}
        try:
            for a, (kind, where, port) in self.targets.items():
                self.devs[a] = NV200Device(self._transport(kind, where, port))
            self._run(self._set_up(), "set-up", timeout=max(5.0, self.timeout_s))
        except BackendFault as e:
            self._close_links()
            raise ConfigError(f"the NV200 set-up failed: {e}") from None
        except Exception:
            self._close_links()
            raise
        for a, (lo, hi) in self.ranges.items():
            self.limits[a] = (max(self.limits[a][0], lo), min(self.limits[a][1], hi))
            if self.limits[a][0] >= self.limits[a][1]:
                self._close_links()
                raise ConfigError(f"{a}: output limits and the NV200's range "
                                  f"[{lo:g}, {hi:g}] V do not overlap")
        if not all(lo <= safe_V <= hi for lo, hi in self.limits.values()):
            self._close_links()
            raise ConfigError(f"safe_voltage_V {safe_V:g} is outside the output limits")
        self.hardware_id = "NV200 x at {} and y at {}".format(*addrs)
        self.started = False

    @staticmethod
    def _transport(kind: str, where: str, port: int | None) -> Any:
        if kind == "tcp":
            from nv200.telnet_protocol import TelnetProtocol
            return TelnetProtocol(host=where, port=port)
        from nv200.serial_protocol import SerialProtocol
        return SerialProtocol(port=where)

    # -- running the package's coroutines ----------------------------------------------
    def _run(self, coro: Awaitable[T], what: str, timeout: float | None = None) -> T:
        """Run ``coro`` on our loop; the package's errors become BackendFault."""
        from nv200.shared_types import DeviceError
        try:
            return self.loop.run_until_complete(
                asyncio.wait_for(coro, timeout or self.timeout_s))
        except DeviceError as e:
            raise BackendFault(f"NV200 error during {what}: {e}") from None
        except (asyncio.TimeoutError, OSError, ConnectionError, EOFError,
                RuntimeError, AttributeError) as e:
            # AttributeError: the package's telnet reader is gone once its link closed
            which = " and ".join(f"{a} at {s}" for a, s in self.addresses.items())
            raise BackendFault(f"link to the NV200 ({which}) lost during {what} "
                               f"({type(e).__name__}{': ' + str(e) if str(e) else ''})"
                               ) from None

    async def _both(self, fn: Callable[[str, Any], Awaitable[T]]) -> PerAxis[T]:
        return dict(zip(self.devs, await asyncio.gather(*(fn(a, d) for a, d in
                                                           self.devs.items()))))

    async def _set_up(self) -> None:
        from nv200.shared_types import ModulationSource, PidLoopMode

        async def one(a: str, dev: Any) -> tuple[Any, float]:
            await dev.connect(auto_adjust_comm_params=False)
            await dev.pid.set_mode(PidLoopMode.OPEN_LOOP)   # we are the controller
            await dev.set_modulation_source(ModulationSource.SET_CMD)
            return await dev.get_voltage_range(), await dev.get_setpoint()
        got = await self._both(one)
        self.ranges = {a: tuple(r) for a, (r, _) in got.items()}
        self.v = {a: float(s) for a, (_, s) in got.items()}

    # -- the streamed loop --------------------------------------------------------------
    def start(self) -> None:
        self.started = True

    def step(self, vx: float, vy: float) -> StepResult:
        """Set both setpoints, read both positions. BackendFault when a link or an
        amplifier fails."""
        out = {a: min(max(v, self.limits[a][0]), self.limits[a][1])
               for a, v in (("x", vx), ("y", vy))}

        async def one(a: str, dev: Any) -> float:
            await dev.set_setpoint(out[a])
            return await dev.get_current_position()
        w = self._run(self._both(one), "a sample")
        self.v = out
        return StepResult({a: float(x) for a, x in w.items()}, dict(out))

    def ramp_to(self, target: PerAxis[float], rate_V_per_s: float) -> None:
        """Ramp both outputs to ``target`` at ``rate_V_per_s``, in steps at the pace the
        package keeps (LINK_HZ at most): a staircase of rate / pace volts."""
        import time
        hz = min(self.rate_hz, LINK_HZ)
        step = rate_V_per_s / hz
        v = dict(self.v)
        t_next = time.monotonic()
        while any(abs(v[a] - target[a]) > 1e-12 for a in v):
            v = {a: min(max(target[a], x - step), x + step) for a, x in v.items()}
            self.step(v["x"], v["y"])
            t_next += 1.0 / hz
            time.sleep(max(0.0, t_next - time.monotonic()))

    # -- the generator and recorder -----------------------------------------------------
    def play(self, vx: np.ndarray, vy: np.ndarray, fs_hz: float,
             ramp_V_per_s: float) -> tuple[PerAxis[np.ndarray], PerAxis[np.ndarray]]:
        """Play the waveform on both amplifiers' generators and record it: -> (applied
        {axis: V}, measured {axis: um}), one value per point. At most 1024 points; the
        rate must be 20 kHz divided by a whole number."""
        vx, vy = np.asarray(vx, dtype=float), np.asarray(vy, dtype=float)
        n = vx.size
        factor = int(round(1.0 / (fs_hz * TICK_S)))
        if factor < 1 or abs(factor * fs_hz * TICK_S - 1.0) > 1e-6:
            raise ConfigError(f"the waveform's rate {fs_hz:g} Hz is not the NV200's 20 kHz "
                              "divided by a whole number")
        if n > WAVE_POINTS:
            raise ConfigError(f"the waveform has {n} points; an NV200's generator holds "
                              f"{WAVE_POINTS} (play longer ones on a PI controller or "
                              "an NI-DAQ card)")
        for a, x in (("x", vx), ("y", vy)):
            lo, hi = self.limits[a]
            if x.min() < lo or x.max() > hi:
                raise ConfigError(f"the waveform's {a} leaves the output limits "
                                  f"[{lo:g}, {hi:g}] V")
        # one recorder sample per tick while it fits (the end of each point's hold, as
        # the sim's records), else one per point (its first tick)
        stride = 1 if n * factor <= RECORDER_POINTS else factor
        length = n * factor // stride
        waves = {"x": vx, "y": vy}
        self.ramp_to({"x": float(vx[0]), "y": float(vy[0])}, ramp_V_per_s)
        rec = self._run(self._play(waves, factor, stride, length), "the play",
                        timeout=60.0 + n * 0.05 + n * factor * TICK_S)
        self.v = {a: float(waves[a][-1]) for a in waves}
        self.ramp_to({"x": self.safe_V, "y": self.safe_V}, ramp_V_per_s)
        pick = slice(factor - 1, None, factor) if stride == 1 else slice(None)
        w = {a: np.asarray(rec[a][0], dtype=float)[pick][:n] for a in rec}
        v = {a: np.asarray(rec[a][1], dtype=float)[pick][:n] for a in rec}
        if any(x.size < n for x in list(w.values()) + list(v.values())):
            raise BackendFault(f"the NV200 recorders returned fewer than {n} points")
        return v, w

    async def _play(self, waves: PerAxis[np.ndarray], factor: int, stride: int,
                    length: int) -> PerAxis[Any]:
        from nv200.data_recorder import DataRecorder, DataRecorderSource, RecorderAutoStartMode
        from nv200.shared_types import ModulationSource
        from nv200.waveform_generator import WaveformGenerator, WaveformUnit

        async def load(a: str, dev: Any) -> tuple[Any, Any]:
            gen, rec = WaveformGenerator(dev), DataRecorder(dev)
            await gen.set_waveform_buffer(list(waves[a]), unit=WaveformUnit.VOLTAGE)
            await gen.set_output_sampling_time(int(round(factor * TICK_S * 1e6)))
            await gen.configure_waveform_loop(0, 0, waves[a].size - 1)
            await rec.set_data_source(0, DataRecorderSource.PIEZO_POSITION)
            await rec.set_data_source(1, DataRecorderSource.PIEZO_VOLTAGE)
            await rec.set_autostart_mode(RecorderAutoStartMode.START_ON_WAVEFORM_GEN_RUN)
            await rec.set_recorder_stride(stride)
            await rec.set_sample_buffer_size(length)
            await rec.start_recording()
            return gen, rec
        parts = await self._both(load)
        await asyncio.gather(*(gen.start(cycles=1) for gen, _ in parts.values()))

        async def finish(a: str, dev: Any) -> Any:
            gen, rec = parts[a]
            await gen.wait_until_finished(timeout_s=30.0 + length * stride * TICK_S)
            await rec.wait_until_finished(timeout_s=30.0)
            data = await rec.read_recorded_data()
            await dev.set_modulation_source(ModulationSource.SET_CMD)
            return data[0].values, data[1].values
        return await self._both(finish)

    # -- the end ----------------------------------------------------------------------
    def close(self, safe_V: float = 0.0, ramp_V_per_s: float = 0.0) -> None:
        """Ramp to the safe voltage at the safe rate and close both links. Safe to call
        twice; a lost link cannot be ramped (the fault said so)."""
        if not self.devs:
            return
        try:
            if self.started and ramp_V_per_s > 0:
                self.ramp_to({"x": safe_V, "y": safe_V}, ramp_V_per_s)
        except BackendFault:
            pass
        finally:
            self._close_links()

    def _close_links(self) -> None:
        async def close_all() -> None:
            for dev in self.devs.values():
                try:
                    await dev.close()
                except Exception:  # noqa: BLE001 - a dead link closes as well as it can
                    pass
        try:
            self.loop.run_until_complete(asyncio.wait_for(close_all(), 2.0))
        except (asyncio.TimeoutError, RuntimeError):
            pass
        self.devs = {}
        self.loop.close()
