"""What the host sustains: the real-time loop's capacity, measured on the loop itself.

A real-time set at ``rate_hz`` holds its rate with margin only where each sample costs
well under a period. Hosts of one kind differ by 2x (docs/realtime.md), so the margin
is measured where the set runs, on the set itself, while it runs disarmed before its
first arm (the loop closed, every node answering each sample):

* the loop's thread: the CPU time it spends per sample (``time.thread_time``). Where
  the driver, the feedforward and the controller share one process and one thread
  (launch's composition, nodes/loop_container.py) that is the whole loop's work; the
  thread's capacity is ``1 / (CPU per sample)`` samples a second.
* the host: every CPU's busy share (every process's CPU clock, ``host_cpu``: the
  recorder, the middleware's threads, a lab's own nodes, anything else running; not
  ``/proc/stat``, whose busy ticks a loop at a multiple of the kernel's tick aliases);
  the host's capacity is the rate
  and what its idle CPUs would take at the set's cost per sample (the busy CPU time
  per sample, at most HOST_PER_THREAD times the loop thread's: a load that does not
  grow with the rate is no cost of a sample).

Both from the first sample the loop answers on time (the set's nodes have started:
their imports and discovery are no load of the loop's). The margin is the smaller
capacity over the rate. A set below ``min_margin`` (2 by
default) would fault at every host hiccup (a host pause, a node joining): it refuses
to arm, saying so in one line, and names the rate it could hold.
"""

from __future__ import annotations

import os
import time
from dataclasses import dataclass

from piezo_stage.core.params import Param, Schema

PARAMETERS: Schema = (
    Param("min_margin", 2.0,
          "real time: the capacity (samples a second the host sustains for this loop, "
          "measured disarmed before the first arm) over the rate that the set needs to "
          "arm; below it the driver refuses with the rate it could hold (0: no check)",
          lo=0.0, hi=100.0),
    Param("capacity_window_s", 0.3,
          "real time: how long the capacity is measured before the first arm [s] (and "
          "over at least 100 samples)", lo=0.05, hi=30.0),
)

# a window holds at least this many samples, whatever its length: 150 at 500 Hz in the
# default 0.3 s, 300 at 1 kHz. A longer window costs every start its length and gives
# no steadier figures: the spread is the host's, start to start (docs/realtime.md)
MIN_WINDOW_SAMPLES = 100

# the host's CPU per sample is at most this many times the loop thread's: the loop's
# nodes in their processes (three, or one composed), the recorder, the middleware's
# threads carrying each sample
HOST_PER_THREAD = 3.0

# the loop's fixed work a second (timers, diagnostics, the executor's own turns), in
# samples' worth: at a lower rate it weighs more per sample, so a measurement at one
# rate says too much of a lower one. Per sample at rate r the cost is c (1 + K / r):
# K differs host to host (docs/realtime.md); a rate named from the 1 kHz figure with
# no such term is refused at the next run
FIXED_SAMPLES_A_SECOND = 400.0

# the rates a set may be run at, the highest first: what a refusal proposes
STANDARD_RATES_HZ = (20000.0, 10000.0, 5000.0, 2000.0, 1000.0, 500.0, 250.0, 200.0, 100.0)


# the CPU clock of a process by its pid (Linux's CPUCLOCK_SCHED of the thread group:
# clock_getcpuclockid(3), which Python's time module does not wrap)
def _process_clock(pid: int) -> int:
    return ((~pid) << 3) | 2


@dataclass
class HostCpu:
    """The host's CPU use at one moment: each process's CPU time [ns] (the kernel's
    threads too), the monotonic clock [s] and the CPUs.

    Each process's clock counts every nanosecond it ran. ``/proc/stat``'s busy share,
    which this replaced, is sampled at the kernel's tick (250 Hz on the CI host's
    kernel, with tick accounting): a loop waking 1000 times a second wakes in step
    with it, and one process taking 0.32 of a CPU in 0.3 ms bursts read 0.00 or 1.00
    CPUs by the burst's phase (docs/realtime.md)."""
    ns: dict[int, int]
    t: float
    cores: int

    def busy_cores_since(self, before: HostCpu) -> float:
        """The CPUs busy on average since ``before``: what each process that lived
        through both ran in between, and all a process born in between ran (one that
        ended in between is not counted: its clock is gone with it)."""
        dt = self.t - before.t
        if dt <= 0:
            return 0.0
        ran = 0
        for pid, ns in self.ns.items():
            ran += ns - before.ns.get(pid, 0)
        return max(ran, 0) * 1e-9 / dt


def host_cpu() -> HostCpu | None:
    """Every process's CPU clock now; None where there is no /proc (not Linux)."""
    try:
        pids = os.listdir("/proc")
    except OSError:
        return None
    ns: dict[int, int] = {}
    clock = time.clock_gettime_ns
    for name in pids:
        if name.isdigit():
            pid = int(name)
            try:
                ns[pid] = clock(_process_clock(pid))
            except OSError:  # ended since the listing
                pass
    return HostCpu(ns, time.monotonic(), os.cpu_count() or 1) if ns else None


