"""Robot bridge: trajectories in, control-board commands out, joint state back; limits and watchdog."""
