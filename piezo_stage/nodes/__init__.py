"""ROS 2 nodes: one per file, each a thin shell over the core (see docs/nodes.md: topics).

``NODES`` is the one list of the set's nodes, in start order (the recorder and the live
view first, so they listen before anything is published; the driver last, so its first
sample finds everyone): the launcher, the ros2 launch file and setup.py (which
installs scripts/<node> to lib/piezo_stage) all read it.
"""

NODES = ("recorder", "live_view", "identifier", "gap", "controller", "feedforward",
         "trajectory", "stage_driver")
