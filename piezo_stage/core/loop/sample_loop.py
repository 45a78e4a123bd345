"""The stage driver's sample loop without ROS (nodes/stage_driver_node.py is its shell:
parameters, topics, services, the gate, timers and logs).

Samples sit on the stage's own sample clock, ``t0 + j * dt``: in lockstep t0 = 0 and one
sample is taken per command stamped for the next one; in real time t0 is the ROS time of
the first tick and a tick serviced more than a period late skips the missed samples (the
backend holds its voltage over them, the stamps show the gap). Commands are applied at
the tick they are stamped for; late ones are counted and dropped, the newest command on
time is held, and only commands on time keep the loop fresh (a stream of late ones
faults it). The arming supervisor (core/loop/arming.py) decides what is applied: the safe
voltage until the loop is proven closed, then commands, and a ramp to the safe voltage
on a fault, an e-stop or a shutdown. Everything is clamped to the voltage limits and
the slew limit.
"""

from __future__ import annotations

import math
import os
import socket
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass
from enum import Enum

from piezo_stage.core.errors import BackendFault, DataError
from piezo_stage.core.loop.arming import ENABLED, FAULTED, ArmingParams, ArmingSupervisor
from piezo_stage.core.loop.backend import Backend
from piezo_stage.core.loop.capacity import PARAMETERS as CAPACITY
from piezo_stage.core.loop.capacity import Capacity, CapacityMeter
from piezo_stage.core.loop.clock import CommandSchedule, SampleClock
from piezo_stage.core.loop.control import clamp_slew
from piezo_stage.core.loop.planner import DONE, TRACK
from piezo_stage.core.params import Param, Schema
from piezo_stage.core.types import Doc, PerAxis

# the driver node's parameters (core/params.py); its arming supervisor's are arming.py's
# real time, max_steps counted from arming: how long a run waits for its loop to close
# at least, however short the run [s] (the launcher bounds a start that never arms)
ARMING_WAIT_S = 10.0

PARAMETERS: Schema = (
    Param("backend", "sim", "stage backend", choices=("sim", "daq", "pi", "nv200", "replay")),
    Param("mode", "lockstep",
          "lockstep (sim, replay) | realtime",
          choices=("lockstep", "realtime")),
    Param("control_rate_hz", 1000.0, "sample rate [Hz]", lo=1.0, hi=1e5),
    Param("lookahead_s", 0.005,
          "real time: commands are computed this far ahead of the sample they answer [s]",
          lo=0.0, hi=1.0),
    Param("max_steps", 0, "stop after this many samples (0: never)", lo=0, hi=2**31 - 1),
    Param("exit_after_max_steps", False, "exit (code 0) after max_steps"),
    Param("max_steps_from_arming", False,
          "count max_steps from the sample the stage first enabled (the approach's start), "
          "not from the first sample; before that at most max_steps samples wait for arming "
          f"(real time: at least {ARMING_WAIT_S:g} s of them)"),
    Param("min_subscribers", 0,
          "lockstep: joint_states subscribers to wait for",
          lo=0, hi=100),
    Param("min_record_subscribers", 0,
          "lockstep: true_position subscribers to wait for (recorders)",
          lo=0, hi=100),
    Param("clock_period_s", 0.05,
          "lockstep: publish /clock (simulated time for nodes on use_sim_time) every this "
          "much sample time [s]; 0: not at all",
          lo=0.0, hi=10.0),
    Param("thread_priority", 50,
          "real time: SCHED_FIFO priority of the sample loop (0: leave the scheduler alone)",
          lo=0, hi=99),
    *CAPACITY,
    Param("managed", False,
          "lifecycle: start unconfigured and leave every transition (configure, activate, "
          "deactivate, cleanup, shutdown) to an outside manager; false: configure and "
          "activate at start, as a launch without --managed does"),
)

# backends that run on their hardware's clock
HARDWARE_BACKENDS = ("daq", "pi", "nv200")

# the counts /diagnostics reports as rates (key, name, the level they raise)
RATES = (("missed_ticks", "missed ticks", 0), ("late_commands", "late commands", 0),
         ("rejected", "malformed commands", 0),
         ("limit_hits", "voltage or slew limit hits", 0))

