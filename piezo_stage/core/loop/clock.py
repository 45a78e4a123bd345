"""The driver's clocks in real time: the sample clock on the host's monotonic clock (or
the hardware's own count) and the schedule of commands by the tick they are stamped for
(late ones counted and dropped). Times in ns, or s where named."""

from __future__ import annotations

from piezo_stage.core.types import PerAxis


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

    def __init__(self, t0_ns: int, dt_ns: int, lookahead_ns: int) -> None:
        from piezo_stage.core.metrics import LatencyHistogram
        self.t0, self.dt, self.lookahead = int(t0_ns), int(dt_ns), int(lookahead_ns)
        self.pending: dict[int, dict[str, float]] = {}  # tick -> voltages
        self.held: tuple[int, dict[str, float]] | None = None  # (tick, voltages) applied last
        self.late = 0
        self.held_ticks = 0          # ticks with no command of their own (held the last)
        self.streak = 0              # such ticks in a row, up to now
        self.longest = 0             # the longest such run since ``longest_hold()`` last
        self.received = 0
        self.arrival_lag = LatencyHistogram()  # sample taken -> its command arrived [s]

    def tick_of(self, stamp_ns: int) -> int:
        """The sample tick a command stamped ``ns`` is for."""
        return (int(stamp_ns) - self.t0 + self.dt // 2) // self.dt

    def add(self, stamp_ns: int, v: PerAxis[float], recv_ns: int, last_tick: int) -> bool:
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

    def due(self, j: int, count_held: bool = True) -> tuple[PerAxis[float] | None, bool]:
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


class SampleClock:
    """The stage's sample clock in real time, on the host's monotonic clock: tick j is
    due at ``mono0 + j * dt``; a tick serviced late belongs to the latest deadline
    passed (the ones skipped are missed ticks). ``late`` holds how late each serviced
    tick ran. A hardware-paced backend (the DAQ) counts its own ticks instead."""

    def __init__(self, dt_s: float, paced: bool) -> None:
        from piezo_stage.core.metrics import LatencyHistogram
        self.dt, self.paced = float(dt_s), bool(paced)
        self.mono0: float | None = None  # the first tick's monotonic time [s]
        self.late = LatencyHistogram()

    def tick(self, now: float, last_j: int) -> int:
        """The index of the tick serviced at monotonic time ``now``."""
        if self.mono0 is None:
            self.mono0 = now
        mono0 = self.mono0
        j = last_j + 1 if self.paced else int((now - mono0) // self.dt)
        self.late.add(now - mono0 - j * self.dt)
        return j

    def deadline(self, j: int) -> float:
        """When to service tick j (0.0: at once, or before the first tick; the hardware
        paces)."""
        return 0.0 if self.paced or self.mono0 is None else self.mono0 + j * self.dt
