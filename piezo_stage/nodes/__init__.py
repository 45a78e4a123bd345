"""ROS 2 nodes: one per file, each a thin shell over the core (see README: topics)."""
