"""The stage driver without ROS: what it holds across its lifecycle.

The backend and the sample loop over it are open from configure to cleanup; across
them the driver keeps where the next loop starts (lockstep: its sample index), the
hardware's fault, the fault a transition reports, and the values it last announced
(what ``state`` says while no loop runs). The node (nodes/stage_driver_node.py) runs the
lifecycle's transitions and the topics; each transition's work is one call here.
"""

from __future__ import annotations

from collections.abc import Callable

from piezo_stage.core.errors import BackendFault, ConfigError, DataError
from piezo_stage.core.loop.arming import ENABLED, ArmingParams
from piezo_stage.core.loop.backend import Backend
from piezo_stage.core.loop.lifecycle import (
    CLEANUP,
    DEACTIVATE,
    closed_status,
    escalation,
    settled,
)
from piezo_stage.core.loop.sample_loop import LoopOptions, SampleLoop
from piezo_stage.core.types import Doc

#: the errors a lab can fix (a backend that cannot open, bad limits)
FIXABLE = (ConfigError, DataError, BackendFault)

#: a state change announced: (state, reason, whether to log it)
OnState = Callable[[str, str, bool], None]


def fixable(e: BaseException) -> bool:
    """A transition that raised ``e`` failed (the lifecycle stays where it was); any
    other error takes the error transition."""
    return isinstance(e, FIXABLE)