# real time: a command stamped further than this from its arrival is no command of this
# loop (the look-ahead is milliseconds); taking it would poison the schedule
COMMAND_WINDOW_NS = 1_000_000_000

CAPACITY_WINDOWS = 3  # windows measured before a refusal; the best judged
# where the loop's own thread holds the margin and the host's other load is what falls
# short, up to this many: a lab's node starting beside the set passes within a few
# seconds (examples/publish_trajectory.py building and sending a long trajectory takes
# part of a CPU for about a second: `bench outside`); a lasting load (another program)
# shows in every window, and is refused after them
CAPACITY_WINDOWS_HOST = 10


def check_mode(backend: str, mode: str, use_sim_time: bool) -> None:
    """Refuse (DataError) a hardware backend in lockstep, and simulated time in real
    time."""
    if backend in HARDWARE_BACKENDS and mode != "realtime":
        raise DataError(f"backend {backend} runs in real time only (mode: realtime)")
    if mode == "realtime" and use_sim_time:
        raise DataError("use_sim_time is for lockstep (the driver's samples are the "
                        "clock); in real time the nodes run on the system clock")


@dataclass
class Sample:
    """One sample taken: its stamp [ns], the measured and (simulated stage) true
    positions [um] and the voltages applied [V]."""
    ns: int
    w: PerAxis[float]
    true: PerAxis[float] | None
    applied: PerAxis[float]


class Next(Enum):
    """What the driver does after a message, as the sample loop decides it."""
    NONE = "none"                    # publish the sample (if any), go on
    DONE = "done"                    # no sample: the run is over (lockstep max_steps, a
                                     # replay ran out): make sure readers have it, exit
    SHUT_DOWN = "shut down"          # a stop's ramp has ended: report, then exit
    FAULT = "fault"                  # the hardware failed (``error``): no sample
    FAULTED_AT_SAFE = "faulted at safe"  # a fault's ramp reached safe (``reason``): a
                                         # managed driver's error transition
    REFUSE = "refuse"                # the host cannot hold the rate (``reason``): end


@dataclass(frozen=True)
class Outcome:
    """The sample loop's answer to one message (``on_command``, ``on_tick``): the
    sample to publish (None: none), whether /clock is due with it, the next action,
    and where a stop began with this sample (real time, max_steps) how long its ramp
    and teardown may take [s]; real time, the next tick's deadline (monotonic [s])."""
    sample: Sample | None = None
    clock_due: bool = False
    next: Next = Next.NONE
    reason: str = ""
    error: BackendFault | None = None
    stop_began_s: float | None = None
    deadline: float | None = None


@dataclass(frozen=True)
class LoopOptions:
    """How a ``SampleLoop`` runs, built by keyword.

    Attributes
    ----------
    rate_hz : float
        The sample rate [Hz].
    lockstep : bool
        One sample per command (sim, replay) or the wall or hardware clock (real time).
    lookahead_s : float
        Real time: how far ahead of its sample a command is computed [s].
    max_steps : int
        Samples to take (0: no end).
    clock_period_s : float
        Lockstep: /clock is due every this much sample time (0: never).
    from_arming : bool
        ``max_steps`` counts from the sample the stage first enabled, so a run's length
        after arming does not depend on how long arming took; before the first enable
        at most ``max_steps`` samples are taken, in real time at least ``ARMING_WAIT_S``
        of them (the nodes join the graph as each finishes its imports: a 1 s run once
        ended before the last of them had, never armed).
    first_j : int
        Lockstep: the first sample's index, so a loop built again for the same run (the
        driver configured again after a cleanup or an error) goes on where the last one
        ended and the set's simulated time never runs back. Real time maps its first
        tick to the ROS time of that tick, so its stamps go on by themselves.
    min_margin : float
        Real time: the capacity over the rate the first arm needs (0: no check).
    capacity_window_s : float
        Real time: how long the capacity is measured before the first arm [s].
    arm_on_start : bool or None
        Whether the loop asks to arm at its start (None: the arming parameters'
        ``auto_arm``).
    """
    rate_hz: float
    lockstep: bool
    lookahead_s: float = 0.005
    max_steps: int = 0
    clock_period_s: float = 0.0
    from_arming: bool = False
    first_j: int = 0
    min_margin: float = 0.0
    capacity_window_s: float = 0.3
    arm_on_start: bool | None = None

    @classmethod
    def from_params(cls, p: Doc, first_j: int = 0,
                    arm_on_start: bool | None = None) -> LoopOptions:
        """The options the driver's parameters (``PARAMETERS``, by name) give, the
        loop's first sample ``first_j``."""
        return cls(rate_hz=p["control_rate_hz"], lockstep=p["mode"] == "lockstep",
                   lookahead_s=p["lookahead_s"], max_steps=p["max_steps"],
                   clock_period_s=p["clock_period_s"], from_arming=p["max_steps_from_arming"],
                   first_j=first_j, min_margin=p["min_margin"],
                   capacity_window_s=p["capacity_window_s"], arm_on_start=arm_on_start)


