"""Odometry: the rover's motion from what it senses (IMU, stereo VO, records, a drift model).

The archive-level entry point is :mod:`lunarloc.odometry.source`."""
