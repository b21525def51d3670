"""Receding-horizon trajectory optimization (thesis 7.4): keypoint plans -> joint trajectories."""
