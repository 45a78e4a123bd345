"""Intake: what comes from outside the loop (trajectories, models) checked, decoded
and prepared off the loop's thread.

In real time the feedforward answers every sample within the driver's look-ahead (5 ms
by default). Taking a 200,000-point trajectory (11.2 MB of CDR) costs its thread
several ticks: the middleware's take, the decoding and the republishing on
``trajectory/accepted``. Done on the loop's thread, that held the driver ticks without
a command (`bench faults` measures it). Here only the take stays there; one worker
thread, at normal priority, does the rest (numpy releases the GIL on large buffers),
and the loop's thread picks up the result at its next sample (``ready``). A model
message is the same: parsing its YAML, checking it and building its inverse would
hold the loop ticks.
"""

from __future__ import annotations

import os
import queue
import sys
import threading
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from piezo_stage.core.types import Doc

SWITCH_INTERVAL_S = 0.0005  # the GIL handed over this often while the worker runs


def warm_up(decode: Callable[[bytes], Any], errors: tuple) -> None:
    """Run ``decode`` (CDR bytes -> trajectory) once on each of its paths now: a layout
    the fast decoder covers, and one it hands to rclpy's ordinary deserialization,
    whose first call loads the type support's shared library and imports with the GIL
    held (ticks of the loop when a malformed trajectory first came: `bench faults`)."""
    from rclpy.serialization import serialize_message
    from trajectory_msgs.msg import JointTrajectory, JointTrajectoryPoint
    point = JointTrajectoryPoint(positions=[0.0, 0.0])
    ragged = JointTrajectoryPoint(positions=[0.0])
    for points in ([point, point, point], [point, ragged]):
        try:
            decode(serialize_message(JointTrajectory(joint_names=["x", "y"], points=points)))
        except errors:
            pass


def _touch_heap(nbytes: int) -> None:
    """Allocate ``nbytes`` in this thread's heap, touch every page and free it (kept:
    the node's real-time recipe stops trimming, ``reserve_heap``). Through ctypes, so
    the GIL is released meanwhile. glibc only; elsewhere nothing."""
    if nbytes <= 0:
        return
    try:
        import ctypes
        import ctypes.util
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
        libc.malloc.restype, libc.malloc.argtypes = ctypes.c_void_p, [ctypes.c_size_t]
        libc.memset.argtypes = [ctypes.c_void_p, ctypes.c_int, ctypes.c_size_t]
        libc.free.argtypes = [ctypes.c_void_p]
        block = libc.malloc(nbytes)
        if block:
            libc.memset(block, 1, nbytes)
            libc.free(block)
    except (OSError, AttributeError):
        pass


def _just_below_the_loop() -> None:
    """This thread one SCHED_FIFO level below the node's main thread when that runs at
    SCHED_FIFO (a new thread inherits it, and the driver's mode sets every thread), at
    normal priority otherwise: the loop's thread preempts it, while a recorder busy
    compressing does not, so the GIL it holds is handed back at once (at normal
    priority the worker, preempted while holding it, held the loop up to 7 ticks)."""
    try:
        main = os.getpid()
        if os.sched_getscheduler(main) == os.SCHED_FIFO:
            prio = os.sched_getparam(main).sched_priority - 1
            if prio >= 1:
                os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(prio))
                return
        os.sched_setscheduler(0, os.SCHED_OTHER, os.sched_param(0))
    except (OSError, AttributeError):
        pass


class Intake:
    """Runs ``works[kind](data)`` for each item on one worker thread, in the order they
    came; ``ready()`` returns the finished ones [(kind, result or the error of
    ``errors`` it raised)] for the caller's thread to apply."""

    def __init__(self, works: Doc, errors: tuple) -> None:
        self.works, self.errors = works, errors
        self.inbox: queue.SimpleQueue = queue.SimpleQueue()
        self.done: queue.SimpleQueue = queue.SimpleQueue()
        self.thread: threading.Thread | None = None

    def start(self, heap_bytes: int = 0) -> None:
        """Start the worker (once). ``heap_bytes``: touched first in the worker's own
        heap, so the largest item's allocations there (decoding, and the middleware's
        copy when it republishes, made with the GIL held) cost no page faults, which
        would hold the loop's thread for ticks."""
        if self.thread is None:
            sys.setswitchinterval(SWITCH_INTERVAL_S)
            self.thread = threading.Thread(target=self._run, args=(int(heap_bytes),),
                                           name="intake", daemon=True)
            self.thread.start()

    def submit(self, kind: str, data: Any) -> None:
        self.start()
        self.inbox.put((kind, data))

    def ready(self) -> list:
        out = []
        while not self.done.empty():
            out.append(self.done.get_nowait())
        return out

    def _run(self, heap_bytes: int) -> None:
        _touch_heap(heap_bytes)
        while True:
            kind, data = self.inbox.get()
            _just_below_the_loop()
            try:
                result = self.works[kind](data)
            except self.errors as e:
                result = e
            self.done.put((kind, result))


@dataclass(frozen=True)
class Input:
    """A kind of input: ``decode`` it and check it (any thread), then ``take`` what
    that returned, or ``refuse`` the error it raised (the loop's thread)."""

    decode: Callable[[Any], Any]
    take: Callable[[Any], None]
    refuse: Callable[[BaseException], None]


class Inputs:
    """A node's inputs by kind: each decoded, then taken or refused; inline (lockstep:
    at once, in order with the samples) or decoded on an ``Intake``'s thread (real
    time: the loop's thread only takes what it finished, ``apply_ready``)."""

    def __init__(self, kinds: dict[str, Input], errors: tuple) -> None:
        self.kinds, self.errors = kinds, errors
        self.intake = Intake({k: v.decode for k, v in kinds.items()}, errors)

    def take(self, kind: str, item: Any, inline: bool) -> None:
        """An item of ``kind``: decoded and taken now (``inline``), else queued."""
        if not inline:
            self.intake.submit(kind, item)
            return
        k = self.kinds[kind]
        try:
            k.take(k.decode(item))
        except self.errors as e:
            k.refuse(e)

    def apply_ready(self, realtime: bool, heap_bytes: int) -> None:
        """Take or refuse what the intake finished; in real time its worker starts
        first (once), with ``heap_bytes`` of its heap touched (``Intake.start``)."""
        if realtime and self.intake.thread is None:
            self.intake.start(heap_bytes)
        for kind, done in self.intake.ready():
            k = self.kinds[kind]
            (k.refuse if isinstance(done, self.errors) else k.take)(done)
