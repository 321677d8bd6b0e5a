"""Odometry from what the rover senses (visual, IMU, recorded poses)."""
