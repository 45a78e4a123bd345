"""Host pauses: stretches when the whole machine stopped running (every CPU at once).

On a virtual machine the hypervisor can stop every virtual CPU for milliseconds; no
priority inside the guest helps, and a hardware-timed single-point loop misses its ticks
then (a real DAQ's output would hold its voltage, and so does our paced sim). To tell
those misses from our own, ``HostPauseMonitor`` runs one sentinel process per CPU,
pinned to it at SCHED_FIFO 99, that sleeps ``period_s`` at a time and records every
wake-up later than ``threshold_s`` as a gap ``(start_ns, end_ns)`` on the system clock
(the ROS wall clock). A host pause is where the gaps of *all* CPUs overlap: a CPU busy
with a higher-priority task cannot delay a FIFO-99 sentinel, and a single stolen CPU
does not stop the others. Cost: about 1,000 short wake-ups per second per CPU (each
sentinel used 7-9 % of a CPU at 2,000; on a 2-core machine whose real-time loop
already needs most of both, the instrument must not take what it measures).

Run as ``python -m benchmarks.host_pauses CPU PERIOD THRESHOLD``: sleeps until
stdin closes, then prints its gaps (one ``start end`` pair of ns per line).
"""

from __future__ import annotations

import os
import subprocess
import sys
import threading
import time

from benchmarks import ROOT


def _sentinel(cpu: int, period_s: float, threshold_s: float) -> int:
    os.sched_setaffinity(0, {cpu})
    try:
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(99))
    except (PermissionError, OSError):
        pass  # still useful at normal priority, only less sharp
    gaps, stop = [], threading.Event()

    def until_stdin_closes() -> None:
        sys.stdin.read()
        stop.set()
    threading.Thread(target=until_stdin_closes, daemon=True).start()
    limit = int(threshold_s * 1e9)
    last = time.time_ns()
    while not stop.is_set():
        time.sleep(period_s)
        now = time.time_ns()
        if now - last > limit:
            gaps.append((last, now))
        last = now
    sys.stdout.write("".join(f"{a} {b}\n" for a, b in gaps))
    return 0


def overlap(per_cpu: list[list[tuple[int, int]]], min_ns: int = 0) -> list[tuple[int, int]]:
    """The stretches covered by a gap of every CPU at once, longer than ``min_ns``."""
    if not per_cpu:
        return []
    common = sorted(per_cpu[0])
    for gaps in per_cpu[1:]:
        out = []
        for a0, a1 in common:
            for b0, b1 in gaps:
                lo, hi = max(a0, b0), min(a1, b1)
                if hi > lo:
                    out.append((lo, hi))
        common = sorted(out)
    return [(a, b) for a, b in common if b - a > min_ns]


class HostPauseMonitor:
    """Context manager: sentinels on every CPU while the block runs; ``pauses`` after."""

    def __init__(self, period_s: float = 0.001, threshold_s: float = 0.0015):
        self.period_s, self.threshold_s = period_s, threshold_s
        self.procs: list = []
        self.pauses: list = []
        self.per_cpu: list = []

    def __enter__(self):
        for cpu in sorted(os.sched_getaffinity(0)):
            self.procs.append(subprocess.Popen(
                [sys.executable, "-m", "benchmarks.host_pauses", str(cpu),
                 repr(self.period_s), repr(self.threshold_s)],
                stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True, cwd=ROOT))
        return self

    def __exit__(self, *exc):
        for p in self.procs:
            out, _ = p.communicate(timeout=30)
            self.per_cpu.append([tuple(int(v) for v in line.split())
                                 for line in out.splitlines() if line.strip()])
        # a sentinel wakes up to period_s late by design: a pause is what all share
        # beyond that
        self.pauses = overlap(self.per_cpu, int(self.period_s * 1e9))
        return False


def inside(t_ns: int, pauses, after_ns: int = 0) -> bool:
    """Whether ``t_ns`` falls in a pause or within ``after_ns`` after its end."""
    return any(a <= t_ns <= b + after_ns for a, b in pauses)


if __name__ == "__main__":
    raise SystemExit(_sentinel(int(sys.argv[1]), float(sys.argv[2]), float(sys.argv[3])))
