"""Pure functions between ROS 2 messages (common_interfaces only) and core data.

The only code in the project that touches message types. SI units on the wire
(metres, volts, seconds; REP 103), micrometres in the core: conversions happen here.

``wire`` (units and joint-state reading) and ``cdr`` (the codecs of the per-sample
topics) need no ROS: the bag readers use them. The message functions of ``convert``
load the message types when first asked for (``piezo_stage_msgs_adapters.joint_state``
and the like).
"""

from piezo_stage_msgs_adapters.wire import JOINTS, UM  # noqa: F401


def __getattr__(name):
    import importlib
    convert = importlib.import_module("piezo_stage_msgs_adapters.convert")
    try:
        return getattr(convert, name)
    except AttributeError:
        raise AttributeError(f"module 'piezo_stage_msgs_adapters' has no attribute "
                             f"{name!r}") from None
