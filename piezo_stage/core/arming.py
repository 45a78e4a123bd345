"""Safe start-up and faults: the driver's arming supervisor, the smooth approach, and
the feedforward's reference planner (hold, approach, track).

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
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike

from piezo_stage.core.control import clamp_slew
from piezo_stage.core.errors import ConfigError

DISARMED, ARMING, APPROACHING, ARMED, FAULTED = (
    "disarmed", "arming", "approaching", "armed", "faulted")
STATES = (DISARMED, ARMING, APPROACHING, ARMED, FAULTED)
ENABLED = (APPROACHING, ARMED)  # the driver applies commands


# -- approach -----------------------------------------------------------------------

@dataclass(frozen=True)
class Approach:
    """A straight move from ``start`` to ``end`` (um per axis) with a trapezoidal speed
    profile: speed <= ``speed_um_s`` and acceleration <= ``accel_um_s2`` along the path,
    all axes arriving together. ``at(tau)`` gives the position tau seconds in."""

    start: dict
    end: dict
    speed_um_s: float
    accel_um_s2: float
    duration_s: float = field(init=False)
    _t_acc: float = field(init=False)
    _dist: float = field(init=False)

    def __post_init__(self):
        if not (self.speed_um_s > 0 and self.accel_um_s2 > 0):
            raise ConfigError("approach speed and acceleration must be > 0")
        d = math.sqrt(sum((self.end[a] - self.start[a]) ** 2 for a in self.start))
        vmax, amax = self.speed_um_s, self.accel_um_s2
        t_acc = vmax / amax
        if amax * t_acc ** 2 >= d:  # triangular: never reaches vmax
            t_acc = math.sqrt(d / amax)
            dur = 2 * t_acc
        else:
            dur = 2 * t_acc + (d - amax * t_acc ** 2) / vmax
        object.__setattr__(self, "_t_acc", t_acc)
        object.__setattr__(self, "_dist", d)
        object.__setattr__(self, "duration_s", dur)

    def fraction(self, tau: float) -> float:
        """Share of the path covered after tau seconds (0..1)."""
        if self._dist == 0.0 or tau >= self.duration_s:
            return 1.0
        if tau <= 0.0:
            return 0.0
        a, ta, T = self.accel_um_s2, self._t_acc, self.duration_s
        if tau < ta:
            s = 0.5 * a * tau ** 2
        elif tau > T - ta:
            s = self._dist - 0.5 * a * (T - tau) ** 2
        else:
            s = 0.5 * a * ta ** 2 + a * ta * (tau - ta)
        return min(max(s / self._dist, 0.0), 1.0)

    def at(self, tau: float) -> dict:
        """The position [um] ``tau`` seconds into the approach."""
        f = self.fraction(tau)
        return {a: self.start[a] + f * (self.end[a] - self.start[a]) for a in self.start}


# -- the feedforward's reference planner -------------------------------------------------

HOLD, APPROACH, TRACK, DONE = "holding", "approaching", "tracking", "done"


class ReferencePlanner:
    """What the stage is asked to be at a target time, given the driver's state.

    Disabled (the driver holds its safe voltage): *holding* where the stage is.
    Enabled: an approach from the held position to the goal (the trajectory's first
    point, or a streamed setpoint), then *tracking*: the trajectory clock starts when
    the approach ends, or at the trajectory's start time if that is later (its first
    point held until then); past its last point the phase is *done* and the last point
    is held. A new trajectory or setpoint while enabled is approached from the
    present desired position; a re-enable after a fault restarts the trajectory from
    its beginning, through the approach. Pure and deterministic: times are the target
    stamps [ns] the caller asks for.
    """

    def __init__(self, speed_um_s: float = 200.0, accel_um_s2: float = 20000.0):
        Approach({"x": 0.0}, {"x": 0.0}, speed_um_s, accel_um_s2)  # validates
        self.speed, self.accel = float(speed_um_s), float(accel_um_s2)
        self.traj = None           # (t [s], {axis: um})
        self.setpoint = None       # {axis: um}
        self.phase = HOLD
        self.desired = None        # {axis: um}: last position asked for
        self._approach = None      # (Approach, start ns)
        self._track_ns = None      # trajectory clock origin [ns]
        self.start_ns = None       # the trajectory's own start time, if it asked for one

    def set_trajectory(self, t: ArrayLike, w: dict, start_ns: int | None = None) -> None:
        """A new trajectory (t [s], {axis: um}): approached from where the stage is
        asked to be; its clock starts when the approach ends, or at ``start_ns`` if
        that is later."""
        self.traj, self.setpoint = (np.asarray(t, float), {a: np.asarray(x, float)
                                                          for a, x in w.items()}), None
        self.start_ns = None if start_ns is None else int(start_ns)
        self._restart()

    def set_setpoint(self, w: dict) -> None:
        """A new streamed setpoint {axis: um}: approached, then held."""
        self.setpoint, self.traj = dict(w), None
        self._restart()

    def _restart(self):
        if self.phase != HOLD:
            self.phase, self._approach, self._track_ns = APPROACH, None, None

    def hold(self, w_now: dict) -> None:
        """Disabled: ask for where the stage is; the next enable starts over."""
        self.phase, self._approach, self._track_ns = HOLD, None, None
        self.desired = dict(w_now)

    def clock_s(self, target_ns: int) -> float | None:
        """Seconds the trajectory clock will have run at target_ns (None: not running)."""
        if self.phase not in (TRACK, DONE) or self._track_ns is None:
            return None
        return (target_ns - self._track_ns) * 1e-9

    def _goal(self) -> dict:
        if self.traj is not None:
            t, w = self.traj
            return {a: float(w[a][0]) if a in w else self.desired[a] for a in self.desired}
        if self.setpoint is not None:
            return {a: self.setpoint.get(a, self.desired[a]) for a in self.desired}
        return dict(self.desired)

    def sample(self, target_ns: int) -> dict:
        """The desired position [um] for ``target_ns`` while enabled."""
        if self.desired is None:
            raise ConfigError("planner: hold() must give the start position first")
        if self.phase == HOLD:
            self.phase = APPROACH
        if self.phase == APPROACH:
            if self._approach is None:
                self._approach = (Approach(dict(self.desired), self._goal(), self.speed,
                                           self.accel), int(target_ns))
            ap, t0 = self._approach
            tau = (target_ns - t0) * 1e-9
            if tau < ap.duration_s:
                self.desired = ap.at(tau)
                return dict(self.desired)
            self.phase, self._track_ns = TRACK, max(t0 + int(round(ap.duration_s * 1e9)),
                                                    self.start_ns or 0)
        if self.traj is not None:
            t, w = self.traj
            tau = (target_ns - self._track_ns) * 1e-9
            self.desired = {a: float(np.interp(tau, t, w[a])) if a in w else self.desired[a]
                            for a in self.desired}
            if tau > t[-1]:
                self.phase = DONE  # the last point, held
        elif self.setpoint is not None:
            self.desired = {a: self.setpoint.get(a, self.desired[a]) for a in self.desired}
        return dict(self.desired)


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

    def __post_init__(self):
        if not (self.ramp_V_per_s > 0 and self.stale_s > 0 and self.confirm_ticks >= 1
                and self.tolerance_V > 0 and math.isfinite(self.safe_V)):
            raise ConfigError("arming: ramp, stale timeout, confirm ticks and tolerance "
                              "must be > 0 and the safe voltage finite")


# The supervisor's settings as node parameters: (parameter name, ArmingParams field,
# description with unit, (lo, hi) or None). Defaults are the dataclass's.
PARAMETERS = (
    ("safe_voltage_V", "safe_V", "disarmed/faulted output [V]", (-200.0, 200.0)),
    ("safe_ramp_V_per_s", "ramp_V_per_s", "ramp rate to the safe voltage [V/s]", (1.0, 1e6)),
    ("stale_timeout_s", "stale_s", "real time: no valid command arriving before its "
     "tick for this long faults the stage [s]", (0.001, 10.0)),
    ("arm_confirm_ticks", "confirm_ticks", "ticks of a closed loop before arming",
     (1, 100000)),
    ("arm_tolerance_V", "tolerance_V", "|command - applied| that counts as holding [V]",
     (1e-9, 10.0)),
    ("auto_arm", "auto_arm", "arm once the loop is closed, and re-arm after a stale "
     "fault", None),
)


class ArmingSupervisor:
    """The driver's state machine: decides, per tick, what voltage to aim for.

    Call ``tick`` once per sample with the command due for it (or None) and whether it
    arrived in time; it returns the target voltages (before the driver's clamp and slew
    limit) and updates ``state``, ``reason`` and ``enable_ns`` (the first sample stamp
    from which commands are applied). ``on_change`` is called with each transition.
    """

    def __init__(self, params: ArmingParams, v0: dict, dt_s: float, lead_ns: int,
                 on_change: Callable[[str, str, int], None] | None = None):
        self.p = params
        self.ramp_step_V = params.ramp_V_per_s * dt_s  # per tick
        self.lead_ns = int(lead_ns)     # an enable takes effect this far ahead
        self.state, self.reason = DISARMED, "started disarmed"
        self.enable_ns = None
        self.v = dict(v0)               # the voltage applied last
        self.evidence = 0               # consecutive ticks with a holding command
        self.link = "no command received yet"
        self.arm_requested = params.auto_arm
        self.estop = False
        self.last_fresh_ns = None       # receipt time of the last valid command on time
        self.late_since_fresh = 0       # valid commands after their tick since then
        self.late_lag_ns = 0            # how far behind their tick the latest of them came
        self.tracking = False           # the feedforward reports its trajectory clock runs
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

    def tick(self, stamp_ns: int, now_ns: int, cmd: dict | None, on_time: bool, link: str = "",
             periods: int = 1) -> dict:
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
            if self.evidence >= self.p.confirm_ticks and at_safe:
                self._enable(stamp_ns)
            elif self.state == ARMING:
                self.reason = ("waiting for the output to reach the safe voltage"
                               if not at_safe else f"waiting for the loop: {self.link}")
        return target

    def applied(self, v: dict) -> None:
        """The voltage really applied this tick (after clamp and slew)."""
        self.v = dict(v)

    # internals --------------------------------------------------------------------
    def _toward_safe(self) -> dict:
        safe = {a: self.p.safe_V for a in self.v}
        if self.estop:  # as fast as the amplifier's slew limit allows (the driver's)
            return safe
        step = self.ramp_step_V * getattr(self, "_periods", 1)
        return clamp_slew(safe, self.v, (-math.inf, math.inf), step)[0]

    def _enable(self, stamp_ns: int):
        self.counts["arms"] += 1
        self.enable_ns = int(stamp_ns) + self.lead_ns
        self.tracking = False
        self._set(APPROACHING, "loop closed: approaching the first point", stamp_ns)

    def _set(self, state: str, reason: str, stamp_ns: int):
        if state not in ENABLED:
            self.enable_ns = None
        changed = state != self.state
        since = self.enable_ns if state == APPROACHING and self.state not in ENABLED \
            else stamp_ns
        self.state, self.reason = state, reason
        if changed:
            self.on_change(state, reason, since)



class CommandSchedule:
    """Commands by the sample tick they are stamped for (real time).

    The driver's samples sit on a grid ``t0_ns + j * dt_ns``; a command stamped ``s``
    is for tick ``round((s - t0_ns) / dt_ns)``. ``due(j)`` gives the newest command for
    tick j or earlier (so the last one is held when none is new) and whether one
    stamped exactly for j arrived before j was executed. A command that arrives after
    its tick is counted late and dropped: applying it would put the stage that far
    behind its path (a stream of them faults the loop: ArmingSupervisor).
    ``lookahead_ns``: how far ahead of the sample it answers a command is stamped, so
    ``add`` can measure the sample-to-arrival latency.
    """

    def __init__(self, t0_ns: int, dt_ns: int, lookahead_ns: int):
        from piezo_stage.core.metrics import LatencyHistogram
        self.t0, self.dt, self.lookahead = int(t0_ns), int(dt_ns), int(lookahead_ns)
        self.pending = {}            # tick -> voltages
        self.held = None             # (tick, voltages) applied last
        self.late = 0
        self.held_ticks = 0          # ticks with no command of their own (held the last)
        self.streak = 0              # such ticks in a row, up to now
        self.longest = 0             # the longest such run since ``longest_hold()`` last
        self.received = 0
        self.arrival_lag = LatencyHistogram()  # sample taken -> its command arrived [s]

    def tick_of(self, stamp_ns: int) -> int:
        """The sample tick a command stamped ``ns`` is for."""
        return (int(stamp_ns) - self.t0 + self.dt // 2) // self.dt

    def add(self, stamp_ns: int, v: dict, recv_ns: int, last_tick: int) -> bool:
        """Keep a command for its tick (late ones are counted and dropped). -> whether
        it arrived before its tick."""
        j = self.tick_of(stamp_ns)
        self.received += 1
        self.arrival_lag.add((int(recv_ns) - (int(stamp_ns) - self.lookahead)) * 1e-9)
        if j <= last_tick:
            self.late += 1
            return False
        self.pending[j] = dict(v)
        return True

    def longest_hold(self) -> int:
        """The longest run of held ticks since the last call (a stall of the commands'
        path shows as one long run, where a busy host holds a tick here and there)."""
        n, self.longest = self.longest, self.streak
        return n

    def due(self, j: int, count_held: bool = True) -> tuple[dict | None, bool]:
        """-> (voltages or None, exactly on time for tick j). With ``count_held`` (the
        stage is applying commands), a tick with no command stamped for it counts as
        held (``held_ticks``)."""
        on_time = j in self.pending
        held = count_held and not on_time
        self.held_ticks += held
        self.streak = self.streak + 1 if held else 0
        self.longest = max(self.longest, self.streak)
        ready = [k for k in self.pending if k <= j]
        if ready:
            k = max(ready)
            if self.held is None or k > self.held[0]:
                self.held = (k, self.pending[k])
            for k in ready:
                del self.pending[k]
        return (dict(self.held[1]) if self.held else None), on_time


class StateTimeline:
    """The driver's state announcements, as the loop nodes see them: each holds from
    its ``since`` stamp on, and a newer announcement supersedes whatever was announced
    for its stamp and later. ``at(ns)`` is the state for the sample stamped ns."""

    def __init__(self, initial: str = DISARMED, keep: int = 16):
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


class SampleClock:
    """The stage's sample clock in real time, on the host's monotonic clock: tick j is
    due at ``mono0 + j * dt``; a tick serviced late belongs to the latest deadline
    passed (the ones skipped are missed ticks). ``late`` holds how late each serviced
    tick ran. A hardware-paced backend (the DAQ) counts its own ticks instead."""

    def __init__(self, dt_s: float, paced: bool):
        from piezo_stage.core.metrics import LatencyHistogram
        self.dt, self.paced, self.mono0 = float(dt_s), bool(paced), None
        self.late = LatencyHistogram()

    def tick(self, now: float, last_j: int) -> int:
        """The index of the tick serviced at monotonic time ``now``."""
        if self.mono0 is None:
            self.mono0 = now
        j = last_j + 1 if self.paced else int((now - self.mono0) // self.dt)
        self.late.add(now - self.mono0 - j * self.dt)
        return j

    def deadline(self, j: int) -> float:
        """When to service tick j (0.0: at once; the hardware paces)."""
        return 0.0 if self.paced else self.mono0 + j * self.dt