class SampleLoop:
    """Commands in, samples out, for one backend.

    Parameters
    ----------
    backend : object
        A stage backend (the drivers package): ``limits``, ``slew_V_per_s``, ``paced``,
        ``step``, ``start``, ``close``.
    arm : ArmingParams
        The supervisor's parameters (safe voltage, ramp, staleness, ...).
    options : LoopOptions
        How the loop runs: its rate, lockstep or real time, and the rest (by keyword).
    on_state_change : callable
        ``(state, reason, since_ns)``, called by the supervisor on every change.
    """

    def __init__(self, backend: Backend, arm: ArmingParams, options: LoopOptions,
                 on_state_change: Callable[[str, str, int], None]) -> None:
        o = self.options = options
        rate_hz, lookahead_s, max_steps = o.rate_hz, o.lookahead_s, o.max_steps
        clock_period_s, arm_on_start = o.clock_period_s, o.arm_on_start
        lockstep, from_arming, first_j = o.lockstep, o.from_arming, o.first_j
        min_margin, capacity_window_s = o.min_margin, o.capacity_window_s
        self.backend, self.lock, self.max_steps = backend, bool(lockstep), int(max_steps)
        self.from_arming, self.enabled_j = bool(from_arming), None
        self.rate_hz = float(rate_hz)
        self.dt_ns = int(round(1e9 / rate_hz))
        # a whole number of sample periods (at least the one asked): the references
        # the look-ahead stamps land on the samples' own stamps at any rate
        self.lookahead_ns = self.dt_ns if self.lock else self.dt_ns * max(
            1, math.ceil(lookahead_s * 1e9 / self.dt_ns - 1e-6))
        self.max_step = {a: s / rate_hz for a, s in backend.slew_V_per_s.items()}
        self.v = {"x": arm.safe_V, "y": arm.safe_V}
        self.j, self.t0_ns = (int(first_j) - 1 if self.lock else -1), 0
        self.stats = {"samples": 0, "rejected": 0, "limit_hits": 0, "unexpected_stamp": 0,
                      "missed_ticks": 0, "late_commands": 0}
        self.step_times: deque[float] = deque(maxlen=1_000_000)  # lockstep: the loop's pace
        def on_change(state: str, reason: str, since_ns: int) -> None:
            if state in ENABLED and self.enabled_j is None:
                self.enabled_j = max(self.j, 0)  # max_steps_from_arming counts from here
            on_state_change(state, reason, since_ns)
        self.sup = ArmingSupervisor(arm, self.v, 1.0 / rate_hz,
                                    3 * self.dt_ns if self.lock else max(
                                        3 * self.dt_ns, 20_000_000), on_change)
        if arm_on_start is not None:  # (None: the arming parameters' auto_arm)
            self.sup.arm_requested = bool(arm_on_start)
        self.sched = CommandSchedule(0, self.dt_ns, self.lookahead_ns)
        self.clock = SampleClock(self.dt_ns * 1e-9, backend.paced)
        self.shutdown_requested = False
        self.shutdown_by = math.inf  # monotonic [s]: when a stop gives up waiting
        self.clock_every = max(1, int(round(clock_period_s * rate_hz))) \
            if clock_period_s else 0
        self.ff_phase = ("", "")  # the feedforward's last (phase, follows): relayed
        # real time: what the host sustains for this loop (core/loop/capacity.py),
        # measured from the first sample on; the first arm waits for the first
        # measurement and is refused below ``min_margin``
        self.capacity = None if self.lock else CapacityMeter(rate_hz, capacity_window_s)
        self.min_margin = float(min_margin)
        self.refusal: str | None = None  # why the loop refuses to run (the capacity)
        self.refused_by: Capacity | None = None  # the measurement it refused on
        self._windows: list[Capacity] = []  # the measurements judged before the first arm
        if self.capacity is not None and self.min_margin > 0:
            self.sup.held_by = "measuring what this host sustains for the loop"

    def stamp(self, j: int) -> int:
        """Sample ``j``'s stamp [ns]."""
        return self.t0_ns + j * self.dt_ns

    def next_tick(self, now: float,
                  ros_now_ns: Callable[[], int]) -> tuple[int, Doc | None, bool, int]:
        """Real time: (the sample due at monotonic ``now``, its command or None, whether
        that was on time, the ticks missed since the last one). At the first tick the
        hardware clock starts (not when built) and the sample clock is mapped to ROS
        time, ``ros_now_ns()``, once."""
        if self.clock.mono0 is None:
            self.backend.start()
            self.t0_ns = self.sched.t0 = int(ros_now_ns())
        j = self.clock.tick(now, self.j)
        cmd, on_time = self.sched.due(j, count_held=self.sup.state in ENABLED)
        return j, cmd, on_time, j - self.j - 1

    # -- one call per message: the driver's whole sample -------------------------------
    def on_command(self, ns: int, v: PerAxis[float], recv_ns: int, link: str = "") -> Outcome:
        """A command (already decoded) for the sample stamped ``ns``, received at
        ``recv_ns``: lockstep, when it is the next sample's, that sample is taken;
        real time it is scheduled for its tick. ``link``: the missing links, named
        where arming is refused."""
        if not self.command(ns, v, recv_ns):
            return Outcome()
        j = self.j + 1
        return self._take(j, v, True, self.stamp(j), link, 0)

    def on_start(self) -> Outcome:
        """Lockstep, at configure: the first sample, at rest (no command)."""
        j = self.j + 1
        return self._take(j, None, False, self.stamp(j), "", 0)

    def on_tick(self, now: float, ros_now_ns: Callable[[], int], link: str = "") -> Outcome:
        """Real time, the tick due at monotonic ``now``: the sample due, with its
        scheduled command (``ros_now_ns()``: the ROS time it is taken at)."""
        j, cmd, on_time, missed = self.next_tick(now, ros_now_ns)
        return self._take(j, cmd, on_time, int(ros_now_ns()), link, missed)

    def _take(self, j: int, cmd: PerAxis[float] | None, on_time: bool, now_ns: int, link: str,
              missed: int) -> Outcome:
        """Sample ``j`` and what follows it (``Outcome``)."""
        if self.ended(j):
            return Outcome(next=Next.DONE)
        stop = self.begin_shutdown() if self.past_max_steps(j) and not self.lock else None
        try:
            s = self.step(j, cmd, on_time, now_ns, link, missed)
        except BackendFault as e:
            self.hardware_fault(e)
            return Outcome(next=Next.FAULT, error=e, stop_began_s=stop)
        if self.refusal:
            return Outcome(next=Next.REFUSE, reason=self.refusal, stop_began_s=stop)
        deadline = None if self.lock else self.clock.deadline(self.j + 1)
        if self.shut_down:
            after, why = Next.SHUT_DOWN, ""
        elif self.faulted_at_safe:
            after, why = Next.FAULTED_AT_SAFE, self.faulted_at_safe
        else:
            after, why = Next.NONE, ""
        return Outcome(s, self.clock_due, after, why, None, stop, deadline)

    def command(self, ns: int, v: PerAxis[float], recv_ns: int) -> bool:
        """A command for the sample stamped ``ns`` (a valid one: the adapter checked
        it), received at ``recv_ns``. True in lockstep when it is the next sample's:
        take that sample now. A stamp that is no sample of this loop is counted."""
        if self.lock:
            if ns != self.stamp(self.j + 1):
                self.stats["unexpected_stamp"] += 1
                return False
            self.sup.note_command(ns)
            return True
        if abs(ns - recv_ns) > COMMAND_WINDOW_NS:  # a stray stamp: never scheduled
            self.stats["unexpected_stamp"] += 1
            return False
        self.sup.note_command(recv_ns, self.sched.add(ns, v, recv_ns, self.j), recv_ns - ns)
        self.stats["late_commands"] = self.sched.late
        return False

    def _past(self, j: int) -> bool:
        """``max_steps`` taken by sample ``j`` (from the first sample, or from the first
        enable with ``from_arming``: until then at most ``max_steps`` wait for it, and in
        real time at least ``ARMING_WAIT_S`` of samples)."""
        if not self.max_steps:
            return False
        if self.from_arming and self.enabled_j is not None:
            return j - self.enabled_j > self.max_steps
        if self.from_arming and not self.lock:  # a short run still waits for its loop
            return j > max(self.max_steps, int(ARMING_WAIT_S * self.rate_hz))
        return j > self.max_steps

    def ended(self, j: int) -> bool:
        """No sample ``j``: a replay ran out, or lockstep took ``max_steps``."""
        return bool(self.backend.exhausted or (self.lock and self._past(j)))

    def past_max_steps(self, j: int) -> bool:
        """Real time: ``max_steps`` taken and no shutdown asked for yet."""
        return self._past(j) and not self.shutdown_requested

    def step(self, j: int, cmd: PerAxis[float] | None, on_time: bool, now_ns: int, link: str = "",
             missed: int = 0) -> Sample:
        """Take sample ``j``: the supervisor's target, clamped and slewed (over the
        missed ticks too, where the backend held the last voltage), applied. Raises the
        backend's BackendFault."""
        target = self.sup.tick(self.stamp(j), now_ns, cmd, on_time, link, missed + 1)
        v, hit = clamp_slew(target, self.v, self.backend.limits,
                            {a: s * (missed + 1) for a, s in self.max_step.items()})
        self.stats["limit_hits"] += hit and self.sup.state in ENABLED
        for _ in range(missed):  # the plant held the last voltage over the missed ticks
            self.backend.step(self.v["x"], self.v["y"])
        r = self.backend.step(v["x"], v["y"])
        w, true, applied, hw_j = r.measured, r.true, r.applied, r.sample_index
        if hw_j is not None:  # the DAQ's own sample count: its misses show in the stamps
            missed, j = missed + hw_j - j, hw_j
        self.stats["missed_ticks"] += missed
        self.v, self.j = dict(applied), j
        self.sup.applied(applied)
        self.stats["samples"] += 1
        if self.lock:
            self.step_times.append(time.perf_counter())
        elif self.capacity is not None and (self.capacity.t0 is not None or
                                            self.sup.evidence >= 1):
            # from the first sample the loop answers on time (the set's nodes have
            # started: their start-up is no load of the loop's), beside the arm's
            # confirmation ticks
            cap = self.capacity.sample()
            if cap is not None and self.sup.held_by:
                self._judge(cap)
        return Sample(self.stamp(j), w, true, applied)

    def _judge(self, cap: Capacity) -> None:
        """A measurement of the capacity before the first arm: at the margin, the arm
        waits no more; below it, up to CAPACITY_WINDOWS windows are measured (the set's
        other nodes may still be starting: a transient load of the host, where a lasting
        one, another program, shows in every window), up to CAPACITY_WINDOWS_HOST where
        the loop's thread alone has the margin (the host's other load falls short), and
        the best of them judged: the loop refuses to run (``refusal``: one line naming
        the rate it could hold)."""
        self._windows.append(cap)
        best = max(self._windows, key=lambda c: c.margin)
        windows = CAPACITY_WINDOWS_HOST if (
            best.thread_capacity_hz >= self.min_margin * best.rate_hz) else CAPACITY_WINDOWS
        if cap.margin < self.min_margin and len(self._windows) < windows:
            return  # held: another window
        cap = best
        self.sup.held_by = ""
        if cap.margin >= self.min_margin:
            return
        could = cap.holdable_rate_hz(self.min_margin)
        self.refused_by = cap  # (what the refusal names, for the launcher too)
        self.refusal = (f"this host sustains {cap.describe()}: under the {self.min_margin:g}"
                        f" x margin a real-time set needs; "
                        + (f"control_rate_hz {could:g} would have it"
                           if could else "no standard rate would have it")
                        + " (min_margin 0 runs it anyway, and it will fault)")

    @property
    def state(self) -> str:
        """The arming supervisor's state (disarmed, arming, armed, fault, ...)."""
        return self.sup.state

    @property
    def reason(self) -> str:
        """Why the supervisor is in its state (the last change's reason)."""
        return self.sup.reason

    @property
    def last_capacity(self) -> Capacity | None:
        """The latest measurement of what the host sustains (real time)."""
        return self.capacity.last if self.capacity is not None else None

    @property
    def clock_due(self) -> bool:
        """Lockstep: the last sample is one /clock is published at."""
        return bool(self.clock_every) and self.j % self.clock_every == 0

    def feedforward_phase(self, phase: str, follows: str = "") -> bool:
        """The feedforward's phase (holding, approaching, tracking, done) and what it
        follows ("trajectory of N points stamped S", "setpoint", ""): arming follows
        the phase. True when either changed (the state topic relays both)."""
        self.sup.set_tracking(phase in (TRACK, DONE), self.stamp(self.j))
        changed = (phase, follows) != self.ff_phase
        self.ff_phase = (phase, follows)
        return changed

    def arm(self, on: bool, link: str = "") -> tuple[bool, str]:
        """Arm (the missing ``link`` named when refused) or disarm: (success, message)."""
        now = self.stamp(self.j)
        if not on:
            return self.sup.request_disarm(now)
        ok, message = self.sup.request_arm(now)
        return ok, message + (f" ({link})" if link and not ok else "")

    # -- the lifecycle's transitions (a managed driver's; the node only relays them) ----
    def activate(self, arm: bool) -> tuple[str, str]:
        """Activate: a latched e-stop is released (this is the explicit re-arm), and
        arming is requested when ``arm`` (a managed set, or ``auto_arm``), else left to
        the arm service. -> (state, reason), what the node announces."""
        if self.sup.estop:
            self.sup.request_disarm(self.stamp(self.j))
        self.sup.arm_requested = bool(arm)
        self.sup.reason = ("activated: waiting for the loop to close" if arm
                           else "activated: arm on the arm service")
        return self.sup.state, self.sup.reason

    def deactivate(self) -> tuple[str, str]:
        """Deactivate: disarm and ramp to the safe voltage, still sampling.
        -> (state, reason)."""
        self.arm(False)
        self.sup.reason = "deactivated: ramping to the safe voltage"
        return self.sup.state, self.sup.reason

    def hardware_fault(self, error: object) -> None:
        """The backend lost its link or its controller failed: faulted at once, at
        the last sample's stamp (no sample is taken after it)."""
        self.sup.fault(f"hardware: {error}", self.stamp(self.j))

    def reject_command(self) -> None:
        """A command that cannot be read (NaN, inf, malformed): counted, never fresh."""
        self.stats["rejected"] += 1

    def end_now(self) -> None:
        """A lockstep stop: no ramp (nothing real is driven), the run ends here."""
        self.shutdown_requested = True

    def estop(self) -> str:
        """Drive to the safe voltage, latched until disarm and re-arm."""
        self.sup.trigger_estop(self.stamp(self.j))
        return "driving to the safe voltage; latched until disarm and re-arm"

    def begin_shutdown(self) -> float:
        """A stop (signal or max_steps) in real time: disarm and ramp to the safe
        voltage. Returns the time [s] the ramp, the backend's close and the teardown
        may take."""
        self.shutdown_requested = True
        self.sup.request_disarm(self.stamp(self.j))
        self.sup.reason = "shutting down"
        span = max(abs(x - self.sup.p.safe_V) for x in self.v.values())
        self.shutdown_by = time.monotonic() + span / self.sup.p.ramp_V_per_s + 1.0
        return 2 * span / self.sup.p.ramp_V_per_s + 6.0

    @property
    def at_safe(self) -> bool:
        """Every axis at the safe voltage (the ramp to it has ended)."""
        return all(abs(x - self.sup.p.safe_V) < 1e-9 for x in self.v.values())

    @property
    def shut_down(self) -> bool:
        """After ``begin_shutdown``: at the safe voltage and disabled, or out of time."""
        return self.shutdown_requested and (
            self.sup.state not in ENABLED and self.at_safe
            or time.monotonic() > self.shutdown_by)

    @property
    def faulted_at_safe(self) -> str | None:
        """A fault whose ramp has reached the safe voltage: its reason (what a managed
        driver's error transition reports), else None."""
        return f"faulted: {self.sup.reason}" if self.sup.state == FAULTED and \
            self.at_safe else None

    def announced(self) -> Doc:
        """What the state topic tells: the look-ahead, the rate and the voltage range
        every axis can take (for the loop's nodes), whose set this is (host, and the
        launcher or shell that started the driver: a second launch on the namespace
        names it), and the feedforward's phase (which trajectory runs, or that it is
        done)."""
        lim = self.backend.limits
        return {"lookahead_s": self.lookahead_ns * 1e-9, "control_rate_hz": self.rate_hz,
                "voltage_limit_lo_V": max(lo for lo, _ in lim.values()),
                "voltage_limit_hi_V": min(hi for _, hi in lim.values()),
                "slew_V_per_s": min(self.backend.slew_V_per_s.values()),
                "host": socket.gethostname(), "pid": str(os.getppid()),
                "feedforward_phase": self.ff_phase[0],
                "feedforward_follows": self.ff_phase[1]}

    def status(self) -> tuple[int, str, Doc]:
        """(level, message, values) for /diagnostics: 2 when faulted (disarmed is a
        state asked for, not a fault)."""
        lag, late, ms = self.sched.arrival_lag, self.clock.late, 1e3
        st = self.sup.state
        values = {**self.stats, "state": st, "reason": self.sup.reason,
                  "v_x_V": self.v["x"], "v_y_V": self.v["y"],
                  "tick_late_median_ms": late.percentile(50) * ms,
                  "tick_late_p99_ms": late.percentile(99) * ms,
                  "tick_late_max_ms": late.max_s * ms,
                  "command_lag_median_ms": lag.percentile(50) * ms,
                  "command_lag_p99_ms": lag.percentile(99) * ms,
                  "command_lag_max_ms": lag.max_s * ms,
                  "late_commands": self.sched.late, "commands": self.sched.received,
                  "held_ticks": self.sched.held_ticks,
                  "longest_hold_ticks": self.sched.longest_hold(),
                  "lookahead_ms": self.lookahead_ns * 1e-6, **self.sup.counts}
        cap = self.last_capacity
        if cap is not None:
            values.update(capacity_hz=cap.capacity_hz, capacity_margin=cap.margin,
                          loop_thread_ms_per_sample=cap.thread_s_per_sample * 1e3,
                          host_busy_cpus=cap.host_busy_cores)
        return 2 if st == "faulted" else 0, f"{st}: {self.sup.reason}", values

    def refusal_figures(self) -> Doc | None:
        """The capacity figures a refusal names, as data (the launcher's ``rate auto``
        runs the set again at a rate the host holds); None when nothing was measured."""
        cap = self.refused_by or self.last_capacity
        if cap is None:
            return None
        return {"capacity_hz": cap.capacity_hz, "margin": cap.margin,
                "rate_hz": cap.rate_hz, "min_margin": self.min_margin,
                "holdable_rate_hz": cap.holdable_rate_hz(self.min_margin)}

    def summary(self) -> str:
        """Where a stop left the stage."""
        return (f"{self.sup.state}, x {self.v['x']:.3f} V, y {self.v['y']:.3f} V (safe "
                f"{self.sup.p.safe_V:g} V) after {self.stats['samples']} samples")
