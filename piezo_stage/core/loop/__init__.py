"""What runs each sample, without ROS: the driver's sample loop, arming and the
reference planner, the feedforward, the controller law, effect compensation, learning
feedforward, stamps, trajectories and gain tuning. Builds on core.model; imports
nothing of core.estimation."""
