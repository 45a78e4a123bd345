"""Safe start-up and faults: the driver's arming supervisor and the state timeline the
loop nodes keep of its announcements (the approach and the feedforward's reference
planner: core/loop/planner.py; the sample clock and the command schedule:
core/loop/clock.py).

The node set starts *disarmed*: the driver holds the safe voltage, the trajectory clock
does not run and the feedback integrators are held. It arms only when the loop is
proven closed, then the stage moves from where it is to the trajectory's first point on
a speed- and acceleration-limited approach, and only then does the trajectory clock
start. States (the driver's, published on a latched topic and on /diagnostics)::

    disarmed --arm--> arming --loop closed, output at safe--> approaching --> armed
        ^                                                          |            |
        +------------------------- disarm --------------------------+------------+
    any --stale commands / e-stop--> faulted --(auto re-arm; e-stop: disarm first)-->

"Loop closed" is evidence the driver collects every tick: commands stamped for that
tick arrive in time (they answer its samples) and, while disarmed, equal the voltage
it applies (the feedforward holds the applied voltage, so the command the controller
sends is the driver's own applied voltage come back around the whole loop). Enabling
is bumpless for the same reason. Times are integers in ns; voltages in V; positions
in um.
"""


from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

from piezo_stage.core.errors import ConfigError
from piezo_stage.core.loop.control import clamp_slew
from piezo_stage.core.params import Param, Schema
from piezo_stage.core.types import Doc, PerAxis

DISARMED, ARMING, APPROACHING, ARMED, FAULTED = (
    "disarmed", "arming", "approaching", "armed", "faulted")
STATES = (DISARMED, ARMING, APPROACHING, ARMED, FAULTED)
ENABLED = (APPROACHING, ARMED)  # the driver applies commands


# -- the driver's supervisor -----------------------------------------------------------

@dataclass
class ArmingParams:
    """The arming supervisor's parameters (safe voltage, ramps, timeouts, tolerances)."""
    safe_V: float = 0.0              # where disarmed and faulted outputs go
    ramp_V_per_s: float = 500.0      # how fast they go there
    stale_s: float = 0.05            # armed: no command on time for this long is a fault
    confirm_ticks: int = 20          # consecutive ticks of evidence that the loop closed
    tolerance_V: float = 0.01        # |command - applied| that counts as "holding"
    auto_arm: bool = False           # arm at start, and re-arm after a stale fault

    def __post_init__(self) -> None:
        if not (self.ramp_V_per_s > 0 and self.stale_s > 0 and self.confirm_ticks >= 1
                and self.tolerance_V > 0 and math.isfinite(self.safe_V)):
            raise ConfigError("arming: ramp, stale timeout, confirm ticks and tolerance "
                              "must be > 0 and the safe voltage finite")


# The supervisor's settings as the driver's parameters (core/params.py), each filling
# the ArmingParams field it names; defaults are the dataclass's.
_D = ArmingParams()
PARAMETERS: Schema = (
    Param("safe_voltage_V", _D.safe_V, "disarmed/faulted output [V]", lo=-200.0, hi=200.0,
          field="safe_V"),
    Param("safe_ramp_V_per_s", _D.ramp_V_per_s, "ramp rate to the safe voltage [V/s]",
          lo=1.0, hi=1e6, field="ramp_V_per_s"),
    Param("stale_timeout_s", _D.stale_s, "real time: no valid command arriving before its "
          "tick for this long faults the stage [s]", lo=0.001, hi=10.0, field="stale_s"),
    Param("arm_confirm_ticks", _D.confirm_ticks, "ticks of a closed loop before arming",
          lo=1, hi=100000, field="confirm_ticks"),
    Param("arm_tolerance_V", _D.tolerance_V, "|command - applied| that counts as holding "
          "[V]", lo=1e-9, hi=10.0, field="tolerance_V"),
    Param("auto_arm", _D.auto_arm, "arm once the loop is closed, and re-arm after a stale "
          "fault", field="auto_arm"),
)


