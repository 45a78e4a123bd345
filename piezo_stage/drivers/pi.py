"""Physik Instrumente backend: a PI digital piezo controller (E-727 and its GCS 2 kin)
through PI's official ``pipython`` package (imported only when used).

The controller runs open loop (servo off on both axes): the stage gets the open-loop
control value, in volts at the piezo, and the controller's sensor reads its position in
um. Two ways to drive it:

- **streamed** (the driver node's real-time loop): each sample writes the two voltages
  (``SVA``, its error check in the same message) and reads both positions (``POS?``): two
  round trips per sample, so the host's link sets the rate (over TCP a few kHz at best;
  over USB or RS-232 far less; ``bench`` figures in docs/hardware.md). The loop is paced
  by the driver on the wall clock; the controller has no sample clock the host can wait
  on.
- **played** (``play``): the whole voltage waveform goes into the controller's wave
  tables (``WAV ... PNT`` in bunches), runs on its own servo clock (``WTR`` points per
  servo cycle, ``WGO`` starts both axes in one command) while the data recorder takes the
  actual position and the piezo voltage of each axis (``DRC``, ``RTR``), read back with
  ``DRR?``: tens of kHz, independent of the host.

Safety as for the DAQ backend: the output limits and slew limit are the driver's (every
value sent is clamped to the limits once more here); before a wave starts the outputs
ramp to its first value, after it they ramp to the safe voltage; ``close`` ramps to the
safe voltage at the safe rate. A lost link (a pulled cable, a controller that stopped
answering within ``pi_timeout_s``) or a controller error raises ``BackendFault``, which
the driver turns into a fault; the controller then keeps its last output: an E-727 has
no watchdog on the host link, so the ramp to safe is only possible once the link is back.
"""

from __future__ import annotations

import gc
import sys
import time
from typing import Any

import numpy as np

from piezo_stage.core.errors import BackendFault, ConfigError
from piezo_stage.core.loop.backend import StepResult
from piezo_stage.core.params import Param, Schema
from piezo_stage.core.types import Params, PerAxis

PI_PARAMS: Schema = (  # the driver node declares them read-only (core/params.py)
    Param("pi_address", "tcp:192.168.0.10:50000", "PI controller: tcp:HOST[:PORT] | "
          "serial:DEVICE[:BAUD] | usb:SERIALNUMBER:PID"),
    Param("pi_axes", ["1", "2"], "PI controller axes driving [x, y]"),
    Param("pi_timeout_s", 0.2, "PI controller: answer timeout in the loop [s] (a lost link "
          "faults after this)"),
)
SERVO_UPDATE_TIME = 0x0E000200  # the controller parameter: servo cycle [s]
RECORD_POSITION, RECORD_VOLTAGE = 2, 7  # data recorder options: actual position of
# axis, piezo voltage of output (pipython's RecordOptions ACTUAL_POSITION_2 and
# PIEZO_VOLTAGE_7)
PLAY_TIMEOUT_MS = 5000  # play: the answer timeout of the upload, the wave and the read-back
WAV_BUNCH = 100  # wave points per WAV command (as pipython's writewavepoints bunches)


def parse_address(address: str) -> tuple[str, list]:
    """``tcp:HOST[:PORT]`` | ``serial:DEVICE[:BAUD]`` | ``usb:SERIAL:PID`` (the USB
    product id, e.g. 0x1016) -> (kind, args); ConfigError for anything else."""
    kind, _, rest = str(address).partition(":")
    parts: list = rest.rsplit(":", 1) if rest.count(":") else [rest]
    if kind not in ("tcp", "serial", "usb") or not parts[0] or \
            (kind == "usb" and len(parts) != 2):
        raise ConfigError(f"pi_address {address!r}: use tcp:HOST[:PORT], "
                          "serial:DEVICE[:BAUD] or usb:SERIALNUMBER:PID")
    if len(parts) == 2:
        try:
            parts[1] = int(parts[1], 0)
        except ValueError:
            raise ConfigError(f"pi_address {address!r}: the port, baud rate or product "
                              "id must be a whole number") from None
    return kind, parts


