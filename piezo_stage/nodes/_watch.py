"""The live watch's diagnoses off the loop: one at a time, in a process of their own.

Spawned, not forked (the node's process holds the middleware's threads), its stops left
to the node (``core/workers.quiet_worker``); the diagnosis itself is the core's
``diagnose_window``, plain data in and out. The worker leads a process group of its own:
the diagnosis forks a process per axis, and a run that ends mid-diagnosis ends the whole
group (an axis's process left behind would hold the worker's pipes open, and the node
could not exit).
"""

from __future__ import annotations

import multiprocessing
import os
import signal
from concurrent.futures import Future, ProcessPoolExecutor

from piezo_stage.core.estimation.gap.watch import WatchRequest, WatchResult, diagnose_window


def _ready() -> None:
    """The worker, first: quiet on stops, the diagnosis's modules imported."""
    from piezo_stage.core.workers import quiet_worker
    quiet_worker()
    os.setpgrp()  # its axes' processes join its group: ended with it (``close``)
    yield_to_the_loop()
    import piezo_stage.core.estimation.gap  # noqa: F401


def yield_to_the_loop() -> None:
    """The worker (and the axes' processes it forks, which inherit it) runs only where a
    CPU would otherwise idle (Linux's SCHED_IDLE; elsewhere the lowest nice): on a
    2-core host a diagnosis at normal priority took the CPU the set's own threads
    wanted (in real time at 500 Hz the command lag's p99 rose 0.96 -> 1.33 ms)."""
    try:
        os.sched_setscheduler(0, os.SCHED_IDLE, os.sched_param(0))
    except (AttributeError, OSError):
        try:
            os.nice(19)
        except OSError:
            pass


class WatchWorker:
    """One diagnosis at a time (``submit``), its answer taken when done (``done``)."""

    def __init__(self) -> None:
        ctx = multiprocessing.get_context("spawn")
        self.pool = ProcessPoolExecutor(max_workers=1, mp_context=ctx, initializer=_ready)
        self.running: tuple[WatchRequest, Future] | None = None

    def submit(self, req: WatchRequest) -> None:
        self.running = (req, self.pool.submit(diagnose_window, req))

    def done(self) -> tuple[WatchRequest, WatchResult] | None:
        """The request and its result once the diagnosis ended (a worker that died: a
        result with its error), else None."""
        if self.running is None or not self.running[1].done():
            return None
        req, fut = self.running
        self.running = None
        try:
            return req, fut.result()
        except Exception as e:  # noqa: BLE001 -- the worker died: said, the watch goes on
            return req, WatchResult(error=f"the diagnosis failed: {e!r}")

    def close(self) -> None:
        """The worker and its axes' processes ended, a diagnosis under way dropped."""
        for p in list((getattr(self.pool, "_processes", None) or {}).values()):
            if p.pid is None:
                continue
            try:
                if os.getpgid(p.pid) == p.pid:  # its group: the worker and its axes
                    os.killpg(p.pid, signal.SIGKILL)
                else:  # not yet its own group (still starting): no axes yet
                    p.kill()
            except ProcessLookupError:  # already gone
                pass
        self.pool.shutdown(wait=False, cancel_futures=True)