class DriverCore:
    """A stage driver's state from its first configure to its exit.

    ``params``: the loop's (core/loop/sample_loop.py PARAMETERS); ``open_backend()``
    opens the stage (drivers.make_backend); ``on_state(state, reason, log)`` announces
    each of the loop's state changes (its values and stamp: ``last_values``,
    ``state_since``).
    """

    def __init__(self, params: Doc, arm: ArmingParams, open_backend: Callable[[], Backend],
                 on_state: OnState) -> None:
        self.p, self.arm_params = params, arm
        self.open_backend, self.on_state = open_backend, on_state
        self.backend: Backend | None = None
        self.loop: SampleLoop | None = None
        self.next_j = 0  # lockstep: the first sample of the next configure
        self.failed: BaseException | None = None  # the hardware's fault, once
        self.why_error = ""  # a fault that takes the error transition
        self.last_values: Doc = {}  # the last announcement's values (for unconfigured)
        self.state_since = 0  # the stamp the last state applies from [ns]
        self.link = ""  # the loop's missing links, in words

    def configure(self, start: Callable[[SampleLoop], object]) -> None:
        """Open the backend and a sample loop over it, disarmed at the safe voltage, and
        ``start(loop)`` it; nothing is left open when either fails."""
        self.backend = self.open_backend()
        self.failed, self.why_error = None, ""
        try:
            self.loop = SampleLoop(self.backend, self.arm_params, LoopOptions.from_params(
                self.p, self.next_j, arm_on_start=False), self.changed)
            self.changed(self.loop.state, "configured: started disarmed at the safe "
                         "voltage", self.loop.stamp(self.loop.j + 1))
            start(self.loop)
        except Exception:
            self.loop = None
            self.close_backend()
            raise

    def changed(self, state: str, reason: str, since_ns: int, log: bool = True) -> None:
        """The loop took ``state`` from ``since_ns``: its values kept, then announced."""
        self.state_since = since_ns
        self.last_values = {**self.running.announced(), "mode": self.p["mode"]}
        self.on_state(state, reason, log)

    def took(self, change: tuple[str, str]) -> None:
        """A state the loop took at its present sample (activate, deactivate)."""
        self.changed(*change, self.running.stamp(self.running.j), log=False)

    def restate(self) -> None:
        """The same state from the same sample, its values changed (a phase)."""
        self.changed(self.running.state, self.running.reason, self.state_since, log=False)

    def close(self, why: str) -> str:
        """The backend ramps to the safe voltage and closes; the next loop starts after
        this one's last sample; a loop that ran announces ``disarmed`` with ``why``.
        Returns the close's error ('' when none)."""
        if self.loop is not None:
            self.next_j = self.loop.j + 1
        error = ""
        try:
            self.close_backend()
        except Exception as e:  # noqa: BLE001 - a link already lost cannot close
            error = str(e)
        if self.loop is not None:
            self.loop = None
            self.on_state("disarmed", f"{why}: the backend is closed", True)
        return error

    def close_backend(self) -> None:
        """The backend (if open) ramps to the safe voltage and closes."""
        if self.backend is not None:
            backend, self.backend = self.backend, None
            backend.close(self.arm_params.safe_V, self.arm_params.ramp_V_per_s)

    def error_reason(self, label: str, transition_error: BaseException | None) -> str:
        """What the error transition reports: the fault that led to it, or the failed
        transition (``label``) and its error; the fault is then taken."""
        reason, self.why_error = self.why_error or f"{label}: {transition_error}", ""
        return reason

    def arm(self, on: bool, label: str) -> tuple[bool, str]:
        """The arm service: arm or disarm the loop, only while ``label`` is active."""
        if label != "active":
            return False, (f"{label}: the driver arms only when active (lifecycle: "
                           "configure, then activate)")
        return self.running.arm(on, self.link)

    def ramp_down(self, realtime: bool) -> float | None:
        """The end of a run: in real time a running loop ramps to the safe voltage
        (returns how long that may take [s]); otherwise it ends at once (None)."""
        if self.loop is not None and realtime:
            return self.loop.begin_shutdown()
        if self.loop is not None:
            self.loop.end_now()
        return None

    def hardware_fault(self, error: BaseException | None) -> bool:
        """Keep the hardware's fault; True the first time (to be said once)."""
        first = self.failed is None
        if first:
            self.failed = error
        return first

    def escalate(self, event: str, managed: bool, label: str, why: str) -> str:
        """The step core/loop/lifecycle.py's table gives ``event`` in lifecycle state
        ``label``; where it is a transition, the error transition that follows reports
        ``why``."""
        step = escalation(event, managed, label)
        if step in (DEACTIVATE, CLEANUP):
            self.why_error = why
        return step

    def announcement(self, label: str) -> Doc:
        """The values ``state`` announces: the last ones, with the lifecycle state
        ``label`` is or leads to."""
        return {**self.last_values, "lifecycle": settled(label)}

    def ahead(self) -> bool:
        """The last state applies at a sample not yet taken (lockstep: announced ahead)."""
        return self.loop is not None and self.state_since > self.loop.stamp(self.loop.j)

    def needs_links(self) -> bool:
        """Not armed: an arming refusal or its reason names the missing links."""
        return self.loop is not None and self.loop.state not in ENABLED

    def links(self, missing: str) -> None:
        """The loop's missing links, in words ('' when none), as the graph shows them."""
        self.link = missing

    @property
    def running(self) -> SampleLoop:
        """The sample loop, where one runs (from configure to cleanup: every caller)."""
        if self.loop is None:
            raise RuntimeError("stage driver: no sample loop outside configure..cleanup")
        return self.loop

    @property
    def shutdown_requested(self) -> bool:
        """The run is ending (a ramp to safe or an end under way)."""
        return self.loop is not None and self.loop.shutdown_requested

    def hardware_id(self) -> str:
        """What /diagnostics names: the backend's, or the closed stage."""
        return self.backend.hardware_id if self.backend is not None else \
            f"{self.p['backend']} stage (closed)"

    def status(self, label: str, thread_priority: int) -> tuple[int, str, Doc]:
        """The diagnostics: the loop's, or the closed driver's, with the driver's values."""
        level, message, values = closed_status(label) if self.loop is None else \
            self.loop.status()
        values.update(backend=self.p["backend"], mode=self.p["mode"], lifecycle=label,
                      thread_priority=thread_priority)
        return level, message, values

    def summary(self, label: str) -> str:
        """What a stop left the stage at."""
        if self.loop is None:
            return f"{label}, the backend closed"
        return f"{self.loop.summary()}; the backend then ramps to safe and closes"

    def estop(self) -> str:
        """An emergency stop's answer (nothing is driven while unconfigured)."""
        return "unconfigured: nothing is driven" if self.loop is None else self.loop.estop()