def _link_errors() -> tuple[type[BaseException], ...]:
    from pipython import GCSError
    return (GCSError, OSError)


class PiBackend:
    """See the module docstring: ``step`` is the streamed loop, ``play`` the wave
    generator. ``params``: PI_PARAMS plus the driver's output_limits_V and slew_V_per_s."""
    paced = False  # the driver paces the loop on the wall clock
    exhausted = False
    dev: Any = None  # pipython's GCSDevice once connected (close: nothing before)

    def __init__(self, rate_hz: float, params: Params, safe_V: float) -> None:
        try:
            from pipython import GCSDevice, GCSError
        except ImportError:
            raise ConfigError("backend pi needs PI's pipython package (pip install "
                              "pipython)") from None
        self.rate_hz = float(rate_hz)
        self.axes = [str(a) for a in params["pi_axes"]]
        if len(self.axes) != 2 or self.axes[0] == self.axes[1]:
            raise ConfigError("pi_axes needs two different axes [x, y]")
        lim = [float(x) for x in params["output_limits_V"]]
        slew = [float(x) for x in params["slew_V_per_s"]]
        if len(lim) != 4 or len(slew) != 2:
            raise ConfigError("output_limits_V needs 4 values, slew_V_per_s 2")
        self.limits = {"x": (lim[0], lim[1]), "y": (lim[2], lim[3])}
        self.slew_V_per_s = {"x": slew[0], "y": slew[1]}
        if any(lo >= hi for lo, hi in self.limits.values()):
            raise ConfigError("output limits need lo < hi")
        if not all(lo <= safe_V <= hi for lo, hi in self.limits.values()):
            raise ConfigError(f"safe_voltage_V {safe_V:g} is outside the output limits")
        self.safe_V = float(safe_V)
        self.timeout_ms = max(1, int(float(params["pi_timeout_s"]) * 1000))
        kind, args = parse_address(params["pi_address"])
        self.address = params["pi_address"]
        try:
            self.gateway = self._gateway(kind, args)
            self.dev = GCSDevice(gateway=self.gateway)
            from pipython.pidevice.gcs30.gcs30device import GCS30Device
            if isinstance(self.dev.gcsdevice, GCS30Device):
                raise ConfigError(f"{self.address}: a GCS 3 controller; the pi backend "
                                  "speaks GCS 2 (E-727 and its kin)")
            idn = self.dev.qIDN().strip()
            have = self.dev.qSAI()
            missing = [a for a in self.axes if a not in have]
            if missing:
                raise ConfigError(f"{self.address}: no axis {', '.join(missing)} "
                                  f"(the controller has {', '.join(have)})")
            self.dev.SVO(self.axes, [False, False])  # open loop: we are the controller
            ov = self.dev.qSVA(self.axes)
            self.servo_s = float(self.dev.qSPA(self.axes[0], SERVO_UPDATE_TIME)
                                 [self.axes[0]][SERVO_UPDATE_TIME])
        except (GCSError, OSError, ConfigError) as e:
            if self.dev is not None:
                self._release()
            if isinstance(e, ConfigError):
                raise
            if isinstance(e, OSError):
                raise ConfigError(f"{self.address}: cannot reach the controller "
                                  f"({e.strerror or e})") from None
            raise ConfigError(f"{self.address}: the controller refused the set-up "
                              f"(GCS error {e.val}: {e})") from None
        self.v = {"x": float(ov[self.axes[0]]), "y": float(ov[self.axes[1]])}
        self.hardware_id = f"PI {idn.split(',')[1].strip() if ',' in idn else idn} at " \
                           f"{self.address} (axes {', '.join(self.axes)})"
        self.dev.embederr = True  # SVA and its ERR? in one message: one round trip
        self.dev.timeout = self.timeout_ms
        self.started = False

    @staticmethod
    def _gateway(kind: str, args: Any) -> Any:
        if kind == "tcp":
            from pipython.pidevice.interfaces.pisocket import PISocket
            return PISocket(host=args[0], port=args[1] if len(args) > 1 else 50000)
        if kind == "serial":
            from pipython.pidevice.interfaces.piserial import PISerial
            return PISerial(port=args[0], baudrate=args[1] if len(args) > 1 else 115200)
        from pipython.pidevice.interfaces.piusb import PIUSB
        gw = PIUSB()
        gw.connect(serialnumber=args[0], pid=args[1])
        return gw

    def _clamp(self, v: PerAxis[float]) -> list:
        return [min(max(v[a], self.limits[a][0]), self.limits[a][1]) for a in ("x", "y")]

    def start(self) -> None:
        self.started = True

    def step(self, vx: float, vy: float) -> StepResult:
        """Write the voltages, read the positions. BackendFault when the link or the
        controller fails."""
        out = self._clamp({"x": vx, "y": vy})
        try:
            self.dev.SVA(self.axes, out)
            pos = self.dev.qPOS(self.axes)
        except _link_errors() as e:
            raise BackendFault(self._fault_text(e)) from None
        self.v = {"x": out[0], "y": out[1]}
        return StepResult({"x": float(pos[self.axes[0]]), "y": float(pos[self.axes[1]])},
                          dict(self.v))

    def _fault_text(self, e: BaseException) -> str:
        from pipython import GCSError
        if isinstance(e, GCSError) and e.val > 0:
            return f"PI controller error {e.val}: {e}"
        return f"link to the PI controller at {self.address} lost ({e})"

    def ramp_to(self, target: PerAxis[float], rate_V_per_s: float) -> None:
        """Ramp both outputs to ``target`` at ``rate_V_per_s`` (streamed, paced here)."""
        step = rate_V_per_s / self.rate_hz
        v = dict(self.v)
        t_next = time.monotonic()
        while any(abs(v[a] - target[a]) > 1e-12 for a in v):
            v = {a: min(max(target[a], x - step), x + step) for a, x in v.items()}
            self.step(v["x"], v["y"])
            t_next += 1.0 / self.rate_hz
            time.sleep(max(0.0, t_next - time.monotonic()))

    def play(self, vx: np.ndarray, vy: np.ndarray, fs_hz: float,
             ramp_V_per_s: float) -> tuple[PerAxis[np.ndarray], PerAxis[np.ndarray]]:
        """Play the waveform (V per axis at ``fs_hz``) on the controller's clock and
        record it: -> (applied {axis: V}, measured {axis: um}), one value per point.
        ``fs_hz`` must divide the controller's servo rate."""
        import numpy as np
        from pipython import GCSError
        vx, vy = np.asarray(vx, dtype=float), np.asarray(vy, dtype=float)
        servo_hz = 1.0 / self.servo_s
        rate = int(round(servo_hz / fs_hz))
        if rate < 1 or abs(rate * fs_hz - servo_hz) > 1e-6 * servo_hz:
            raise ConfigError(f"the waveform's rate {fs_hz:g} Hz is not the controller's "
                              f"servo rate {servo_hz:g} Hz divided by a whole number")
        for a, x in (("x", vx), ("y", vy)):
            lo, hi = self.limits[a]
            if x.min() < lo or x.max() > hi:
                raise ConfigError(f"the waveform's {a} leaves the output limits "
                                  f"[{lo:g}, {hi:g}] V")
        gens = [1, 2]
        tables = {1: (self.axes[0], RECORD_POSITION), 2: (self.axes[1], RECORD_POSITION),
                  3: (self.axes[0], RECORD_VOLTAGE), 4: (self.axes[1], RECORD_VOLTAGE)}
        try:
            self.ramp_to({"x": float(vx[0]), "y": float(vy[0])}, ramp_V_per_s)
            # the upload and the wave are not the loop: each answer may take its time
            # (pi_timeout_s bounds the streamed loop's; a 181,000-point upload is 3,620
            # WAV commands, each checked, and one answer past 0.2 s on a loaded host
            # would fail the upload)
            self.dev.timeout = max(self.timeout_ms, PLAY_TIMEOUT_MS)
            for g, wave in zip(gens, (vx, vy)):
                for k in range(0, wave.size, WAV_BUNCH):
                    part = [float(x) for x in wave[k:k + WAV_BUNCH]]
                    self.dev.WAV_PNT(g, k + 1, len(part), "X" if k == 0 else "&", part)
            self.dev.WSL(gens, gens)
            self.dev.WGC(gens, [1, 1])
            self.dev.WTR(gens, [rate, rate], [0, 0])
            self.dev.DRC(list(tables), [s for s, _ in tables.values()],
                         [o for _, o in tables.values()])
            self.dev.RTR(rate)
            self.dev.WGO(gens, [1, 1])  # both axes in one command: one start
            end = time.monotonic() + vx.size / fs_hz + 10.0
            while any(self.dev.qWGO(gens).values()):
                if time.monotonic() > end:
                    raise BackendFault("the wave generator did not finish")
                time.sleep(min(0.05, vx.size / fs_hz / 10))
            self.dev.qDRR(list(tables), 1, vx.size)
            while self.dev.bufstate is not True:
                time.sleep(0.01)
            cols = self.dev.bufdata
            # the outputs the wave left, still within the play's timeout: the host may
            # still be busy with the record just read (after a 181,000-point record this
            # answer can take more than 0.2 s)
            ov = self.dev.qSVA(self.axes)
        except GCSError as e:
            raise BackendFault(self._fault_text(e)) from None
        except OSError as e:
            raise BackendFault(self._fault_text(e)) from None
        finally:
            self.dev.timeout = self.timeout_ms
        self.v = {"x": float(ov[self.axes[0]]), "y": float(ov[self.axes[1]])}
        self.ramp_to({"x": self.safe_V, "y": self.safe_V}, ramp_V_per_s)
        n = min(len(c) for c in cols)
        if n < vx.size:
            raise BackendFault(f"the data recorder returned {n} of {vx.size} points")
        return ({"x": np.array(cols[2][:n]), "y": np.array(cols[3][:n])},
                {"x": np.array(cols[0][:n]), "y": np.array(cols[1][:n])})

    def close(self, safe_V: float = 0.0, ramp_V_per_s: float = 0.0) -> None:
        """Ramp to the safe voltage at the safe rate, leave it there, close the link.
        Safe to call twice; a lost link cannot be ramped (said by the fault before)."""
        if self.dev is None:
            return
        try:
            if self.started and ramp_V_per_s > 0:
                self.ramp_to({"x": safe_V, "y": safe_V}, ramp_V_per_s)
        except BackendFault:
            pass
        finally:
            self._release()

    def _release(self) -> None:
        """Close the link the way pipython's device object does (its context exit): that
        also takes it off pipython's class-wide list of connection callbacks, which would
        otherwise keep it alive and call it on the next connection this process opens.
        Its ``__del__`` closes once more; on a lost link both closes raise OSError, which
        the fault has said already: not again as an ignored-exception traceback. The
        device sits in reference cycles of pipython's own objects, so it is collected
        here (``gc.collect``), not at a later moment the collector picks: in the middle
        of an import, its ``__del__`` broke Python 3.11's import lock (a KeyError from
        importlib)."""
        dev, self.dev, self.gateway = self.dev, None, None
        hook = sys.unraisablehook
        sys.unraisablehook = lambda u: None if isinstance(u.exc_value, OSError) else hook(u)
        try:
            try:
                dev.__exit__(None, None, None)
            except OSError:
                pass
            del dev
            gc.collect()
        finally:
            sys.unraisablehook = hook
