"""Records and files: CSV tables, model and plant YAML, bags (rosbag2 layout, MCAP)."""
