"""The stage driver's lifecycle as tables: where each transition settles, and what a
fault escalates to.

ROS 2's managed node runs the transitions (rclpy.lifecycle); what the driver decides
within them is data here, as ros2/demos' lifecycle talker keeps each transition a few
lines. The driver node looks an event up and calls the transition it names.
"""

from __future__ import annotations

from piezo_stage.core.types import Doc

#: a transition's own state -> the state it leads to when it succeeds
SETTLES_TO = {"configuring": "inactive", "activating": "active", "deactivating": "inactive",
              "cleaningup": "unconfigured", "shuttingdown": "finalized",
              "errorprocessing": "unconfigured"}

#: the events a driver escalates
HARDWARE_FAULT = "hardware fault"  # a lost link or a controller error
FAULTED_AT_SAFE = "faulted at safe"  # a loop fault whose ramp reached the safe voltage

#: the driver's next step
DEACTIVATE = "deactivate"  # reporting the fault: the error transition follows
CLEANUP = "cleanup"  # inactive has no error edge: cleanup closes what the link allows
EXIT = "exit"  # unmanaged: the node exits 1 with the reason
STAY = "stay"  # nothing to do: unmanaged recovery (auto_arm), or not active

#: (event, managed, lifecycle state) -> the next step; any other: ``UNLISTED``
ESCALATION = {
    (HARDWARE_FAULT, True, "active"): DEACTIVATE,
    (HARDWARE_FAULT, True, "inactive"): CLEANUP,
    (FAULTED_AT_SAFE, True, "active"): DEACTIVATE,
}
#: an event's step in every state the table does not list
UNLISTED = {HARDWARE_FAULT: EXIT, FAULTED_AT_SAFE: STAY}


def settled(label: str) -> str:
    """The lifecycle state ``label`` is or leads to (a transition's: where it goes)."""
    return SETTLES_TO.get(label, label)


def escalation(event: str, managed: bool, label: str) -> str:
    """The driver's next step after ``event`` in lifecycle state ``label``."""
    if event not in UNLISTED:
        raise ValueError(f"unknown event {event!r}; known: {', '.join(UNLISTED)}")
    return ESCALATION.get((event, managed, label), UNLISTED[event])


def closed_status(label: str) -> tuple[int, str, Doc]:
    """A driver's diagnostics with no sample loop (unconfigured, or after cleanup)."""
    message = f"{label}: the backend is closed"
    return 0, message, {"state": "disarmed", "reason": message}
