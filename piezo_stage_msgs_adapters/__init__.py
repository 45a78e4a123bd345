"""Pure functions between ROS 2 messages (common_interfaces only) and core data.

The only code in the project that touches message types. SI units on the wire
(metres, volts, seconds; REP 103), micrometres in the core: conversions happen here.
"""

from piezo_stage_msgs_adapters.convert import *  # noqa: F401,F403
