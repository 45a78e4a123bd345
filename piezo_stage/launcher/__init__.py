"""Our launcher (the ROS 2 launch tooling is not installable from the package index)."""
