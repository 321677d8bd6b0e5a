"""Fusion over time: the 4-DoF pose graph of fixes and odometry."""
