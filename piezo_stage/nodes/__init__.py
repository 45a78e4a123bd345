"""ROS 2 nodes: one per file, each a thin shell over the core (see docs/nodes.md: topics).

``NODES`` is the one list of the set's nodes, in start order (the recorder and the live
view first, so they listen before anything is published; the driver last, so its first
sample finds everyone): the launcher, the ros2 launch file and setup.py (which
installs scripts/<node> to lib/piezo_stage) all read it.
"""

NODES = ("recorder", "live_view", "identifier", "gap", "controller", "feedforward",
         "trajectory", "stage_driver")

# the writer history [samples] the loop's nodes publish their per-sample topics with,
# where this is set (``_common.data_out_qos``): `piezo-stage launch` sets it for a
# real-time set (REALTIME_WRITER_DEPTH); unset, the writers keep QOS_DATA's 5000
WRITER_DEPTH_ENV = "PIEZO_STAGE_WRITER_DEPTH"
REALTIME_WRITER_DEPTH = 250