@dataclass
class Capacity:
    """One measurement: samples over ``seconds``, the loop thread's CPU per sample
    [s], the host's busy CPUs (of ``cores``), and the capacities [samples/s] they
    give at ``rate_hz``."""
    rate_hz: float
    samples: int
    seconds: float
    thread_s_per_sample: float
    host_busy_cores: float
    cores: int

    @property
    def thread_capacity_hz(self) -> float:
        """Samples a second the loop's thread could take: 1 / its CPU per sample."""
        return 1.0 / self.thread_s_per_sample if self.thread_s_per_sample > 0 else \
            float("inf")

    @property
    def host_s_per_sample(self) -> float:
        """The set's cost of a sample to the host [CPU s]: the host's busy CPU time per
        sample, but never more than HOST_PER_THREAD times the loop thread's (a load
        that does not grow with the rate, another program or the set's own fixed work,
        is no cost of a sample: at 100 Hz it would otherwise count a hundred times
        more per sample than at 10 kHz)."""
        per_sample = self.host_busy_cores / self.rate_hz
        if self.thread_s_per_sample > 0:
            per_sample = min(per_sample, HOST_PER_THREAD * self.thread_s_per_sample)
        return per_sample

    @property
    def host_capacity_hz(self) -> float:
        """Samples a second until every CPU is busy: the rate and what the idle CPUs
        would take at the set's cost per sample (host_s_per_sample)."""
        busy = self.host_busy_cores
        if busy <= 0:
            return float("inf")
        return self.rate_hz + max(self.cores - busy, 0.0) / self.host_s_per_sample

    @property
    def capacity_hz(self) -> float:
        """What the host sustains for this loop: the smaller of the two."""
        return min(self.thread_capacity_hz, self.host_capacity_hz)

    @property
    def margin(self) -> float:
        """The capacity over the rate."""
        return self.capacity_hz / self.rate_hz

    def at(self, rate_hz: float) -> Capacity:
        """What this measurement says of the same set at ``rate_hz``: each sample's
        cost (the loop thread's, the set's share of the host's) scaled by the fixed
        work a second (FIXED_SAMPLES_A_SECOND), and a load of the host that is not the
        set's (another program) as it was."""
        k = FIXED_SAMPLES_A_SECOND
        f = (1.0 + k / rate_hz) / (1.0 + k / self.rate_hz)
        per_sample = self.host_s_per_sample
        other = max(self.host_busy_cores - self.rate_hz * per_sample, 0.0)
        busy = other + rate_hz * per_sample * f
        return Capacity(rate_hz, self.samples, self.seconds, self.thread_s_per_sample * f,
                        min(busy, float(self.cores)), self.cores)

    def holdable_rate_hz(self, min_margin: float) -> float | None:
        """The highest standard rate, at most this one, that this measurement says the
        host holds with ``min_margin`` (``at``: a lower rate's samples cost more each),
        None: not even the lowest."""
        for r in STANDARD_RATES_HZ:
            if r <= self.rate_hz and self.at(r).margin >= max(min_margin, 1e-9):
                return r
        return None

    def describe(self) -> str:
        """The measurement in words."""
        ms = self.thread_s_per_sample * 1e3
        return (f"{self.capacity_hz:,.0f} samples/s = {self.margin:.2f} x the "
                f"{self.rate_hz:g} Hz rate (the loop's thread {ms:.3f} ms of CPU a "
                f"sample; the host {self.host_busy_cores:.2f} of {self.cores} CPUs busy)")


class CapacityMeter:
    """Measures the loop's capacity over a window of samples (``start``, then
    ``sample`` each sample, ``result`` once ``done``); call from the loop's thread."""

    def __init__(self, rate_hz: float, window_s: float) -> None:
        self.rate_hz, self.window_s = float(rate_hz), float(window_s)
        self.t0: float | None = None
        self.n = 0
        self._cpu0 = 0.0
        self._host0: HostCpu | None = None
        self.last: Capacity | None = None

    def start(self, host: HostCpu | None = None) -> None:
        """A new window from now (``host``: the host's reading now, where taken)."""
        self.t0, self.n = time.monotonic(), 0
        self._cpu0 = time.thread_time()
        self._host0 = host if host is not None else host_cpu()

    def sample(self) -> Capacity | None:
        """One sample taken; the measurement when the window is full (then it starts
        over), else None."""
        if self.t0 is None:
            self.start()
            return None
        self.n += 1
        dt = time.monotonic() - self.t0
        if dt < self.window_s or self.n < MIN_WINDOW_SAMPLES:
            return None
        cpu = time.thread_time() - self._cpu0
        h1 = host_cpu()
        busy, cores = 0.0, os.cpu_count() or 1
        if h1 is not None and self._host0 is not None:
            busy = min(h1.busy_cores_since(self._host0), float(h1.cores))
            cores = h1.cores
        self.last = Capacity(self.rate_hz, self.n, dt, cpu / self.n, busy, cores)
        self.start(h1)
        return self.last