class ArmingSupervisor:
    """The driver's state machine: decides, per tick, what voltage to aim for.

    Call ``tick`` once per sample with the command due for it (or None) and whether it
    arrived in time; it returns the target voltages (before the driver's clamp and slew
    limit) and updates ``state``, ``reason`` and ``enable_ns`` (the first sample stamp
    from which commands are applied). ``on_change`` is called with each transition.
    """

    def __init__(self, params: ArmingParams, v0: PerAxis[float], dt_s: float, lead_ns: int,
                 on_change: Callable[[str, str, int], None] | None = None) -> None:
        self.p = params
        self.ramp_step_V = params.ramp_V_per_s * dt_s  # per tick
        self.lead_ns = int(lead_ns)     # an enable takes effect this far ahead
        self.state, self.reason = DISARMED, "started disarmed"
        self.enable_ns: int | None = None  # the first sample stamp commands apply from
        self.v = dict(v0)               # the voltage applied last
        self.evidence = 0               # consecutive ticks with a holding command
        self.link = "no command received yet"
        self.arm_requested = params.auto_arm
        self.estop = False
        self._periods = 1               # sample periods the last tick spanned
        self.last_fresh_ns: int | None = None  # receipt of the last valid command on time
        self.late_since_fresh = 0       # valid commands after their tick since then
        self.late_lag_ns = 0            # how far behind their tick the latest of them came
        self.tracking = False           # the feedforward reports its trajectory clock runs
        self.held_by = ""               # why arming waits besides the loop (the capacity)
        self.on_change = on_change or (lambda *a: None)
        self.counts = {"faults": 0, "arms": 0}

    # requests --------------------------------------------------------------------
    def request_arm(self, now_ns: int) -> tuple[bool, str]:
        """Ask to arm; refused with the reason while a link of the loop is not closed."""
        if self.estop:
            return False, "e-stop is latched: disarm first, then arm"
        if self.state in ENABLED:
            return True, f"already {self.state}"
        if self.evidence < self.p.confirm_ticks:
            return False, f"loop not closed: {self.link}"
        self.arm_requested = True
        self._enable(now_ns)
        return True, "arming: approaching the first point"

    def request_disarm(self, now_ns: int) -> tuple[bool, str]:
        """Disarm at ``ns``: the outputs ramp to the safe voltage."""
        self.arm_requested = False
        self.estop = False
        self._set(DISARMED, "disarmed on request", now_ns)
        return True, "disarmed: holding the safe voltage"

    def trigger_estop(self, now_ns: int) -> None:
        """Emergency stop: latched until disarm and re-arm."""
        self.estop, self.arm_requested = True, False
        self._set(FAULTED, "e-stop (latched until disarm and re-arm)", now_ns)

    def fault(self, reason: str, now_ns: int) -> None:
        """Fault with ``reason``: ramp to the safe voltage and stay there."""
        self.counts["faults"] += 1
        self._set(FAULTED, reason, now_ns)

    def set_tracking(self, tracking: bool, now_ns: int) -> None:
        """The feedforward reports the approach ended: the state becomes armed."""
        self.tracking = bool(tracking)
        if self.state == APPROACHING and tracking:
            self._set(ARMED, "tracking", now_ns)
        elif self.state == ARMED and not tracking:
            self._set(APPROACHING, "approaching a new goal", now_ns)

    # per tick --------------------------------------------------------------------
    def note_command(self, recv_ns: int, on_time: bool = True, lag_ns: int = 0) -> None:
        """A valid (finite) command arrived, ``lag_ns`` after the tick it is stamped
        for when late. Only one ``on_time`` (before that tick) keeps the loop fresh: a
        stream of late ones is a loop that no longer keeps up (a controller starved or
        restarted behind), and following it would put the stage that far behind its
        path; the schedule drops them."""
        if on_time:
            self.last_fresh_ns, self.late_since_fresh = recv_ns, 0
        else:
            self.late_since_fresh += 1
            self.late_lag_ns = int(lag_ns)

    def tick(self, stamp_ns: int, now_ns: int, cmd: PerAxis[float] | None, on_time: bool,
             link: str = "",
             periods: int = 1) -> Doc:
        """Target voltages for the sample stamped ``stamp_ns`` (driver time), ``now_ns``
        the receipt clock of ``note_command``. ``cmd``: the command due for this sample
        ({axis: V}) or None; ``on_time``: it arrived before its tick. ``link``: the
        node's own diagnosis of a missing link (which node/topic), used in reasons.
        ``periods``: sample periods since the last tick (more after missed ticks), so
        the ramp to the safe voltage keeps its rate in seconds."""
        self._periods = max(int(periods), 1)
        holding = cmd is not None and on_time and all(
            abs(cmd[a] - self.v[a]) <= self.p.tolerance_V for a in self.v)
        self.evidence = self.evidence + 1 if holding else 0
        if cmd is None:
            self.link = link or "no command answers the samples"
        elif not on_time:
            self.link = "commands arrive after the tick they are stamped for"
        elif not holding:
            self.link = ("commands do not equal the applied voltage (the feedforward "
                         "or controller is not holding it)")
        else:
            self.link = "closed"
        if self.state in ENABLED:
            if self.enable_ns is not None and stamp_ns < self.enable_ns:
                return self._toward_safe()  # the enable takes effect at enable_ns
            age = None if self.last_fresh_ns is None else (now_ns - self.last_fresh_ns) * 1e-9
            if age is None or age > self.p.stale_s:
                age = age if age is not None else 0.0
                if self.late_since_fresh:
                    self.fault(f"late commands: {self.late_lag_ns * 1e-6:.0f} ms behind for "
                               f"{age * 1e3:.0f} ms (> stale_timeout_s {self.p.stale_s:g}; "
                               f"{self.late_since_fresh} arrived after their tick, "
                               "dropped)", stamp_ns)
                else:
                    self.fault(f"stale commands: none on time for {age:.3f} s "
                               f"(> stale_timeout_s {self.p.stale_s:g})", stamp_ns)
                return self._toward_safe()
            return dict(cmd) if cmd is not None else dict(self.v)
        target = self._toward_safe()
        at_safe = all(abs(x - self.p.safe_V) <= 1e-9 for x in self.v.values())
        if self.state == DISARMED and self.arm_requested:
            self._set(ARMING, "waiting for the loop to close", stamp_ns)
        # a fault is reported as such until the loop is back; with auto_arm it then
        # re-arms through the approach (an e-stop waits for disarm and arm)
        rearm = self.state == FAULTED and self.arm_requested and not self.estop
        if self.state == ARMING or rearm:
            if self.evidence >= self.p.confirm_ticks and at_safe and not self.held_by:
                self._enable(stamp_ns)
            elif self.state == ARMING:
                self.reason = ("waiting for the output to reach the safe voltage"
                               if not at_safe else f"waiting for the loop: {self.link}"
                               if self.evidence < self.p.confirm_ticks else self.held_by)
        return target

    def applied(self, v: PerAxis[float]) -> None:
        """The voltage really applied this tick (after clamp and slew)."""
        self.v = dict(v)

    # internals --------------------------------------------------------------------
    def _toward_safe(self) -> PerAxis[float]:
        safe = {a: self.p.safe_V for a in self.v}
        if self.estop:  # as fast as the amplifier's slew limit allows (the driver's)
            return safe
        step = self.ramp_step_V * self._periods
        return clamp_slew(safe, self.v, (-math.inf, math.inf), step)[0]

    def _enable(self, stamp_ns: int) -> None:
        self.counts["arms"] += 1
        self.enable_ns = int(stamp_ns) + self.lead_ns
        self.tracking = False
        self._set(APPROACHING, "loop closed: approaching the first point", stamp_ns)

    def _set(self, state: str, reason: str, stamp_ns: int) -> None:
        if state not in ENABLED:
            self.enable_ns = None
        changed = state != self.state
        since = self.enable_ns if state == APPROACHING and self.state not in ENABLED \
            and self.enable_ns is not None else stamp_ns
        self.state, self.reason = state, reason
        if changed:
            self.on_change(state, reason, since)


class StateTimeline:
    """The driver's state announcements, as the loop nodes see them: each holds from
    its ``since`` stamp on, and a newer announcement supersedes whatever was announced
    for its stamp and later. ``at(ns)`` is the state for the sample stamped ns."""

    def __init__(self, initial: str = DISARMED, keep: int = 16) -> None:
        self.entries = [(-(2 ** 63), initial)]
        self.keep = keep

    def add(self, since_ns: int, state: str) -> None:
        """The state ``state`` applies from stamp ``since_ns`` on."""
        self.entries = [e for e in self.entries if e[0] < since_ns][-self.keep:]
        self.entries.append((int(since_ns), state))

    def at(self, ns: int) -> str:
        """The state at stamp ``ns``."""
        for since, state in reversed(self.entries):
            if since <= ns:
                return state
        return self.entries[0][1]

    def enabled(self, ns: int) -> bool:
        """Whether the driver applies commands at stamp ``ns``."""
        return self.at(ns) in ENABLED
