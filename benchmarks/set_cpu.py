"""The CPU each process of a running node set spends a sample: every process's CPU clock
(core/loop/capacity.py ``host_cpu``, the clock the set's own capacity check reads),
sampled from a thread beside the run, the processes named from their command lines.

``SetCpu`` runs while a set does (``with SetCpu() as c: launch.run(...)``); ``per_sample``
then gives each process's CPU over the longest stretch in which the same processes
ran, a few seconds in (their start-up left out), over the samples that stretch held at
``rate_hz``."""

from __future__ import annotations

import os
import threading

from piezo_stage.core.loop.capacity import HostCpu, host_cpu

PERIOD_S = 0.5
SETTLE_S = 3.0  # the stretch starts this long after all of the set's processes are up


def _name(pid: int) -> str | None:
    """The set's process ``pid`` by its node or nodes ("stage_driver", "loop_container
    controller feedforward"), None: not one of the set's."""
    try:
        with open(f"/proc/{pid}/cmdline", "rb") as fh:
            argv = fh.read().split(b"\0")
    except OSError:
        return None
    words = [a.decode(errors="replace") for a in argv]
    for i, w in enumerate(words):
        if w.startswith("piezo_stage.nodes."):
            name = w.rsplit(".", 1)[-1].removesuffix("_node")
            if name == "loop_container":  # its nodes follow it, up to the first option
                nodes = []
                for x in words[i + 1:]:
                    if x.startswith("-"):
                        break
                    nodes.append(x)
                name = " + ".join(sorted(nodes)) + " (composed)"
            return name
    return None


class SetCpu:
    """Samples the set's processes' CPU clocks every PERIOD_S while it runs."""

    def __init__(self) -> None:
        self.snaps: list[tuple[float, dict[str, int], HostCpu]] = []  # (t, name -> ns, host)
        self._names: dict[int, str | None] = {}
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)

    def __enter__(self) -> SetCpu:
        self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self._stop.set()
        self._thread.join(5.0)

    def _run(self) -> None:
        while not self._stop.wait(PERIOD_S):
            h = host_cpu()
            if h is None:
                return
            mine: dict[str, int] = {}
            for pid, ns in h.ns.items():
                if pid not in self._names:
                    self._names[pid] = _name(pid) if pid != os.getpid() else None
                name = self._names[pid]
                if name is not None:
                    mine[name] = mine.get(name, 0) + ns
            self.snaps.append((h.t, mine, h))

    def per_sample(self, rate_hz: float) -> tuple[dict[str, float], float, float]:
        """({process: its CPU a sample [us]}, the set's whole CPU a sample [us], the
        host's busy CPUs) over the longest stretch of the same processes, SETTLE_S in;
        ({}, nan, nan): no such stretch of a second."""
        full = max((len(m) for _, m, _ in self.snaps), default=0)
        runs = [s for s in self.snaps if len(s[1]) == full and full]
        if not runs:
            return {}, float("nan"), float("nan")
        names = set(runs[0][1])
        same = [s for s in runs if set(s[1]) == names]
        first = next((s for s in same if s[0] >= same[0][0] + SETTLE_S), None)
        last = same[-1]
        if first is None or last[0] - first[0] < 1.0:
            return {}, float("nan"), float("nan")
        span = last[0] - first[0]
        us = {n: (last[1][n] - first[1][n]) * 1e-3 / (span * rate_hz) for n in sorted(names)}
        busy = last[2].busy_cores_since(first[2])
        return us, sum(us.values()), busy


def describe(us: dict[str, float]) -> str:
    """``{process: us}`` in words, the dearest first."""
    return ", ".join(f"{n} {v:.0f}" for n, v in sorted(us.items(), key=lambda x: -x[1]))
